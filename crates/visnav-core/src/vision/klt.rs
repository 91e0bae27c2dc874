//! KLT feature tracking for frame-to-frame visual odometry: Shi-Tomasi corners, an image pyramid
//! that carries its gradients, Bouguet's pyramidal Lucas-Kanade and Kalal's forward-backward
//! check. Reference semantics: OpenCV's `buildOpticalFlowPyramid`, `goodFeaturesToTrack` and
//! `calcOpticalFlowPyrLK`; the differences are listed below.
//!
//! **Pyramid.** Level 0 is the image; level `L + 1` is OpenCV's `pyrDown` of level `L`: the 5x5
//! Gaussian `k k^T / 256`, `k = [1 4 6 4 1]`, with `BORDER_REFLECT_101`, keeping the even rows and
//! columns, size `((w + 1) / 2, (h + 1) / 2)`. Pixel `(x, y)` of level `L + 1` is centred on pixel
//! `(2x, 2y)` of level `L`, so a level-0 point `p` is `p / 2^L` at level `L` (pixel centres at
//! integers, as everywhere in `vision`). A level is added while both its sides exceed the tracking
//! window (OpenCV's rule), up to the caller's `max_level`. Each level stores its gradients:
//! Scharr's `[3 10 3]^T [-1 0 1] / 32` and its transpose (OpenCV's `calcSharrDeriv` without the
//! fixed-point scale), in grey levels per pixel, exact on a linear ramp; borders reflect-101.
//!
//! **Corners** (J. Shi, C. Tomasi, "Good features to track", CVPR 1994). The structure tensor
//! `M = sum_block [Ix^2 IxIy; IxIy Iy^2] / block^2` over a `block x block` box (reflect-101 at the
//! borders) gives the response `lambda_min(M) = (a + c - sqrt((a - c)^2 + 4 b^2)) / 2` (OpenCV's
//! `cornerMinEigenVal`). As in `goodFeaturesToTrack`, the candidates are the 3x3 local maxima
//! above `quality_level * max response`, taken strongest first and kept when no kept corner lies
//! within `min_distance_px` (looked up on a grid of cells of that side), up to `max_corners`.
//! Additions: an absolute floor on the response ([`FLAT_CORNER_RESPONSE`]), so a blank or uniform
//! image gives no corners; a margin `border_px` from the image edges (so the tracking window
//! fits); an optional spread grid (at most `k` corners per cell) so features cover the frame.
//! Differences: the gradients are the pyramid's Scharr, not `cornerMinEigenVal`'s Sobel, and the
//! response is the block mean, not the sum (the same ranking and relative threshold for a given
//! block size). Corners are at integer pixels, like OpenCV's. Order: strongest first, equal
//! responses in row-major order, so the output is deterministic.
//!
//! **Tracking** (J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature tracker:
//! description of the algorithm", Intel, 2000). From the top level down to 0, with the estimate
//! starting at the caller's guess (the predicted position, OpenCV's `OPTFLOW_USE_INITIAL_FLOW`) or
//! at the point itself, scaled to the level: the template is the `win x win` window of the
//! previous image around the point `u^L` (bilinear), with its gradients, and the spatial gradient
//! matrix `G = sum [Ix^2 IxIy; IxIy Iy^2]` (Bouguet eq. 19-20) is computed once per level. Then
//! `b_k = sum dI_k [Ix Iy]^T` with the image difference `dI_k = I(x) - J(x + v)` (eq. 28-29),
//! `eta = G^-1 b_k` (eq. 30) and `v += eta`, until `|eta| <= epsilon_px` or `max_iterations`,
//! plus OpenCV's oscillation rule (two opposite steps within 0.01 px: take the midpoint, stop).
//! The estimate passes to the next finer level doubled (eq. 34, the guess `g^L` folded into the
//! estimate). Only the template's gradients enter (Bouguet's form and OpenCV's), so a pyramid's
//! gradients serve when it is the previous image (the backward pass, the next frame pair).
//!
//! A level's template is flat (no texture or an edge only: the aperture problem) when
//! `lambda_min(G) / (1024 win^2) < min_eig_threshold`. That is OpenCV's `minEigThreshold` test:
//! OpenCV multiplies products of derivatives that are 32 times the gradient (its fixed-point
//! Scharr) by `2^-20`, so its matrix is `G / 1024`, and normalises by the window area. At level 0
//! a flat template, a window not fully inside the previous image or a final window not fully
//! inside the next image lose the point. At the coarser levels, as in OpenCV, such a level is
//! skipped (the estimate passes on unchanged), and a window that straddles the border is masked:
//! its outside samples get a zero template gradient (they add nothing to `G` or `b`) and
//! border-clamped intensities. (OpenCV pads its levels with zero derivatives too, but with
//! reflected intensities, and also tracks straddling windows at level 0; there the reflection is
//! not texture of the scene.) The residual is the mean absolute difference `sum |J - I| / win^2`
//! over the final level-0 window (OpenCV's `err`).
//!
//! **Forward-backward check** (Z. Kalal, K. Mikolajczyk, J. Matas, "Forward-Backward Error:
//! Automatic Detection of Tracking Failures", ICPR 2010). Every tracked point is tracked back from
//! the next image to the previous one (with the guess's motion reversed when a guess was given)
//! and lost when the backward track is lost or misses its start by more than `max_fb_error_px`.
//!
//! **Speed.** Each level keeps its gradients (and the coarser levels their intensities) with a
//! border `win / 2 + 2` pixels wide, zero gradients and replicated intensities, so any window
//! whose centre is inside reads its pixels straight from memory, with the values the border rule
//! gives (a window larger than the pyramid was built for goes through a patch filled by the same
//! rule). Points are tracked level by level (as in OpenCV), in row-major order, so the level's
//! planes stay in cache. Window rows are padded to a multiple of 8 floats (zeros in the padding)
//! and the sums accumulate into 8 lanes, which the compiler vectorises (a plain `sum()` is
//! serial). The detector streams its response rows; no full-size response image is stored. One
//! thread, no allocation per point. `visnav bench vo` times it per VGA frame (docs/status.md).
//!
//! Inputs from outside never panic: empty or non-finite images are errors, non-finite or outside
//! points are lost tracks.

use super::{GrayImage, VisionError};

/// Tracking window side in pixels (OpenCV's default `winSize` 21x21): 10 px of texture on each
/// side of the point, 441 samples per iteration.
pub const DEFAULT_WIN_SIZE_PX: usize = 21;
/// Pyramid levels above the image (OpenCV's default `maxLevel`): level 3 is 8 times coarser, so
/// motions of a few tens of pixels converge without a guess.
pub const DEFAULT_MAX_LEVEL: usize = 3;
/// Iterations per level (OpenCV's default criteria: 30 iterations or 0.01 px).
pub const DEFAULT_MAX_ITERATIONS: usize = 30;
/// Stop a level's iterations when the step is at most this long (OpenCV's default criteria).
pub const DEFAULT_EPSILON_PX: f32 = 0.01;
/// OpenCV's default `minEigThreshold`: the template's smallest eigenvalue, on OpenCV's scale
/// (see the module documentation), below which the window is flat.
pub const DEFAULT_MIN_EIG_THRESHOLD: f32 = 1e-4;
/// Largest forward-backward round-trip error of a kept track: correct tracks of textured windows
/// return within a few hundredths of a pixel (the tests here), drift and false matches by pixels.
pub const DEFAULT_MAX_FB_ERROR_PX: f32 = 0.5;

/// Corners kept by default: 200-300 features suffice for frame-to-frame odometry.
pub const DEFAULT_MAX_CORNERS: usize = 300;
/// Corners must reach this fraction of the strongest response (OpenCV's usual `qualityLevel`).
pub const DEFAULT_QUALITY_LEVEL: f32 = 0.01;
/// Smallest distance between two corners: half a tracking window, so windows overlap by half.
pub const DEFAULT_MIN_DISTANCE_PX: f32 = 10.0;
/// Structure-tensor box side (OpenCV's default `blockSize`).
pub const DEFAULT_BLOCK_SIZE_PX: usize = 3;
/// Corners keep this margin from the image edges: half the default window, so it fits.
pub const DEFAULT_BORDER_PX: usize = DEFAULT_WIN_SIZE_PX / 2;
/// Absolute floor of the corner response, `lambda_min` of the block-mean structure tensor in
/// (grey levels per pixel)^2: a weakest-direction RMS gradient of 0.1 grey level per pixel is
/// below 8-bit quantisation, so a weaker "corner" is noise on a flat image.
pub const FLAT_CORNER_RESPONSE: f32 = 0.01;

/// Largest accepted window side: the cost grows with its square; OpenCV has no bound.
const MAX_WIN_SIZE_PX: usize = 101;
/// Largest accepted `max_level`: level 16 is 65536 times coarser, beyond any image.
const MAX_PYRAMID_LEVEL: usize = 16;
/// Largest accepted iteration count, a bound on the work per point and level.
const MAX_ITERATIONS_LIMIT: usize = 1000;
/// Largest accepted corner block side: the box costs `block` passes per row.
const MAX_BLOCK_SIZE_PX: usize = 31;
/// Largest accepted spread-grid side in cells: a cell of a VGA frame is then 2-3 px wide.
const MAX_SPREAD_CELLS: usize = 256;
/// OpenCV's structure matrix is `G / 1024` (module documentation): `minEigThreshold`'s scale.
const OPENCV_EIG_SCALE: f32 = 1024.0;
/// OpenCV's oscillation rule: two successive steps cancelling within this many pixels.
const OSCILLATION_PX: f32 = 0.01;
/// Accumulator lanes (and row padding) of the window sums: two SSE or one AVX register.
const LANES: usize = 8;

fn klt_error(msg: impl Into<String>) -> VisionError {
    VisionError::Klt(msg.into())
}

// ---------------------------------------------------------------------------------------------
// Parameters

/// At most `max_per_cell` corners in each cell of a `cols x rows` grid over the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct SpreadGrid {
    /// Grid columns across the image.
    pub cols: usize,
    /// Grid rows down the image.
    pub rows: usize,
    /// Most corners kept in one cell (the strongest first).
    pub max_per_cell: usize,
}

/// Corner detection parameters, with `goodFeaturesToTrack`'s meanings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FeatureParams {
    /// Keep at most this many corners, strongest first; 0 keeps all (OpenCV's `maxCorners <= 0`).
    pub max_corners: usize,
    /// Keep responses above this fraction of the strongest, in `(0, 1]` (`qualityLevel`).
    pub quality_level: f32,
    /// Smallest Euclidean distance between kept corners (`minDistance`); 0 disables.
    pub min_distance_px: f32,
    /// Side of the structure-tensor box, odd (`blockSize`).
    pub block_size_px: usize,
    /// Smallest distance from a corner to the image edges (at least 1, for the 3x3 maximum).
    pub border_px: usize,
    /// Optional spread: at most `max_per_cell` corners per grid cell.
    pub spread: Option<SpreadGrid>,
}

impl Default for FeatureParams {
    fn default() -> Self {
        Self {
            max_corners: DEFAULT_MAX_CORNERS,
            quality_level: DEFAULT_QUALITY_LEVEL,
            min_distance_px: DEFAULT_MIN_DISTANCE_PX,
            block_size_px: DEFAULT_BLOCK_SIZE_PX,
            border_px: DEFAULT_BORDER_PX,
            spread: None,
        }
    }
}

impl FeatureParams {
    /// Check ranges; names the offending field.
    pub fn validate(&self) -> Result<(), VisionError> {
        if !(self.quality_level > 0.0 && self.quality_level <= 1.0) {
            return Err(klt_error("`quality_level` must be in (0, 1]"));
        }
        if !(self.min_distance_px.is_finite() && self.min_distance_px >= 0.0) {
            return Err(klt_error("`min_distance_px` must be finite and >= 0"));
        }
        let b = self.block_size_px;
        if b.is_multiple_of(2) || b > MAX_BLOCK_SIZE_PX {
            return Err(klt_error(format!(
                "`block_size_px` must be odd and in 1..={MAX_BLOCK_SIZE_PX}"
            )));
        }
        if let Some(g) = self.spread
            && !((1..=MAX_SPREAD_CELLS).contains(&g.cols)
                && (1..=MAX_SPREAD_CELLS).contains(&g.rows)
                && g.max_per_cell > 0)
        {
            return Err(klt_error(format!(
                "`spread` needs `cols` and `rows` in 1..={MAX_SPREAD_CELLS}, `max_per_cell` > 0"
            )));
        }
        Ok(())
    }
}

