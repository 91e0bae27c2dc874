//! The PNG plots of the closed-loop simulator's report folder (`visnav sim --out DIR`), drawn with
//! the `plotters` crate on its bitmap backend:
//!
//! * [`errors`] (`errors.png`): horizontal position error against time in two panels. The upper
//!   panel is linear and shows visnav alone with its claimed 1-sigma and 3-sigma bounds and the
//!   accepted fixes: the metres that decide whether the claimed accuracy holds. The lower panel is
//!   logarithmic and sets visnav beside the no-vision control: a linear axis that holds the
//!   control's hundreds of metres flattens visnav's metres onto the time axis, a log axis shows
//!   both and keeps their ratio readable. The GPS-on periods are shaded in both.
//! * [`track`] (`track.png`): truth, visnav, the control and the accepted fixes over the
//!   camera-year orthophoto in the map's CRS, beside a zoomed panel on the stretch of the GPS
//!   outage where visnav is farthest from the truth ([`zoom_window`]): at the whole track's scale
//!   the two lines sit on top of each other.
//! * [`residuals`] (`residuals.png`): the accepted fixes' north and east errors against time
//!   within their claimed 3-sigma, the rejected attempts' times marked, and a scatter of east
//!   against north with the median claimed 3-sigma circle.
//!
//! Text uses a subset of DejaVu Sans compiled into the binary (`fonts/`, registered with
//! plotters' `ab_glyph` font table): no font file or fontconfig is needed at run time.
//!
//! The drawing functions are pure (they return an [`RgbImage`]); the only I/O is [`save_png`].
//! Lines break at non-finite values and are clipped to each panel; empty data draws empty axes.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use image::RgbImage;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

/// The font family every text of the plots uses (registered from [`FONT`]).
const FAMILY: &str = "sans-serif";

/// DejaVu Sans (fonts-dejavu-core 2.37), cut to ASCII and a few signs; licence in `fonts/`.
const FONT: &[u8] = include_bytes!("../fonts/DejaVuSans-subset.ttf");

// Colours of the plots.
/// The true track: near black.
pub const TRUTH: RGBColor = RGBColor(20, 20, 20);
/// visnav's output, its claimed bounds and its north residuals: blue.
pub const VISNAV: RGBColor = RGBColor(0, 90, 220);
/// The no-vision control, and fixes beyond their own 3-sigma: red.
pub const CONTROL: RGBColor = RGBColor(220, 40, 30);
/// Accepted fixes: green.
pub const FIX: RGBColor = RGBColor(0, 170, 60);
/// Rejected fix attempts: purple.
pub const REJECTED: RGBColor = RGBColor(150, 60, 170);
/// East residuals: orange.
pub const EAST: RGBColor = RGBColor(235, 130, 0);
/// The zoomed window's outline on the whole track, and the line joining truth and visnav at
/// their largest gap: yellow.
pub const ZOOM: RGBColor = RGBColor(255, 200, 0);
const GPS_SHADE: RGBColor = RGBColor(228, 228, 228);
const GRID: RGBColor = RGBColor(232, 232, 232);

/// Errors of this module; each names the file it was drawing or writing.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The plotting library failed.
    #[error("cannot draw {file}: {message}")]
    Draw {
        /// The plot's file name.
        file: &'static str,
        /// The library's error in words.
        message: String,
    },
    /// The PNG could not be encoded or written.
    #[error("cannot write PNG {path}: {cause}")]
    Save {
        /// The file.
        path: PathBuf,
        /// The encoder's or the file system's error.
        cause: image::ImageError,
    },
}

/// `errors.png`'s data: one sample per step, NaN where a filter has no output.
#[derive(Debug, Clone, Default)]
pub struct ErrorsData {
    /// The plot's title.
    pub title: String,
    /// Step times, s.
    pub t_s: Vec<f64>,
    /// visnav's horizontal error per step, m.
    pub visnav_m: Vec<f64>,
    /// visnav's claimed horizontal 1-sigma per step, m.
    pub sigma_m: Vec<f64>,
    /// The no-vision control's horizontal error, m.
    pub control_m: Vec<f64>,
    /// GPS-on periods `(start, end)`, s.
    pub gps_on: Vec<(f64, f64)>,
    /// Accepted fixes: capture time, s, and horizontal error, m.
    pub fixes: Vec<(f64, f64)>,
    /// How many fixes were accepted, in words with their scope (the console's wording, e.g.
    /// "586 in the GPS outage (30-330 s), 636 in the whole flight"); empty: the number drawn.
    pub fixes_count: String,
}

/// `track.png`'s data: map CRS metres (x east, y north).
#[derive(Debug, Clone, Default)]
pub struct TrackData<'a> {
    /// The plot's title.
    pub title: String,
    /// The CRS's name for the axis labels.
    pub crs: String,
    /// The orthophoto and its extent `[min_x, min_y, max_x, max_y]` (row 0 at the north edge).
    pub background: Option<(&'a RgbImage, [f64; 4])>,
    /// Step times, s.
    pub t_s: Vec<f64>,
    /// The true position per step.
    pub truth: Vec<(f64, f64)>,
    /// visnav's position per step (NaN without an output).
    pub visnav: Vec<(f64, f64)>,
    /// The control's position per step (NaN without an output).
    pub control: Vec<(f64, f64)>,
    /// Whether GPS was lost at each step.
    pub outage: Vec<bool>,
    /// Accepted fixes' positions.
    pub fixes: Vec<(f64, f64)>,
}

/// One accepted fix's residual.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Residual {
    /// Capture time, s.
    pub t_s: f64,
    /// North error against the true camera position, m.
    pub north_m: f64,
    /// East error against the true camera position, m.
    pub east_m: f64,
    /// The fix's claimed horizontal 1-sigma, m.
    pub sigma_m: f64,
    /// Outside its own 3-sigma ellipse.
    pub beyond_3sigma: bool,
}

/// `residuals.png`'s data.
#[derive(Debug, Clone, Default)]
pub struct ResidualsData {
    /// The plot's title.
    pub title: String,
    /// The accepted fixes' residuals.
    pub accepted: Vec<Residual>,
    /// Capture times of the rejected attempts, s.
    pub rejected_t_s: Vec<f64>,
    /// GPS-on periods `(start, end)`, s.
    pub gps_on: Vec<(f64, f64)>,
    /// The run's time span, s (the time axis).
    pub t_range: (f64, f64),
}

type Area<'a> = DrawingArea<BitMapBackend<'a>, Shift>;
type Chart<'a, 'b, Y> = ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, Y>>;
type XyChart<'a, 'b> = Chart<'a, 'b, RangedCoordf64>;

/// Maps a plotters error to [`PlotError::Draw`] for `file`.
fn draw_err<E: std::fmt::Display>(file: &'static str) -> impl Fn(E) -> PlotError {
    move |e| PlotError::Draw {
        file,
        message: e.to_string(),
    }
}

/// Registers the compiled-in font once.
fn register_font(file: &'static str) -> Result<(), PlotError> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE
        .get_or_init(|| plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).is_ok());
    if ok {
        Ok(())
    } else {
        Err(PlotError::Draw {
            file,
            message: "the compiled-in font does not load".into(),
        })
    }
}

fn text(size: u32) -> TextStyle<'static> {
    (FAMILY, size).into_font().color(&BLACK)
}

/// Draws a `w` x `h` image with `draw` on a white canvas.
fn render(
    file: &'static str,
    (w, h): (u32, u32),
    draw: impl FnOnce(&Area) -> Result<(), PlotError>,
) -> Result<RgbImage, PlotError> {
    register_font(file)?;
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        draw(&root)?;
        root.present().map_err(draw_err(file))?;
    }
    RgbImage::from_raw(w, h, buf).ok_or_else(|| PlotError::Draw {
        file,
        message: "the image buffer has the wrong size".into(),
    })
}

