//! PNG plots for the closed-loop simulator's report folder (`visnav sim --out DIR`): line/scatter
//! charts with uncertainty bands ([`chart`]) and map track plots over a georeferenced background
//! ([`track`]).
//!
//! Pure module: every function returns an [`image::RgbImage`]; the only I/O is [`save_png`]. No font
//! files are needed: text uses a built-in 5x7 bitmap font with a descender row (ASCII 32..126,
//! 6 px advance, scaled by an integer factor; other characters are drawn as `?`).
//!
//! # Drawing model
//!
//! * Axes: the data range (or [`PlotSpec::x_range`] / [`PlotSpec::y_range`]) is mapped linearly to
//!   the plot rectangle; pixel `(i, j)` of the plot rectangle covers `[i, i + 1) x [j, j + 1)` in
//!   plot-local pixel units, `x` grows to the right, `y` grows **up** (image rows grow down). Ticks
//!   are "nice" numbers ([`nice_ticks`]: steps of 1, 2 or 5 x 10^k, after Heckbert, "Nice numbers for
//!   graph labels", Graphics Gems, 1990).
//! * Lines and dots are rasterised as coverage masks: each pixel's coverage is
//!   `clamp(w/2 + 0.5 - d, 0, 1)` where `d` is the distance of the pixel centre from the segment (or
//!   dot centre), which gives anti-aliased edges of about one pixel; a whole series is accumulated
//!   with `max` (no darker joints) and composited once, `out = bg (1 - a) + rgb a`. Where the
//!   coverage is 1 the series colour appears exactly. A non-finite point (NaN) breaks a line.
//! * Bands `(x, lo, hi)` are filled column by column between the linearly interpolated `lo` and `hi`
//!   edges, composited at 25 % opacity.
//! * Everything is clipped to the plot rectangle; segments are clipped (Liang-Barsky) before
//!   rasterisation so off-scale values cost nothing.
//! * Map tracks ([`track`]): map frame x east, y north (metres); the background image's row 0 is the
//!   north edge of its `extent = [min_x, min_y, max_x, max_y]` and column 0 the west edge (pixel
//!   corners at the extent edges). Equal metres per pixel on both axes is always enforced.
//!
//! Robustness: empty or all-NaN data, single points, zero-width ranges, huge values and tiny images
//! never panic; where nothing can be drawn the plot says "no data". Images are at least 1 x 1 and at
//! most [`MAX_SIDE_PX`] on a side.

use std::path::{Path, PathBuf};

use image::{Rgb, RgbImage};

/// Largest image side accepted by [`chart`] and [`track`] (larger requests are clamped).
pub const MAX_SIDE_PX: u32 = 16384;

/// Errors of this module.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The PNG could not be encoded or written.
    #[error("cannot write PNG {path}: {cause}")]
    Save {
        path: PathBuf,
        cause: image::ImageError,
    },
}

/// How a series is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Style {
    /// Poly-line; it breaks at non-finite points (NaN = gap).
    #[default]
    Line,
    /// One filled dot per finite point.
    Dots,
    /// Both.
    LineDots,
}

/// One data series: `(x, y)` points in data units.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text (an empty name is left out of the legend).
    pub name: String,
    pub rgb: [u8; 3],
    pub points: Vec<(f64, f64)>,
    pub style: Style,
}

impl Series {
    /// Convenience constructor.
    pub fn new(
        name: impl Into<String>,
        rgb: [u8; 3],
        style: Style,
        points: Vec<(f64, f64)>,
    ) -> Self {
        Series {
            name: name.into(),
            rgb,
            points,
            style,
        }
    }
}

/// A shaded translucent area between `lo` and `hi` over `x`, e.g. a +-3 sigma envelope.
#[derive(Debug, Clone, PartialEq)]
pub struct Band {
    /// Legend text (an empty name is left out of the legend).
    pub name: String,
    pub rgb: [u8; 3],
    /// `(x, lo, hi)`; a non-finite entry breaks the band.
    pub points: Vec<(f64, f64, f64)>,
}

/// Size, texts and axis options of one plot.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotSpec {
    pub width_px: u32,
    pub height_px: u32,
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// Same data units per pixel on both axes (always on for [`track`]).
    pub equal_aspect: bool,
    /// Fixed x range (data units); `None` fits the data.
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range (data units); `None` fits the data.
    pub y_range: Option<(f64, f64)>,
    /// Integer text scale (1 = 5x7 px glyphs); 0 picks one from the image size.
    pub font_scale: u32,
}

impl Default for PlotSpec {
    fn default() -> Self {
        PlotSpec {
            width_px: 1000,
            height_px: 700,
            title: String::new(),
            x_label: String::new(),
            y_label: String::new(),
            equal_aspect: false,
            x_range: None,
            y_range: None,
            font_scale: 0,
        }
    }
}

impl PlotSpec {
    /// A spec with the given size and texts, automatic ranges and font scale.
    pub fn new(
        width_px: u32,
        height_px: u32,
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
    ) -> Self {
        PlotSpec {
            width_px,
            height_px,
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            ..PlotSpec::default()
        }
    }
}

/// Writes `img` as a PNG file at `path` (the parent directory must exist).
pub fn save_png(img: &RgbImage, path: &Path) -> Result<(), PlotError> {
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| PlotError::Save {
            path: path.to_path_buf(),
            cause: source,
        })
}

// ---------------------------------------------------------------------------------------------
// Ticks
// ---------------------------------------------------------------------------------------------

/// "Nice" tick values covering `[lo, hi]` (the order of `lo` and `hi` does not matter): the step is
/// the smallest of 1, 2, 5 x 10^k that is at least `(hi - lo) / max_ticks`, and the ticks are the
/// multiples of the step inside `[lo, hi]` (so at most `max_ticks + 1` of them), increasing.
/// Returns `[lo]` when `lo == hi`, and nothing for non-finite input or `max_ticks == 0`.
pub fn nice_ticks(lo: f64, hi: f64, max_ticks: usize) -> Vec<f64> {
    nice_ticks_step(lo, hi, max_ticks).0
}

/// [`nice_ticks`] plus the step (0 when there is none).
fn nice_ticks_step(lo: f64, hi: f64, max_ticks: usize) -> (Vec<f64>, f64) {
    if !lo.is_finite() || !hi.is_finite() || max_ticks == 0 {
        return (Vec::new(), 0.0);
    }
    let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
    if lo == hi {
        return (vec![lo], 0.0);
    }
    let n = max_ticks.min(1000) as f64;
    // Halves so that the span of any two finite numbers stays finite.
    let half_span = hi / 2.0 - lo / 2.0;
    let raw = half_span / n * 2.0;
    let Some(step) = nice_step(raw) else {
        return (Vec::new(), 0.0);
    };
    let first = (lo / step).ceil();
    let last = (hi / step).floor();
    let mut ticks = Vec::new();
    let mut k = first;
    while k <= last && ticks.len() <= max_ticks {
        ticks.push(k * step);
        let next = k + 1.0;
        if next == k {
            break; // index beyond f64 integer precision
        }
        k = next;
    }
    (ticks, step)
}

/// Smallest 1/2/5 x 10^k that is >= `raw` (> 0, finite).
fn nice_step(raw: f64) -> Option<f64> {
    if !(raw.is_finite() && raw > 0.0) {
        return None;
    }
    let mut exp = raw.log10().floor();
    let mut mag = 10f64.powf(exp);
    // powf/log10 rounding: make sure mag <= raw < 10 mag.
    if mag > raw {
        exp -= 1.0;
        mag = 10f64.powf(exp);
    }
    if mag * 10.0 <= raw {
        exp += 1.0;
        mag = 10f64.powf(exp);
    }
    for m in [1.0, 2.0, 5.0, 10.0] {
        let s = m * mag;
        if s >= raw && s.is_finite() && s > 0.0 {
            return Some(s);
        }
    }
    None
}