/// Tracking parameters, with `calcOpticalFlowPyrLK`'s meanings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackParams {
    /// Window side, odd, in 3..=101 (`winSize`).
    pub win_size_px: usize,
    /// Top pyramid level used (`maxLevel`); the pyramids may have fewer levels.
    pub max_level: usize,
    /// Iterations per level, in 1..=1000 (`criteria.maxCount`).
    pub max_iterations: usize,
    /// Stop a level when the step is at most this long (`criteria.epsilon`).
    pub epsilon_px: f32,
    /// Flat-window threshold on OpenCV's scale (`minEigThreshold`).
    pub min_eig_threshold: f32,
    /// [`track_checked`]: largest forward-backward round-trip error of a kept track.
    pub max_fb_error_px: f32,
}

impl Default for TrackParams {
    fn default() -> Self {
        Self {
            win_size_px: DEFAULT_WIN_SIZE_PX,
            max_level: DEFAULT_MAX_LEVEL,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            epsilon_px: DEFAULT_EPSILON_PX,
            min_eig_threshold: DEFAULT_MIN_EIG_THRESHOLD,
            max_fb_error_px: DEFAULT_MAX_FB_ERROR_PX,
        }
    }
}

impl TrackParams {
    /// Check ranges; names the offending field.
    pub fn validate(&self) -> Result<(), VisionError> {
        validate_win_size(self.win_size_px)?;
        if self.max_level > MAX_PYRAMID_LEVEL {
            return Err(klt_error(format!(
                "`max_level` must be at most {MAX_PYRAMID_LEVEL}"
            )));
        }
        if !(1..=MAX_ITERATIONS_LIMIT).contains(&self.max_iterations) {
            return Err(klt_error(format!(
                "`max_iterations` must be in 1..={MAX_ITERATIONS_LIMIT}"
            )));
        }
        if !(self.epsilon_px.is_finite() && self.epsilon_px >= 0.0) {
            return Err(klt_error("`epsilon_px` must be finite and >= 0"));
        }
        if !(self.min_eig_threshold.is_finite() && self.min_eig_threshold >= 0.0) {
            return Err(klt_error("`min_eig_threshold` must be finite and >= 0"));
        }
        if !(self.max_fb_error_px.is_finite() && self.max_fb_error_px > 0.0) {
            return Err(klt_error("`max_fb_error_px` must be finite and > 0"));
        }
        Ok(())
    }
}

fn validate_win_size(win_size_px: usize) -> Result<(), VisionError> {
    if win_size_px.is_multiple_of(2) || !(3..=MAX_WIN_SIZE_PX).contains(&win_size_px) {
        return Err(klt_error(format!(
            "`win_size_px` must be odd and in 3..={MAX_WIN_SIZE_PX}"
        )));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Image checks and borders

/// Non-empty with finite pixels. The finiteness test sums `0 v` (0, or NaN for NaN and +-inf)
/// into 8 lanes so it vectorises.
fn check_image(img: &GrayImage) -> Result<(), VisionError> {
    if img.width() == 0 || img.height() == 0 || img.data().is_empty() {
        return Err(klt_error(format!(
            "image size {}x{}: both sides must be positive",
            img.width(),
            img.height()
        )));
    }
    let chunks = img.data().chunks_exact(LANES);
    let rest = chunks.remainder();
    let mut acc = [0f32; LANES];
    for c in chunks {
        for k in 0..LANES {
            acc[k] += c[k] * 0.0;
        }
    }
    if acc.iter().chain(rest).all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(klt_error("image has non-finite pixels"))
    }
}

/// OpenCV's `BORDER_REFLECT_101` index (`gfedcb|abcdefgh|gfedcba`) for any `i`; 0 when `n <= 1`.
fn reflect101(i: isize, n: usize) -> usize {
    if n <= 1 {
        return 0;
    }
    let period = 2 * (n as isize - 1);
    let m = i.rem_euclid(period);
    (if m < n as isize { m } else { period - m }) as usize
}

// ---------------------------------------------------------------------------------------------
// Pyramid

/// One pyramid level: the image and its Scharr gradients (grey levels per pixel). For the
/// tracker's windows the gradients are stored with a zero border and the coarser levels'
/// intensities with a replicated border, `pad` pixels wide, so a window whose centre is inside
/// reads its pixels straight from memory with the same values the border rule gives.
#[derive(Clone, Debug)]
pub struct PyramidLevel {
    image: GrayImage,
    /// Level 0: `None`, the image is read directly (its template windows lie inside).
    intensity: Option<Padded>,
    grad_x: Padded,
    grad_y: Padded,
}

impl PyramidLevel {
    fn new(image: GrayImage, pad: usize, pad_intensity: bool) -> Self {
        let (grad_x, grad_y) = scharr_gradients(&image, pad);
        let intensity = pad_intensity.then(|| Padded::replicate(&image, pad));
        Self {
            image,
            intensity,
            grad_x,
            grad_y,
        }
    }
    /// The level's image.
    pub fn image(&self) -> &GrayImage {
        &self.image
    }
    /// `[dI/dx, dI/dy]` (Scharr / 32) at pixel `(x, y)`; `None` outside.
    pub fn gradient(&self, x: usize, y: usize) -> Option<[f32; 2]> {
        (x < self.width() && y < self.height())
            .then(|| [self.grad_x.view().row(y)[x], self.grad_y.view().row(y)[x]])
    }
    fn width(&self) -> usize {
        self.image.width()
    }
    fn height(&self) -> usize {
        self.image.height()
    }
    /// Intensity, `dI/dx`, `dI/dy`.
    fn planes(&self) -> [Plane<'_>; 3] {
        let img = match &self.intensity {
            Some(p) => p.view(),
            None => Plane {
                data: self.image.data(),
                w: self.width(),
                h: self.height(),
                pad: 0,
            },
        };
        [img, self.grad_x.view(), self.grad_y.view()]
    }
}

/// A row-major `w x h` plane stored with `pad` extra pixels on every side.
#[derive(Clone, Debug)]
struct Padded {
    data: Vec<f32>,
    w: usize,
    h: usize,
    pad: usize,
}

impl Padded {
    fn zeros(w: usize, h: usize, pad: usize) -> Self {
        Self {
            data: vec![0.0; (w + 2 * pad) * (h + 2 * pad)],
            w,
            h,
            pad,
        }
    }
    /// `img` with its border pixels replicated outwards.
    fn replicate(img: &GrayImage, pad: usize) -> Self {
        let (w, h) = (img.width(), img.height());
        let mut p = Self::zeros(w, h, pad);
        let stride = w + 2 * pad;
        for (r, row) in p.data.chunks_exact_mut(stride).enumerate() {
            let y = r.saturating_sub(pad).min(h - 1);
            let src = &img.data()[y * w..(y + 1) * w];
            row[..pad].fill(src[0]);
            row[pad..pad + w].copy_from_slice(src);
            row[pad + w..].fill(src[w - 1]);
        }
        p
    }
    fn view(&self) -> Plane<'_> {
        Plane {
            data: &self.data,
            w: self.w,
            h: self.h,
            pad: self.pad,
        }
    }
    fn row_mut(&mut self, y: usize) -> &mut [f32] {
        let stride = self.w + 2 * self.pad;
        &mut self.data[(y + self.pad) * stride + self.pad..][..self.w]
    }
}

/// A borrowed [`Padded`] plane (or an image, `pad` 0).
#[derive(Clone, Copy)]
struct Plane<'a> {
    data: &'a [f32],
    w: usize,
    h: usize,
    pad: usize,
}

impl<'a> Plane<'a> {
    fn stride(&self) -> usize {
        self.w + 2 * self.pad
    }
    /// The `w` pixels of row `y < h`.
    fn row(&self, y: usize) -> &'a [f32] {
        &self.data[(y + self.pad) * self.stride() + self.pad..][..self.w]
    }
}

/// An image pyramid with per-level gradients (OpenCV's `buildOpticalFlowPyramid` with
/// derivatives). Always at least level 0; pixels are finite.
#[derive(Clone, Debug)]
pub struct Pyramid {
    levels: Vec<PyramidLevel>,
}

impl Pyramid {
    /// Levels `0..=max_level` of `img`, stopping before a level whose width or height would not
    /// exceed `win_size_px` (odd, 3..=101). Fails on an empty image, non-finite pixels or bad
    /// parameters.
    pub fn new(img: &GrayImage, max_level: usize, win_size_px: usize) -> Result<Self, VisionError> {
        Self::from_image(img.clone(), max_level, win_size_px)
    }

    /// [`Pyramid::new`] taking the image as level 0 (no copy; it stays readable through
    /// [`Pyramid::levels`]).
    pub fn from_image(
        img: GrayImage,
        max_level: usize,
        win_size_px: usize,
    ) -> Result<Self, VisionError> {
        check_image(&img)?;
        validate_win_size(win_size_px)?;
        if max_level > MAX_PYRAMID_LEVEL {
            return Err(klt_error(format!(
                "`max_level` must be at most {MAX_PYRAMID_LEVEL}"
            )));
        }
        // A window whose centre is inside reads up to `half + 1` pixels beyond the edge.
        let pad = win_size_px / 2 + 2;
        let mut levels = vec![PyramidLevel::new(img, pad, false)];
        while let Some(last) = levels.last()
            && levels.len() <= max_level
        {
            let (w, h) = (last.width().div_ceil(2), last.height().div_ceil(2));
            if w <= win_size_px || h <= win_size_px {
                break;
            }
            let down = pyr_down(&last.image)?;
            levels.push(PyramidLevel::new(down, pad, true));
        }
        Ok(Self { levels })
    }

    /// The levels, finest (the image) first.
    pub fn levels(&self) -> &[PyramidLevel] {
        &self.levels
    }

    /// [`good_features`] on level 0, reusing its gradients.
    pub fn good_features(&self, params: &FeatureParams) -> Result<Vec<[f32; 2]>, VisionError> {
        self.good_features_where(params, |_| true)
    }

    /// [`Self::good_features`] among the candidates at which `keep` holds (a region of
    /// interest): the quality threshold still follows the strongest response of the whole image
    /// (OpenCV's `mask` argument), the cap, spacing and spread are spent inside the region only.
    pub fn good_features_where(
        &self,
        params: &FeatureParams,
        keep: impl Fn([f32; 2]) -> bool,
    ) -> Result<Vec<[f32; 2]>, VisionError> {
        params.validate()?;
        let Some(l0) = self.levels.first() else {
            return Ok(Vec::new());
        };
        Ok(detect_corners_where(
            l0.grad_x.view(),
            l0.grad_y.view(),
            params,
            keep,
        ))
    }
}

/// OpenCV's `pyrDown`: the 5x5 Gaussian `[1 4 6 4 1]^T [1 4 6 4 1] / 256` (reflect-101 borders),
/// then the even rows and columns; size `((w + 1) / 2, (h + 1) / 2)`. Fails on an empty image.
pub fn pyr_down(img: &GrayImage) -> Result<GrayImage, VisionError> {
    let (w, h) = (img.width(), img.height());
    if w == 0 || h == 0 {
        return Err(klt_error("pyr_down of an empty image"));
    }
    let (dw, dh) = (w.div_ceil(2), h.div_ceil(2));
    let src = img.data();
    // Vertical pass at the kept rows (full width, vectorised), then the horizontal pass at the
    // kept columns: the strided work is done on a quarter of the pixels only.
    let mut column = vec![0f32; w];
    let mut dst = vec![0f32; dw * dh];
    for (y, out) in dst.chunks_exact_mut(dw).enumerate() {
        let row = |d: isize| {
            let i = reflect101(2 * y as isize + d, h);
            &src[i * w..(i + 1) * w]
        };
        let (a, b, c, d, e) = (row(-2), row(-1), row(0), row(1), row(2));
        let taps = column.iter_mut().zip(a).zip(b).zip(c).zip(d).zip(e);
        for (((((o, a), b), c), d), e) in taps {
            *o = (a + e + 4.0 * (b + d) + 6.0 * c) * (1.0 / 256.0);
        }
        smooth_decimate_row(&column, out);
    }
    GrayImage::new(dw, dh, dst)
}