/// Writes `img` as PNG to `path`.
pub fn save_png(img: &RgbImage, path: &Path) -> Result<(), PlotError> {
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|source| PlotError::Save {
            path: path.to_path_buf(),
            cause: source,
        })
}

// ---------------------------------------------------------------------------------------------
// Data helpers

fn finite(p: &(f64, f64)) -> bool {
    p.0.is_finite() && p.1.is_finite()
}

/// `[lo, hi]` of the finite values, `None` if there are none.
fn span(values: impl IntoIterator<Item = f64>) -> Option<(f64, f64)> {
    values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold(None, |acc, v| match acc {
            None => Some((v, v)),
            Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
        })
}

/// A usable axis range: `(lo, hi)` padded by `pad` of its width, widened when degenerate.
fn padded(s: Option<(f64, f64)>, pad: f64) -> Range<f64> {
    let (lo, hi) = s.unwrap_or((0.0, 1.0));
    let w = hi - lo;
    if w > 0.0 {
        (lo - pad * w)..(hi + pad * w)
    } else {
        let d = (lo.abs() * 1e-3).max(1.0);
        (lo - d)..(hi + d)
    }
}

/// The `q` quantile (0..1) of the finite values (nearest rank).
fn quantile(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let i = ((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    v.get(i).copied()
}

/// Liang-Barsky: the part of segment `a`-`b` inside `[x0, x1] x [y0, y1]`.
fn clip_segment(a: (f64, f64), b: (f64, f64), r: [f64; 4]) -> Option<((f64, f64), (f64, f64))> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - r[0]),
        (dx, r[2] - a.0),
        (-dy, a.1 - r[1]),
        (dy, r[3] - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    let at = |t: f64| (a.0 + t * dx, a.1 + t * dy);
    (t0 <= t1).then_some((at(t0), at(t1)))
}

/// A poly-line cut into the runs that lie inside `r = [x0, y0, x1, y1]`; it also breaks at
/// non-finite points.
pub fn clip_polyline(points: &[(f64, f64)], r: [f64; 4]) -> Vec<Vec<(f64, f64)>> {
    let mut runs: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut cur: Vec<(f64, f64)> = Vec::new();
    for w in points.windows(2) {
        let seg = if finite(&w[0]) && finite(&w[1]) {
            clip_segment(w[0], w[1], r)
        } else {
            None
        };
        match seg {
            Some((p, q)) => {
                if cur.last() != Some(&p) && !cur.is_empty() {
                    runs.push(std::mem::take(&mut cur));
                }
                if cur.is_empty() {
                    cur.push(p);
                }
                cur.push(q);
                if q != w[1] {
                    runs.push(std::mem::take(&mut cur));
                }
            }
            None if !cur.is_empty() => runs.push(std::mem::take(&mut cur)),
            None => {}
        }
    }
    if !cur.is_empty() {
        runs.push(cur);
    }
    runs
}

fn inside(p: &(f64, f64), r: [f64; 4]) -> bool {
    finite(p) && p.0 >= r[0] && p.0 <= r[2] && p.1 >= r[1] && p.1 <= r[3]
}

/// The outage sample where visnav is farthest from the truth: its index and that distance, m.
fn zoom_sample(d: &TrackData) -> Option<(usize, f64)> {
    d.truth
        .iter()
        .zip(&d.visnav)
        .zip(&d.outage)
        .enumerate()
        .filter(|(_, ((t, v), out))| **out && finite(t) && finite(v))
        .map(|(i, ((t, v), _))| (i, (t.0 - v.0).hypot(t.1 - v.1)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The square window `[min_x, min_y, max_x, max_y]` of the zoomed track panel: centred between
/// truth and visnav where visnav is farthest from the truth while GPS is lost, wide enough
/// (8 times that distance, at least 40 m) to show both lines and their gap. `None` without an
/// outage sample where both are known.
pub fn zoom_window(d: &TrackData) -> Option<[f64; 4]> {
    let (i, err) = zoom_sample(d)?;
    let (t, v) = (d.truth[i], d.visnav[i]);
    let (cx, cy) = ((t.0 + v.0) / 2.0, (t.1 + v.1) / 2.0);
    let half = (4.0 * err).max(20.0);
    Some([cx - half, cy - half, cx + half, cy + half])
}

/// `[lo, hi]` runs of `flags` over `t` (the GPS-on periods from per-step flags).
pub fn periods(t: &[f64], flags: &[bool]) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    let mut start: Option<f64> = None;
    let mut last = f64::NAN;
    for (&ti, &on) in t.iter().zip(flags) {
        match (on, start) {
            (true, None) => start = Some(ti),
            (false, Some(s)) => {
                out.push((s, ti));
                start = None;
            }
            _ => {}
        }
        last = ti;
    }
    if let Some(s) = start {
        out.push((s, last));
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Drawing helpers

fn label_fmt(step: f64) -> impl Fn(&f64) -> String {
    let decimals = if step >= 1.0 || step <= 0.0 {
        0
    } else {
        (-step.log10()).ceil().clamp(0.0, 6.0) as usize
    };
    move |v| format!("{v:.decimals$}")
}

fn tick_step(r: &Range<f64>, n: f64) -> f64 {
    let raw = (r.end - r.start) / n;
    if !(raw.is_finite() && raw > 0.0) {
        return 1.0;
    }
    let p = 10f64.powf(raw.log10().floor());
    [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * p)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * p)
}

/// The charts' label areas (x below, y at the left), px.
const CHART_LABELS: (u32, u32) = (46, 78);

/// A linear chart in `area` with its mesh (grid, labels, axis descriptions).
fn linear_chart<'a, 'b>(
    file: &'static str,
    area: &'a Area<'b>,
    (x, y): (Range<f64>, Range<f64>),
    (x_desc, y_desc): (&str, &str),
    caption: &str,
) -> Result<XyChart<'a, 'b>, PlotError> {
    let mut builder = ChartBuilder::on(area);
    if !caption.is_empty() {
        builder.caption(caption, text(20));
    }
    let mut chart = builder
        .margin(12)
        .x_label_area_size(CHART_LABELS.0)
        .y_label_area_size(CHART_LABELS.1)
        .build_cartesian_2d(x.clone(), y.clone())
        .map_err(draw_err(file))?;
    let (fx, fy) = (label_fmt(tick_step(&x, 8.0)), label_fmt(tick_step(&y, 8.0)));
    chart
        .configure_mesh()
        .light_line_style(WHITE)
        .bold_line_style(GRID)
        .x_labels(9)
        .y_labels(9)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style(text(14))
        .axis_desc_style(text(16))
        .x_desc(x_desc)
        .y_desc(y_desc)
        .draw()
        .map_err(draw_err(file))?;
    Ok(chart)
}

/// Draws the clipped runs of a poly-line and gives it a legend entry (if `label` is not empty).
fn draw_line<Y>(
    file: &'static str,
    chart: &mut Chart<'_, '_, Y>,
    runs: Vec<Vec<(f64, f64)>>,
    style: ShapeStyle,
    label: &str,
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    let ann = chart
        .draw_series(runs.into_iter().map(|r| PathElement::new(r, style)))
        .map_err(draw_err(file))?;
    if !label.is_empty() {
        ann.label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], style));
    }
    Ok(())
}

/// Draws filled dots with a white rim (visible over the map) at the points inside `r`, with a
/// legend entry.
fn draw_dots<Y>(
    file: &'static str,
    chart: &mut Chart<'_, '_, Y>,
    points: &[(f64, f64)],
    (r, size, color): ([f64; 4], i32, RGBColor),
    label: &str,
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    let pts: Vec<(f64, f64)> = points.iter().copied().filter(|p| inside(p, r)).collect();
    let rims = pts
        .iter()
        .map(|&p| Circle::new(p, size + 1, WHITE.filled()));
    chart.draw_series(rims).map_err(draw_err(file))?;
    let ann = chart
        .draw_series(
            pts.into_iter()
                .map(|p| Circle::new(p, size, color.filled())),
        )
        .map_err(draw_err(file))?;
    if !label.is_empty() {
        ann.label(label)
            .legend(move |(x, y)| Circle::new((x + 12, y), size, color.filled()));
    }
    Ok(())
}

/// Shades the GPS-on periods over the whole height `y` of the chart.
fn shade_gps<Y>(
    file: &'static str,
    chart: &mut Chart<'_, '_, Y>,
    gps_on: &[(f64, f64)],
    y: (f64, f64),
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    let ann = chart
        .draw_series(
            gps_on
                .iter()
                .filter(|p| finite(p))
                .map(|&(a, b)| Rectangle::new([(a, y.0), (b, y.1)], GPS_SHADE.filled())),
        )
        .map_err(draw_err(file))?;
    if !gps_on.is_empty() {
        ann.label("GPS on")
            .legend(|(x, y)| Rectangle::new([(x, y - 6), (x + 24, y + 6)], GPS_SHADE.filled()));
    }
    Ok(())
}

/// Fills the band between `lo` and `hi` along `t` (runs of finite samples), clamped to `y`.
fn draw_band<Y>(
    file: &'static str,
    chart: &mut Chart<'_, '_, Y>,
    samples: impl Iterator<Item = (f64, f64, f64)>,
    y: (f64, f64),
    (color, label): (RGBAColor, &str),
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    let mut polys: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut run: Vec<(f64, f64, f64)> = Vec::new();
    let close = |run: &mut Vec<(f64, f64, f64)>, polys: &mut Vec<Vec<(f64, f64)>>| {
        if run.len() >= 2 {
            let c = |v: f64| v.clamp(y.0, y.1);
            let mut p: Vec<(f64, f64)> = run.iter().map(|s| (s.0, c(s.2))).collect();
            p.extend(run.iter().rev().map(|s| (s.0, c(s.1))));
            polys.push(p);
        }
        run.clear();
    };
    for s in samples {
        if s.0.is_finite() && s.1.is_finite() && s.2.is_finite() {
            run.push(s);
        } else {
            close(&mut run, &mut polys);
        }
    }
    close(&mut run, &mut polys);
    let ann = chart
        .draw_series(polys.into_iter().map(|p| Polygon::new(p, color.filled())))
        .map_err(draw_err(file))?;
    ann.label(label)
        .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 24, y + 6)], color.filled()));
    Ok(())
}