/// Tick labels for ticks spaced by `step`: fixed-point with just enough decimals, or exponent
/// notation for very large or very small magnitudes.
fn tick_labels(ticks: &[f64], step: f64) -> Vec<String> {
    let max_abs = ticks.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let step = if step > 0.0 && step.is_finite() {
        step
    } else if max_abs > 0.0 {
        max_abs
    } else {
        1.0
    };
    let k = (step.log10() + 1e-9).floor() as i32;
    let exponent = max_abs >= 1e9 || (max_abs > 0.0 && k < -5);
    ticks
        .iter()
        .map(|&v| {
            let v = if v.abs() < step * 1e-6 { 0.0 } else { v };
            if exponent {
                let digits = ((max_abs.log10().floor() as i32) - k).clamp(0, 15) as usize;
                format!("{v:.digits$e}")
            } else {
                let dec = (-k).clamp(0, 15) as usize;
                format!("{v:.dec$}")
            }
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Font
// ---------------------------------------------------------------------------------------------

/// Glyph cell: 5 columns x 8 rows (capitals and digits use rows 0..=6, descenders of g j p q y
/// and the comma reach row 7); the advance is one blank column more.
const GLYPH_W: u32 = 5;
const GLYPH_H: u32 = 8;
/// Height of capitals and digits (rows 0..=6), for vertical centring.
const CAP_H: u32 = 7;
/// Horizontal advance per character at scale 1, pixels.
pub const GLYPH_ADVANCE: u32 = 6;

/// 5x7 font for ASCII 32..=126 (plus one descender row), one byte per column, bit 0 = top row
/// (after the classic HD44780-style table, public domain; lower-case descenders redrawn).
#[rustfmt::skip]
const FONT: [[u8; 5]; 95] = [
    [0x00, 0x00, 0x00, 0x00, 0x00], // ' '
    [0x00, 0x00, 0x5F, 0x00, 0x00], // !
    [0x00, 0x07, 0x00, 0x07, 0x00], // "
    [0x14, 0x7F, 0x14, 0x7F, 0x14], // #
    [0x24, 0x2A, 0x7F, 0x2A, 0x12], // $
    [0x23, 0x13, 0x08, 0x64, 0x62], // %
    [0x36, 0x49, 0x55, 0x22, 0x50], // &
    [0x00, 0x05, 0x03, 0x00, 0x00], // '
    [0x00, 0x1C, 0x22, 0x41, 0x00], // (
    [0x00, 0x41, 0x22, 0x1C, 0x00], // )
    [0x08, 0x2A, 0x1C, 0x2A, 0x08], // *
    [0x08, 0x08, 0x3E, 0x08, 0x08], // +
    [0x00, 0x80, 0x60, 0x00, 0x00], // ,
    [0x08, 0x08, 0x08, 0x08, 0x08], // -
    [0x00, 0x60, 0x60, 0x00, 0x00], // .
    [0x20, 0x10, 0x08, 0x04, 0x02], // /
    [0x3E, 0x51, 0x49, 0x45, 0x3E], // 0
    [0x00, 0x42, 0x7F, 0x40, 0x00], // 1
    [0x42, 0x61, 0x51, 0x49, 0x46], // 2
    [0x21, 0x41, 0x45, 0x4B, 0x31], // 3
    [0x18, 0x14, 0x12, 0x7F, 0x10], // 4
    [0x27, 0x45, 0x45, 0x45, 0x39], // 5
    [0x3C, 0x4A, 0x49, 0x49, 0x30], // 6
    [0x01, 0x71, 0x09, 0x05, 0x03], // 7
    [0x36, 0x49, 0x49, 0x49, 0x36], // 8
    [0x06, 0x49, 0x49, 0x29, 0x1E], // 9
    [0x00, 0x36, 0x36, 0x00, 0x00], // :
    [0x00, 0x80, 0x66, 0x06, 0x00], // ;
    [0x08, 0x14, 0x22, 0x41, 0x00], // <
    [0x14, 0x14, 0x14, 0x14, 0x14], // =
    [0x00, 0x41, 0x22, 0x14, 0x08], // >
    [0x02, 0x01, 0x51, 0x09, 0x06], // ?
    [0x32, 0x49, 0x79, 0x41, 0x3E], // @
    [0x7E, 0x11, 0x11, 0x11, 0x7E], // A
    [0x7F, 0x49, 0x49, 0x49, 0x36], // B
    [0x3E, 0x41, 0x41, 0x41, 0x22], // C
    [0x7F, 0x41, 0x41, 0x22, 0x1C], // D
    [0x7F, 0x49, 0x49, 0x49, 0x41], // E
    [0x7F, 0x09, 0x09, 0x09, 0x01], // F
    [0x3E, 0x41, 0x49, 0x49, 0x7A], // G
    [0x7F, 0x08, 0x08, 0x08, 0x7F], // H
    [0x00, 0x41, 0x7F, 0x41, 0x00], // I
    [0x20, 0x40, 0x41, 0x3F, 0x01], // J
    [0x7F, 0x08, 0x14, 0x22, 0x41], // K
    [0x7F, 0x40, 0x40, 0x40, 0x40], // L
    [0x7F, 0x02, 0x0C, 0x02, 0x7F], // M
    [0x7F, 0x04, 0x08, 0x10, 0x7F], // N
    [0x3E, 0x41, 0x41, 0x41, 0x3E], // O
    [0x7F, 0x09, 0x09, 0x09, 0x06], // P
    [0x3E, 0x41, 0x51, 0x21, 0x5E], // Q
    [0x7F, 0x09, 0x19, 0x29, 0x46], // R
    [0x46, 0x49, 0x49, 0x49, 0x31], // S
    [0x01, 0x01, 0x7F, 0x01, 0x01], // T
    [0x3F, 0x40, 0x40, 0x40, 0x3F], // U
    [0x1F, 0x20, 0x40, 0x20, 0x1F], // V
    [0x3F, 0x40, 0x38, 0x40, 0x3F], // W
    [0x63, 0x14, 0x08, 0x14, 0x63], // X
    [0x07, 0x08, 0x70, 0x08, 0x07], // Y
    [0x61, 0x51, 0x49, 0x45, 0x43], // Z
    [0x00, 0x7F, 0x41, 0x41, 0x00], // [
    [0x02, 0x04, 0x08, 0x10, 0x20], // backslash
    [0x00, 0x41, 0x41, 0x7F, 0x00], // ]
    [0x04, 0x02, 0x01, 0x02, 0x04], // ^
    [0x40, 0x40, 0x40, 0x40, 0x40], // _
    [0x00, 0x01, 0x02, 0x04, 0x00], // `
    [0x20, 0x54, 0x54, 0x54, 0x78], // a
    [0x7F, 0x48, 0x44, 0x44, 0x38], // b
    [0x38, 0x44, 0x44, 0x44, 0x20], // c
    [0x38, 0x44, 0x44, 0x48, 0x7F], // d
    [0x38, 0x54, 0x54, 0x54, 0x18], // e
    [0x08, 0x7E, 0x09, 0x01, 0x02], // f
    [0x98, 0xA4, 0xA4, 0xA4, 0x7C], // g
    [0x7F, 0x08, 0x04, 0x04, 0x78], // h
    [0x00, 0x44, 0x7D, 0x40, 0x00], // i
    [0x40, 0x80, 0x84, 0x7D, 0x00], // j
    [0x7F, 0x10, 0x28, 0x44, 0x00], // k
    [0x00, 0x41, 0x7F, 0x40, 0x00], // l
    [0x7C, 0x04, 0x18, 0x04, 0x78], // m
    [0x7C, 0x08, 0x04, 0x04, 0x78], // n
    [0x38, 0x44, 0x44, 0x44, 0x38], // o
    [0xFC, 0x24, 0x24, 0x24, 0x18], // p
    [0x18, 0x24, 0x24, 0x24, 0xFC], // q
    [0x7C, 0x08, 0x04, 0x04, 0x08], // r
    [0x48, 0x54, 0x54, 0x54, 0x20], // s
    [0x04, 0x3F, 0x44, 0x40, 0x20], // t
    [0x3C, 0x40, 0x40, 0x20, 0x7C], // u
    [0x1C, 0x20, 0x40, 0x20, 0x1C], // v
    [0x3C, 0x40, 0x30, 0x40, 0x3C], // w
    [0x44, 0x28, 0x10, 0x28, 0x44], // x
    [0x9C, 0xA0, 0xA0, 0xA0, 0x7C], // y
    [0x44, 0x64, 0x54, 0x4C, 0x44], // z
    [0x00, 0x08, 0x36, 0x41, 0x00], // {
    [0x00, 0x00, 0x7F, 0x00, 0x00], // |
    [0x00, 0x41, 0x36, 0x08, 0x00], // }
    [0x08, 0x04, 0x08, 0x10, 0x08], // ~
];

fn glyph(c: char) -> &'static [u8; 5] {
    let code = c as u32;
    let idx = if (32..=126).contains(&code) {
        (code - 32) as usize
    } else {
        ('?' as u32 - 32) as usize
    };
    &FONT[idx]
}

/// Size `(width, height)` in pixels of `text` drawn at `scale` (>= 1): `chars x 6 x scale` by
/// `8 x scale`.
pub fn text_size(text: &str, scale: u32) -> (u32, u32) {
    let s = scale.max(1);
    let n = u32::try_from(text.chars().count()).unwrap_or(u32::MAX);
    (n.saturating_mul(GLYPH_ADVANCE * s), GLYPH_H * s)
}

/// Calls `ink(dx, dy)` for every ink pixel of `text` at `scale`, relative to the top-left corner.
fn for_each_ink(text: &str, scale: u32, mut ink: impl FnMut(i64, i64)) {
    let s = i64::from(scale.max(1));
    for (i, c) in text.chars().enumerate() {
        let ox = i as i64 * i64::from(GLYPH_ADVANCE) * s;
        for (col, bits) in glyph(c).iter().enumerate() {
            for row in 0..GLYPH_H {
                if bits >> row & 1 == 1 {
                    for sy in 0..s {
                        for sx in 0..s {
                            ink(ox + col as i64 * s + sx, i64::from(row) * s + sy);
                        }
                    }
                }
            }
        }
        if ox > i64::from(MAX_SIDE_PX) * 4 {
            break; // the rest cannot be on any image
        }
    }
    const { assert!(GLYPH_W < GLYPH_ADVANCE) };
}

/// Draws `text` with its top-left corner at `(x, y)`, clipped to the image.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: u32, rgb: [u8; 3]) {
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    for_each_ink(text, scale, |dx, dy| {
        let (px, py) = (x + dx, y + dy);
        if px >= 0 && py >= 0 && px < w && py < h {
            img.put_pixel(px as u32, py as u32, Rgb(rgb));
        }
    });
}

/// Draws `text` rotated 90 degrees counter-clockwise (reading bottom to top); `(x, y)` is the
/// bottom-left corner of the rotated text's first character.
fn draw_text_up(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: u32, rgb: [u8; 3]) {
    let (w, h) = (i64::from(img.width()), i64::from(img.height()));
    for_each_ink(text, scale, |dx, dy| {
        let (px, py) = (x + dy, y - 1 - dx);
        if px >= 0 && py >= 0 && px < w && py < h {
            img.put_pixel(px as u32, py as u32, Rgb(rgb));
        }
    });
}

// ---------------------------------------------------------------------------------------------
// Raster primitives
// ---------------------------------------------------------------------------------------------

/// Integer rectangle in image pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Rect {
    x: i64,
    y: i64,
    w: i64,
    h: i64,
}

impl Rect {
    fn contains(&self, px: i64, py: i64) -> bool {
        px >= self.x && py >= self.y && px < self.x + self.w && py < self.y + self.h
    }
    fn intersects(&self, o: &Rect) -> bool {
        self.x < o.x + o.w && o.x < self.x + self.w && self.y < o.y + o.h && o.y < self.y + self.h
    }
}

fn blend(img: &mut RgbImage, px: i64, py: i64, rgb: [u8; 3], a: f32) {
    if px < 0 || py < 0 || px >= i64::from(img.width()) || py >= i64::from(img.height()) {
        return;
    }
    let a = a.clamp(0.0, 1.0);
    let p = img.get_pixel_mut(px as u32, py as u32);
    for (c, &t) in p.0.iter_mut().zip(rgb.iter()) {
        *c = (f32::from(*c) * (1.0 - a) + f32::from(t) * a).round() as u8;
    }
}