/// `out[x] = sum_k [1 4 6 4 1]_k row[2x + k - 2]` (reflect-101 at the ends).
fn smooth_decimate_row(row: &[f32], out: &mut [f32]) {
    let n = row.len();
    let at = |i: usize, d: isize| row[reflect101(i as isize + d, n)];
    for (x, o) in out.iter_mut().enumerate() {
        let c = 2 * x;
        *o = if c >= 2 && c + 2 < n {
            let s = &row[c - 2..c + 3];
            s[0] + s[4] + 4.0 * (s[1] + s[3]) + 6.0 * s[2]
        } else {
            at(c, -2) + at(c, 2) + 4.0 * (at(c, -1) + at(c, 1)) + 6.0 * at(c, 0)
        };
    }
}

/// Scharr gradients / 32 (grey levels per pixel), reflect-101 borders. OpenCV's order: vertical
/// smoothing `s = 3 (a + c) + 10 b` and difference `d = c - a` of the rows above, at and below,
/// then `gx = (s[x+1] - s[x-1]) / 32`, `gy = (3 (d[x-1] + d[x+1]) + 10 d[x]) / 32`.
fn scharr_gradients(img: &GrayImage, pad: usize) -> (Padded, Padded) {
    let (w, h) = (img.width(), img.height());
    let src = img.data();
    let mut gx = Padded::zeros(w, h, pad);
    let mut gy = Padded::zeros(w, h, pad);
    let (mut s, mut d) = (vec![0f32; w], vec![0f32; w]);
    let row = |i: usize| &src[i * w..(i + 1) * w];
    for y in 0..h {
        let a = row(reflect101(y as isize - 1, h));
        let b = row(y);
        let c = row(reflect101(y as isize + 1, h));
        for ((((s, d), a), b), c) in s.iter_mut().zip(d.iter_mut()).zip(a).zip(b).zip(c) {
            *s = 3.0 * (a + c) + 10.0 * b;
            *d = c - a;
        }
        scharr_row(&s, &d, gx.row_mut(y), gy.row_mut(y));
    }
    (gx, gy)
}

fn scharr_row(s: &[f32], d: &[f32], gx: &mut [f32], gy: &mut [f32]) {
    const NORM: f32 = 1.0 / 32.0;
    let w = s.len();
    if w == 0 {
        return;
    }
    if w >= 3 {
        let inner = gx[1..w - 1].iter_mut().zip(&s[2..]).zip(&s[..w - 2]);
        for ((o, sp), sm) in inner {
            *o = (sp - sm) * NORM;
        }
        let inner = gy[1..w - 1]
            .iter_mut()
            .zip(&d[2..])
            .zip(&d[1..])
            .zip(&d[..w - 2]);
        for (((o, dp), dc), dm) in inner {
            *o = (3.0 * (dp + dm) + 10.0 * dc) * NORM;
        }
    }
    for x in [0, w - 1] {
        let (m, p) = (reflect101(x as isize - 1, w), reflect101(x as isize + 1, w));
        gx[x] = (s[p] - s[m]) * NORM;
        gy[x] = (3.0 * (d[m] + d[p]) + 10.0 * d[x]) * NORM;
    }
}

// ---------------------------------------------------------------------------------------------
// Corners

/// Shi-Tomasi corners of `img` (module documentation): strongest first, at most
/// `params.max_corners`. Fails on an empty image, non-finite pixels or bad parameters.
pub fn good_features(
    img: &GrayImage,
    params: &FeatureParams,
) -> Result<Vec<[f32; 2]>, VisionError> {
    params.validate()?;
    check_image(img)?;
    let (gx, gy) = scharr_gradients(img, 0);
    Ok(detect_corners(gx.view(), gy.view(), params))
}

fn detect_corners(gx: Plane<'_>, gy: Plane<'_>, p: &FeatureParams) -> Vec<[f32; 2]> {
    detect_corners_where(gx, gy, p, |_| true)
}

fn detect_corners_where(
    gx: Plane<'_>,
    gy: Plane<'_>,
    p: &FeatureParams,
    keep: impl Fn([f32; 2]) -> bool,
) -> Vec<[f32; 2]> {
    let (mut keys, max) = corner_candidates(gx, gy, p.block_size_px, p.border_px.max(1));
    let threshold = p.quality_level * max;
    let w = gx.w;
    keys.retain(|&k| {
        let i = key_index(k);
        key_response(k) > threshold && keep([(i % w) as f32, (i / w) as f32])
    });
    keys.sort_unstable_by(|a, b| b.cmp(a));
    select_corners(&keys, gx.w, gx.h, p)
}

/// One pass over the rows: each row's response (three rows kept), the 3x3 local maxima above
/// [`FLAT_CORNER_RESPONSE`] of the row before it (at least `border` from the edges), and the
/// largest response of the image. The relative threshold, which needs that maximum, is applied
/// to the candidates afterwards, so no full-size response image is stored.
fn corner_candidates(gx: Plane<'_>, gy: Plane<'_>, block: usize, border: usize) -> (Vec<u64>, f32) {
    let (w, h) = (gx.w, gx.h);
    let mut responses = ResponseRows::new(gx, gy, block);
    let mut rows = [vec![0f32; w], vec![0f32; w], vec![0f32; w]];
    let mut nmax = vec![0f32; w];
    let mut max = [0f32; LANES];
    let mut keys = Vec::new();
    for y in 0..h {
        let row = &mut rows[y % 3];
        responses.row(y, row);
        for chunk in row.chunks(LANES) {
            for (m, v) in max.iter_mut().zip(chunk) {
                *m = fmax(*m, *v);
            }
        }
        // Row `y - 1` is tested once row `y` exists.
        if y >= 2 && y > border && y - 1 + border < h {
            let [a, b, c] = [&rows[(y - 2) % 3], &rows[(y - 1) % 3], &rows[y % 3]];
            let mut hits = RowMaxima {
                y: y - 1,
                border,
                nmax: &mut nmax,
                keys: &mut keys,
            };
            hits.find(a, b, c);
        }
    }
    (keys, max.iter().fold(0f32, |m, v| fmax(m, *v)))
}

/// The response rows of a gradient pair, `lambda_min` of the block-mean structure tensor. Each
/// source row's products `Ix^2, Ix Iy, Iy^2`, boxed along the row, are computed once into a ring
/// of `block` rows; an output row sums the ring's rows.
struct ResponseRows<'a> {
    gx: Plane<'a>,
    gy: Plane<'a>,
    r: isize,
    scale: f32,
    ring: ProductRing,
    sums: [Vec<f32>; 3],
}

impl<'a> ResponseRows<'a> {
    fn new(gx: Plane<'a>, gy: Plane<'a>, block: usize) -> Self {
        let w = gx.w;
        Self {
            gx,
            gy,
            r: (block / 2) as isize,
            scale: 0.5 / (block * block) as f32,
            ring: ProductRing::new(w, block),
            sums: [vec![0f32; w], vec![0f32; w], vec![0f32; w]],
        }
    }

    /// Row `y`'s responses into `out` (`w` long).
    fn row(&mut self, y: usize, out: &mut [f32]) {
        let (w, h, r, scale) = (self.gx.w, self.gx.h, self.r, self.scale);
        let rows = |dy: isize| reflect101(y as isize + dy, h);
        for dy in -r..=r {
            self.ring.prepare(rows(dy), self.gx, self.gy);
        }
        let ring = &self.ring;
        if r == 1 {
            // The default 3x3 block: the three rows summed in the eigenvalue pass.
            let [p, q, t] = [ring.get(rows(-1)), ring.get(rows(0)), ring.get(rows(1))];
            let (xx, xy, yy) = (
                [&p[0][..w], &q[0][..w], &t[0][..w]],
                [&p[1][..w], &q[1][..w], &t[1][..w]],
                [&p[2][..w], &q[2][..w], &t[2][..w]],
            );
            let out = &mut out[..w];
            for i in 0..w {
                let a = xx[0][i] + xx[1][i] + xx[2][i];
                let b = xy[0][i] + xy[1][i] + xy[2][i];
                let c = yy[0][i] + yy[1][i] + yy[2][i];
                out[i] = min_eigenvalue(a, b, c, scale);
            }
            return;
        }
        for (k, dy) in (-r..=r).enumerate() {
            for (s, p) in self.sums.iter_mut().zip(ring.get(rows(dy))) {
                if k == 0 {
                    s.copy_from_slice(p);
                } else {
                    for (s, p) in s.iter_mut().zip(p) {
                        *s += p;
                    }
                }
            }
        }
        let [a, b, c] = &self.sums;
        for (((o, a), b), c) in out.iter_mut().zip(a).zip(b).zip(c) {
            *o = min_eigenvalue(*a, *b, *c, scale);
        }
    }
}

/// `2 scale lambda_min([a b; b c]) = scale (a + c - sqrt((a - c)^2 + 4 b^2))`.
#[inline(always)]
fn min_eigenvalue(a: f32, b: f32, c: f32, scale: f32) -> f32 {
    let t = a - c;
    ((a + c) - (t * t + 4.0 * b * b).sqrt()) * scale
}

/// The row-boxed gradient products of the last `block` source rows used, slot `row % block`.
struct ProductRing {
    r: usize,
    tags: Vec<usize>,
    rows: Vec<[Vec<f32>; 3]>,
    scratch: [Vec<f32>; 3],
}

impl ProductRing {
    fn new(w: usize, block: usize) -> Self {
        let row = || [vec![0f32; w], vec![0f32; w], vec![0f32; w]];
        Self {
            r: block / 2,
            tags: vec![usize::MAX; block],
            rows: (0..block).map(|_| row()).collect(),
            scratch: row(),
        }
    }

    /// Compute `[box(Ix^2), box(Ix Iy), box(Iy^2)]` of source row `y` unless held.
    fn prepare(&mut self, y: usize, gx: Plane<'_>, gy: Plane<'_>) {
        let slot = y % self.tags.len();
        if self.tags[slot] == y {
            return;
        }
        let [xx, xy, yy] = &mut self.scratch;
        let products = xx.iter_mut().zip(xy.iter_mut()).zip(yy.iter_mut());
        for (((xx, xy), yy), (a, b)) in products.zip(gx.row(y).iter().zip(gy.row(y))) {
            *xx = a * a;
            *xy = a * b;
            *yy = b * b;
        }
        for (src, dst) in self.scratch.iter().zip(self.rows[slot].iter_mut()) {
            box_sum_row(src, self.r, dst);
        }
        self.tags[slot] = y;
    }

    /// Row `y`'s products, [`ProductRing::prepare`]d (among the last `block` rows).
    fn get(&self, y: usize) -> &[Vec<f32>; 3] {
        &self.rows[y % self.tags.len()]
    }
}

/// `dst[x] = sum_{k=-r..=r} src[x + k]`, reflect-101 at the ends.
fn box_sum_row(src: &[f32], r: usize, dst: &mut [f32]) {
    let w = src.len();
    let inner = if w > 2 * r { r..w - r } else { w..w };
    if !inner.is_empty() {
        let out = &mut dst[inner.clone()];
        if r == 1 {
            // The default 3x3 block in one pass.
            for (((o, a), b), c) in out.iter_mut().zip(src).zip(&src[1..]).zip(&src[2..]) {
                *o = a + b + c;
            }
        } else {
            out.copy_from_slice(&src[..w - 2 * r]);
            for k in 1..=2 * r {
                for (o, v) in out.iter_mut().zip(&src[k..]) {
                    *o += v;
                }
            }
        }
    }
    let edges = if inner.is_empty() { 0..w } else { 0..r };
    for x in edges.chain(inner.end..w) {
        let xi = x as isize;
        dst[x] = (-(r as isize)..=r as isize)
            .map(|k| src[reflect101(xi + k, w)])
            .sum();
    }
}

/// Sort key of a corner: the response's bits (positive floats order as their bits) above the
/// complemented pixel index, so a descending sort is strongest first, ties in row-major order.
fn corner_key(response: f32, index: usize) -> u64 {
    (u64::from(response.to_bits()) << 32) | u64::from(u32::MAX - index as u32)
}

fn key_index(key: u64) -> usize {
    (u32::MAX - key as u32) as usize
}

fn key_response(key: u64) -> f32 {
    f32::from_bits((key >> 32) as u32)
}

/// The 3x3 local maxima of a response row: pixels at least `border` (>= 1) from the side edges
/// whose response exceeds [`FLAT_CORNER_RESPONSE`] and is not below any of its 8 neighbours
/// (OpenCV's dilate-and-compare), appended to `keys`.
struct RowMaxima<'a> {
    y: usize,
    border: usize,
    /// Scratch, the neighbours' maximum.
    nmax: &'a mut [f32],
    keys: &'a mut Vec<u64>,
}