fn draw_legend<'a, 'b: 'a, Y>(
    file: &'static str,
    chart: &mut Chart<'a, 'b, Y>,
    pos: SeriesLabelPosition,
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    chart
        .configure_series_labels()
        .position(pos)
        .background_style(WHITE.mix(0.88))
        .border_style(RGBColor(150, 150, 150))
        .label_font(text(14))
        .margin(8)
        .draw()
        .map_err(draw_err(file))
}

/// Writes `note` in the middle of a chart (e.g. "no data").
fn draw_note<Y>(
    file: &'static str,
    chart: &mut Chart<'_, '_, Y>,
    note: &str,
) -> Result<(), PlotError>
where
    Y: Ranged<ValueType = f64>,
{
    let (px, py) = chart.plotting_area().get_pixel_range();
    let area = chart.plotting_area().strip_coord_spec();
    let (cx, cy) = ((px.end - px.start) / 2 - 40, (py.end - py.start) / 2);
    area.draw(&Text::new(note.to_string(), (cx.max(0), cy), text(18)))
        .map_err(draw_err(file))
}

// ---------------------------------------------------------------------------------------------
// errors.png

const ERRORS_FILE: &str = "errors.png";
/// `errors.png`'s size, px.
pub const ERRORS_SIZE: (u32, u32) = (1400, 1000);
/// The log panel's floor, m: smaller errors are drawn on it.
const LOG_FLOOR_M: f64 = 0.1;

/// `errors.png`: visnav's error with its claimed bounds (linear) over visnav against the control
/// (log).
pub fn errors(d: &ErrorsData) -> Result<RgbImage, PlotError> {
    render(ERRORS_FILE, ERRORS_SIZE, |root| {
        root.fill(&WHITE).map_err(draw_err(ERRORS_FILE))?;
        let root = root
            .titled(&d.title, text(24))
            .map_err(draw_err(ERRORS_FILE))?;
        let (top, bottom) = root.split_vertically(52.percent_height());
        errors_linear(d, &top)?;
        errors_log(d, &bottom)
    })
}

fn time_range(t: &[f64]) -> Range<f64> {
    padded(span(t.iter().copied()), 0.0)
}

/// The upper panel's top, m: visnav's error, the fixes' and most of the 3-sigma bound (its
/// start-up values before convergence would flatten everything else).
fn linear_top(d: &ErrorsData) -> f64 {
    let three: Vec<f64> = d.sigma_m.iter().map(|s| 3.0 * s).collect();
    let errors = d.visnav_m.iter().chain(d.fixes.iter().map(|p| &p.1));
    let top = span(errors.copied()).map_or(1.0, |s| s.1);
    top.max(quantile(&three, 0.9).unwrap_or(0.0)).max(1.0) * 1.1
}

/// The upper panel: visnav, its 1- and 3-sigma, the accepted fixes; linear metres.
fn errors_linear(d: &ErrorsData, area: &Area) -> Result<(), PlotError> {
    let f = ERRORS_FILE;
    let x = time_range(&d.t_s);
    let top = linear_top(d);
    let y = 0.0..top;
    let r = [x.start, y.start, x.end, y.end];
    let mut chart = linear_chart(
        f,
        area,
        (x, y),
        ("time [s]", "horizontal error [m]"),
        "visnav: horizontal error and its claimed bounds (linear)",
    )?;
    shade_gps(f, &mut chart, &d.gps_on, (0.0, top))?;
    let t = &d.t_s;
    let band = |k: f64| {
        t.iter()
            .zip(&d.sigma_m)
            .map(move |(&t, &s)| (t, 0.0, k * s))
    };
    draw_band(
        f,
        &mut chart,
        band(3.0),
        (0.0, top),
        (VISNAV.mix(0.12), "visnav claimed 3-sigma"),
    )?;
    draw_band(
        f,
        &mut chart,
        band(1.0),
        (0.0, top),
        (VISNAV.mix(0.25), "visnav claimed 1-sigma"),
    )?;
    let vis: Vec<(f64, f64)> = t.iter().copied().zip(d.visnav_m.iter().copied()).collect();
    draw_line(
        f,
        &mut chart,
        clip_polyline(&vis, r),
        VISNAV.stroke_width(2),
        "visnav",
    )?;
    let count = if d.fixes_count.is_empty() {
        d.fixes.len().to_string()
    } else {
        d.fixes_count.clone()
    };
    draw_dots(
        f,
        &mut chart,
        &d.fixes,
        (r, 4, FIX),
        &format!("accepted fixes, their error: {count}"),
    )?;
    if vis.iter().all(|p| !finite(p)) {
        draw_note(f, &mut chart, "no data")?;
    }
    draw_legend(f, &mut chart, SeriesLabelPosition::UpperLeft)
}