fn fill_rect(img: &mut RgbImage, r: Rect, rgb: [u8; 3], a: f32) {
    let x0 = r.x.max(0);
    let y0 = r.y.max(0);
    let x1 = (r.x + r.w).min(i64::from(img.width()));
    let y1 = (r.y + r.h).min(i64::from(img.height()));
    for py in y0..y1 {
        for px in x0..x1 {
            blend(img, px, py, rgb, a);
        }
    }
}

fn hline(img: &mut RgbImage, x0: i64, x1: i64, y: i64, rgb: [u8; 3]) {
    fill_rect(
        img,
        Rect {
            x: x0.min(x1),
            y,
            w: (x1 - x0).abs() + 1,
            h: 1,
        },
        rgb,
        1.0,
    );
}

fn vline(img: &mut RgbImage, x: i64, y0: i64, y1: i64, rgb: [u8; 3]) {
    fill_rect(
        img,
        Rect {
            x,
            y: y0.min(y1),
            w: 1,
            h: (y1 - y0).abs() + 1,
        },
        rgb,
        1.0,
    );
}

fn stroke_rect(img: &mut RgbImage, r: Rect, rgb: [u8; 3]) {
    if r.w <= 0 || r.h <= 0 {
        return;
    }
    hline(img, r.x, r.x + r.w - 1, r.y, rgb);
    hline(img, r.x, r.x + r.w - 1, r.y + r.h - 1, rgb);
    vline(img, r.x, r.y, r.y + r.h - 1, rgb);
    vline(img, r.x + r.w - 1, r.y, r.y + r.h - 1, rgb);
}

/// Largest plot-local coordinate magnitude kept before clipping (keeps the arithmetic finite).
const COORD_LIMIT: f64 = 1e7;

/// Per-series coverage mask over the plot rectangle (plot-local pixels).
struct Mask {
    w: usize,
    h: usize,
    cov: Vec<f32>,
}

impl Mask {
    fn new(w: usize, h: usize) -> Self {
        Mask {
            w,
            h,
            cov: vec![0.0; w * h],
        }
    }

    fn put(&mut self, i: usize, j: usize, c: f32) {
        let k = j * self.w + i;
        if c > self.cov[k] {
            self.cov[k] = c;
        }
    }

    /// Thick anti-aliased segment of width `2 half_w` between plot-local points.
    fn segment(&mut self, a: (f64, f64), b: (f64, f64), half_w: f64) {
        let pad = half_w + 1.0;
        let Some((a, b)) = clip_segment(a, b, -pad, -pad, self.w as f64 + pad, self.h as f64 + pad)
        else {
            return;
        };
        let (dx, dy) = (b.0 - a.0, b.1 - a.1);
        let len2 = dx * dx + dy * dy;
        let i0 = (a.0.min(b.0) - pad).floor().max(0.0) as usize;
        let i1 = ((a.0.max(b.0) + pad).ceil().max(0.0) as usize).min(self.w);
        let j0 = (a.1.min(b.1) - pad).floor().max(0.0) as usize;
        let j1 = ((a.1.max(b.1) + pad).ceil().max(0.0) as usize).min(self.h);
        for j in j0..j1 {
            let cy = j as f64 + 0.5;
            for i in i0..i1 {
                let cx = i as f64 + 0.5;
                let t = if len2 > 0.0 {
                    (((cx - a.0) * dx + (cy - a.1) * dy) / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let (qx, qy) = (a.0 + t * dx - cx, a.1 + t * dy - cy);
                let d = (qx * qx + qy * qy).sqrt();
                let c = (half_w + 0.5 - d).clamp(0.0, 1.0);
                if c > 0.0 {
                    self.put(i, j, c as f32);
                }
            }
        }
    }

    /// Filled anti-aliased disc.
    fn disc(&mut self, c: (f64, f64), r: f64) {
        let pad = r + 1.0;
        if c.0 < -pad || c.1 < -pad || c.0 > self.w as f64 + pad || c.1 > self.h as f64 + pad {
            return;
        }
        self.segment(c, c, r);
    }

    /// Fully covers rows `[y0, y1)` (fractional edges anti-aliased) of column `i`.
    fn span(&mut self, i: usize, y0: f64, y1: f64) {
        if i >= self.w {
            return;
        }
        let (y0, y1) = (y0.min(y1).max(0.0), y1.max(y0).min(self.h as f64));
        if y1 <= y0 {
            return;
        }
        let j0 = y0.floor() as usize;
        let j1 = (y1.ceil() as usize).min(self.h);
        for j in j0..j1 {
            let top = (j as f64).max(y0);
            let bottom = ((j + 1) as f64).min(y1);
            let c = (bottom - top).clamp(0.0, 1.0);
            if c > 0.0 {
                self.put(i, j, c as f32);
            }
        }
    }

    fn composite(&self, img: &mut RgbImage, plot: Rect, rgb: [u8; 3], alpha: f32) {
        for j in 0..self.h {
            for i in 0..self.w {
                let c = self.cov[j * self.w + i];
                if c > 0.0 {
                    blend(img, plot.x + i as i64, plot.y + j as i64, rgb, c * alpha);
                }
            }
        }
    }
}

/// Liang-Barsky clipping of segment `a`-`b` to `[x0, x1] x [y0, y1]`.
fn clip_segment(
    a: (f64, f64),
    b: (f64, f64),
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
) -> Option<((f64, f64), (f64, f64))> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let mut t0 = 0.0f64;
    let mut t1 = 1.0f64;
    for (p, q) in [
        (-dx, a.0 - x0),
        (dx, x1 - a.0),
        (-dy, a.1 - y0),
        (dy, y1 - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
            if t0 > t1 {
                return None;
            }
        }
    }
    Some((
        (a.0 + t0 * dx, a.1 + t0 * dy),
        (a.0 + t1 * dx, a.1 + t1 * dy),
    ))
}

// ---------------------------------------------------------------------------------------------
// Layout
// ---------------------------------------------------------------------------------------------

const WHITE: [u8; 3] = [255, 255, 255];
const TEXT: [u8; 3] = [20, 20, 20];
const AXIS: [u8; 3] = [60, 60, 60];
const GRID: [u8; 3] = [225, 225, 225];
const OFF_MAP: [u8; 3] = [232, 232, 232];
const BAND_ALPHA: f32 = 0.25;

/// Where the data goes: the plot rectangle and the data ranges mapped to it.
#[derive(Debug, Clone)]
struct Frame {
    img_w: u32,
    img_h: u32,
    scale: u32,
    title_scale: u32,
    plot: Rect,
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
    x_ticks: Vec<f64>,
    x_step: f64,
    y_ticks: Vec<f64>,
    y_step: f64,
}

impl Frame {
    /// Data -> plot-local pixel coordinates (continuous; y grows down), limited to +-1e7.
    fn to_local(&self, x: f64, y: f64) -> (f64, f64) {
        let u = (x / 2.0 - self.x0 / 2.0) / (self.x1 / 2.0 - self.x0 / 2.0) * self.plot.w as f64;
        let v = (self.y1 / 2.0 - y / 2.0) / (self.y1 / 2.0 - self.y0 / 2.0) * self.plot.h as f64;
        let lim = |t: f64| {
            if t.is_nan() {
                t
            } else {
                t.clamp(-COORD_LIMIT, COORD_LIMIT)
            }
        };
        (lim(u), lim(v))
    }