impl RowMaxima<'_> {
    /// `a`, `b`, `c`: the rows above, at and below. The neighbours' maximum is computed over
    /// equally long shifted slices (vectorised); the rare hits are then collected.
    fn find(&mut self, a: &[f32], b: &[f32], c: &[f32]) {
        let (w, border) = (b.len(), self.border);
        if w <= 2 * border {
            return;
        }
        let n = w - 2 * border;
        // Row `row` shifted by `dx - 1`, over the tested columns `border..w - border`.
        let at = |row, dx| shifted(row, border + dx - 1, n);
        let (a0, a1, a2) = (at(a, 0), at(a, 1), at(a, 2));
        let (b0, b2) = (at(b, 0), at(b, 2));
        let (c0, c1, c2) = (at(c, 0), at(c, 1), at(c, 2));
        let nmax = &mut self.nmax[..n];
        for i in 0..n {
            let top = fmax(fmax(a0[i], a1[i]), a2[i]);
            let bottom = fmax(fmax(c0[i], c1[i]), c2[i]);
            nmax[i] = fmax(fmax(top, bottom), fmax(b0[i], b2[i]));
        }
        for (i, (&v, &m)) in at(b, 1).iter().zip(nmax.iter()).enumerate() {
            if v > FLAT_CORNER_RESPONSE && v >= m {
                self.keys.push(corner_key(v, self.y * w + border + i));
            }
        }
    }
}

/// `row[start..start + n]`, with the lifetime of `row`.
fn shifted(row: &[f32], start: usize, n: usize) -> &[f32] {
    &row[start..][..n]
}

/// `max(a, b)` for non-NaN values as one SIMD instruction (`f32::max`'s NaN rule costs more).
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// Greedy selection in key order: a corner is kept when its spread cell has room and no kept
/// corner is nearer than `min_distance_px`.
fn select_corners(keys: &[u64], w: usize, h: usize, p: &FeatureParams) -> Vec<[f32; 2]> {
    let limit = if p.max_corners == 0 {
        usize::MAX
    } else {
        p.max_corners
    };
    let mut near = MinDistanceGrid::new(w, h, p.min_distance_px);
    let mut spread = p.spread.map(|g| SpreadCounter::new(g, w, h));
    let mut out = Vec::new();
    for &key in keys {
        if out.len() >= limit {
            break;
        }
        let i = key_index(key);
        let pt = [(i % w) as f32, (i / w) as f32];
        if spread.as_ref().is_some_and(|s| s.is_full(pt)) || near.has_neighbour(pt) {
            continue;
        }
        near.insert(pt);
        if let Some(s) = spread.as_mut() {
            s.add(pt);
        }
        out.push(pt);
    }
    out
}

/// Kept corners bucketed in square cells of side `min_distance`: any corner nearer than that
/// lies in the 3x3 cells around a point.
struct MinDistanceGrid {
    min_d2: f32,
    side: f32,
    cols: usize,
    rows: usize,
    cells: Vec<Vec<[f32; 2]>>,
}

impl MinDistanceGrid {
    fn new(w: usize, h: usize, min_distance_px: f32) -> Self {
        let side = min_distance_px.max(1.0);
        let cols = ((w as f32 / side).ceil() as usize).max(1);
        let rows = ((h as f32 / side).ceil() as usize).max(1);
        // Distinct pixels are at least 1 px apart: a smaller distance never rejects.
        let n = if min_distance_px > 1.0 {
            cols * rows
        } else {
            0
        };
        Self {
            min_d2: min_distance_px * min_distance_px,
            side,
            cols,
            rows,
            cells: vec![Vec::new(); n],
        }
    }
    fn cell(&self, pt: [f32; 2]) -> (usize, usize) {
        let cx = ((pt[0] / self.side) as usize).min(self.cols - 1);
        let cy = ((pt[1] / self.side) as usize).min(self.rows - 1);
        (cx, cy)
    }
    fn has_neighbour(&self, pt: [f32; 2]) -> bool {
        if self.cells.is_empty() {
            return false;
        }
        let (cx, cy) = self.cell(pt);
        for y in cy.saturating_sub(1)..=(cy + 1).min(self.rows - 1) {
            for x in cx.saturating_sub(1)..=(cx + 1).min(self.cols - 1) {
                let close = self.cells[y * self.cols + x].iter().any(|q| {
                    let (dx, dy) = (q[0] - pt[0], q[1] - pt[1]);
                    dx * dx + dy * dy < self.min_d2
                });
                if close {
                    return true;
                }
            }
        }
        false
    }
    fn insert(&mut self, pt: [f32; 2]) {
        if self.cells.is_empty() {
            return;
        }
        let (cx, cy) = self.cell(pt);
        self.cells[cy * self.cols + cx].push(pt);
    }
}

/// Corner counts per cell of a [`SpreadGrid`].
pub(crate) struct SpreadCounter {
    grid: SpreadGrid,
    w: usize,
    h: usize,
    counts: Vec<usize>,
}

impl SpreadCounter {
    pub(crate) fn new(grid: SpreadGrid, w: usize, h: usize) -> Self {
        Self {
            grid,
            w,
            h,
            counts: vec![0; grid.cols * grid.rows],
        }
    }
    fn index(&self, pt: [f32; 2]) -> usize {
        let cx = (pt[0] as usize * self.grid.cols / self.w).min(self.grid.cols - 1);
        let cy = (pt[1] as usize * self.grid.rows / self.h).min(self.grid.rows - 1);
        cy * self.grid.cols + cx
    }
    pub(crate) fn is_full(&self, pt: [f32; 2]) -> bool {
        self.counts[self.index(pt)] >= self.grid.max_per_cell
    }
    pub(crate) fn add(&mut self, pt: [f32; 2]) {
        let i = self.index(pt);
        self.counts[i] += 1;
    }
    /// Cells holding at least one point.
    pub(crate) fn covered(&self) -> usize {
        self.counts.iter().filter(|c| **c > 0).count()
    }
}

// ---------------------------------------------------------------------------------------------
// Tracking

/// Why a point was lost.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum LostReason {
    /// The point or its guess is not finite.
    InvalidPoint,
    /// The level-0 window is not fully inside the previous image, or the estimate left the next
    /// image (its window at the end, its centre during the iterations).
    OutOfImage,
    /// The level-0 template is flat or an edge: `lambda_min` below `min_eig_threshold`.
    Flat,
    /// [`track_checked`]: the backward track was lost or missed the start by more than
    /// `max_fb_error_px`.
    ForwardBackward,
}

/// Tracked, or lost with the reason.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum TrackStatus {
    /// The point was tracked and passed every check.
    Tracked,
    /// The track was lost, for this reason.
    Lost(LostReason),
}

/// One point's track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Track {
    /// The point in the next image (pixels). For a lost track, the last estimate (diagnostics).
    pub point: [f32; 2],
    /// Tracked, or lost with the reason.
    pub status: TrackStatus,
    /// Mean absolute intensity difference over the final window, grey levels (OpenCV's `err`);
    /// `f32::INFINITY` for a lost track, so a residual gate never keeps one.
    pub residual: f32,
}

impl Track {
    /// True when the point was tracked ([`TrackStatus::Tracked`]).
    pub fn is_tracked(&self) -> bool {
        self.status == TrackStatus::Tracked
    }
    fn lost(point: [f32; 2], reason: LostReason) -> Self {
        Self {
            point,
            status: TrackStatus::Lost(reason),
            residual: f32::INFINITY,
        }
    }
}

/// Track `pts_prev` from `prev` to `next` (Bouguet's pyramidal Lucas-Kanade, module
/// documentation). `guess_next`, one per point, is the predicted position in the next image
/// (e.g. from the IMU); without it the search starts at the point itself. One [`Track`] per
/// point, in order. Fails on bad parameters or a guess list of another length.
pub fn track(
    prev: &Pyramid,
    next: &Pyramid,
    pts_prev: &[[f32; 2]],
    guess_next: Option<&[[f32; 2]]>,
    params: &TrackParams,
) -> Result<Vec<Track>, VisionError> {
    params.validate()?;
    if let Some(g) = guess_next
        && g.len() != pts_prev.len()
    {
        return Err(klt_error(format!(
            "{} guesses for {} points",
            g.len(),
            pts_prev.len()
        )));
    }
    let top = params
        .max_level
        .min(prev.levels.len().saturating_sub(1))
        .min(next.levels.len().saturating_sub(1));
    // Start: the guess or the point; none when either is not finite (lost at once).
    let starts: Vec<Option<[f32; 2]>> = pts_prev
        .iter()
        .enumerate()
        .map(|(i, &p)| {
            let start = guess_next.and_then(|g| g.get(i).copied()).unwrap_or(p);
            (is_finite2(p) && is_finite2(start)).then_some(start)
        })
        .collect();
    let live: Vec<usize> = row_major_order(pts_prev)
        .into_iter()
        .filter(|&i| starts[i].is_some())
        .collect();
    let mut win = Window::new(params.win_size_px);
    let mut est: Vec<[f32; 2]> = starts
        .iter()
        .map(|s| scale2(s.unwrap_or_default(), level_scale(top)))
        .collect();
    // Level by level (as OpenCV), the points in row-major order: the level's planes and the
    // neighbouring windows stay in cache.
    for level in (1..=top).rev() {
        let (Some(lp), Some(ln)) = (prev.levels.get(level), next.levels.get(level)) else {
            continue;
        };
        for &i in &live {
            let pl = scale2(pts_prev[i], level_scale(level));
            if let Ok(q) = track_level(lp, ln, pl, est[i], false, params, &mut win) {
                est[i] = q;
            }
            est[i] = scale2(est[i], 2.0);
        }
    }
    let mut tracks: Vec<Track> = pts_prev
        .iter()
        .map(|&p| Track::lost(p, LostReason::InvalidPoint))
        .collect();
    // A pyramid always has level 0.
    if let (Some(lp), Some(ln)) = (prev.levels.first(), next.levels.first()) {
        for &i in &live {
            tracks[i] = track_base(lp, ln, pts_prev[i], est[i], params, &mut win);
        }
    }
    Ok(tracks)
}

/// Point indices sorted by row, then column (non-finite coordinates last).
fn row_major_order(pts: &[[f32; 2]]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..pts.len()).collect();
    let key = |p: [f32; 2]| {
        let f = |v: f32| if v.is_finite() { v } else { f32::INFINITY };
        [f(p[1]), f(p[0])]
    };
    order.sort_by(|&a, &b| {
        let (ka, kb) = (key(pts[a]), key(pts[b]));
        ka[0].total_cmp(&kb[0]).then(ka[1].total_cmp(&kb[1]))
    });
    order
}

fn level_scale(level: usize) -> f32 {
    1.0 / (1u32 << level) as f32
}

/// [`track`], then each tracked point back from `next` to `prev` (Kalal et al. 2010): a track is
/// lost ([`LostReason::ForwardBackward`]) when the backward track is lost or ends farther than
/// `params.max_fb_error_px` from the start. With a guess, the backward guess is the forward
/// point minus the guessed motion.
pub fn track_checked(
    prev: &Pyramid,
    next: &Pyramid,
    pts_prev: &[[f32; 2]],
    guess_next: Option<&[[f32; 2]]>,
    params: &TrackParams,
) -> Result<Vec<Track>, VisionError> {
    let mut fwd = track(prev, next, pts_prev, guess_next, params)?;
    let kept: Vec<usize> = (0..fwd.len()).filter(|&i| fwd[i].is_tracked()).collect();
    let back_from: Vec<[f32; 2]> = kept.iter().map(|&i| fwd[i].point).collect();
    let back_guess: Option<Vec<[f32; 2]>> = guess_next.map(|g| {
        kept.iter()
            .map(|&i| {
                let (f, s, q) = (fwd[i].point, pts_prev[i], g[i]);
                [f[0] - (q[0] - s[0]), f[1] - (q[1] - s[1])]
            })
            .collect()
    });
    let back = track(next, prev, &back_from, back_guess.as_deref(), params)?;
    for (&i, b) in kept.iter().zip(&back) {
        let s = pts_prev[i];
        let err_px = (b.point[0] - s[0]).hypot(b.point[1] - s[1]);
        if !(b.is_tracked() && err_px <= params.max_fb_error_px) {
            fwd[i] = Track::lost(fwd[i].point, LostReason::ForwardBackward);
        }
    }
    Ok(fwd)
}