/// The log panel's range, whole decades: from the decade at or below the errors' 2nd percentile
/// (not below [`LOG_FLOOR_M`]) to the one at or above the largest, at least one decade.
fn log_range(values: impl Iterator<Item = f64> + Clone) -> Range<f64> {
    let pos: Vec<f64> = values.filter(|v| v.is_finite() && *v > 0.0).collect();
    let lo = quantile(&pos, 0.02).unwrap_or(1.0).max(LOG_FLOOR_M);
    let hi = span(pos.iter().copied())
        .map_or(10.0, |s| s.1)
        .max(lo * 10.0);
    10f64.powf(lo.log10().floor())..10f64.powf(hi.log10().ceil())
}

/// The lower panel: visnav and the control on a log axis.
fn errors_log(d: &ErrorsData, area: &Area) -> Result<(), PlotError> {
    let f = ERRORS_FILE;
    let x = time_range(&d.t_s);
    let y = log_range(d.visnav_m.iter().chain(&d.control_m).copied());
    let r = [x.start, y.start, x.end, y.end];
    let mut chart = ChartBuilder::on(area)
        .caption("visnav against the no-vision control (log scale)", text(20))
        .margin(12)
        .x_label_area_size(CHART_LABELS.0)
        .y_label_area_size(CHART_LABELS.1)
        .build_cartesian_2d(x.clone(), y.clone().log_scale())
        .map_err(draw_err(f))?;
    let fx = label_fmt(tick_step(&x, 8.0));
    chart
        .configure_mesh()
        .light_line_style(WHITE)
        .bold_line_style(GRID)
        .x_labels(9)
        .x_label_formatter(&fx)
        .y_label_formatter(&|v| format_log_label(*v))
        .label_style(text(14))
        .axis_desc_style(text(16))
        .x_desc("time [s]")
        .y_desc("horizontal error [m]")
        .draw()
        .map_err(draw_err(f))?;
    shade_gps(f, &mut chart, &d.gps_on, (y.start, y.end))?;
    // Below the floor is drawn on it (a zero error has no place on a log axis).
    let floor = |v: f64| if v.is_finite() { v.max(y.start) } else { v };
    let line = |e: &[f64]| -> Vec<(f64, f64)> {
        d.t_s.iter().zip(e).map(|(&t, &v)| (t, floor(v))).collect()
    };
    let three: Vec<f64> = d.sigma_m.iter().map(|s| 3.0 * s).collect();
    let dashed = VISNAV.mix(0.6).stroke_width(1);
    draw_line(
        f,
        &mut chart,
        clip_polyline(&line(&three), r),
        dashed,
        "visnav claimed 3-sigma",
    )?;
    draw_line(
        f,
        &mut chart,
        clip_polyline(&line(&d.control_m), r),
        CONTROL.stroke_width(2),
        "no-vision control",
    )?;
    draw_line(
        f,
        &mut chart,
        clip_polyline(&line(&d.visnav_m), r),
        VISNAV.stroke_width(2),
        "visnav",
    )?;
    draw_legend(f, &mut chart, SeriesLabelPosition::UpperLeft)
}