    /// Data -> image pixel index (the pixel containing the point), if finite.
    #[cfg(test)]
    fn to_pixel(&self, x: f64, y: f64) -> Option<(i64, i64)> {
        let (u, v) = self.to_local(x, y);
        (u.is_finite() && v.is_finite()).then(|| {
            (
                self.plot.x + u.floor() as i64,
                self.plot.y + v.floor() as i64,
            )
        })
    }
}

/// Finite min/max accumulator.
#[derive(Debug, Clone, Copy)]
struct Extent {
    lo: f64,
    hi: f64,
}

impl Extent {
    fn empty() -> Self {
        Extent {
            lo: f64::INFINITY,
            hi: f64::NEG_INFINITY,
        }
    }
    fn add(&mut self, v: f64) {
        if v.is_finite() {
            self.lo = self.lo.min(v);
            self.hi = self.hi.max(v);
        }
    }
    fn valid(&self) -> bool {
        self.lo <= self.hi
    }
}

/// Data extents of the finite points (a point counts only when both coordinates are finite).
fn data_extent(bands: &[Band], series: &[Series]) -> (Extent, Extent) {
    let mut ex = Extent::empty();
    let mut ey = Extent::empty();
    for s in series {
        for &(x, y) in &s.points {
            if x.is_finite() && y.is_finite() {
                ex.add(x);
                ey.add(y);
            }
        }
    }
    for b in bands {
        for &(x, lo, hi) in &b.points {
            if x.is_finite() && lo.is_finite() && hi.is_finite() {
                ex.add(x);
                ey.add(lo);
                ey.add(hi);
            }
        }
    }
    (ex, ey)
}

/// A usable (finite, increasing, non-empty) range from a requested or data range, with `pad`
/// relative margin on each side for data ranges.
fn usable_range(fixed: Option<(f64, f64)>, data: Extent, pad: f64) -> (f64, f64, bool) {
    if let Some((a, b)) = fixed
        && a.is_finite()
        && b.is_finite()
    {
        let (lo, hi) = (a.min(b), a.max(b));
        let (lo, hi) = widen_degenerate(lo, hi);
        return (lo, hi, true);
    }
    if !data.valid() {
        return (0.0, 1.0, false);
    }
    let (lo, hi) = widen_degenerate(data.lo, data.hi);
    let m = (hi / 2.0 - lo / 2.0) * 2.0 * pad;
    let (plo, phi) = (lo - m, hi + m);
    if plo.is_finite() && phi.is_finite() && plo < phi {
        (plo, phi, true)
    } else {
        (lo, hi, true)
    }
}

/// `lo == hi` (or a span too small to resolve) -> a range around the value.
fn widen_degenerate(lo: f64, hi: f64) -> (f64, f64) {
    let mid = lo / 2.0 + hi / 2.0;
    let tiny = mid.abs() * 1e-12;
    if hi - lo > tiny && (hi - lo) > 0.0 {
        return (lo, hi);
    }
    let d = if mid.abs() > 0.0 {
        mid.abs() * 0.05
    } else {
        1.0
    };
    let (a, b) = (mid - d, mid + d);
    if a < b && a.is_finite() && b.is_finite() {
        (a, b)
    } else {
        (mid - 1.0, mid + 1.0)
    }
}

/// Expands one of the ranges so that both axes have the same data units per pixel.
fn equalize(x: (f64, f64), y: (f64, f64), w: i64, h: i64) -> ((f64, f64), (f64, f64)) {
    let (w, h) = (w.max(1) as f64, h.max(1) as f64);
    let hx = x.1 / 2.0 - x.0 / 2.0;
    let hy = y.1 / 2.0 - y.0 / 2.0;
    let upp = (hx / w).max(hy / h); // half units per pixel
    let cx = x.0 / 2.0 + x.1 / 2.0;
    let cy = y.0 / 2.0 + y.1 / 2.0;
    let nx = (cx - upp * w, cx + upp * w);
    let ny = (cy - upp * h, cy + upp * h);
    let ok = |r: (f64, f64)| r.0.is_finite() && r.1.is_finite() && r.0 < r.1;
    if ok(nx) && ok(ny) { (nx, ny) } else { (x, y) }
}

fn auto_scale(spec: &PlotSpec, w: u32, h: u32) -> u32 {
    if spec.font_scale > 0 {
        spec.font_scale.min(16)
    } else {
        // 1 up to ~900 x 600 px, 2 for 1000 x 700, ...
        (w.min(h.saturating_mul(3) / 2) / 450).clamp(1, 4)
    }
}

/// Computes the plot rectangle, ranges and ticks. `has_data` is false when the x/y ranges do not
/// come from data or fixed ranges.
fn layout(
    spec: &PlotSpec,
    w: u32,
    h: u32,
    xr: (f64, f64),
    yr: (f64, f64),
    equal_aspect: bool,
) -> Frame {
    let s = auto_scale(spec, w, h);
    let si = i64::from(s);
    let (iw, ih) = (i64::from(w), i64::from(h));
    let pad = 6 * si;
    let char_h = i64::from(GLYPH_H) * si;
    let title_scale = {
        let big = s + 1;
        if i64::from(text_size(&spec.title, big).0) + 2 * pad <= iw {
            big
        } else {
            s
        }
    };
    let top = if spec.title.is_empty() {
        pad + char_h / 2
    } else {
        2 * pad + i64::from(GLYPH_H * title_scale)
    };
    let tick_len = 4 * si;
    let bottom = tick_len
        + 3 * si
        + char_h
        + if spec.x_label.is_empty() {
            pad
        } else {
            2 * pad + char_h
        };
    let right = 3 * i64::from(GLYPH_ADVANCE) * si;
    let plot_h = ih - top - bottom;
    let y_max_ticks = usize::try_from((plot_h / (char_h * 4)).max(2)).unwrap_or(2);
    let ylab_w = if spec.y_label.is_empty() {
        0
    } else {
        char_h + pad
    };

    let mut xr = xr;
    let mut yr = yr;
    let mut left = pad + ylab_w + tick_len + 3 * si + 4 * i64::from(GLYPH_ADVANCE) * si;
    let mut y_ticks = (Vec::new(), 0.0);
    // The left margin depends on the y tick labels, which depend on the range, which (equal
    // aspect) depends on the plot width: a few fixed-point passes settle it.
    for _ in 0..3 {
        let plot_w = iw - left - right;
        if equal_aspect {
            (xr, yr) = equalize(xr, yr, plot_w, plot_h);
        }
        y_ticks = nice_ticks_step(yr.0, yr.1, y_max_ticks);
        let labels = tick_labels(&y_ticks.0, y_ticks.1);
        let widest = labels
            .iter()
            .map(|l| i64::from(text_size(l, s).0))
            .max()
            .unwrap_or(0);
        let need = pad + ylab_w + tick_len + 3 * si + widest;
        if need <= left {
            break;
        }
        left = need;
    }
    let plot_w = iw - left - right;
    if equal_aspect {
        (xr, yr) = equalize(xr, yr, plot_w, plot_h);
        y_ticks = nice_ticks_step(yr.0, yr.1, y_max_ticks);
    }
    // x labels: leave room for about 8 characters per tick.
    let x_max_ticks =
        usize::try_from((plot_w / (10 * i64::from(GLYPH_ADVANCE) * si)).max(2)).unwrap_or(2);
    let mut x_ticks = nice_ticks_step(xr.0, xr.1, x_max_ticks);
    // Make sure the x labels do not overlap: thin the ticks if needed.
    let xl = tick_labels(&x_ticks.0, x_ticks.1);
    let widest_x = xl
        .iter()
        .map(|l| i64::from(text_size(l, s).0))
        .max()
        .unwrap_or(0);
    if x_ticks.0.len() >= 2 && plot_w > 0 {
        let spacing = plot_w as f64 * x_ticks.1 / (xr.1 / 2.0 - xr.0 / 2.0) / 2.0;
        if spacing < (widest_x + 2 * i64::from(GLYPH_ADVANCE) * si) as f64 {
            let n = (plot_w / (widest_x + 2 * i64::from(GLYPH_ADVANCE) * si)).max(1);
            x_ticks = nice_ticks_step(xr.0, xr.1, usize::try_from(n).unwrap_or(1));
        }
    }
    Frame {
        img_w: w,
        img_h: h,
        scale: s,
        title_scale,
        plot: Rect {
            x: left,
            y: top,
            w: plot_w,
            h: plot_h,
        },
        x0: xr.0,
        x1: xr.1,
        y0: yr.0,
        y1: yr.1,
        x_ticks: x_ticks.0,
        x_step: x_ticks.1,
        y_ticks: y_ticks.0,
        y_step: y_ticks.1,
    }
}

/// Smallest plot rectangle side worth drawing into.
const MIN_PLOT_PX: i64 = 8;

fn usable(frame: &Frame) -> bool {
    frame.plot.w >= MIN_PLOT_PX && frame.plot.h >= MIN_PLOT_PX
}

fn clamp_size(spec: &PlotSpec) -> (u32, u32) {
    (
        spec.width_px.clamp(1, MAX_SIDE_PX),
        spec.height_px.clamp(1, MAX_SIDE_PX),
    )
}

/// Title, axis labels, grid, ticks and tick labels. The grid is drawn before the data
/// (`grid_only`), the frame and labels after.
fn draw_grid(img: &mut RgbImage, f: &Frame) {
    let p = f.plot;
    for &t in &f.x_ticks {
        let (u, _) = f.to_local(t, f.y0);
        if u.is_finite() {
            let px = p.x + (u.floor() as i64).clamp(0, p.w - 1);
            vline(img, px, p.y, p.y + p.h - 1, GRID);
        }
    }
    for &t in &f.y_ticks {
        let (_, v) = f.to_local(f.x0, t);
        if v.is_finite() {
            let py = p.y + (v.floor() as i64).clamp(0, p.h - 1);
            hline(img, p.x, p.x + p.w - 1, py, GRID);
        }
    }
}

fn draw_axes(img: &mut RgbImage, f: &Frame, spec: &PlotSpec) {
    let p = f.plot;
    let s = f.scale;
    let si = i64::from(s);
    let tick_len = 4 * si;
    let char_h = i64::from(GLYPH_H) * si;
    stroke_rect(
        img,
        Rect {
            x: p.x - 1,
            y: p.y - 1,
            w: p.w + 2,
            h: p.h + 2,
        },
        AXIS,
    );
    let xl = tick_labels(&f.x_ticks, f.x_step);
    let mut last_right = i64::MIN;
    for (&t, l) in f.x_ticks.iter().zip(&xl) {
        let (u, _) = f.to_local(t, f.y0);
        if !u.is_finite() {
            continue;
        }
        let px = p.x + (u.floor() as i64).clamp(0, p.w - 1);
        for k in 0..si {
            vline(img, px - si / 2 + k, p.y + p.h, p.y + p.h + tick_len, AXIS);
        }
        let tw = i64::from(text_size(l, s).0);
        let lx = (px - tw / 2).clamp(0, (i64::from(f.img_w) - tw).max(0));
        if lx > last_right {
            draw_text(img, lx, p.y + p.h + tick_len + 3 * si, l, s, TEXT);
            last_right = lx + tw + i64::from(GLYPH_ADVANCE) * si;
        }
    }
    let yl = tick_labels(&f.y_ticks, f.y_step);
    for (&t, l) in f.y_ticks.iter().zip(&yl) {
        let (_, v) = f.to_local(f.x0, t);
        if !v.is_finite() {
            continue;
        }
        let py = p.y + (v.floor() as i64).clamp(0, p.h - 1);
        for k in 0..si {
            hline(img, p.x - 1 - tick_len, p.x - 1, py - si / 2 + k, AXIS);
        }
        let tw = i64::from(text_size(l, s).0);
        draw_text(
            img,
            p.x - 1 - tick_len - 3 * si - tw,
            py - i64::from(CAP_H) * si / 2,
            l,
            s,
            TEXT,
        );
    }
    // Title centred over the whole image (or left-aligned when it does not fit).
    if !spec.title.is_empty() {
        let ts = f.title_scale;
        let tw = i64::from(text_size(&spec.title, ts).0);
        let x = ((i64::from(f.img_w) - tw) / 2).max(2);
        draw_text(img, x, 6 * si, &spec.title, ts, TEXT);
    }
    if !spec.x_label.is_empty() {
        let tw = i64::from(text_size(&spec.x_label, s).0);
        let x = (p.x + (p.w - tw) / 2).max(2);
        let y = p.y + p.h + tick_len + 3 * si + char_h + 6 * si;
        draw_text(img, x, y, &spec.x_label, s, TEXT);
    }
    if !spec.y_label.is_empty() {
        let tw = i64::from(text_size(&spec.y_label, s).0);
        let y = (p.y + (p.h + tw) / 2).min(i64::from(f.img_h) - 2);
        draw_text_up(img, 6 * si, y, &spec.y_label, s, TEXT);
    }
}

/// "no data" (or another note) centred in the plot rectangle, or in the image when there is none.
fn draw_note(img: &mut RgbImage, f: &Frame, note: &str) {
    let s = f.scale;
    let (tw, th) = text_size(note, s);
    let (cx, cy) = if usable(f) {
        (f.plot.x + f.plot.w / 2, f.plot.y + f.plot.h / 2)
    } else {
        (i64::from(f.img_w) / 2, i64::from(f.img_h) / 2)
    };
    draw_text(
        img,
        cx - i64::from(tw) / 2,
        cy - i64::from(th) / 2,
        note,
        s,
        [150, 30, 30],
    );
}

fn line_half_width(scale: u32) -> f64 {
    (1.0 + f64::from(scale)) / 2.0
}

fn dot_radius(scale: u32) -> f64 {
    1.5 + f64::from(scale)
}

/// Rasterises one series into a fresh mask.
fn series_mask(f: &Frame, s: &Series, half_w: f64, dot_r: f64) -> Mask {
    let mut m = Mask::new(f.plot.w.max(0) as usize, f.plot.h.max(0) as usize);
    let pts: Vec<(f64, f64)> = s
        .points
        .iter()
        .map(|&(x, y)| {
            if x.is_finite() && y.is_finite() {
                f.to_local(x, y)
            } else {
                (f64::NAN, f64::NAN)
            }
        })
        .collect();
    let valid = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    if matches!(s.style, Style::Line | Style::LineDots) {
        let mut prev: Option<(f64, f64)> = None;
        let mut run_len = 0usize;
        for p in &pts {
            if valid(p) {
                if let Some(q) = prev {
                    m.segment(q, *p, half_w);
                }
                prev = Some(*p);
                run_len += 1;
            } else {
                // A lone point between gaps would be invisible as a line: draw it as a dot.
                if run_len == 1
                    && let Some(q) = prev
                {
                    m.disc(q, dot_r);
                }
                prev = None;
                run_len = 0;
            }
        }
        if run_len == 1
            && let Some(q) = prev
        {
            m.disc(q, dot_r);
        }
    }
    if matches!(s.style, Style::Dots | Style::LineDots) {
        for p in pts.iter().filter(|p| valid(p)) {
            m.disc(*p, dot_r);
        }
    }
    m
}

fn band_mask(f: &Frame, b: &Band) -> Mask {
    let mut m = Mask::new(f.plot.w.max(0) as usize, f.plot.h.max(0) as usize);
    let mut prev: Option<(f64, f64, f64)> = None;
    for &(x, lo, hi) in &b.points {
        if !(x.is_finite() && lo.is_finite() && hi.is_finite()) {
            prev = None;
            continue;
        }
        let (u, vlo) = f.to_local(x, lo);
        let (_, vhi) = f.to_local(x, hi);
        let cur = (u, vlo, vhi);
        if let Some(p) = prev {
            let (a, b) = if p.0 <= cur.0 { (p, cur) } else { (cur, p) };
            let i0 = a.0.floor().max(0.0);
            let i1 = b.0.ceil().min(m.w as f64);
            let mut i = i0;
            while i < i1 {
                let cx = i + 0.5;
                let t = if b.0 > a.0 {
                    ((cx - a.0) / (b.0 - a.0)).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                if cx >= a.0 - 0.5 && cx <= b.0 + 0.5 {
                    let y_lo = a.1 + t * (b.1 - a.1);
                    let y_hi = a.2 + t * (b.2 - a.2);
                    m.span(i as usize, y_hi, y_lo);
                }
                i += 1.0;
            }
        } else {
            // A single column for an isolated point.
            if u >= 0.0 && u < m.w as f64 {
                m.span(u as usize, vhi, vlo);
            }
        }
        prev = Some(cur);
    }
    m
}

#[derive(Debug, Clone, Copy)]
enum Swatch {
    Band,
    Series(Style),
}

/// Legend box in the corner of the plot rectangle holding the fewest data points.
fn draw_legend(
    img: &mut RgbImage,
    f: &Frame,
    entries: &[(String, [u8; 3], Swatch)],
    points: &[(f64, f64)],
) {
    let entries: Vec<_> = entries.iter().filter(|e| !e.0.is_empty()).collect();
    if entries.is_empty() || !usable(f) {
        return;
    }
    let s = f.scale;
    let si = i64::from(s);
    let pad = 5 * si;
    let row_h = i64::from(GLYPH_H) * si + 5 * si;
    let sw_w = 18 * si;
    let text_w = entries
        .iter()
        .map(|e| i64::from(text_size(&e.0, s).0))
        .max()
        .unwrap_or(0);
    let bw = pad + sw_w + pad + text_w + pad;
    let bh = pad + row_h * entries.len() as i64 - 5 * si + pad;
    let p = f.plot;
    let m = 6 * si;
    let corners = [
        (p.x + p.w - m - bw, p.y + m),
        (p.x + m, p.y + m),
        (p.x + p.w - m - bw, p.y + p.h - m - bh),
        (p.x + m, p.y + p.h - m - bh),
    ];
    let best = corners
        .iter()
        .map(|&(x, y)| {
            let r = Rect { x, y, w: bw, h: bh };
            let n = points
                .iter()
                .filter(|&&(u, v)| {
                    u.is_finite() && v.is_finite() && r.contains(p.x + u as i64, p.y + v as i64)
                })
                .count();
            (n, r)
        })
        .min_by_key(|(n, _)| *n)
        .map(|(_, r)| r)
        .unwrap_or(Rect {
            x: corners[0].0,
            y: corners[0].1,
            w: bw,
            h: bh,
        });
    let box_r = Rect {
        x: best.x.max(p.x),
        y: best.y.max(p.y),
        w: bw,
        h: bh,
    };
    if !box_r.intersects(&p) {
        return;
    }
    fill_rect(img, box_r, WHITE, 0.88);
    stroke_rect(img, box_r, [150, 150, 150]);
    let half_w = line_half_width(s);
    for (k, (name, rgb, sw)) in entries.iter().enumerate() {
        let ry = box_r.y + pad + k as i64 * row_h;
        let cy = ry + i64::from(CAP_H) * si / 2;
        let sx = box_r.x + pad;
        let mut mk = Mask::new((sw_w + 2) as usize, (row_h + 2) as usize);
        let local_cy = (cy - ry) as f64 + 1.5;
        match sw {
            Swatch::Band => {
                fill_rect(
                    img,
                    Rect {
                        x: sx,
                        y: ry,
                        w: sw_w,
                        h: i64::from(GLYPH_H) * si,
                    },
                    *rgb,
                    BAND_ALPHA * 1.6,
                );
            }
            Swatch::Series(style) => {
                if matches!(style, Style::Line | Style::LineDots) {
                    mk.segment(
                        (1.0 + half_w, local_cy),
                        (sw_w as f64 + 1.0 - half_w, local_cy),
                        half_w,
                    );
                }
                if matches!(style, Style::Dots | Style::LineDots) {
                    mk.disc((sw_w as f64 / 2.0 + 1.0, local_cy), dot_radius(s));
                }
            }
        }
        mk.composite(
            img,
            Rect {
                x: sx - 1,
                y: ry - 1,
                w: sw_w + 2,
                h: row_h + 2,
            },
            *rgb,
            1.0,
        );
        draw_text(img, sx + sw_w + pad, ry, name, s, TEXT);
    }
}

fn legend_entries(bands: &[Band], series: &[Series]) -> Vec<(String, [u8; 3], Swatch)> {
    bands
        .iter()
        .map(|b| (b.name.clone(), b.rgb, Swatch::Band))
        .chain(
            series
                .iter()
                .map(|s| (s.name.clone(), s.rgb, Swatch::Series(s.style))),
        )
        .collect()
}

/// Plot-local positions of all finite data points (for the legend placement).
fn local_points(f: &Frame, bands: &[Band], series: &[Series]) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for s in series {
        for &(x, y) in &s.points {
            if x.is_finite() && y.is_finite() {
                out.push(f.to_local(x, y));
            }
        }
    }
    for b in bands {
        for &(x, lo, hi) in &b.points {
            if x.is_finite() && lo.is_finite() && hi.is_finite() {
                out.push(f.to_local(x, lo));
                out.push(f.to_local(x, hi));
                out.push(f.to_local(x, lo / 2.0 + hi / 2.0));
            }
        }
    }
    out
}

fn has_finite(bands: &[Band], series: &[Series]) -> bool {
    let (ex, ey) = data_extent(bands, series);
    ex.valid() && ey.valid()
}

// ---------------------------------------------------------------------------------------------
// Public plots
// ---------------------------------------------------------------------------------------------

/// Layout of a chart (shared by [`chart`] and the tests).
fn chart_frame(spec: &PlotSpec, bands: &[Band], series: &[Series]) -> Frame {
    let (w, h) = clamp_size(spec);
    let (ex, ey) = data_extent(bands, series);
    let (x0, x1, _) = usable_range(spec.x_range, ex, 0.02);
    let (y0, y1, _) = usable_range(spec.y_range, ey, 0.05);
    layout(spec, w, h, (x0, x1), (y0, y1), spec.equal_aspect)
}

/// Line/scatter chart: axes with "nice" ticks (1-2-5 steps), grid lines, tick labels, title, axis
/// labels, legend box (series and bands), data clipped to the plot area. Bands are drawn first
/// (25 % opacity), then the series in order (later ones on top).
pub fn chart(spec: &PlotSpec, bands: &[Band], series: &[Series]) -> RgbImage {
    let f = chart_frame(spec, bands, series);
    let mut img = RgbImage::from_pixel(f.img_w, f.img_h, Rgb(WHITE));
    if !usable(&f) {
        draw_note(&mut img, &f, "no data");
        return img;
    }
    draw_grid(&mut img, &f);
    for b in bands {
        band_mask(&f, b).composite(&mut img, f.plot, b.rgb, BAND_ALPHA);
    }
    let (hw, dr) = (line_half_width(f.scale), dot_radius(f.scale));
    for s in series {
        series_mask(&f, s, hw, dr).composite(&mut img, f.plot, s.rgb, 1.0);
    }
    draw_axes(&mut img, &f, spec);
    if !has_finite(bands, series) {
        draw_note(&mut img, &f, "no data");
    }
    draw_legend(
        &mut img,
        &f,
        &legend_entries(bands, series),
        &local_points(&f, bands, series),
    );
    img
}

/// A background usable for [`track`]: non-empty image and a finite, non-degenerate extent.
fn valid_background(bg: Option<(&RgbImage, [f64; 4])>) -> Option<(&RgbImage, [f64; 4])> {
    bg.filter(|(im, e)| {
        im.width() > 0
            && im.height() > 0
            && e.iter().all(|v| v.is_finite())
            && e[2] > e[0]
            && e[3] > e[1]
            && (e[2] / 2.0 - e[0] / 2.0).is_finite()
    })
}

/// Layout of a track plot (shared by [`track`] and the tests).
fn track_frame(spec: &PlotSpec, bg: Option<(&RgbImage, [f64; 4])>, series: &[Series]) -> Frame {
    let (w, h) = clamp_size(spec);
    let (ex, ey) = data_extent(&[], series);
    let (mut ex, mut ey) = (ex, ey);
    // A margin of 8 % of the larger side (at least 20 m) around the track, 2 % around a
    // background shown alone.
    let mut rel_margin = 0.08;
    if !(ex.valid() && ey.valid())
        && let Some((_, e)) = bg
    {
        ex = Extent { lo: e[0], hi: e[2] };
        ey = Extent { lo: e[1], hi: e[3] };
        rel_margin = 0.02;
    }
    let span = (ex.hi / 2.0 - ex.lo / 2.0).max(ey.hi / 2.0 - ey.lo / 2.0) * 2.0;
    let margin = if span.is_finite() {
        (span * rel_margin).max(20.0)
    } else {
        0.0
    };
    let pad_ext = |e: Extent| {
        if e.valid() && (e.lo - margin).is_finite() && (e.hi + margin).is_finite() {
            Extent {
                lo: e.lo - margin,
                hi: e.hi + margin,
            }
        } else {
            e
        }
    };
    let (x0, x1, _) = usable_range(spec.x_range, pad_ext(ex), 0.0);
    let (y0, y1, _) = usable_range(spec.y_range, pad_ext(ey), 0.0);
    layout(spec, w, h, (x0, x1), (y0, y1), true)
}

/// Draws the background (bilinear, faded towards white by 35 %) under the plot rectangle.
fn draw_background(img: &mut RgbImage, f: &Frame, bg: &RgbImage, e: [f64; 4]) {
    let p = f.plot;
    let (bw, bh) = (bg.width() as f64, bg.height() as f64);
    let sx = bw / (e[2] - e[0]);
    let sy = bh / (e[3] - e[1]);
    let upx = (f.x1 - f.x0) / p.w as f64;
    let upy = (f.y1 - f.y0) / p.h as f64;
    for j in 0..p.h {
        let y = f.y1 - (j as f64 + 0.5) * upy;
        let row = (e[3] - y) * sy - 0.5;
        for i in 0..p.w {
            let x = f.x0 + (i as f64 + 0.5) * upx;
            let col = (x - e[0]) * sx - 0.5;
            let rgb = if row >= -0.5 && row <= bh - 0.5 && col >= -0.5 && col <= bw - 0.5 {
                let c = bilinear(bg, col, row);
                let g = 0.3 * c[0] + 0.59 * c[1] + 0.11 * c[2];
                let mut o = [0u8; 3];
                for k in 0..3 {
                    // 25 % desaturated, then faded 35 % towards white.
                    let v = 0.75 * c[k] + 0.25 * g;
                    o[k] = (0.65 * v + 0.35 * 255.0).round().clamp(0.0, 255.0) as u8;
                }
                o
            } else {
                OFF_MAP
            };
            img.put_pixel((p.x + i) as u32, (p.y + j) as u32, Rgb(rgb));
        }
    }
}

fn bilinear(im: &RgbImage, col: f64, row: f64) -> [f64; 3] {
    let (w, h) = (i64::from(im.width()), i64::from(im.height()));
    let c0 = col.floor();
    let r0 = row.floor();
    let (fc, fr) = (col - c0, row - r0);
    let px = |c: i64, r: i64| {
        im.get_pixel(c.clamp(0, w - 1) as u32, r.clamp(0, h - 1) as u32)
            .0
    };
    let (c0, r0) = (c0 as i64, r0 as i64);
    let a = px(c0, r0);
    let b = px(c0 + 1, r0);
    let c = px(c0, r0 + 1);
    let d = px(c0 + 1, r0 + 1);
    let mut o = [0.0; 3];
    for k in 0..3 {
        let top = f64::from(a[k]) * (1.0 - fc) + f64::from(b[k]) * fc;
        let bot = f64::from(c[k]) * (1.0 - fc) + f64::from(d[k]) * fc;
        o[k] = top * (1.0 - fr) + bot * fr;
    }
    o
}

/// Map track plot: a georeferenced background image (e.g. the orthophoto, RGB) covering the map
/// rectangle `extent = [min_x, min_y, max_x, max_y]` (x east, y north, metres; image row 0 = north
/// edge) drawn under the series with equal aspect, the ranges fitted to the series (plus margin) or
/// to the background; axis ticks in metres; legend. Lines get a thin white halo so they stay visible
/// on dark imagery.
pub fn track(
    spec: &PlotSpec,
    background: Option<(&RgbImage, [f64; 4])>,
    series: &[Series],
) -> RgbImage {
    let bg = valid_background(background);
    let f = track_frame(spec, bg, series);
    let mut img = RgbImage::from_pixel(f.img_w, f.img_h, Rgb(WHITE));
    if !usable(&f) {
        draw_note(&mut img, &f, "no data");
        return img;
    }
    if let Some((im, e)) = bg {
        draw_background(&mut img, &f, im, e);
    }
    draw_grid_over_map(&mut img, &f, bg.is_some());
    let (hw, dr) = (line_half_width(f.scale), dot_radius(f.scale));
    for s in series {
        let halo = series_mask(&f, s, hw + 1.0, dr + 1.0);
        halo.composite(&mut img, f.plot, WHITE, 0.8);
        series_mask(&f, s, hw, dr).composite(&mut img, f.plot, s.rgb, 1.0);
    }
    draw_axes(&mut img, &f, spec);
    if !has_finite(&[], series) && bg.is_none() {
        draw_note(&mut img, &f, "no data");
    }
    draw_legend(
        &mut img,
        &f,
        &legend_entries(&[], series),
        &local_points(&f, &[], series),
    );
    img
}

/// Grid lines for the track plot: light gray on white, translucent white over imagery.
fn draw_grid_over_map(img: &mut RgbImage, f: &Frame, over_image: bool) {
    if !over_image {
        draw_grid(img, f);
        return;
    }
    let p = f.plot;
    for &t in &f.x_ticks {
        let (u, _) = f.to_local(t, f.y0);
        if u.is_finite() {
            let px = p.x + (u.floor() as i64).clamp(0, p.w - 1);
            for py in p.y..p.y + p.h {
                blend(img, px, py, WHITE, 0.35);
            }
        }
    }
    for &t in &f.y_ticks {
        let (_, v) = f.to_local(f.x0, t);
        if v.is_finite() {
            let py = p.y + (v.floor() as i64).clamp(0, p.h - 1);
            for px in p.x..p.x + p.w {
                blend(img, px, py, WHITE, 0.35);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const RED: [u8; 3] = [220, 20, 30];
    const BLUE: [u8; 3] = [20, 60, 220];

    fn spec(w: u32, h: u32) -> PlotSpec {
        PlotSpec::new(w, h, "Title: test (sigma) 1.5%", "time [s]", "error [m]")
    }

    fn count_rgb(img: &RgbImage, rgb: [u8; 3]) -> usize {
        img.pixels().filter(|p| p.0 == rgb).count()
    }

    fn target_dir() -> PathBuf {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("target")
    }

    #[test]
    fn nice_ticks_examples() {
        assert_eq!(
            nice_ticks(0.0, 10.0, 5),
            vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
        );
        assert_eq!(
            nice_ticks(10.0, 0.0, 5),
            vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]
        );
        assert_eq!(nice_ticks(-3.0, 7.0, 2), vec![0.0, 5.0]);
        assert_eq!(nice_ticks(3.0, 3.0, 5), vec![3.0]);
        assert!(nice_ticks(f64::NAN, 1.0, 5).is_empty());
        assert!(nice_ticks(0.0, f64::INFINITY, 5).is_empty());
        assert!(nice_ticks(0.0, 1.0, 0).is_empty());
        // Extreme but finite ranges do not panic and stay bounded.
        assert!(nice_ticks(-f64::MAX, f64::MAX, 4).len() <= 5);
        assert!(nice_ticks(1e300, 1e300 * (1.0 + 1e-15), 4).len() <= 5);
    }

    #[test]
    fn tick_labels_are_compact() {
        let (t, s) = nice_ticks_step(0.0, 1.0, 5);
        assert_eq!(
            tick_labels(&t, s),
            vec!["0.0", "0.2", "0.4", "0.6", "0.8", "1.0"]
        );
        let (t, s) = nice_ticks_step(5_234_000.0, 5_236_000.0, 4);
        assert_eq!(tick_labels(&t, s)[0], "5234000");
        let (t, s) = nice_ticks_step(-1e12, 1e12, 4);
        assert!(
            tick_labels(&t, s)
                .iter()
                .all(|l| l.contains('e') || l == "0")
        );
    }

    proptest! {
        #[test]
        fn nice_ticks_properties(lo in -1e6f64..1e6, span in 1e-6f64..1e6, max_ticks in 1usize..30) {
            let hi = lo + span;
            prop_assume!(hi > lo);
            let (ticks, step) = nice_ticks_step(lo, hi, max_ticks);
            prop_assert!(!ticks.is_empty() || step > span * 0.5);
            prop_assert!(ticks.len() <= max_ticks + 1);
            // step = m 10^k with m in {1, 2, 5}
            let k = step.log10().floor();
            let m = step / 10f64.powf(k);
            prop_assert!([1.0, 2.0, 5.0, 10.0].iter().any(|c| (m - c).abs() < 1e-9), "step {}", step);
            for w in ticks.windows(2) {
                prop_assert!(w[1] > w[0]);
                prop_assert!(((w[1] - w[0]) - step).abs() <= step * 1e-6 + hi.abs().max(lo.abs()) * 1e-12);
            }
            for &t in &ticks {
                prop_assert!(t >= lo - step && t <= hi + step, "tick {} outside [{}, {}] +- {}", t, lo, hi, step);
                // A multiple of the step.
                let q = t / step;
                prop_assert!((q - q.round()).abs() < 1e-6);
            }
            // The step is the smallest nice step covering the range in max_ticks intervals.
            prop_assert!(step * max_ticks as f64 >= span * (1.0 - 1e-9));
        }
    }

    #[test]
    fn glyphs_render_with_fixed_advance() {
        for scale in 1..=3 {
            let text = "Abc 0.5-+:/()%=_,[]sigma";
            let (w, h) = text_size(text, scale);
            assert_eq!(w, text.chars().count() as u32 * GLYPH_ADVANCE * scale);
            assert_eq!(h, GLYPH_H * scale);
            let mut img = RgbImage::from_pixel(w + 20, h + 20, Rgb(WHITE));
            draw_text(&mut img, 10, 10, text, scale, TEXT);
            let ink: Vec<(u32, u32)> = img
                .enumerate_pixels()
                .filter(|(_, _, p)| p.0 == TEXT)
                .map(|(x, y, _)| (x, y))
                .collect();
            assert!(!ink.is_empty());
            // All ink inside the text box.
            assert!(
                ink.iter()
                    .all(|&(x, y)| x >= 10 && x < 10 + w && y >= 10 && y < 10 + h)
            );
            // First and last characters reach near the box edges.
            assert!(ink.iter().any(|&(x, _)| x < 10 + scale));
            assert!(
                ink.iter()
                    .any(|&(x, _)| x >= 10 + w - GLYPH_ADVANCE * scale)
            );
        }
        // Every printable character except the space has ink, and distinct glyphs for letters.
        for c in '!'..='~' {
            assert!(glyph(c).iter().any(|&b| b != 0), "glyph {c:?} empty");
        }
        assert_ne!(glyph('a'), glyph('A'));
        assert_eq!(glyph('\u{3c3}'), glyph('?'));
    }

    #[test]
    fn point_colour_appears_where_it_maps_and_nowhere_else() {
        let sp = spec(600, 400);
        let series = vec![Series::new(
            "truth",
            RED,
            Style::Dots,
            vec![(0.0, 0.0), (10.0, 5.0), (3.0, 2.0)],
        )];
        let f = chart_frame(&sp, &[], &series);
        let img = chart(&sp, &[], &series);
        let r = dot_radius(f.scale);
        let centres: Vec<(i64, i64)> = series[0]
            .points
            .iter()
            .map(|&(x, y)| f.to_pixel(x, y).expect("finite"))
            .collect();
        for &(px, py) in &centres {
            assert!(f.plot.contains(px, py));
            assert_eq!(img.get_pixel(px as u32, py as u32).0, RED);
        }
        // Every other exact-colour pixel is within a dot radius of a point, or in the legend row.
        let legend_y = f.plot.y + f.plot.h / 2; // the legend sits in a corner, not mid-height
        let mut outside = 0;
        for (x, y, p) in img.enumerate_pixels() {
            if p.0 != RED {
                continue;
            }
            let near = centres.iter().any(|&(cx, cy)| {
                let (dx, dy) = (x as f64 + 0.5 - cx as f64, y as f64 + 0.5 - cy as f64);
                (dx * dx + dy * dy).sqrt() <= r + 1.5
            });
            if !near {
                outside += 1;
                // The legend swatch: near a plot corner band, never in the middle rows.
                assert!(
                    (i64::from(y) - legend_y).abs() > f.plot.h / 4,
                    "stray at {x},{y}"
                );
            }
        }
        assert!(outside > 0, "legend swatch expected");
    }

    #[test]
    fn nan_breaks_the_line() {
        let sp = PlotSpec {
            y_range: Some((-1.0, 1.0)),
            ..spec(600, 400)
        };
        let series = vec![Series::new(
            "",
            BLUE,
            Style::Line,
            vec![
                (0.0, 0.0),
                (1.0, 0.0),
                (f64::NAN, f64::NAN),
                (3.0, 0.0),
                (4.0, 0.0),
            ],
        )];
        let f = chart_frame(&sp, &[], &series);
        let img = chart(&sp, &[], &series);
        let (x1, y) = f.to_pixel(1.0, 0.0).expect("finite");
        let (x3, _) = f.to_pixel(3.0, 0.0).expect("finite");
        let x0 = f.to_pixel(0.0, 0.0).expect("finite").0;
        let blueish = |p: &Rgb<u8>| p.0[2] > 150 && p.0[0] < 150;
        // Both segments are drawn ...
        assert!(blueish(img.get_pixel(((x0 + x1) / 2) as u32, y as u32)));
        assert!(blueish(
            img.get_pixel(((x1 + x3) / 2 + (x3 - x1)) as u32, y as u32)
        ));
        // ... and nothing between them.
        let hw = line_half_width(f.scale).ceil() as i64 + 2;
        for px in x1 + hw..x3 - hw {
            for py in y - 3..=y + 3 {
                let p = img.get_pixel(px as u32, py as u32);
                assert!(!blueish(p), "line pixel in the gap at {px},{py}");
            }
        }
        // Without the NaN the gap is filled.
        let joined = vec![Series::new(
            "",
            BLUE,
            Style::Line,
            vec![(0.0, 0.0), (1.0, 0.0), (3.0, 0.0), (4.0, 0.0)],
        )];
        let img2 = chart(&sp, &[], &joined);
        assert!(blueish(img2.get_pixel(((x1 + x3) / 2) as u32, y as u32)));
    }

    #[test]
    fn band_is_shaded_between_lo_and_hi() {
        let sp = PlotSpec {
            y_range: Some((-10.0, 10.0)),
            x_range: Some((0.0, 10.0)),
            ..spec(600, 400)
        };
        let bands = vec![Band {
            name: "+-3 sigma".into(),
            rgb: BLUE,
            points: (0..=10).map(|i| (f64::from(i), -3.0, 3.0)).collect(),
        }];
        let f = chart_frame(&sp, &bands, &[]);
        let img = chart(&sp, &bands, &[]);
        let tinted = |x: f64, y: f64| {
            let (px, py) = f.to_pixel(x, y).expect("finite");
            let p = img.get_pixel(px as u32, py as u32).0;
            i32::from(p[2]) - i32::from(p[0]) > 30
        };
        for x in [1.3, 4.7, 6.1] {
            for y in [-2.5, 0.3, 2.5] {
                assert!(tinted(x, y), "no shade at {x},{y}");
            }
            for y in [-5.3, 4.1, 8.7] {
                assert!(!tinted(x, y), "shade outside at {x},{y}");
            }
        }
    }

    /// Centroid of the pixels of exactly `rgb` inside the plot rectangle.
    fn centroid(img: &RgbImage, f: &Frame, rgb: [u8; 3]) -> (f64, f64) {
        let (mut sx, mut sy, mut n) = (0.0, 0.0, 0.0);
        for (x, y, p) in img.enumerate_pixels() {
            if p.0 == rgb && f.plot.contains(i64::from(x), i64::from(y)) {
                sx += f64::from(x);
                sy += f64::from(y);
                n += 1.0;
            }
        }
        assert!(n > 0.0);
        (sx / n, sy / n)
    }

    #[test]
    fn equal_aspect_gives_equal_metres_per_pixel() {
        let c = [[200, 0, 0], [0, 200, 0], [0, 0, 200]];
        // A wide data range in x, narrow in y, on a tall image: y must be stretched.
        let mk = |p: (f64, f64), k: usize| Series::new("", c[k], Style::Dots, vec![p]);
        let series = vec![
            mk((0.0, 0.0), 0),
            mk((100.0, 0.0), 1),
            mk((0.0, 100.0), 2),
            Series::new(
                "",
                [9, 9, 9],
                Style::Line,
                vec![(-300.0, 0.0), (800.0, 40.0)],
            ),
        ];
        for (w, h) in [(500, 700), (900, 400)] {
            for img_f in [
                {
                    let sp = PlotSpec {
                        equal_aspect: true,
                        ..spec(w, h)
                    };
                    let f = chart_frame(&sp, &[], &series);
                    (chart(&sp, &[], &series), f)
                },
                {
                    let sp = spec(w, h);
                    let f = track_frame(&sp, None, &series);
                    (track(&sp, None, &series), f)
                },
            ] {
                let (img, f) = img_f;
                let o = centroid(&img, &f, c[0]);
                let e = centroid(&img, &f, c[1]);
                let n = centroid(&img, &f, c[2]);
                let east_px = e.0 - o.0;
                let north_px = o.1 - n.1;
                assert!(east_px > 5.0 && north_px > 5.0);
                assert!(
                    (east_px - north_px).abs() <= 1.0,
                    "{w}x{h}: 100 m east = {east_px} px, 100 m north = {north_px} px"
                );
                assert!((e.1 - o.1).abs() < 0.5 && (n.0 - o.0).abs() < 0.5);
                let mppx = (f.x1 - f.x0) / f.plot.w as f64;
                let mppy = (f.y1 - f.y0) / f.plot.h as f64;
                assert!((mppx / mppy - 1.0).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn track_background_is_georeferenced() {
        // Background: west half red, east half blue, extent 0..200 x 0..100 m; north-west
        // quarter green (row 0 = north).
        let mut bg = RgbImage::from_pixel(20, 10, Rgb([255, 0, 0]));
        for y in 0..10 {
            for x in 10..20 {
                bg.put_pixel(x, y, Rgb([0, 0, 255]));
            }
        }
        for y in 0..5 {
            for x in 0..10 {
                bg.put_pixel(x, y, Rgb([0, 255, 0]));
            }
        }
        let extent = [0.0, 0.0, 200.0, 100.0];
        let sp = spec(600, 400);
        let f = track_frame(&sp, Some((&bg, extent)), &[]);
        let img = track(&sp, Some((&bg, extent)), &[]);
        let at = |x: f64, y: f64| {
            let (px, py) = f.to_pixel(x, y).expect("finite");
            img.get_pixel(px as u32, py as u32).0
        };
        let dominant = |p: [u8; 3]| (0..3).max_by_key(|&k| p[k]).unwrap_or(0);
        assert_eq!(dominant(at(30.0, 20.0)), 0, "south-west red");
        assert_eq!(dominant(at(170.0, 50.0)), 2, "east blue");
        assert_eq!(dominant(at(30.0, 80.0)), 1, "north-west green");
        // Dimmed: not the raw colour.
        assert_ne!(at(30.0, 20.0), [255, 0, 0]);
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let nan = f64::NAN;
        let cases: Vec<Vec<Series>> = vec![
            vec![],
            vec![Series::new("empty", RED, Style::Line, vec![])],
            vec![Series::new(
                "nan",
                RED,
                Style::LineDots,
                vec![(nan, nan), (nan, 1.0)],
            )],
            vec![Series::new("one", RED, Style::Line, vec![(3.0, 4.0)])],
            vec![Series::new(
                "flat",
                RED,
                Style::Line,
                vec![(3.0, 4.0), (3.0, 4.0)],
            )],
            vec![Series::new(
                "huge",
                RED,
                Style::LineDots,
                vec![(-f64::MAX, f64::MAX), (f64::MAX, -f64::MAX), (0.0, 1e-300)],
            )],
            vec![Series::new(
                "inf",
                RED,
                Style::Line,
                vec![(f64::INFINITY, 1.0), (0.0, f64::NEG_INFINITY), (1.0, 2.0)],
            )],
        ];
        let bands = [
            vec![],
            vec![Band {
                name: "b".into(),
                rgb: BLUE,
                points: vec![(nan, 1.0, 2.0), (1.0, 5.0, -5.0), (1.0, 1.0, 1.0)],
            }],
        ];
        let ranges = [
            None,
            Some((1.0, 1.0)),
            Some((5.0, -5.0)),
            Some((nan, 1.0)),
            Some((-f64::MAX, f64::MAX)),
        ];
        let bg = RgbImage::from_pixel(4, 3, Rgb([10, 200, 10]));
        let empty_bg = RgbImage::new(0, 0);
        for (w, h) in [(0, 0), (1, 1), (30, 20), (90, 60), (400, 300), (100_000, 3)] {
            for s in &cases {
                for b in &bands {
                    for r in ranges {
                        let sp = PlotSpec {
                            x_range: r,
                            y_range: r,
                            ..spec(w, h)
                        };
                        let img = chart(&sp, b, s);
                        assert!(img.width() >= 1 && img.height() >= 1);
                        assert!(img.width() <= MAX_SIDE_PX);
                        let eq = PlotSpec {
                            equal_aspect: true,
                            ..sp.clone()
                        };
                        chart(&eq, b, s);
                    }
                }
                let sp = spec(w, h);
                for bgd in [
                    None,
                    Some((&bg, [0.0, 0.0, 10.0, 10.0])),
                    Some((&bg, [0.0, 0.0, 0.0, 10.0])),
                    Some((&bg, [nan, 0.0, 1.0, 10.0])),
                    Some((&bg, [-f64::MAX, -f64::MAX, f64::MAX, f64::MAX])),
                    Some((&empty_bg, [0.0, 0.0, 10.0, 10.0])),
                ] {
                    track(&sp, bgd, s);
                }
            }
        }
    }

    #[test]
    fn no_data_note_is_written() {
        let sp = spec(400, 300);
        let empty = chart(&sp, &[], &[]);
        let nan = chart(
            &sp,
            &[],
            &[Series::new("x", RED, Style::Line, vec![(f64::NAN, 1.0)])],
        );
        let note = [150, 30, 30];
        assert!(count_rgb(&empty, note) > 10);
        assert!(count_rgb(&nan, note) > 10);
        let data = chart(
            &sp,
            &[],
            &[Series::new(
                "x",
                RED,
                Style::Line,
                vec![(0.0, 1.0), (1.0, 2.0)],
            )],
        );
        assert_eq!(count_rgb(&data, note), 0);
        assert!(count_rgb(&track(&sp, None, &[]), note) > 10);
    }

    #[test]
    fn save_png_names_the_path_on_error() {
        let img = RgbImage::new(2, 2);
        let bad = Path::new("/nonexistent-dir-visnav/x.png");
        let err = save_png(&img, bad).expect_err("cannot write there");
        assert!(err.to_string().contains("/nonexistent-dir-visnav/x.png"));
    }

    #[test]
    fn demo_chart_png() {
        let t: Vec<f64> = (0..=600).map(|i| f64::from(i) * 0.5).collect();
        let sigma: Vec<f64> = t.iter().map(|&t| 4.0 + 12.0 * (t / 300.0)).collect();
        let err: Vec<(f64, f64)> = t
            .iter()
            .zip(&sigma)
            .map(|(&t, &s)| (t, s * 0.9 * (t * 0.07).sin() * (t * 0.011).cos()))
            .collect();
        let mut err = err;
        for p in err.iter_mut().skip(250).take(20) {
            p.1 = f64::NAN; // a data gap
        }
        let fixes: Vec<(f64, f64)> = (0..30)
            .map(|i| {
                let t = f64::from(i) * 10.0 + 3.0;
                (t, 6.0 * (f64::from(i) * 1.7).sin())
            })
            .collect();
        let band = Band {
            name: "+-3 sigma".into(),
            rgb: [40, 90, 220],
            points: t
                .iter()
                .zip(&sigma)
                .map(|(&t, &s)| (t, -3.0 * s, 3.0 * s))
                .collect(),
        };
        let sp = PlotSpec::new(
            1000,
            600,
            "North position error, scenario naip_nd (sigma from EKF)",
            "time since start [s]",
            "north error [m]",
        );
        let img = chart(
            &sp,
            &[band],
            &[
                Series::new("EKF - truth", [200, 30, 30], Style::Line, err),
                Series::new("vision fix - truth", [20, 140, 40], Style::Dots, fixes),
            ],
        );
        let path = target_dir().join("plot_demo_chart.png");
        save_png(&img, &path).expect("target/ is writable");
        eprintln!("wrote {}", path.display());
        // Small and degenerate plots, for looking at the layout.
        let small = PlotSpec::new(320, 220, "one point", "x [s]", "y [m]");
        let one = chart(
            &small,
            &[],
            &[Series::new(
                "p",
                [200, 30, 30],
                Style::Line,
                vec![(5.0, 5.0)],
            )],
        );
        save_png(&one, &target_dir().join("plot_demo_small.png")).expect("target/ is writable");
        let none = chart(&small, &[], &[]);
        save_png(&none, &target_dir().join("plot_demo_nodata.png")).expect("target/ is writable");
        // Font sheet, for looking at the glyphs.
        let mut sheet = RgbImage::from_pixel(700, 90, Rgb(WHITE));
        let all: String = (' '..='~').collect();
        let (a, b) = all.split_at(48);
        draw_text(&mut sheet, 5, 5, a, 2, TEXT);
        draw_text(&mut sheet, 5, 30, b, 2, TEXT);
        draw_text(
            &mut sheet,
            5,
            60,
            "+-3 sigma: 12.5% (x/y) [m] a_b, A=B",
            2,
            TEXT,
        );
        save_png(&sheet, &target_dir().join("plot_demo_font.png")).expect("target/ is writable");
    }

    #[test]
    fn demo_track_png() {
        let path = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join("sitl/maps/naip_nd_2014.tif");
        let raster = match visnav_io::geo::geotiff::load_geotiff(&path, None) {
            Ok(r) => r,
            Err(e) => {
                eprintln!("skipping demo_track_png: {e}");
                return;
            }
        };
        let (w, h, nb) = (raster.width(), raster.height(), raster.bands());
        let Some(data) = raster.data().as_u8() else {
            eprintln!("skipping demo_track_png: not 8-bit");
            return;
        };
        assert!(nb >= 3);
        let mut bg = RgbImage::new(w as u32, h as u32);
        for (i, p) in bg.pixels_mut().enumerate() {
            p.0 = [data[i * nb], data[i * nb + 1], data[i * nb + 2]];
        }
        let b = raster.bounds();
        let extent = [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m];
        let (cx, cy) = ((b.min_x_m + b.max_x_m) / 2.0, (b.min_y_m + b.max_y_m) / 2.0);
        let truth: Vec<(f64, f64)> = (0..=400)
            .map(|i| {
                let a = f64::from(i) / 400.0 * std::f64::consts::TAU;
                (cx + 1200.0 * a.sin(), cy + 700.0 * (2.0 * a).sin())
            })
            .collect();
        let est: Vec<(f64, f64)> = truth
            .iter()
            .enumerate()
            .map(|(i, &(x, y))| {
                let e = f64::from(i as u32) * 0.15;
                (x + e * (f64::from(i as u32) * 0.05).sin(), y + 0.5 * e)
            })
            .collect();
        let fixes: Vec<(f64, f64)> = truth
            .iter()
            .step_by(25)
            .enumerate()
            .map(|(k, &(x, y))| (x + 15.0 * (k as f64).cos(), y + 15.0 * (k as f64).sin()))
            .collect();
        let sp = PlotSpec::new(
            1000,
            800,
            "Track over naip_nd_2014 (UTM 14N)",
            "easting [m]",
            "northing [m]",
        );
        let series = [
            Series::new("truth", [0, 0, 0], Style::Line, truth),
            Series::new("EKF estimate", [230, 30, 30], Style::Line, est),
            Series::new("vision fixes", [250, 200, 0], Style::Dots, fixes),
        ];
        let img = track(&sp, Some((&bg, extent)), &series);
        let out = target_dir().join("plot_demo_track.png");
        save_png(&img, &out).expect("target/ is writable");
        eprintln!("wrote {}", out.display());
        // The truth line is drawn over the background somewhere.
        assert!(count_rgb(&img, [0, 0, 0]) > 100);
        // Whole background without tracks.
        let all = track(&sp, Some((&bg, extent)), &[]);
        save_png(&all, &target_dir().join("plot_demo_track_bg.png")).expect("writable");
    }
}