fn is_finite2(p: [f32; 2]) -> bool {
    p[0].is_finite() && p[1].is_finite()
}

fn scale2(p: [f32; 2], s: f32) -> [f32; 2] {
    [p[0] * s, p[1] * s]
}

/// Level 0 of one point: the iteration from the estimate `q`, then the residual.
fn track_base(
    prev: &PyramidLevel,
    next: &PyramidLevel,
    p: [f32; 2],
    q: [f32; 2],
    params: &TrackParams,
    win: &mut Window,
) -> Track {
    let q = match track_level(prev, next, p, q, true, params, win) {
        Ok(q) => q,
        Err(reason) => return Track::lost(q, reason),
    };
    match win.residual(next, q) {
        Some(residual) => Track {
            point: q,
            status: TrackStatus::Tracked,
            residual,
        },
        None => Track::lost(q, LostReason::OutOfImage),
    }
}

/// Bouguet's iteration at one level: `p` the point in the previous level, `q` the estimate in the
/// next. `base` (level 0) requires the template window fully inside; the coarser levels only the
/// point. Returns the refined estimate or why the level failed.
fn track_level(
    prev: &PyramidLevel,
    next: &PyramidLevel,
    p: [f32; 2],
    mut q: [f32; 2],
    base: bool,
    params: &TrackParams,
    win: &mut Window,
) -> Result<[f32; 2], LostReason> {
    let half = win.half();
    let inside = if base {
        window_inside(prev, p, half)
    } else {
        window_inside(prev, p, 0.0)
    };
    if !inside {
        return Err(LostReason::OutOfImage);
    }
    win.load_template(prev, [p[0] - half, p[1] - half]);
    let [gxx, gxy, gyy] = win.gradient_matrix();
    let t = gxx - gyy;
    let min_eig = (gxx + gyy - (t * t + 4.0 * gxy * gxy).sqrt()) * 0.5;
    let area = (win.n * win.n) as f32;
    let det = gxx * gyy - gxy * gxy;
    if !(min_eig / (OPENCV_EIG_SCALE * area) >= params.min_eig_threshold && det > 0.0) {
        return Err(LostReason::Flat);
    }
    let eps2 = params.epsilon_px * params.epsilon_px;
    let mut last = [0f32; 2];
    for it in 0..params.max_iterations {
        if !window_inside(next, q, 0.0) {
            return Err(LostReason::OutOfImage);
        }
        win.load_next(next, [q[0] - half, q[1] - half]);
        let [b1, b2] = win.mismatch();
        let eta = [(gyy * b1 - gxy * b2) / det, (gxx * b2 - gxy * b1) / det];
        q = [q[0] + eta[0], q[1] + eta[1]];
        if eta[0] * eta[0] + eta[1] * eta[1] <= eps2 {
            break;
        }
        if it > 0
            && (eta[0] + last[0]).abs() < OSCILLATION_PX
            && (eta[1] + last[1]).abs() < OSCILLATION_PX
        {
            q = [q[0] - 0.5 * eta[0], q[1] - 0.5 * eta[1]];
            break;
        }
        last = eta;
    }
    Ok(q)
}

/// Whether all of `[c - half, c + half]^2` lies within the pixel centres of `level` (false for
/// non-finite `c`).
fn window_inside(level: &PyramidLevel, c: [f32; 2], half: f32) -> bool {
    let (w, h) = ((level.width() - 1) as f32, (level.height() - 1) as f32);
    c[0] - half >= 0.0 && c[1] - half >= 0.0 && c[0] + half <= w && c[1] + half <= h
}

/// What a sample outside the image reads.
#[derive(Clone, Copy)]
enum Outside {
    /// The nearest border pixel (intensities).
    Clamp,
    /// Zero (template gradients: the outside adds nothing to the sums).
    Zero,
}

/// Scratch of one tracking window: template intensities and gradients, and the next image's
/// window, each `n` rows of `stride` floats (`n` rounded up to [`LANES`], zero padding).
struct Window {
    n: usize,
    ti: Vec<f32>,
    tx: Vec<f32>,
    ty: Vec<f32>,
    j: Vec<f32>,
    sampler: Sampler,
}

impl Window {
    fn new(n: usize) -> Self {
        let stride = n.div_ceil(LANES) * LANES;
        let len = n * stride;
        Self {
            n,
            ti: vec![0.0; len],
            tx: vec![0.0; len],
            ty: vec![0.0; len],
            j: vec![0.0; len],
            sampler: Sampler {
                n,
                stride,
                patch: vec![0.0; (n + 1) * (n + 1)],
            },
        }
    }

    fn half(&self) -> f32 {
        (self.n / 2) as f32
    }

    fn load_template(&mut self, level: &PyramidLevel, origin: [f32; 2]) {
        let [img, gx, gy] = level.planes();
        self.sampler
            .sample(img, origin, Outside::Clamp, &mut self.ti);
        self.sampler.sample(gx, origin, Outside::Zero, &mut self.tx);
        self.sampler.sample(gy, origin, Outside::Zero, &mut self.ty);
    }

    fn load_next(&mut self, level: &PyramidLevel, origin: [f32; 2]) {
        let [img, _, _] = level.planes();
        self.sampler
            .sample(img, origin, Outside::Clamp, &mut self.j);
    }

    /// `[sum Ix^2, sum Ix Iy, sum Iy^2]` over the template.
    fn gradient_matrix(&self) -> [f32; 3] {
        [
            dot(&self.tx, &self.tx),
            dot(&self.tx, &self.ty),
            dot(&self.ty, &self.ty),
        ]
    }

    /// Bouguet's `b_k = sum (I - J) [Ix Iy]^T`.
    fn mismatch(&self) -> [f32; 2] {
        let (mut b1, mut b2) = ([0f32; LANES], [0f32; LANES]);
        let it = self.ti.chunks_exact(LANES).zip(self.j.chunks_exact(LANES));
        let grads = self.tx.chunks_exact(LANES).zip(self.ty.chunks_exact(LANES));
        for ((i, j), (gx, gy)) in it.zip(grads) {
            for k in 0..LANES {
                let d = i[k] - j[k];
                b1[k] += d * gx[k];
                b2[k] += d * gy[k];
            }
        }
        [b1.iter().sum(), b2.iter().sum()]
    }

    /// Mean `|J - I|` of the template against the next level's window at `q`; `None` when that
    /// window is not fully inside.
    fn residual(&mut self, next: &PyramidLevel, q: [f32; 2]) -> Option<f32> {
        let half = self.half();
        if !window_inside(next, q, half) {
            return None;
        }
        self.load_next(next, [q[0] - half, q[1] - half]);
        let mut acc = [0f32; LANES];
        for (i, j) in self.ti.chunks_exact(LANES).zip(self.j.chunks_exact(LANES)) {
            for k in 0..LANES {
                acc[k] += (i[k] - j[k]).abs();
            }
        }
        Some(acc.iter().sum::<f32>() / (self.n * self.n) as f32)
    }
}

/// `sum a b` over equally long slices whose length is a multiple of [`LANES`], in lanes.
/// (One accumulator pair per call: three accumulators in one loop measured 4x slower.)
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; LANES];
    for (a, b) in a.chunks_exact(LANES).zip(b.chunks_exact(LANES)) {
        for k in 0..LANES {
            acc[k] += a[k] * b[k];
        }
    }
    acc.iter().sum()
}

/// Bilinear window sampling: `n x n` samples at `origin + (c, r)` into rows of `stride` floats
/// (the padding columns are not written).
struct Sampler {
    n: usize,
    stride: usize,
    /// The `(n + 1)^2` source pixels of a window at or across the border, the border rule
    /// applied.
    patch: Vec<f32>,
}

impl Sampler {
    /// Where the window's source pixels start in the plane's data (row stride `src.stride()`);
    /// `None` when the window needs the patch.
    fn direct(&self, src: Plane<'_>, origin: [f32; 2]) -> Option<usize> {
        let (fx, fy) = (origin[0].floor(), origin[1].floor());
        // `as` saturates (NaN to 0), the sums saturate: any origin is safe.
        let (ix, iy, p, m) = (fx as isize, fy as isize, src.pad as isize, self.n as isize);
        let fits = ix >= -p
            && iy >= -p
            && ix.saturating_add(m) < src.w as isize + p
            && iy.saturating_add(m) < src.h as isize + p;
        fits.then(|| (iy + p) as usize * src.stride() + (ix + p) as usize)
    }

    /// Straight from the plane when the `(n + 1)^2` source pixels are inside it (its padding
    /// included); otherwise through the patch, filled by `outside`'s rule.
    fn sample(&mut self, src: Plane<'_>, origin: [f32; 2], outside: Outside, out: &mut [f32]) {
        let (fx, fy) = (origin[0].floor(), origin[1].floor());
        let (ax, ay) = (origin[0] - fx, origin[1] - fy);
        let wts = [
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        ];
        let n = self.n;
        if let Some(start) = self.direct(src, origin) {
            bilinear(&src.data[start..], src.stride(), n, wts, self.stride, out);
        } else {
            let corner = [fx as isize, fy as isize];
            fill_patch(src, corner, n + 1, outside, &mut self.patch);
            bilinear(&self.patch, n + 1, n, wts, self.stride, out);
        }
    }
}

/// `out[r * stride + c]` = the bilinear blend with weights `wts` of `src`'s pixels `(c, r)`,
/// `(c + 1, r)`, `(c, r + 1)`, `(c + 1, r + 1)` (row stride `src_stride`), for `r, c in 0..n`.
/// (Zipped slices: the compiler vectorises this; indexed fixed-width chunks measured 3x slower.)
fn bilinear(
    src: &[f32],
    src_stride: usize,
    n: usize,
    wts: [f32; 4],
    stride: usize,
    out: &mut [f32],
) {
    for (r, o) in out.chunks_exact_mut(stride).take(n).enumerate() {
        let s0 = &src[r * src_stride..][..n + 1];
        let s1 = &src[(r + 1) * src_stride..][..n + 1];
        let taps = s0.iter().zip(&s0[1..]).zip(s1.iter().zip(&s1[1..]));
        for (o, ((a, b), (c, d))) in o[..n].iter_mut().zip(taps) {
            *o = wts[0] * a + wts[1] * b + wts[2] * c + wts[3] * d;
        }
    }
}