/// A log axis label: `0.1`, `1`, `20`, `500` (no trailing zeros).
fn format_log_label(v: f64) -> String {
    if v >= 1.0 {
        format!("{v:.0}")
    } else {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

// ---------------------------------------------------------------------------------------------
// track.png

const TRACK_FILE: &str = "track.png";
/// `track.png`'s size, px.
pub const TRACK_SIZE: (u32, u32) = (1800, 960);

/// `track.png`: the whole track over the orthophoto beside the zoom on the outage.
pub fn track(d: &TrackData) -> Result<RgbImage, PlotError> {
    render(TRACK_FILE, TRACK_SIZE, |root| {
        root.fill(&WHITE).map_err(draw_err(TRACK_FILE))?;
        let root = root
            .titled(&d.title, text(24))
            .map_err(draw_err(TRACK_FILE))?;
        let (left, right) = root.split_horizontally(50.percent_width());
        let zoom = zoom_window(d);
        let all = track_extent(d);
        let mark = zoom.map(Mark::Window);
        track_panel(
            d,
            &left,
            all,
            mark,
            "whole flight over the camera-year orthophoto",
        )?;
        match (zoom, zoom_sample(d)) {
            (Some(z), Some((i, e))) => {
                let t = d.t_s.get(i).copied().unwrap_or(f64::NAN);
                let cap = format!("zoom: GPS lost, t = {t:.1} s, visnav {e:.1} m from the truth");
                track_panel(d, &right, z, Some(Mark::Gap(i)), &cap)
            }
            _ => track_panel(d, &right, all, None, "no GPS outage to zoom on"),
        }
    })
}

/// The whole track's extent: truth, visnav, control and fixes.
fn track_extent(d: &TrackData) -> [f64; 4] {
    let pts = || {
        d.truth
            .iter()
            .chain(&d.visnav)
            .chain(&d.control)
            .chain(&d.fixes)
    };
    let x = padded(span(pts().map(|p| p.0)), 0.05);
    let y = padded(span(pts().map(|p| p.1)), 0.05);
    [x.start, y.start, x.end, y.end]
}

/// `want` grown about its centre to the aspect of a `w` x `h` px plot: equal metres per pixel.
fn equal_aspect(want: [f64; 4], (w, h): (u32, u32)) -> [f64; 4] {
    let (w, h) = (f64::from(w.max(1)), f64::from(h.max(1)));
    let m = ((want[2] - want[0]) / w).max((want[3] - want[1]) / h);
    let (cx, cy) = ((want[0] + want[2]) / 2.0, (want[1] + want[3]) / 2.0);
    let (hx, hy) = (m * w / 2.0, m * h / 2.0);
    [cx - hx, cy - hy, cx + hx, cy + hy]
}

/// The plot rectangle's size in `area` with `(x, y)` label areas, px (a chart built and
/// dropped: building draws nothing).
fn plot_size(
    file: &'static str,
    area: &Area,
    (xl, yl): (u32, u32),
) -> Result<(u32, u32), PlotError> {
    let chart = ChartBuilder::on(area)
        .margin(12)
        .x_label_area_size(xl)
        .y_label_area_size(yl)
        .build_cartesian_2d(0f64..1f64, 0f64..1f64)
        .map_err(draw_err(file))?;
    let (x, y) = chart.plotting_area().get_pixel_range();
    Ok((
        (x.end - x.start).max(1) as u32,
        (y.end - y.start).max(1) as u32,
    ))
}

/// The map panels' label areas, px.
const MAP_LABELS: (u32, u32) = (50, 90);

/// What a map panel marks besides the tracks.
#[derive(Debug, Clone, Copy)]
enum Mark {
    /// The zoom window's outline.
    Window([f64; 4]),
    /// Truth and visnav at sample `i`, joined.
    Gap(usize),
}

/// One map panel: `want` (grown to equal scale), the orthophoto, the tracks and the `mark`.
fn track_panel(
    d: &TrackData,
    area: &Area,
    want: [f64; 4],
    mark: Option<Mark>,
    caption: &str,
) -> Result<(), PlotError> {
    let f = TRACK_FILE;
    let area = area.titled(caption, text(18)).map_err(draw_err(f))?;
    let size = plot_size(f, &area, MAP_LABELS)?;
    let r = equal_aspect(want, size);
    let mut chart = ChartBuilder::on(&area)
        .margin(12)
        .x_label_area_size(MAP_LABELS.0)
        .y_label_area_size(MAP_LABELS.1)
        .build_cartesian_2d(r[0]..r[2], r[1]..r[3])
        .map_err(draw_err(f))?;
    if let Some((img, extent)) = d.background {
        draw_background(&chart, img, extent, r, size)?;
    }
    let fx = label_fmt(tick_step(&(r[0]..r[2]), 6.0));
    let fy = label_fmt(tick_step(&(r[1]..r[3]), 6.0));
    chart
        .configure_mesh()
        .light_line_style(TRANSPARENT)
        .bold_line_style(WHITE.mix(0.35))
        .x_labels(6)
        .y_labels(7)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style(text(14))
        .axis_desc_style(text(15))
        .x_desc(format!("easting [m], {}", d.crs))
        .y_desc(format!("northing [m], {}", d.crs))
        .draw()
        .map_err(draw_err(f))?;
    let marks = match mark {
        Some(Mark::Gap(_)) => FixMarks::Distinct,
        _ => FixMarks::Faint,
    };
    draw_tracks(d, &mut chart, r, marks)?;
    match mark {
        Some(Mark::Window(z)) => {
            let outline = vec![
                (z[0], z[1]),
                (z[2], z[1]),
                (z[2], z[3]),
                (z[0], z[3]),
                (z[0], z[1]),
            ];
            draw_line(
                f,
                &mut chart,
                clip_polyline(&outline, r),
                ZOOM.stroke_width(3),
                "zoomed at right",
            )?;
        }
        Some(Mark::Gap(i)) => draw_gap(d, &mut chart, i, r)?,
        None => {}
    }
    draw_legend(f, &mut chart, SeriesLabelPosition::UpperLeft)
}

/// Truth and visnav at sample `i` as rings joined by a line.
fn draw_gap(d: &TrackData, chart: &mut XyChart, i: usize, r: [f64; 4]) -> Result<(), PlotError> {
    let (Some(&t), Some(&v)) = (d.truth.get(i), d.visnav.get(i)) else {
        return Ok(());
    };
    let style = ZOOM.stroke_width(3);
    draw_line(
        TRACK_FILE,
        chart,
        clip_polyline(&[t, v], r),
        style,
        "truth and visnav at that time",
    )?;
    let rings = [(t, TRUTH), (v, VISNAV)]
        .into_iter()
        .filter(|(p, _)| inside(p, r));
    chart
        .draw_series(rings.map(|(p, c)| Circle::new(p, 7, c.stroke_width(3))))
        .map_err(draw_err(TRACK_FILE))?;
    Ok(())
}

/// How a map panel draws the accepted fixes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FixMarks {
    /// Small translucent dots without rim: at the whole flight's scale hundreds of fixes lie
    /// within a few pixels of the track and opaque dots would cover the lines.
    Faint,
    /// Dots with a white rim, for a zoomed panel where only a few fixes fall.
    Distinct,
}

/// Radius of the faint fix dots, px, and their opacity.
const FAINT_FIX: (i32, f64) = (3, 0.5);

/// The tracks of a map panel. The fixes go first, under the lines: the lines are what the panel
/// is read for, the fixes a cloud around them.
fn draw_tracks(
    d: &TrackData,
    chart: &mut XyChart,
    r: [f64; 4],
    marks: FixMarks,
) -> Result<(), PlotError> {
    let f = TRACK_FILE;
    let n = d.fixes.iter().filter(|p| finite(p)).count();
    let label = format!("accepted vision fixes ({n})");
    match marks {
        FixMarks::Distinct => draw_dots(f, chart, &d.fixes, (r, 4, FIX), &label)?,
        FixMarks::Faint => {
            let (size, alpha) = FAINT_FIX;
            let style = FIX.mix(alpha).filled();
            let pts = d.fixes.iter().copied().filter(|p| inside(p, r));
            chart
                .draw_series(pts.map(|p| Circle::new(p, size, style)))
                .map_err(draw_err(f))?
                .label(label)
                .legend(move |(x, y)| Circle::new((x + 12, y), size + 2, style));
        }
    }
    draw_line(
        f,
        chart,
        clip_polyline(&d.control, r),
        CONTROL.stroke_width(2),
        "no-vision control",
    )?;
    draw_line(
        f,
        chart,
        clip_polyline(&d.truth, r),
        TRUTH.stroke_width(3),
        "truth",
    )?;
    draw_line(
        f,
        chart,
        clip_polyline(&d.visnav, r),
        VISNAV.stroke_width(2),
        "visnav",
    )
}

/// Resamples the orthophoto (bilinear) into the plot rectangle showing `r`.
fn draw_background(
    chart: &XyChart,
    img: &RgbImage,
    extent: [f64; 4],
    r: [f64; 4],
    (w, h): (u32, u32),
) -> Result<(), PlotError> {
    if img.width() == 0 || img.height() == 0 || !(extent[2] > extent[0] && extent[3] > extent[1]) {
        return Ok(());
    }
    let mut buf = vec![255u8; w as usize * h as usize * 3];
    for (k, px) in buf.chunks_exact_mut(3).enumerate() {
        let (i, j) = ((k % w as usize) as f64, (k / w as usize) as f64);
        let x = r[0] + (i + 0.5) / f64::from(w) * (r[2] - r[0]);
        let y = r[3] - (j + 0.5) / f64::from(h) * (r[3] - r[1]);
        let col = (x - extent[0]) / (extent[2] - extent[0]) * f64::from(img.width());
        let row = (extent[3] - y) / (extent[3] - extent[1]) * f64::from(img.height());
        if let Some(rgb) = bilinear(img, col, row) {
            px.copy_from_slice(&rgb);
        }
    }
    let elem = BitMapElement::with_owned_buffer((0, 0), (w, h), buf).ok_or(PlotError::Draw {
        file: TRACK_FILE,
        message: "the background buffer has the wrong size".into(),
    })?;
    chart
        .plotting_area()
        .strip_coord_spec()
        .draw(&elem)
        .map_err(draw_err(TRACK_FILE))
}

/// The image at pixel-corner coordinates `(col, row)`, `None` outside it.
fn bilinear(img: &RgbImage, col: f64, row: f64) -> Option<[u8; 3]> {
    let (w, h) = (f64::from(img.width()), f64::from(img.height()));
    if !(col >= 0.0 && row >= 0.0 && col < w && row < h) {
        return None;
    }
    let (x, y) = (
        (col - 0.5).clamp(0.0, w - 1.0),
        (row - 0.5).clamp(0.0, h - 1.0),
    );
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = (
        (x0 + 1).min(img.width() - 1),
        (y0 + 1).min(img.height() - 1),
    );
    let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
    let p = |x, y| img.get_pixel(x, y).0;
    let (a, b, c, e) = (p(x0, y0), p(x1, y0), p(x0, y1), p(x1, y1));
    let mut out = [0u8; 3];
    for (k, o) in out.iter_mut().enumerate() {
        let top = f64::from(a[k]) * (1.0 - fx) + f64::from(b[k]) * fx;
        let bot = f64::from(c[k]) * (1.0 - fx) + f64::from(e[k]) * fx;
        *o = (top * (1.0 - fy) + bot * fy).round().clamp(0.0, 255.0) as u8;
    }
    Some(out)
}

// ---------------------------------------------------------------------------------------------
// residuals.png

const RESIDUALS_FILE: &str = "residuals.png";
/// `residuals.png`'s size, px.
pub const RESIDUALS_SIZE: (u32, u32) = (1600, 820);

/// `residuals.png`: the accepted fixes' north / east errors against time (with their claimed
/// 3-sigma and the rejected attempts) beside a scatter of east against north.
pub fn residuals(d: &ResidualsData) -> Result<RgbImage, PlotError> {
    render(RESIDUALS_FILE, RESIDUALS_SIZE, |root| {
        root.fill(&WHITE).map_err(draw_err(RESIDUALS_FILE))?;
        let root = root
            .titled(&d.title, text(24))
            .map_err(draw_err(RESIDUALS_FILE))?;
        let (left, right) = root.split_horizontally(60.percent_width());
        residuals_time(d, &left)?;
        residuals_scatter(d, &right)
    })
}

/// The quantile of the residual components (|north|, |east|) the residual panels' range holds.
const RESIDUAL_QUANTILE: f64 = 0.99;
/// Headroom of the residual panels over what they must hold.
const RESIDUAL_MARGIN: f64 = 1.15;

/// The residual panels' half range, m: 99 % of the residual components and the median claimed
/// 3-sigma, with some headroom. Not the largest value: a few fixes claim a 3-sigma ten times
/// the typical one (a frame with few inliers), and a range set by them would flatten the body
/// of the residuals onto the zero line. What lies beyond is drawn at the edge and counted
/// ([`residual_clipping`]).
pub fn residual_extent(d: &ResidualsData) -> f64 {
    let comps: Vec<f64> = d
        .accepted
        .iter()
        .flat_map(|r| [r.north_m.abs(), r.east_m.abs()])
        .collect();
    let three: Vec<f64> = d.accepted.iter().map(|r| 3.0 * r.sigma_m).collect();
    let body = quantile(&comps, RESIDUAL_QUANTILE).unwrap_or(0.0);
    let band = quantile(&three, 0.5).unwrap_or(0.0);
    body.max(band).max(1.0) * RESIDUAL_MARGIN
}

/// What the residuals-against-time panel of half range `m` cannot hold: residual components
/// (north and east counted apart) and claimed 3-sigma bounds beyond `m`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ResidualClipping {
    /// Residual components beyond the range.
    pub components: usize,
    /// Claimed 3-sigma bounds beyond the range.
    pub sigma_bounds: usize,
}

/// The residuals and 3-sigma bounds beyond the half range `m` ([`ResidualClipping`]).
pub fn residual_clipping(d: &ResidualsData, m: f64) -> ResidualClipping {
    let beyond = |v: f64| v.is_finite() && v.abs() > m;
    ResidualClipping {
        components: d
            .accepted
            .iter()
            .map(|r| usize::from(beyond(r.north_m)) + usize::from(beyond(r.east_m)))
            .sum(),
        sigma_bounds: d
            .accepted
            .iter()
            .filter(|r| beyond(3.0 * r.sigma_m))
            .count(),
    }
}

/// Which edge of a panel a clipped point is drawn on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Edge {
    Top,
    Bottom,
    Left,
    Right,
}

/// A point beyond the panel `r`, moved onto its edge, and the edge it crossed (the farther one,
/// in units of the panel's size, when it is beyond two); `None` for a point inside or not finite.
fn onto_edge(p: (f64, f64), r: [f64; 4]) -> Option<((f64, f64), Edge)> {
    if !finite(&p) || inside(&p, r) {
        return None;
    }
    let (w, h) = (
        (r[2] - r[0]).max(f64::MIN_POSITIVE),
        (r[3] - r[1]).max(f64::MIN_POSITIVE),
    );
    let dx = ((r[0] - p.0).max(p.0 - r[2])).max(0.0) / w;
    let dy = ((r[1] - p.1).max(p.1 - r[3])).max(0.0) / h;
    let q = (p.0.clamp(r[0], r[2]), p.1.clamp(r[1], r[3]));
    let edge = if dy >= dx {
        if p.1 > r[3] { Edge::Top } else { Edge::Bottom }
    } else if p.0 > r[2] {
        Edge::Right
    } else {
        Edge::Left
    };
    Some((q, edge))
}

/// A triangle pointing out of the panel across `edge`, its tip on the edge, px.
fn edge_triangle(edge: Edge) -> Vec<(i32, i32)> {
    const L: i32 = 11;
    const W: i32 = 6;
    match edge {
        Edge::Top => vec![(0, 0), (-W, L), (W, L)],
        Edge::Bottom => vec![(0, 0), (-W, -L), (W, -L)],
        Edge::Left => vec![(0, 0), (L, -W), (L, W)],
        Edge::Right => vec![(0, 0), (-L, -W), (-L, W)],
    }
}

/// Draws the `points` (each with its colour) that lie beyond `r` as triangles on the edge they
/// cross, pointing out, with a legend entry when there are any; returns how many.
fn draw_clipped<'a, 'b: 'a>(
    chart: &mut XyChart<'a, 'b>,
    points: &[((f64, f64), RGBColor)],
    r: [f64; 4],
    label: impl Fn(usize) -> String,
) -> Result<usize, PlotError> {
    let marks: Vec<((f64, f64), Edge, RGBColor)> = points
        .iter()
        .filter_map(|&(p, c)| onto_edge(p, r).map(|(q, e)| (q, e, c)))
        .collect();
    let n = marks.len();
    let ann = chart
        .draw_series(marks.into_iter().map(|(q, e, c)| {
            EmptyElement::at(q)
                + Polygon::new(edge_triangle(e), c.filled())
                + PathElement::new(
                    {
                        let mut t = edge_triangle(e);
                        t.push((0, 0));
                        t
                    },
                    BLACK.stroke_width(1),
                )
        }))
        .map_err(draw_err(RESIDUALS_FILE))?;
    if n > 0 {
        ann.label(label(n)).legend(|(x, y)| {
            EmptyElement::at((x + 12, y - 5))
                + Polygon::new(edge_triangle(Edge::Top), BLACK.mix(0.6).filled())
        });
    }
    Ok(n)
}

/// A half range for labels: `34.5` -> "34", `3.2` -> "3.2".
fn fmt_extent(m: f64) -> String {
    if m >= 10.0 {
        format!("{m:.0}")
    } else {
        format!("{m:.1}")
    }
}

fn residuals_time(d: &ResidualsData, area: &Area) -> Result<(), PlotError> {
    let f = RESIDUALS_FILE;
    let x = padded(Some(d.t_range), 0.0);
    let m = residual_extent(d);
    let clip = residual_clipping(d, m);
    let y = -m..m;
    let r = [x.start, -m, x.end, m];
    let caption = "accepted fixes' error against time";
    let mut chart = linear_chart(
        f,
        area,
        (x.clone(), y),
        ("time [s]", "fix error [m]"),
        caption,
    )?;
    shade_gps(f, &mut chart, &d.gps_on, (-m, m))?;
    let band = d
        .accepted
        .iter()
        .map(|a| (a.t_s, -3.0 * a.sigma_m, 3.0 * a.sigma_m));
    let band_label = if clip.sigma_bounds > 0 {
        format!(
            "claimed 3-sigma (cut at the edge for {} of {} fixes)",
            clip.sigma_bounds,
            d.accepted.len()
        )
    } else {
        "claimed 3-sigma".to_string()
    };
    draw_band(
        f,
        &mut chart,
        band,
        (-m, m),
        (VISNAV.mix(0.15), &band_label),
    )?;
    let zero = vec![(x.start, 0.0), (x.end, 0.0)];
    draw_line(
        f,
        &mut chart,
        vec![zero],
        BLACK.mix(0.5).stroke_width(1),
        "",
    )?;
    let north: Vec<(f64, f64)> = d.accepted.iter().map(|a| (a.t_s, a.north_m)).collect();
    let east: Vec<(f64, f64)> = d.accepted.iter().map(|a| (a.t_s, a.east_m)).collect();
    draw_dots(f, &mut chart, &north, (r, 4, VISNAV), "north error")?;
    draw_dots(f, &mut chart, &east, (r, 4, EAST), "east error")?;
    let beyond: Vec<((f64, f64), RGBColor)> = north
        .iter()
        .map(|&p| (p, VISNAV))
        .chain(east.iter().map(|&p| (p, EAST)))
        .collect();
    let ext = fmt_extent(m);
    draw_clipped(&mut chart, &beyond, r, |n| {
        format!("{n} off the scale (over {ext} m), drawn at the edge")
    })?;
    draw_rejected(&mut chart, &d.rejected_t_s, (x, m))?;
    if d.accepted.is_empty() {
        draw_note(f, &mut chart, "no accepted fix")?;
    }
    draw_legend(f, &mut chart, SeriesLabelPosition::UpperLeft)
}