/// The `m x m` source pixels from `corner` into `patch`; outside pixels read the nearest border
/// pixel (`Clamp`) or zero (`Zero`).
fn fill_patch(src: Plane<'_>, corner: [isize; 2], m: usize, outside: Outside, patch: &mut [f32]) {
    let (w, h) = (src.w as isize, src.h as isize);
    let (x0, m_i) = (corner[0], m as isize);
    // Patch columns [0, left) are left of the image, [left, left + mid) inside, the rest right.
    let lo = x0.clamp(0, w);
    let hi = x0.saturating_add(m_i).clamp(0, w);
    let left = lo.saturating_sub(x0).clamp(0, m_i) as usize;
    let mid = (hi - lo).max(0) as usize;
    for (r, row) in patch.chunks_exact_mut(m).take(m).enumerate() {
        let y = corner[1].saturating_add(r as isize);
        if !(0..h).contains(&y) && matches!(outside, Outside::Zero) {
            row.fill(0.0);
            continue;
        }
        let line = src.row(y.clamp(0, h - 1) as usize);
        let (edge_l, edge_r) = match outside {
            Outside::Clamp => (line[0], line[src.w - 1]),
            Outside::Zero => (0.0, 0.0),
        };
        row[..left].fill(edge_l);
        row[left..left + mid].copy_from_slice(&line[lo as usize..lo as usize + mid]);
        row[left + mid..].fill(edge_r);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use proptest::prelude::*;

    /// The whole response image (the detector streams it).
    fn min_eigen_response(gx: Plane<'_>, gy: Plane<'_>, block: usize) -> Vec<f32> {
        let mut rows = ResponseRows::new(gx, gy, block);
        let mut out = vec![0f32; gx.w * gx.h];
        for (y, row) in out.chunks_exact_mut(gx.w).enumerate() {
            rows.row(y, row);
        }
        out
    }

    /// Separable `[1 4 6 4 1] / 16` blur with clamped borders (sigma 1 px).
    fn blur(img: &GrayImage) -> GrayImage {
        let (w, h) = (img.width(), img.height());
        let k = [1.0, 4.0, 6.0, 4.0, 1.0];
        let at = |x: isize, y: isize| {
            img.get(
                x.clamp(0, w as isize - 1) as usize,
                y.clamp(0, h as isize - 1) as usize,
            )
        };
        let horiz = GrayImage::from_fn(w, h, |x, y| {
            (0..5)
                .map(|i| k[i] * at(x as isize + i as isize - 2, y as isize))
                .sum::<f32>()
                / 16.0
        });
        let at = |x: usize, y: isize| horiz.get(x, y.clamp(0, h as isize - 1) as usize);
        GrayImage::from_fn(w, h, |x, y| {
            (0..5)
                .map(|i| k[i] * at(x, y as isize + i as isize - 2))
                .sum::<f32>()
                / 16.0
        })
    }

    /// Aerial-like texture: smoothed uniform noise (three blurs, sigma about 1.7 px) plus three
    /// plane waves of 20-60 px wavelength, around grey 128.
    fn texture(w: usize, h: usize, seed: u64) -> GrayImage {
        let mut rng = Rng::new(seed);
        let noise = GrayImage::from_fn(w, h, |_, _| rng.range(-1.0, 1.0) as f32);
        let smooth = blur(&blur(&blur(&noise)));
        let waves: Vec<[f32; 4]> = (0..3)
            .map(|_| {
                let len_px = rng.range(20.0, 60.0) as f32;
                let dir = rng.range(0.0, std::f64::consts::TAU) as f32;
                let k = std::f32::consts::TAU / len_px;
                [
                    k * dir.cos(),
                    k * dir.sin(),
                    rng.range(0.0, 6.3) as f32,
                    12.0,
                ]
            })
            .collect();
        GrayImage::from_fn(w, h, |x, y| {
            let (xf, yf) = (x as f32, y as f32);
            let wave: f32 = waves
                .iter()
                .map(|[kx, ky, ph, a]| a * (kx * xf + ky * yf + ph).sin())
                .sum();
            128.0 + 260.0 * smooth.get(x, y) + wave
        })
    }

    /// The `w x h` image whose pixel `(x, y)` is `src` at `map(x, y)` (bilinear; 128 outside).
    fn warp(src: &GrayImage, w: usize, h: usize, map: impl Fn(f64, f64) -> [f64; 2]) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| {
            let [u, v] = map(x as f64, y as f64);
            src.sample_bilinear(u, v).unwrap_or(128.0)
        })
    }

    /// Frames `w x h` cut from a textured canvas with a `margin`: the previous at the canvas
    /// offset, the next translated by `t` (a scene point at `p` moves to `p + t`).
    fn translated_pair(w: usize, h: usize, t: [f64; 2], margin: usize) -> (GrayImage, GrayImage) {
        let canvas = texture(w + 2 * margin, h + 2 * margin, 7);
        let m = margin as f64;
        let prev = warp(&canvas, w, h, |x, y| [x + m, y + m]);
        let next = warp(&canvas, w, h, |x, y| [x + m - t[0], y + m - t[1]]);
        (prev, next)
    }

    fn pyramid(img: &GrayImage) -> Pyramid {
        Pyramid::new(img, DEFAULT_MAX_LEVEL, DEFAULT_WIN_SIZE_PX).unwrap()
    }

    fn median(mut v: Vec<f32>) -> f32 {
        assert!(!v.is_empty());
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    }

    /// Errors of the tracked points against the truth, and the tracked fraction.
    fn errors(tracks: &[Track], truth: &[[f32; 2]]) -> (Vec<f32>, f32) {
        let errs: Vec<f32> = tracks
            .iter()
            .zip(truth)
            .filter(|(t, _)| t.is_tracked())
            .map(|(t, p)| (t.point[0] - p[0]).hypot(t.point[1] - p[1]))
            .collect();
        let frac = errs.len() as f32 / tracks.len().max(1) as f32;
        (errs, frac)
    }

    /// Features of `prev` whose translated position keeps a window inside the frame.
    fn features_inside(prev: &GrayImage, truth: impl Fn([f32; 2]) -> [f32; 2]) -> Vec<[f32; 2]> {
        let (w, h) = (prev.width() as f32, prev.height() as f32);
        let half = (DEFAULT_WIN_SIZE_PX / 2) as f32 + 1.0;
        good_features(prev, &FeatureParams::default())
            .unwrap()
            .into_iter()
            .filter(|&p| {
                let q = truth(p);
                q[0] >= half && q[1] >= half && q[0] <= w - 1.0 - half && q[1] <= h - 1.0 - half
            })
            .collect()
    }

    #[test]
    fn pyr_down_is_the_5x5_gaussian_at_even_pixels() {
        let mut rng = Rng::new(3);
        let img = GrayImage::from_fn(13, 10, |_, _| rng.range(0.0, 255.0) as f32);
        let down = pyr_down(&img).unwrap();
        assert_eq!((down.width(), down.height()), (7, 5));
        let k = [1.0f64, 4.0, 6.0, 4.0, 1.0];
        for y in 0..5 {
            for x in 0..7 {
                let mut want = 0.0;
                for (j, kj) in k.iter().enumerate() {
                    for (i, ki) in k.iter().enumerate() {
                        let sx = reflect101(2 * x as isize + i as isize - 2, 13);
                        let sy = reflect101(2 * y as isize + j as isize - 2, 10);
                        want += ki * kj * f64::from(img.get(sx, sy));
                    }
                }
                let got = f64::from(down.get(x, y));
                assert!(
                    (got - want / 256.0).abs() < 1e-3,
                    "({x}, {y}): {got} vs {want}"
                );
            }
        }
        // reflect-101: gfedcb|abcdefgh|gfedcba.
        let idx: Vec<usize> = (-3..11).map(|i| reflect101(i, 8)).collect();
        assert_eq!(idx, [3, 2, 1, 0, 1, 2, 3, 4, 5, 6, 7, 6, 5, 4]);
        assert_eq!(reflect101(-5, 1), 0);
        assert_eq!([reflect101(2, 2), reflect101(3, 2)], [0, 1]);
    }

    #[test]
    fn the_pyramid_stops_before_a_level_smaller_than_the_window() {
        let img = GrayImage::from_fn(640, 480, |x, y| ((x * 7 + y * 3) % 255) as f32);
        let sizes = |p: &Pyramid| -> Vec<(usize, usize)> {
            p.levels()
                .iter()
                .map(|l| (l.image().width(), l.image().height()))
                .collect()
        };
        // 20x15 would not exceed 21: levels 0..=4.
        let all = Pyramid::new(&img, 10, 21).unwrap();
        assert_eq!(
            sizes(&all),
            [(640, 480), (320, 240), (160, 120), (80, 60), (40, 30)]
        );
        assert_eq!(Pyramid::new(&img, 2, 21).unwrap().levels().len(), 3);
        assert_eq!(Pyramid::new(&img, 0, 21).unwrap().levels().len(), 1);
        let odd = GrayImage::from_fn(101, 75, |x, _| x as f32);
        assert_eq!(
            sizes(&Pyramid::new(&odd, 3, 21).unwrap()),
            [(101, 75), (51, 38)]
        );
    }

    #[test]
    fn scharr_gradients_are_the_slope_of_a_ramp() {
        let img = GrayImage::from_fn(9, 7, |x, y| 3.0 * x as f32 - 2.0 * y as f32 + 7.0);
        let pyr = Pyramid::new(&img, 0, 3).unwrap();
        let level = &pyr.levels()[0];
        for y in 1..6 {
            for x in 1..8 {
                let [gx, gy] = level.gradient(x, y).unwrap();
                assert!((gx - 3.0).abs() < 1e-5 && (gy + 2.0).abs() < 1e-5);
            }
        }
        // Reflect-101 borders: the slope across the edge is zero.
        assert_eq!(level.gradient(0, 3).unwrap()[0], 0.0);
        assert_eq!(level.gradient(4, 0).unwrap()[1], 0.0);
        assert_eq!(level.gradient(9, 0), None);
    }

    /// A window's pixels read from the padded levels equal those the border rule gives through
    /// the patch (a pyramid padded for a 3 px window makes the 21 px windows take the patch):
    /// identical tracks, near the borders too.
    #[test]
    fn padded_levels_and_border_patches_agree() {
        let (prev, next) = translated_pair(320, 240, [9.3, -6.1], 20);
        let pts: Vec<[f32; 2]> = (0..40)
            .map(|i| [12.0 + 7.0 * i as f32, if i % 2 == 0 { 16.5 } else { 225.0 }])
            .collect();
        let params = TrackParams::default();
        let padded = track(&pyramid(&prev), &pyramid(&next), &pts, None, &params).unwrap();
        let (pp, pn) = (
            Pyramid::new(&prev, 3, 3).unwrap(),
            Pyramid::new(&next, 3, 3).unwrap(),
        );
        assert_eq!(pp.levels().len(), 4);
        let patched = track(&pp, &pn, &pts, None, &params).unwrap();
        assert_eq!(padded, patched);
        assert!(padded.iter().filter(|t| t.is_tracked()).count() >= 35);
    }

    /// The streamed response is `lambda_min` of the block-mean structure tensor (reflect-101
    /// borders), against a direct double-precision sum, for the 3x3 fast path and a 5x5 block.
    #[test]
    fn the_response_is_lambda_min_of_the_block_mean_tensor() {
        let img = texture(47, 31, 4);
        let (gx, gy) = scharr_gradients(&img, 0);
        let g = |x: isize, y: isize| {
            let (x, y) = (reflect101(x, 47), reflect101(y, 31));
            [
                f64::from(gx.view().row(y)[x]),
                f64::from(gy.view().row(y)[x]),
            ]
        };
        for block in [3usize, 5] {
            let got = min_eigen_response(gx.view(), gy.view(), block);
            let r = (block / 2) as isize;
            for y in 0..31isize {
                for x in 0..47isize {
                    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let [u, v] = g(x + dx, y + dy);
                            (a, b, c) = (a + u * u, b + u * v, c + v * v);
                        }
                    }
                    let n = (block * block) as f64;
                    let (a, b, c) = (a / n, b / n, c / n);
                    let want = (a + c - ((a - c).powi(2) + 4.0 * b * b).sqrt()) / 2.0;
                    let have = f64::from(got[y as usize * 47 + x as usize]);
                    assert!(
                        (have - want).abs() <= 1e-3 * want.abs().max(1.0),
                        "{block} ({x}, {y})"
                    );
                }
            }
        }
    }

    /// Without a distance, count or spread limit the corners are exactly the 3x3 maxima of the
    /// response above the absolute floor and `quality_level` times the strongest, strongest first.
    #[test]
    fn corners_are_the_local_maxima_above_the_thresholds() {
        let img = texture(90, 70, 8);
        let params = FeatureParams {
            max_corners: 0,
            quality_level: 0.2,
            min_distance_px: 0.0,
            border_px: 3,
            ..FeatureParams::default()
        };
        let pts = good_features(&img, &params).unwrap();
        let (gx, gy) = scharr_gradients(&img, 0);
        let resp = min_eigen_response(gx.view(), gy.view(), 3);
        let max = resp.iter().fold(0f32, |m, v| m.max(*v));
        let at = |x: usize, y: usize| resp[y * 90 + x];
        let (mut want, mut weak) = (Vec::new(), 0);
        for y in 3..67 {
            for x in 3..87 {
                let v = at(x, y);
                let local = (y - 1..=y + 1).all(|j| (x - 1..=x + 1).all(|i| v >= at(i, j)));
                if local && v > FLAT_CORNER_RESPONSE && v > 0.2 * max {
                    want.push((v, [x as f32, y as f32]));
                } else if local && v > FLAT_CORNER_RESPONSE {
                    weak += 1;
                }
            }
        }
        want.sort_by(|a, b| b.0.total_cmp(&a.0));
        assert!(
            want.len() > 20 && weak > 20,
            "{} kept, {weak} below quality",
            want.len()
        );
        let want: Vec<[f32; 2]> = want.into_iter().map(|(_, p)| p).collect();
        assert_eq!(pts, want);
    }

    /// Bright squares on a dark ground: every corner of every square is found (within 2.5 px: the
    /// response's peak sits inside a blurred corner) and nothing else, strongest first, deterministic.
    #[test]
    fn corners_are_the_corners_of_squares() {
        let squares = [(20usize, 20usize), (70, 30), (40, 70), (90, 80)];
        let sharp = GrayImage::from_fn(130, 120, |x, y| {
            let inside = squares
                .iter()
                .any(|&(sx, sy)| (sx..sx + 16).contains(&x) && (sy..sy + 16).contains(&y));
            if inside { 200.0 } else { 50.0 }
        });
        let img = blur(&sharp);
        let params = FeatureParams {
            max_corners: 0,
            quality_level: 0.1,
            min_distance_px: 5.0,
            ..FeatureParams::default()
        };
        let pts = good_features(&img, &params).unwrap();
        assert_eq!(pts, good_features(&img, &params).unwrap());
        let corners: Vec<[f32; 2]> = squares
            .iter()
            .flat_map(|&(sx, sy)| {
                let (a, b) = (sx as f32 - 0.5, sy as f32 - 0.5);
                [[a, b], [a + 16.0, b], [a, b + 16.0], [a + 16.0, b + 16.0]]
            })
            .collect();
        let dist = |p: [f32; 2], q: [f32; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
        assert_eq!(pts.len(), corners.len(), "{pts:?}");
        for c in &corners {
            assert!(
                pts.iter().any(|&p| dist(p, *c) <= 2.5),
                "{c:?} not in {pts:?}"
            );
        }
        let (gx, gy) = scharr_gradients(&img, 0);
        let resp = min_eigen_response(gx.view(), gy.view(), 3);
        let r: Vec<f32> = pts
            .iter()
            .map(|p| resp[p[1] as usize * 130 + p[0] as usize])
            .collect();
        assert!(r.windows(2).all(|w| w[0] >= w[1]), "{r:?}");
    }

    #[test]
    fn corners_keep_the_distance_count_and_border() {
        let img = texture(320, 240, 11);
        let params = FeatureParams {
            max_corners: 150,
            min_distance_px: 12.0,
            border_px: 15,
            ..FeatureParams::default()
        };
        let pts = good_features(&img, &params).unwrap();
        assert_eq!(pts.len(), 150);
        for (i, p) in pts.iter().enumerate() {
            assert!(p[0] >= 15.0 && p[1] >= 15.0 && p[0] <= 304.0 && p[1] <= 224.0);
            for q in &pts[..i] {
                assert!((p[0] - q[0]).hypot(p[1] - q[1]) >= 12.0, "{p:?} {q:?}");
            }
        }
        // The pyramid's level-0 gradients give the same corners.
        assert_eq!(pyramid(&img).good_features(&params).unwrap(), pts);
    }

    /// Strong texture on the left, weak on the right: without a spread grid the left takes all,
    /// with one every cell gets corners and none more than its quota.
    #[test]
    fn the_spread_grid_covers_the_frame() {
        let tex = texture(320, 240, 5);
        let img = GrayImage::from_fn(320, 240, |x, y| {
            let c = if x < 160 { 1.0 } else { 0.25 };
            128.0 + c * (tex.get(x, y) - 128.0)
        });
        let base = FeatureParams {
            max_corners: 60,
            ..FeatureParams::default()
        };
        let plain = good_features(&img, &base).unwrap();
        assert_eq!(plain.len(), 60);
        assert!(plain.iter().all(|p| p[0] < 160.0), "{plain:?}");
        let grid = SpreadGrid {
            cols: 4,
            rows: 2,
            max_per_cell: 8,
        };
        let spread = FeatureParams {
            spread: Some(grid),
            ..base
        };
        let pts = good_features(&img, &spread).unwrap();
        let mut counts = [0usize; 8];
        for p in &pts {
            counts[(p[1] as usize / 120) * 4 + p[0] as usize / 80] += 1;
        }
        assert!(counts.iter().all(|&c| (1..=8).contains(&c)), "{counts:?}");
        assert!(pts.iter().filter(|p| p[0] >= 160.0).count() >= 16);
    }

    /// A region of interest spends the whole budget inside it: all corners in the right half,
    /// as many as without the region (the unrestricted search spends most on the left).
    #[test]
    fn a_region_of_interest_spends_the_budget_inside_it() {
        let img = texture(320, 240, 9);
        let params = FeatureParams {
            max_corners: 80,
            ..FeatureParams::default()
        };
        let right = |p: [f32; 2]| p[0] >= 160.0;
        let pyr = pyramid(&img);
        let inside = pyr.good_features_where(&params, right).unwrap();
        assert_eq!(inside.len(), 80);
        assert!(inside.iter().all(|&p| right(p)), "{inside:?}");
        let all = pyr.good_features(&params).unwrap();
        let all_right = all.iter().filter(|&&p| right(p)).count();
        assert!(
            all_right < 60,
            "the unrestricted search spends {all_right} of 80 on the right"
        );
        // Restricted to where the unrestricted search found its right-half corners, the
        // search finds those first (same order, same spacing).
        let only_those = |p: [f32; 2]| all.iter().any(|q| *q == p && right(p));
        let same = pyr.good_features_where(&params, only_those).unwrap();
        assert_eq!(same.len(), all_right);
    }

    /// (a) A sub-pixel translation (bilinear resampling of a textured image): median error
    /// under 0.05 px, nearly all points tracked, small residuals.
    #[test]
    fn a_subpixel_translation_is_tracked_within_five_hundredths() {
        let t = [3.37f32, -1.82];
        let (prev, next) = translated_pair(320, 240, [3.37, -1.82], 10);
        let pts = features_inside(&prev, |p| [p[0] + t[0], p[1] + t[1]]);
        assert!(pts.len() > 100, "{}", pts.len());
        let truth: Vec<[f32; 2]> = pts.iter().map(|p| [p[0] + t[0], p[1] + t[1]]).collect();
        let tracks = track(
            &pyramid(&prev),
            &pyramid(&next),
            &pts,
            None,
            &TrackParams::default(),
        )
        .unwrap();
        let (errs, frac) = errors(&tracks, &truth);
        assert!(frac >= 0.98, "tracked {frac}");
        let med = median(errs.clone());
        assert!(med < 0.05, "median error {med} px");
        let worst = errs.iter().fold(0f32, |m, e| m.max(*e));
        assert!(worst < 0.3, "worst error {worst} px");
        let res = median(tracks.iter().map(|t| t.residual).collect());
        assert!(res < 2.0, "median residual {res}");
    }

    /// The residual is the mean absolute difference over the window: near zero for an exact
    /// integer shift, the offset for a brightness offset.
    #[test]
    fn the_residual_is_the_mean_absolute_difference() {
        let (prev, next) = translated_pair(200, 160, [3.0, -2.0], 10);
        let pts = features_inside(&prev, |p| [p[0] + 3.0, p[1] - 2.0]);
        let pp = pyramid(&prev);
        let tr = track(&pp, &pyramid(&next), &pts, None, &TrackParams::default()).unwrap();
        assert!(median(tr.iter().map(|t| t.residual).collect()) < 0.5);
        let brighter = GrayImage::from_fn(200, 160, |x, y| next.get(x, y) + 10.0);
        let tr = track(
            &pp,
            &pyramid(&brighter),
            &pts,
            None,
            &TrackParams::default(),
        )
        .unwrap();
        let res = median(tr.iter().map(|t| t.residual).collect());
        assert!((res - 10.0).abs() < 1.0, "median residual {res}");
    }

    /// (b) A 25 px shift, no guess: the pyramid brings it in; a single level does not.
    #[test]
    fn a_25_px_shift_is_tracked_through_the_pyramid() {
        let t = [23.6f32, -9.1];
        let (prev, next) = translated_pair(320, 240, [23.6, -9.1], 30);
        let pts = features_inside(&prev, |p| [p[0] + t[0], p[1] + t[1]]);
        let truth: Vec<[f32; 2]> = pts.iter().map(|p| [p[0] + t[0], p[1] + t[1]]).collect();
        let (pp, pn) = (pyramid(&prev), pyramid(&next));
        let tracks = track(&pp, &pn, &pts, None, &TrackParams::default()).unwrap();
        let (errs, frac) = errors(&tracks, &truth);
        assert!(frac >= 0.95, "tracked {frac}");
        let med = median(errs);
        assert!(med < 0.05, "median error {med} px");
        let flat = TrackParams {
            max_level: 0,
            ..TrackParams::default()
        };
        let tracks = track(&pp, &pn, &pts, None, &flat).unwrap();
        let (errs, _) = errors(&tracks, &truth);
        let good = errs.iter().filter(|&&e| e < 0.1).count();
        assert!(
            good * 10 < pts.len(),
            "{good} of {} without the pyramid",
            pts.len()
        );
    }

    /// (c) An 80 px shift with a guess 4 px off the truth (the IMU's prediction): tracked; the
    /// same without the guess is mostly not.
    #[test]
    fn an_80_px_shift_is_tracked_with_a_guess() {
        let t = [62.0f32, -50.3];
        let (prev, next) = translated_pair(320, 240, [62.0, -50.3], 90);
        let pts = features_inside(&prev, |p| [p[0] + t[0], p[1] + t[1]]);
        assert!(pts.len() > 30, "{}", pts.len());
        let truth: Vec<[f32; 2]> = pts.iter().map(|p| [p[0] + t[0], p[1] + t[1]]).collect();
        let guess: Vec<[f32; 2]> = truth.iter().map(|q| [q[0] + 3.1, q[1] - 2.7]).collect();
        let (pp, pn) = (pyramid(&prev), pyramid(&next));
        let tracks = track(&pp, &pn, &pts, Some(&guess), &TrackParams::default()).unwrap();
        let (errs, frac) = errors(&tracks, &truth);
        assert!(frac >= 0.95, "tracked {frac}");
        let med = median(errs);
        assert!(med < 0.05, "median error {med} px");
        let blind = track(&pp, &pn, &pts, None, &TrackParams::default()).unwrap();
        let (errs, _) = errors(&blind, &truth);
        let good = errs.iter().filter(|&&e| e < 0.1).count();
        assert!(
            good * 2 < pts.len(),
            "{good} of {} without a guess",
            pts.len()
        );
    }

    /// (d) A 2 degree rotation and 1.03 scale about the centre, no guess: median error under
    /// 0.1 px (the translation-only window model absorbs the small affine part).
    #[test]
    fn a_small_rotation_and_scale_are_tracked() {
        let (w, h) = (320usize, 240usize);
        let canvas = texture(w, h, 9);
        let (ang, s) = (2f64.to_radians(), 1.03f64);
        let (cx, cy) = ((w - 1) as f64 / 2.0, (h - 1) as f64 / 2.0);
        let (c, sn) = (ang.cos(), ang.sin());
        // next(x) = prev(c + R^-1 (x - c) / s): a point p moves to c + s R (p - c).
        let next = warp(&canvas, w, h, |x, y| {
            let (dx, dy) = ((x - cx) / s, (y - cy) / s);
            [cx + c * dx + sn * dy, cy - sn * dx + c * dy]
        });
        let truth_of = |p: [f32; 2]| {
            let (dx, dy) = (f64::from(p[0]) - cx, f64::from(p[1]) - cy);
            [
                (cx + s * (c * dx - sn * dy)) as f32,
                (cy + s * (sn * dx + c * dy)) as f32,
            ]
        };
        let pts = features_inside(&canvas, truth_of);
        let truth: Vec<[f32; 2]> = pts.iter().map(|&p| truth_of(p)).collect();
        let tracks = track(
            &pyramid(&canvas),
            &pyramid(&next),
            &pts,
            None,
            &TrackParams::default(),
        )
        .unwrap();
        let (errs, frac) = errors(&tracks, &truth);
        assert!(frac >= 0.95, "tracked {frac}");
        let med = median(errs);
        assert!(med < 0.1, "median error {med} px");
    }

    /// Counts of [`fb_scene`]: points leaving the frame, occluded, clear of the occluder; clear
    /// ones kept by the check; occluded ones the forward tracker alone kept.
    #[derive(Debug)]
    struct FbCounts {
        leaving: usize,
        occluded: usize,
        clear: usize,
        kept_clear: usize,
        occluded_passing_forward: usize,
    }

    /// A 14.3, 6.6 px shift with the area `[100, 180) x [80, 160)` of the next frame blanked to
    /// `fill`. Asserts that every point leaving the frame or occluded is lost by the check (and
    /// that the check's rejections of forward-kept points are forward-backward ones), and that
    /// kept clear points (farther than `clear_px` from the occluder) are accurate.
    fn fb_scene(fill: f32, clear_px: f32) -> FbCounts {
        let t = [14.3f32, 6.6];
        let (w, h) = (320usize, 240usize);
        let (prev, next) = translated_pair(w, h, [14.3, 6.6], 30);
        let occluded =
            |q: [f32; 2]| (100.0..180.0).contains(&q[0]) && (80.0..160.0).contains(&q[1]);
        let next = GrayImage::from_fn(w, h, |x, y| {
            if occluded([x as f32, y as f32]) {
                fill
            } else {
                next.get(x, y)
            }
        });
        let pts = good_features(&prev, &FeatureParams::default()).unwrap();
        let truth: Vec<[f32; 2]> = pts.iter().map(|p| [p[0] + t[0], p[1] + t[1]]).collect();
        let half = (DEFAULT_WIN_SIZE_PX / 2) as f32;
        let leaves = |q: [f32; 2]| q[0] > (w - 1) as f32 - half || q[1] > (h - 1) as f32 - half;
        // Windows entirely in the blank area; straddling ones may go either way.
        let blanked = |q: [f32; 2]| {
            occluded([q[0] - half, q[1] - half]) && occluded([q[0] + half, q[1] + half])
        };
        let clear = |q: [f32; 2]| {
            let near = |a: f32, lo: f32, hi: f32| a > lo - clear_px && a < hi + clear_px;
            !(near(q[0], 100.0, 180.0) && near(q[1], 80.0, 160.0))
        };
        let (pp, pn) = (pyramid(&prev), pyramid(&next));
        let params = TrackParams::default();
        let plain = track(&pp, &pn, &pts, None, &params).unwrap();
        let checked = track_checked(&pp, &pn, &pts, None, &params).unwrap();
        let mut n = FbCounts {
            leaving: 0,
            occluded: 0,
            clear: 0,
            kept_clear: 0,
            occluded_passing_forward: 0,
        };
        for ((c, p), q) in checked.iter().zip(&plain).zip(&truth) {
            if p.is_tracked() && !c.is_tracked() {
                assert_eq!(c.status, TrackStatus::Lost(LostReason::ForwardBackward));
            }
            if leaves(*q) {
                n.leaving += 1;
                assert!(!c.is_tracked(), "{q:?} left the frame: {c:?}");
            } else if blanked(*q) {
                n.occluded += 1;
                assert!(!c.is_tracked(), "{q:?} is occluded: {c:?}");
                n.occluded_passing_forward += usize::from(p.is_tracked());
            } else if clear(*q) {
                n.clear += 1;
                if c.is_tracked() {
                    n.kept_clear += 1;
                    let e = (c.point[0] - q[0]).hypot(c.point[1] - q[1]);
                    assert!(e < 0.2, "{q:?}: error {e}");
                }
            }
        }
        n
    }

    /// (e) Points that leave the frame or land in a blanked (occluded) area are rejected by the
    /// forward-backward check, some of which the forward tracker alone keeps (what the check is
    /// for). With the occluder at the texture's mean grey, the points clear of it are kept.
    /// A dark occluder's edges are the strongest structure at the coarse levels: its rejections
    /// are as safe, but the backward pass of clear points within the top level's window
    /// footprint (10 px x 2^3) is misled by them, so there only points beyond it are counted.
    #[test]
    fn forward_backward_rejects_leaving_and_occluded_points() {
        for (fill, clear_px) in [(128.0, 12.0), (40.0, 90.0)] {
            let n = fb_scene(fill, clear_px);
            assert!(n.leaving >= 5 && n.occluded >= 5, "{fill}: {n:?}");
            assert!(n.occluded_passing_forward > 0, "{fill}: {n:?}");
            assert!(n.kept_clear * 100 >= n.clear * 95, "{fill}: {n:?}");
            assert!(n.clear >= 30, "{fill}: {n:?}");
        }
    }

    /// (f) A blank image has no corners, and tracking on it reports flat windows, not zero
    /// motion.
    #[test]
    fn a_blank_image_gives_no_features_and_flat_tracks() {
        let blank = GrayImage::from_fn(160, 120, |_, _| 77.0);
        assert!(
            good_features(&blank, &FeatureParams::default())
                .unwrap()
                .is_empty()
        );
        let pb = pyramid(&blank);
        assert!(
            pb.good_features(&FeatureParams::default())
                .unwrap()
                .is_empty()
        );
        let pts = [[40.0, 40.0], [80.5, 60.25], [120.0, 90.0]];
        for tr in [
            track(&pb, &pb, &pts, None, &TrackParams::default()).unwrap(),
            track_checked(&pb, &pb, &pts, None, &TrackParams::default()).unwrap(),
        ] {
            for t in tr {
                assert_eq!(t.status, TrackStatus::Lost(LostReason::Flat));
                assert_eq!(t.residual, f32::INFINITY);
            }
        }
        // An image of vertical stripes is an edge everywhere: flat too (aperture problem).
        let stripes = GrayImage::from_fn(160, 120, |x, _| 128.0 + 60.0 * (x as f32 * 0.4).sin());
        let ps = pyramid(&stripes);
        for t in track(&ps, &ps, &pts, None, &TrackParams::default()).unwrap() {
            assert_eq!(t.status, TrackStatus::Lost(LostReason::Flat));
        }
    }

    /// OpenCV's `minEigThreshold` scale: a window of `A (sin kx + sin ky)` has
    /// `lambda_min(G) / area ~ A^2 k^2 / 2`, flat on OpenCV's scale when that is under
    /// `1e-4 * 1024`, i.e. `A k < 0.45`.
    #[test]
    fn the_flat_threshold_has_opencvs_scale() {
        let k = std::f32::consts::TAU / 20.0;
        let status = |a: f32| {
            let img = GrayImage::from_fn(100, 100, |x, y| {
                128.0 + a * ((k * x as f32).sin() + (k * y as f32).sin())
            });
            let p = pyramid(&img);
            track(&p, &p, &[[50.0, 50.0]], None, &TrackParams::default()).unwrap()[0].status
        };
        assert_eq!(status(0.3 / k), TrackStatus::Lost(LostReason::Flat));
        assert_eq!(status(0.65 / k), TrackStatus::Tracked);
    }

    /// (g) Degenerate inputs give errors or lost tracks, never a panic.
    #[test]
    fn degenerate_inputs_do_not_panic() {
        let params = TrackParams::default();
        let img = texture(64, 48, 1);
        let p = pyramid(&img);
        assert!(track(&p, &p, &[], None, &params).unwrap().is_empty());
        assert!(
            track_checked(&p, &p, &[], Some(&[]), &params)
                .unwrap()
                .is_empty()
        );
        // Empty, 1x1 and 2x2 images.
        let empty = GrayImage::from_fn(0, 0, |_, _| 0.0);
        assert!(Pyramid::new(&empty, 3, 21).is_err());
        assert!(good_features(&empty, &FeatureParams::default()).is_err());
        assert!(pyr_down(&empty).is_err());
        for side in [1usize, 2] {
            let tiny = GrayImage::from_fn(side, side, |x, y| (x + y) as f32);
            let pt = Pyramid::new(&tiny, 3, 21).unwrap();
            assert_eq!(pt.levels().len(), 1);
            assert_eq!(pyr_down(&tiny).unwrap().width(), 1);
            assert!(
                good_features(&tiny, &FeatureParams::default())
                    .unwrap()
                    .is_empty()
            );
            let tr = track_checked(&pt, &pt, &[[0.0, 0.0], [0.5, 0.5]], None, &params).unwrap();
            assert!(
                tr.iter()
                    .all(|t| t.status == TrackStatus::Lost(LostReason::OutOfImage))
            );
            // Pyramids of different sizes.
            let tr = track(&pt, &p, &[[0.0, 0.0], [30.0, 20.0]], None, &params).unwrap();
            assert!(tr.iter().all(|t| !t.is_tracked()));
        }
        // Non-finite pixels.
        for bad in [f32::NAN, f32::INFINITY] {
            let mut nan = img.clone();
            nan.data_mut()[100] = bad;
            assert!(Pyramid::new(&nan, 3, 21).is_err());
            assert!(good_features(&nan, &FeatureParams::default()).is_err());
        }
        // Points outside, non-finite points and guesses, huge coordinates.
        let pts = [
            [-5.0, 10.0],
            [30.0, 500.0],
            [f32::NAN, 10.0],
            [10.0, f32::INFINITY],
            [1e30, -1e30],
            [30.0, 24.0],
        ];
        let tr = track_checked(&p, &p, &pts, None, &params).unwrap();
        let want = [
            LostReason::OutOfImage,
            LostReason::OutOfImage,
            LostReason::InvalidPoint,
            LostReason::InvalidPoint,
            LostReason::OutOfImage,
        ];
        for (t, r) in tr.iter().zip(want) {
            assert_eq!(t.status, TrackStatus::Lost(r));
        }
        assert!(tr[5].is_tracked());
        let guesses = [[f32::NAN, 0.0], [1e30, 1e30], [-1e6, 3.0]];
        let tr = track(&p, &p, &[[30.0, 24.0]; 3], Some(&guesses), &params).unwrap();
        assert_eq!(tr[0].status, TrackStatus::Lost(LostReason::InvalidPoint));
        assert!(
            tr[1..]
                .iter()
                .all(|t| t.status == TrackStatus::Lost(LostReason::OutOfImage))
        );
        // A guess list of another length.
        assert!(track(&p, &p, &[[30.0, 24.0]], Some(&[]), &params).is_err());
        assert!(track_checked(&p, &p, &[[30.0, 24.0]], Some(&[]), &params).is_err());
    }

    #[test]
    fn bad_parameters_are_errors() {
        let img = texture(64, 48, 1);
        let p = pyramid(&img);
        let pts = [[30.0, 24.0]];
        let bad_track = [
            TrackParams {
                win_size_px: 20,
                ..TrackParams::default()
            },
            TrackParams {
                win_size_px: 1,
                ..TrackParams::default()
            },
            TrackParams {
                max_level: 17,
                ..TrackParams::default()
            },
            TrackParams {
                max_iterations: 0,
                ..TrackParams::default()
            },
            TrackParams {
                epsilon_px: f32::NAN,
                ..TrackParams::default()
            },
            TrackParams {
                min_eig_threshold: -1.0,
                ..TrackParams::default()
            },
            TrackParams {
                max_fb_error_px: 0.0,
                ..TrackParams::default()
            },
        ];
        for b in &bad_track {
            assert!(track(&p, &p, &pts, None, b).is_err(), "{b:?}");
        }
        assert!(Pyramid::new(&img, 3, 4).is_err());
        assert!(Pyramid::new(&img, 99, 21).is_err());
        let bad_features = [
            FeatureParams {
                quality_level: 0.0,
                ..FeatureParams::default()
            },
            FeatureParams {
                quality_level: f32::NAN,
                ..FeatureParams::default()
            },
            FeatureParams {
                min_distance_px: -1.0,
                ..FeatureParams::default()
            },
            FeatureParams {
                block_size_px: 4,
                ..FeatureParams::default()
            },
            FeatureParams {
                spread: Some(SpreadGrid {
                    cols: 0,
                    rows: 2,
                    max_per_cell: 3,
                }),
                ..FeatureParams::default()
            },
        ];
        for b in &bad_features {
            assert!(good_features(&img, b).is_err(), "{b:?}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// (h) Random sub-pixel translations up to 4 px: median error under 0.05 px, at least
        /// 95 % of the points tracked, every kept forward-backward track within 0.3 px.
        #[test]
        fn random_subpixel_translations_are_tracked(tx in -4.0f64..4.0, ty in -4.0f64..4.0) {
            let (prev, next) = translated_pair(160, 120, [tx, ty], 8);
            let t = [tx as f32, ty as f32];
            let pts = features_inside(&prev, |p| [p[0] + t[0], p[1] + t[1]]);
            prop_assert!(pts.len() >= 20);
            let truth: Vec<[f32; 2]> = pts.iter().map(|p| [p[0] + t[0], p[1] + t[1]]).collect();
            let (pp, pn) = (pyramid(&prev), pyramid(&next));
            let tracks = track_checked(&pp, &pn, &pts, None, &TrackParams::default()).unwrap();
            let (errs, frac) = errors(&tracks, &truth);
            prop_assert!(frac >= 0.95, "tracked {}", frac);
            prop_assert!(errs.iter().all(|&e| e < 0.3), "{:?}", errs);
            let med = median(errs);
            prop_assert!(med < 0.05, "median error {} px", med);
        }
    }
}