/// The rejected attempts: a short tick each along the bottom of the panel.
fn draw_rejected(
    chart: &mut XyChart,
    times: &[f64],
    (x, m): (Range<f64>, f64),
) -> Result<(), PlotError> {
    let (lo, hi) = (-m, -m + 0.08 * m);
    let ticks: Vec<Vec<(f64, f64)>> = times
        .iter()
        .filter(|t| t.is_finite() && x.contains(t))
        .map(|&t| vec![(t, lo), (t, hi)])
        .collect();
    let label = format!("rejected attempts ({})", times.len());
    draw_line(
        RESIDUALS_FILE,
        chart,
        ticks,
        REJECTED.stroke_width(2),
        &label,
    )
}

fn residuals_scatter(d: &ResidualsData, area: &Area) -> Result<(), PlotError> {
    let f = RESIDUALS_FILE;
    let m = residual_extent(d);
    let area = area
        .titled("east against north", text(20))
        .map_err(draw_err(f))?;
    let r = equal_aspect([-m, -m, m, m], plot_size(f, &area, CHART_LABELS)?);
    let mut chart = linear_chart(
        f,
        &area,
        (r[0]..r[2], r[1]..r[3]),
        ("east error [m]", "north error [m]"),
        "",
    )?;
    let sig: Vec<f64> = d.accepted.iter().map(|a| a.sigma_m).collect();
    if let Some(s) = quantile(&sig, 0.5) {
        let circle: Vec<(f64, f64)> = (0..=120)
            .map(|k| {
                let a = f64::from(k) / 120.0 * std::f64::consts::TAU;
                (3.0 * s * a.cos(), 3.0 * s * a.sin())
            })
            .collect();
        let label = format!("median claimed 3-sigma ({:.1} m)", 3.0 * s);
        draw_line(
            f,
            &mut chart,
            clip_polyline(&circle, r),
            VISNAV.stroke_width(2),
            &label,
        )?;
    }
    let (out, ok): (Vec<&Residual>, Vec<&Residual>) =
        d.accepted.iter().partition(|a| a.beyond_3sigma);
    let en =
        |v: &[&Residual]| -> Vec<(f64, f64)> { v.iter().map(|a| (a.east_m, a.north_m)).collect() };
    draw_dots(
        f,
        &mut chart,
        &en(&ok),
        (r, 4, FIX),
        "within its own 3-sigma",
    )?;
    let n = out.len();
    draw_dots(
        f,
        &mut chart,
        &en(&out),
        (r, 5, CONTROL),
        &format!("beyond its own 3-sigma ({n})"),
    )?;
    let beyond: Vec<((f64, f64), RGBColor)> = en(&ok)
        .into_iter()
        .map(|p| (p, FIX))
        .chain(en(&out).into_iter().map(|p| (p, CONTROL)))
        .collect();
    draw_clipped(&mut chart, &beyond, r, |n| {
        format!("{n} off the scale, drawn at the edge")
    })?;
    draw_legend(f, &mut chart, SeriesLabelPosition::UpperLeft)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn count(img: &RgbImage, c: RGBColor) -> usize {
        img.pixels().filter(|p| p.0 == [c.0, c.1, c.2]).count()
    }

    fn target_dir() -> PathBuf {
        PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("target")
    }

    /// Saves, decodes again and checks the size and that the image is not blank.
    fn check_png(img: &RgbImage, name: &str, size: (u32, u32)) -> RgbImage {
        let path = target_dir().join(format!("plot_test_{name}"));
        save_png(img, &path).unwrap();
        let back = image::open(&path).unwrap().to_rgb8();
        assert_eq!(back.dimensions(), size, "{name}");
        let white = count(&back, WHITE);
        assert!(white < back.pixels().count(), "{name} is blank");
        back
    }

    /// 120 s at 10 Hz: GPS for 30 s, then visnav within metres and the control drifting away.
    fn synthetic_errors() -> ErrorsData {
        let t: Vec<f64> = (0..1200).map(|i| f64::from(i) * 0.1).collect();
        let on: Vec<bool> = t.iter().map(|&t| t < 30.0).collect();
        ErrorsData {
            title: "synthetic: horizontal position error".into(),
            visnav_m: t
                .iter()
                .map(|&t| 2.0 + (t * 0.3).sin().abs() * 3.0)
                .collect(),
            sigma_m: t
                .iter()
                .map(|&t| if t < 30.0 { 1.0 } else { 2.5 })
                .collect(),
            control_m: t
                .iter()
                .map(|&t| 1.0 + 0.02 * (t - 30.0).max(0.0).powi(2))
                .collect(),
            gps_on: periods(&t, &on),
            fixes: (4..12).map(|k| (f64::from(k) * 10.0, 2.5)).collect(),
            fixes_count: String::new(),
            t_s: t,
        }
    }

    #[test]
    fn errors_png_draws_both_panels() {
        let img = errors(&synthetic_errors()).unwrap();
        let back = check_png(&img, "errors.png", ERRORS_SIZE);
        for c in [VISNAV, CONTROL, FIX] {
            assert!(count(&back, c) > 50, "colour {c:?} missing");
        }
    }

    #[test]
    fn errors_png_survives_empty_and_nan_data() {
        let empty = errors(&ErrorsData::default()).unwrap();
        assert_eq!(empty.dimensions(), ERRORS_SIZE);
        let mut d = synthetic_errors();
        d.visnav_m.iter_mut().for_each(|v| *v = f64::NAN);
        d.control_m[5] = f64::INFINITY;
        d.sigma_m[7] = 0.0;
        assert!(errors(&d).is_ok());
    }

    fn synthetic_track(bg: Option<(&RgbImage, [f64; 4])>) -> TrackData<'_> {
        let t: Vec<f64> = (0..900).map(|i| f64::from(i) * 0.1).collect();
        let truth: Vec<(f64, f64)> = t
            .iter()
            .map(|&t| (500_000.0 + 600.0 * (t / 15.0).sin(), 5_200_000.0 + 8.0 * t))
            .collect();
        let err = |t: f64| {
            if t < 30.0 {
                0.5
            } else {
                2.0 + (t - 30.0) * 0.1
            }
        };
        TrackData {
            title: "synthetic: track".into(),
            crs: "UTM zone 14N (WGS84)".into(),
            background: bg,
            visnav: truth
                .iter()
                .zip(&t)
                .map(|(p, &t)| (p.0 + err(t), p.1))
                .collect(),
            control: truth
                .iter()
                .zip(&t)
                .map(|(p, &t)| (p.0 + (t - 30.0).max(0.0).powi(2) * 0.05, p.1))
                .collect(),
            outage: t.iter().map(|&t| t >= 30.0).collect(),
            fixes: truth.iter().step_by(50).copied().collect(),
            truth,
            t_s: t,
        }
    }

    #[test]
    fn track_png_draws_the_map_and_the_zoom() {
        let mut bg = RgbImage::new(64, 64);
        bg.pixels_mut().for_each(|p| p.0 = [90, 140, 90]);
        let extent = [499_000.0, 5_199_500.0, 501_000.0, 5_201_500.0];
        let d = synthetic_track(Some((&bg, extent)));
        let z = zoom_window(&d).unwrap();
        // The largest gap is at the end of the outage (7.99 m): the window is 8 times as wide.
        assert!((z[2] - z[0] - 63.92).abs() < 1e-6, "{z:?}");
        let img = track(&d).unwrap();
        let back = check_png(&img, "track.png", TRACK_SIZE);
        for c in [VISNAV, CONTROL, TRUTH, ZOOM] {
            assert!(count(&back, c) > 50, "colour {c:?} missing");
        }
        assert!(
            count(&back, RGBColor(90, 140, 90)) > 10_000,
            "background missing"
        );
        // The zoomed panel (right half) shows visnav and the truth apart.
        let right = image::imageops::crop_imm(&back, 900, 0, 900, 960).to_image();
        assert!(count(&right, VISNAV) > 200 && count(&right, TRUTH) > 200);
    }

    #[test]
    fn track_lines_are_drawn_over_the_fixes() {
        // A fix on every step, right on visnav's line: the line must stay as visible as without
        // them (the fixes lie under the lines), and the fixes must still show.
        let mut d = synthetic_track(None);
        d.fixes.clear();
        let bare = track(&d).unwrap();
        d.fixes = d.visnav.clone();
        let with = track(&d).unwrap();
        let left = |img: &RgbImage| image::imageops::crop_imm(img, 0, 0, 900, 960).to_image();
        let (a, b) = (count(&left(&bare), VISNAV), count(&left(&with), VISNAV));
        assert!(a > 500, "visnav line missing: {a} px");
        assert!(
            b * 100 >= a * 97,
            "fixes cover the visnav line: {b} of {a} px left"
        );
        let differ = left(&bare)
            .pixels()
            .zip(left(&with).pixels())
            .filter(|(p, q)| p != q)
            .count();
        assert!(differ > 500, "the fixes are not drawn: {differ} px differ");
    }

    fn residuals_with_spikes() -> ResidualsData {
        // 200 fixes within +-10 m claiming 3-sigma 12 m, four of them claiming 150 m, one of
        // those 150 m off to the north.
        let accepted: Vec<Residual> = (0..200)
            .map(|k| {
                let a = f64::from(k);
                let spike = k % 60 == 5;
                Residual {
                    t_s: 30.0 + a,
                    north_m: if k == 65 {
                        150.0
                    } else {
                        9.0 * (a * 0.7).sin()
                    },
                    east_m: 9.0 * (a * 1.3).cos(),
                    sigma_m: if spike { 50.0 } else { 4.0 },
                    beyond_3sigma: false,
                }
            })
            .collect();
        ResidualsData {
            title: "synthetic: fix residuals with spikes".into(),
            accepted,
            rejected_t_s: vec![41.0],
            gps_on: vec![(0.0, 30.0)],
            t_range: (0.0, 240.0),
        }
    }

    #[test]
    fn residual_range_comes_from_the_body_not_the_spikes() {
        let d = residuals_with_spikes();
        let m = residual_extent(&d);
        // The median claimed 3-sigma (12 m) and 99 % of the residuals (9 m), with headroom:
        // not the 150 m of the spikes.
        assert!((m - 12.0 * RESIDUAL_MARGIN).abs() < 1e-9, "half range {m}");
        assert_eq!(
            residual_clipping(&d, m),
            ResidualClipping {
                components: 1,
                sigma_bounds: 4
            }
        );
        let img = residuals(&d).unwrap();
        check_png(&img, "residuals_spikes.png", RESIDUALS_SIZE);
        // Without fixes: a unit range, nothing clipped.
        let empty = ResidualsData::default();
        assert_eq!(residual_extent(&empty), RESIDUAL_MARGIN);
        assert_eq!(residual_clipping(&empty, 1.0), ResidualClipping::default());
    }

    #[test]
    fn clipped_points_go_onto_the_edge_they_cross() {
        let r = [0.0, -10.0, 100.0, 10.0];
        assert_eq!(onto_edge((50.0, 5.0), r), None);
        assert_eq!(onto_edge((f64::NAN, 50.0), r), None);
        assert_eq!(onto_edge((50.0, 150.0), r), Some(((50.0, 10.0), Edge::Top)));
        assert_eq!(
            onto_edge((50.0, -11.0), r),
            Some(((50.0, -10.0), Edge::Bottom))
        );
        assert_eq!(
            onto_edge((130.0, 0.0), r),
            Some(((100.0, 0.0), Edge::Right))
        );
        // Beyond two edges: the farther in units of the panel (x: 0.1 widths, y: 2 heights).
        assert_eq!(onto_edge((-10.0, 50.0), r), Some(((0.0, 10.0), Edge::Top)));
    }

    #[test]
    fn track_png_without_background_or_outage() {
        let mut d = synthetic_track(None);
        d.outage.iter_mut().for_each(|o| *o = false);
        assert!(zoom_window(&d).is_none());
        assert_eq!(track(&d).unwrap().dimensions(), TRACK_SIZE);
        assert!(track(&TrackData::default()).is_ok());
    }

    #[test]
    fn residuals_png_draws_fixes_and_rejections() {
        let accepted: Vec<Residual> = (0..40)
            .map(|k| {
                let a = f64::from(k);
                Residual {
                    t_s: 30.0 + a * 2.0,
                    north_m: 3.0 * (a * 0.7).sin(),
                    east_m: 2.0 * (a * 1.3).cos(),
                    sigma_m: 1.5,
                    beyond_3sigma: k == 7,
                }
            })
            .collect();
        let d = ResidualsData {
            title: "synthetic: fix residuals".into(),
            accepted,
            rejected_t_s: vec![41.0, 55.0, 77.5],
            gps_on: vec![(0.0, 30.0)],
            t_range: (0.0, 120.0),
        };
        let img = residuals(&d).unwrap();
        let back = check_png(&img, "residuals.png", RESIDUALS_SIZE);
        for c in [VISNAV, EAST, FIX, REJECTED, CONTROL] {
            assert!(count(&back, c) > 20, "colour {c:?} missing");
        }
        assert!(residuals(&ResidualsData::default()).is_ok());
    }

    #[test]
    fn clipping_and_periods() {
        let r = [0.0, 0.0, 10.0, 10.0];
        let runs = clip_polyline(&[(-5.0, 5.0), (5.0, 5.0), (15.0, 5.0), (f64::NAN, 1.0)], r);
        assert_eq!(runs, vec![vec![(0.0, 5.0), (5.0, 5.0), (10.0, 5.0)]]);
        let runs = clip_polyline(
            &[
                (1.0, 1.0),
                (2.0, 2.0),
                (f64::NAN, 0.0),
                (3.0, 3.0),
                (4.0, 4.0),
            ],
            r,
        );
        assert_eq!(runs.len(), 2);
        assert!(clip_polyline(&[(20.0, 20.0), (30.0, 30.0)], r).is_empty());
        let t = [0.0, 1.0, 2.0, 3.0, 4.0];
        assert_eq!(
            periods(&t, &[true, true, false, true, true]),
            vec![(0.0, 2.0), (3.0, 4.0)]
        );
        assert_eq!(format_log_label(0.1), "0.1");
        assert_eq!(format_log_label(200.0), "200");
        assert_eq!(log_range([0.5, 300.0].into_iter()), 0.1..1000.0);
    }
}
