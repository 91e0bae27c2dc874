//! SURF: Speeded-Up Robust Features (H. Bay, A. Ess, T. Tuytelaars, L. Van Gool, "Speeded-Up Robust
//! Features (SURF)", CVIU 110(3):346-359, 2008), with OpenCV's parameter meanings
//! (`hessianThreshold`, `nOctaves`, `nOctaveLayers`, `extended`, `upright`) as reference semantics.
//!
//! **Detector (sec. 3.2-3.3).** Box-filter approximations `Dxx, Dyy, Dxy` of the Gaussian second
//! derivatives are read from the integral image. A filter of size `L = 3 l` (lobe length `l`) has
//! `Dxx`/`Dyy` lobes of `l x (2l - 1)` pixels with weights `1, -2, 1` and `Dxy` quadrants of
//! `l x l` with weights `+1, -1, -1, +1` separated by a one-pixel cross (Bay fig. 1; OpenSURF's
//! widths). As in OpenCV every lobe sum is divided by the lobe area, which makes the responses
//! scale-normalised, and `det(H) = Dxx Dyy - (0.9 Dxy)^2` (relative weight 0.9, Bay eq. 4). The
//! sign of the trace `Dxx + Dyy` (the Laplacian) is kept on the keypoint (OpenCV's `class_id`):
//! `-1` for bright blobs on dark ground, `+1` for dark blobs.
//!
//! Scale space (Bay sec. 3.3): octave `o` (0-based) holds `n_octave_layers + 2` filters of sizes
//! `L(o, k) = 3 (2^(o+1) (k + 1) + 1)`, i.e. 9, 15, 21, 27 in the first octave, 15, 27, 39, 51 in
//! the second, 27, 51, 75, 99 in the third (the step between sizes doubles per octave), and the
//! responses are sampled every `init_sample_step * 2^o` pixels. Layers shared between octaves
//! (e.g. 15 and 27) are computed once and subsampled. All layers of one octave sample the same
//! grid of centres `(c * step, r * step)`, and a response exists only where the whole filter lies
//! inside the image. A sample is a keypoint when `det > hessian_threshold` and it exceeds its 26
//! neighbours in the 3x3x3 (x, y, scale) neighbourhood of a middle layer. Its position and scale
//! are refined by fitting a 3-D quadratic (Brown & Lowe 2002), rejected when the offset exceeds one
//! sample in any dimension (OpenCV's rule). Keypoint scale `s = 1.2 L / 9` (the Gaussian sigma the
//! filter approximates), `size = L` (OpenCV's `KeyPoint::size`).
//!
//! **Orientation (sec. 4.1).** Haar wavelet responses of side `4s` at the points of a grid of
//! spacing `s` within radius `6s`, weighted with a Gaussian `sigma = 2s`, are summed in a window of
//! angle `pi/3` sliding around the circle (evaluated every 5 degrees with 5-degree bins); the
//! longest sum vector gives the orientation. Upright mode (U-SURF) sets it to 0: for
//! attitude-rectified images, faster and more distinctive.
//!
//! **Descriptor (sec. 4.2).** A square window of side `20s` oriented along the keypoint is sampled
//! on a regular grid (20 x 20 samples, spacing `s`) with Haar wavelets of side `2s`, weighted with
//! a Gaussian `sigma = 3.3s` centred on the keypoint, and summed per subregion as
//! `(sum dx, sum dy, sum |dx|, sum |dy|)`. Upright keypoints sample axis-aligned wavelets. For
//! oriented SURF-36/64 the window is covered by a grid of `(n+1)^2` cells (axis-aligned `s x s`
//! pixel boxes at the rotated cell centres, 4 integral-image loads each) and each wavelet is the
//! difference of two pairs of neighbouring cells along the keypoint axes (OpenCV's rotated-patch
//! scheme, without its warp); SURF-128 samples an axis-aligned wavelet at each rotated sample and
//! rotates the response vector (Bay's formulation). Both give the same descriptor at orientation
//! 0 (integer `s`, window inside the image):
//! * `Surf64`: 4 x 4 subregions of 5 x 5 samples, 64 values;
//! * `Surf128` ("extended"): the sums of `dx, |dx|` split by the sign of `dy` and those of
//!   `dy, |dy|` split by the sign of `dx` (OpenCV's order), 128 values;
//! * `Surf36`: the seed thesis's "modified SURF" (Bay's SURF-36): 3 x 3 subregions of the same
//!   `20s` window, sampled 18 x 18 (spacing `20s/18`, 6 x 6 samples per subregion), 36 values.
//!
//! Descriptors are unit-normalised (L2). They are stored with a row stride rounded up to a
//! multiple of 8 floats (36 -> 40, padded with zeros) so the matcher's distance loop vectorises.
//!
//! Integral-image precision: see `integral` (exact wrapping `i32` on 8-bit-quantised intensities).

use std::sync::OnceLock;

use rayon::prelude::*;

use super::{GrayImage, IntegralImage, VisionError};

/// Which descriptor to compute.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum DescriptorKind {
    /// 3 x 3 subregions x 4 values (the seed thesis's modified SURF).
    Surf36,
    /// 4 x 4 subregions x 4 values (standard SURF).
    Surf64,
    /// 4 x 4 subregions x 8 values (OpenCV `extended = true`).
    Surf128,
    /// 256 binary tests (ORB's steered BRIEF, [`super::orb`]), stored as 8 words of 32 bits.
    Binary256,
}

/// How two descriptors of a kind are compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Family {
    /// Unit vectors of floats: Euclidean distance.
    Float,
    /// Bit strings: Hamming distance.
    Binary,
}

/// `SURF-64` and so on (the descriptor's length), `binary-256`.
impl std::fmt::Display for DescriptorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Binary256 => write!(f, "binary-256"),
            _ => write!(f, "SURF-{}", self.len()),
        }
    }
}

impl DescriptorKind {
    /// Number of stored descriptor values: floats, or the 32-bit words of a binary kind.
    #[allow(clippy::len_without_is_empty)] // a descriptor kind is never empty
    pub fn len(self) -> usize {
        match self {
            Self::Surf36 => 36,
            Self::Surf64 => 64,
            Self::Surf128 => 128,
            Self::Binary256 => 8,
        }
    }
    /// How descriptors of this kind are compared.
    pub fn family(self) -> Family {
        match self {
            Self::Binary256 => Family::Binary,
            _ => Family::Float,
        }
    }
    /// Storage stride in floats (length rounded up to a multiple of 8).
    pub fn stride(self) -> usize {
        self.len().div_ceil(8) * 8
    }
    /// Subregions per side.
    pub fn subregions(self) -> usize {
        match self {
            Self::Surf36 => 3,
            _ => 4,
        }
    }
    /// Samples per side of the 20s window.
    pub fn samples(self) -> usize {
        match self {
            Self::Surf36 => 18,
            _ => 20,
        }
    }
}

/// SURF parameters, with OpenCV's meanings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SurfParams {
    /// Keep samples with `det(H) > hessian_threshold` (responses are lobe-area normalised on the
    /// 0..255 intensity scale, as in OpenCV; typical 100..1000, OpenCV's default 100).
    pub hessian_threshold: f32,
    /// Number of octaves (OpenCV default 4).
    pub n_octaves: usize,
    /// Layers per octave in which extrema are searched; each octave computes this + 2 filters.
    /// 2 gives the paper's 9, 15, 21, 27 (OpenCV's default is 3).
    pub n_octave_layers: usize,
    /// Sampling step of the first octave in pixels; doubles per octave (OpenCV: 1, OpenSURF: 2).
    pub init_sample_step: usize,
    /// U-SURF: skip orientation assignment (orientation 0).
    pub upright: bool,
    /// Descriptor variant.
    pub descriptor: DescriptorKind,
    /// Keep at most this many keypoints, the strongest with an even spatial spread (see
    /// [`select_spread`]); `None` keeps all.
    pub max_features: Option<usize>,
}

impl Default for SurfParams {
    fn default() -> Self {
        Self {
            hessian_threshold: 100.0,
            n_octaves: 4,
            n_octave_layers: 2,
            init_sample_step: 1,
            upright: false,
            descriptor: DescriptorKind::Surf64,
            max_features: None,
        }
    }
}

impl SurfParams {
    /// Check ranges; names the offending field.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |name, reason: &str| {
            Err(VisionError::InvalidParam {
                detector: "SURF",
                name,
                reason: reason.to_string(),
            })
        };
        if !(self.hessian_threshold.is_finite() && self.hessian_threshold >= 0.0) {
            return bad("hessian_threshold", "must be finite and >= 0");
        }
        if !(1..=8).contains(&self.n_octaves) {
            return bad("n_octaves", "must be in 1..=8");
        }
        if !(1..=8).contains(&self.n_octave_layers) {
            return bad("n_octave_layers", "must be in 1..=8");
        }
        if !(1..=8).contains(&self.init_sample_step) {
            return bad("init_sample_step", "must be in 1..=8");
        }
        if self.max_features == Some(0) {
            return bad("max_features", "must be positive when set");
        }
        if self.descriptor.family() != Family::Float {
            return bad("descriptor", "SURF computes SURF-36, SURF-64 or SURF-128");
        }
        Ok(())
    }
}

/// A SURF keypoint. Coordinates in pixels, see the module documentation of `vision`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct KeyPoint {
    /// Column coordinate (pixel centres at integers).
    pub x: f32,
    /// Row coordinate.
    pub y: f32,
    /// Filter size `L` in pixels (OpenCV's `KeyPoint::size`).
    pub size: f32,
    /// Scale `s = 1.2 L / 9` in pixels.
    pub scale: f32,
    /// `det(H)` at the detected maximum.
    pub response: f32,
    /// Orientation from `+x` towards `+y` (clockwise on screen), radians; 0 in upright mode.
    pub orientation_rad: f32,
    /// Sign of the Laplacian (trace of H): -1 bright blob, +1 dark blob (OpenCV's `class_id`).
    pub laplacian: i8,
    /// Octave index (0-based).
    pub octave: u8,
}

/// Keypoints with their descriptors.
#[derive(Clone, Debug)]
pub struct Features {
    /// Keypoints, strongest first.
    pub keypoints: Vec<KeyPoint>,
    descriptors: Vec<f32>,
    kind: DescriptorKind,
}

impl Features {
    /// Assemble from keypoints and row-major descriptors of `kind.stride()` floats each.
    pub fn new(
        keypoints: Vec<KeyPoint>,
        descriptors: Vec<f32>,
        kind: DescriptorKind,
    ) -> Result<Self, VisionError> {
        if descriptors.len() != keypoints.len() * kind.stride() {
            return Err(VisionError::InvalidParam {
                detector: "SURF",
                name: "descriptors",
                reason: format!(
                    "{} floats for {} keypoints of stride {}",
                    descriptors.len(),
                    keypoints.len(),
                    kind.stride()
                ),
            });
        }
        Ok(Self {
            keypoints,
            descriptors,
            kind,
        })
    }
    /// Number of features.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }
    /// True when there are no features.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
    /// The descriptor variant.
    pub fn kind(&self) -> DescriptorKind {
        self.kind
    }
    /// Features whose rows the caller built to `kind`'s stride (the detectors of this module).
    pub(crate) fn from_rows(
        keypoints: Vec<KeyPoint>,
        descriptors: Vec<f32>,
        kind: DescriptorKind,
    ) -> Self {
        debug_assert_eq!(descriptors.len(), keypoints.len() * kind.stride());
        Self {
            keypoints,
            descriptors,
            kind,
        }
    }
    /// The features of `kept` (keypoints of these features, in `kept`'s order) with their rows;
    /// a keypoint that is not one of them (same level, position and response) is left out.
    pub fn subset(&self, kept: &[KeyPoint]) -> Self {
        let key = |k: &KeyPoint| (k.octave, k.x.to_bits(), k.y.to_bits(), k.response.to_bits());
        let index: std::collections::HashMap<_, usize> = self
            .keypoints
            .iter()
            .enumerate()
            .map(|(i, k)| (key(k), i))
            .collect();
        let st = self.kind.stride();
        let (mut kps, mut rows) = (Vec::with_capacity(kept.len()), Vec::new());
        for k in kept {
            if let Some(&i) = index.get(&key(k)) {
                kps.push(*k);
                rows.extend_from_slice(&self.descriptors[i * st..(i + 1) * st]);
            }
        }
        Self::from_rows(kps, rows, self.kind)
    }
    /// Binary descriptor `i` as its 8 words of 32 bits (test `k` is bit `k % 32` of word
    /// `k / 32`). A binary kind's words are kept in the float rows bit for bit: rows are only
    /// copied, never computed with, and a copy keeps a float's bits. Zero for a float kind.
    pub fn binary_descriptor(&self, i: usize) -> [u32; 8] {
        let mut words = [0u32; 8];
        if self.kind.family() == Family::Binary {
            let st = self.kind.stride();
            for (w, v) in words.iter_mut().zip(&self.descriptors[i * st..i * st + 8]) {
                *w = v.to_bits();
            }
        }
        words
    }
    /// Descriptor `i` (`kind().len()` values).
    pub fn descriptor(&self, i: usize) -> &[f32] {
        let st = self.kind.stride();
        &self.descriptors[i * st..i * st + self.kind.len()]
    }
    /// All descriptors, `kind().stride()` floats per row (zero padding beyond `kind().len()`).
    pub fn descriptors_padded(&self) -> &[f32] {
        &self.descriptors
    }
}

/// A configured SURF extractor.
#[derive(Debug)]
pub struct Surf {
    params: SurfParams,
    /// Response-layer buffers kept between calls: fresh multi-megabyte allocations are
    /// page-faulted in on every frame otherwise (about 6 % of the VGA time).
    scratch: std::sync::Mutex<Vec<Vec<f32>>>,
}

impl Clone for Surf {
    fn clone(&self) -> Self {
        Self {
            params: self.params.clone(),
            scratch: std::sync::Mutex::new(Vec::new()),
        }
    }
}

const DXY_WEIGHT_SQ: f32 = 0.81;
const ORI_BINS: usize = 72;
const ORI_WIN_BINS: usize = 12; // 60 degrees

struct Tables {
    /// (i + 6, j + 6, weight): the 113 orientation samples `(i s, j s)`, i^2 + j^2 <= 36, as grid
    /// indices, with the Gaussian weight of sigma 2 (units of s).
    ori_idx: Vec<(u8, u8, f32)>,
    /// Gaussian sigma 3.3 (units of s) on the 20x20 sample grid.
    desc20: Vec<f32>,
    /// Same on the 18x18 grid of SURF-36.
    desc18: Vec<f32>,
}

fn tables() -> &'static Tables {
    static T: OnceLock<Tables> = OnceLock::new();
    T.get_or_init(|| {
        let mut ori_idx = Vec::new();
        for j in -6i32..=6 {
            for i in -6i32..=6 {
                let r2 = (i * i + j * j) as f32;
                if r2 <= 36.0 {
                    ori_idx.push(((i + 6) as u8, (j + 6) as u8, (-r2 / 8.0).exp()));
                }
            }
        }
        let grid = |n: usize| {
            let sp = 20.0 / n as f32;
            let c = (n as f32 - 1.0) / 2.0;
            let mut w = Vec::with_capacity(n * n);
            for j in 0..n {
                for i in 0..n {
                    let u = (i as f32 - c) * sp;
                    let v = (j as f32 - c) * sp;
                    w.push((-(u * u + v * v) / (2.0 * 3.3 * 3.3)).exp());
                }
            }
            w
        };
        Tables {
            ori_idx,
            desc20: grid(20),
            desc18: grid(18),
        }
    })
}

/// The stages of [`Surf::detect_and_describe_staged`], in their order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SurfStage {
    /// The integral image.
    Integral,
    /// The box-filter response layers of every octave.
    Responses,
    /// The 3 x 3 x 3 extrema, their quadratic refinement and the capped even spread.
    Extrema,
    /// Every keypoint's orientation (nothing for upright SURF).
    Orientation,
    /// Every keypoint's descriptor.
    Descriptors,
}

impl SurfStage {
    /// Every stage, in order.
    pub const ALL: [SurfStage; 5] = [
        SurfStage::Integral,
        SurfStage::Responses,
        SurfStage::Extrema,
        SurfStage::Orientation,
        SurfStage::Descriptors,
    ];

    /// A short name for tables and JSON.
    pub fn name(self) -> &'static str {
        match self {
            SurfStage::Integral => "integral",
            SurfStage::Responses => "responses",
            SurfStage::Extrema => "extrema",
            SurfStage::Orientation => "orientation",
            SurfStage::Descriptors => "descriptors",
        }
    }
}

/// One response layer: `det(H)` for filter size `size` on a grid of step `step`.
struct Layer {
    size: usize,
    step: usize,
    rows: usize,
    cols: usize,
    det: Vec<f32>,
}

impl Layer {
    fn spec(&self) -> LayerSpec {
        LayerSpec {
            size: self.size,
            step: self.step,
            rows: self.rows,
            cols: self.cols,
        }
    }

    fn new(s: &LayerSpec, det: Vec<f32>) -> Self {
        Self {
            size: s.size,
            step: s.step,
            rows: s.rows,
            cols: s.cols,
            det,
        }
    }
}

/// Where a response layer is sampled ([`Surf::layer_plan`]): `det(H)` of the box filter of
/// `size` at the pixels `(c * step, r * step)`, `r < rows`, `c < cols`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LayerSpec {
    /// Box filter side, pixels (9, 15, 21, ... in the first octave).
    pub size: usize,
    /// Sampling step, pixels.
    pub step: usize,
    /// Sample rows.
    pub rows: usize,
    /// Sample columns.
    pub cols: usize,
}

/// The response layer `spec` of an image, computed on the CPU (the reference the GPU path is
/// tested against): row-major, 0 where the filter does not fit.
pub fn response_layer(ii: &IntegralImage, spec: &LayerSpec) -> Vec<f32> {
    compute_layer(ii, spec.size, spec.step, spec.rows, spec.cols, Vec::new())
}

/// The Hessian weight of `Dxy` squared (`0.9^2`, Bay et al. 2008 eq. 4): part of the GPU path's
/// contract.
pub const HESSIAN_DXY_WEIGHT_SQ: f32 = DXY_WEIGHT_SQ;

/// Orientation histogram bins over `2 pi` and the sliding window's width in bins (`pi / 3`): part
/// of the GPU path's contract.
pub const ORIENTATION_BINS: usize = ORI_BINS;
/// See [`ORIENTATION_BINS`].
pub const ORIENTATION_WINDOW_BINS: usize = ORI_WIN_BINS;

/// The orientation samples of Bay sec. 4.1 as `(i + 6, j + 6, weight)`: the grid points `(i s,
/// j s)` with `i^2 + j^2 <= 36`, in the CPU's summation order, with their Gaussian weight
/// (sigma 2 s). The GPU path reads these so its weights are the CPU's bit for bit.
pub fn orientation_samples() -> &'static [(u8, u8, f32)] {
    &tables().ori_idx
}

/// The Gaussian weights (sigma 3.3 s) of the descriptor's `samples x samples` grid, row-major
/// (for the GPU path, as [`orientation_samples`]).
pub fn descriptor_weights(kind: DescriptorKind) -> &'static [f32] {
    let t = tables();
    if kind.samples() == 18 {
        &t.desc18
    } else {
        &t.desc20
    }
}

/// Where the extrema of a middle layer are searched (`find_maxima`'s margin): the grid cells
/// `c_lo..=c_hi`, `r_lo..=r_hi` at which the largest filter of the triple (`hi`) fits at every
/// neighbour sample. `None`: nowhere.
pub fn extrema_window(
    width: usize,
    height: usize,
    mid: &LayerSpec,
    hi: &LayerSpec,
) -> Option<ExtremaWindow> {
    let step = mid.step;
    let hs_top = (hi.size - 1) / 2;
    let c_lo = hs_top.div_ceil(step) + 1;
    let r_lo = c_lo;
    if width < 1 + hs_top || height < 1 + hs_top {
        return None;
    }
    let c_hi = ((width - 1 - hs_top) / step).saturating_sub(1);
    let r_hi = ((height - 1 - hs_top) / step).saturating_sub(1);
    // The last two hold for every layer of a plan; they guard the neighbour reads of other callers.
    if c_hi < c_lo || r_hi < r_lo || c_hi + 1 >= mid.cols || r_hi + 1 >= mid.rows {
        return None;
    }
    Some(ExtremaWindow {
        c_lo,
        c_hi,
        r_lo,
        r_hi,
    })
}

/// Grid cells searched for extrema (inclusive bounds), see [`extrema_window`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ExtremaWindow {
    /// First grid column searched.
    pub c_lo: usize,
    /// Last grid column searched.
    pub c_hi: usize,
    /// First grid row searched.
    pub r_lo: usize,
    /// Last grid row searched.
    pub r_hi: usize,
}

/// One 3x3x3 maximum of the response layers, as found ([`keypoint_at`] places it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extremum {
    /// Grid cell `[c, r]` of the middle layer.
    pub cell: [usize; 2],
    /// Interpolated offset `[dx, dy, ds]` in samples (`ds` in units of the filter-size step).
    pub offset: [f64; 3],
    /// `det(H)` at the cell.
    pub response: f32,
    /// Sign of the trace of H: -1 bright blob, +1 dark blob.
    pub laplacian: i8,
}

/// The keypoint of maximum `e` of layer `mid` (octave `octave`), `ds` in units of the
/// filter-size step `mid.size - lo_size`: position in pixels, filter size, scale `1.2 L / 9`.
/// The one formula of the CPU and GPU paths.
pub fn keypoint_at(e: &Extremum, mid: &LayerSpec, lo_size: usize, octave: usize) -> KeyPoint {
    let Extremum {
        cell: [c, r],
        offset: [ox, oy, os],
        response,
        laplacian,
    } = *e;
    let step = mid.step as f64;
    let ds = (mid.size - lo_size) as f64;
    let size = mid.size as f64 + os * ds;
    KeyPoint {
        x: ((c as f64 + ox) * step) as f32,
        y: ((r as f64 + oy) * step) as f32,
        size: size as f32,
        scale: (1.2 * size / 9.0) as f32,
        response,
        orientation_rad: 0.0,
        laplacian,
        octave: octave as u8,
    }
}

/// The orientation of the best window's sum vector `(bx, by)` (what the sliding window of
/// Bay sec. 4.1 gives): `atan2(by, bx)`, 0 for a zero vector. Shared with the GPU path, which
/// returns the vector.
pub fn orientation_of_window(bx: f32, by: f32) -> f32 {
    if bx * bx + by * by > 0.0 {
        by.atan2(bx)
    } else {
        0.0
    }
}

impl Surf {
    /// Validate the parameters and build the extractor.
    pub fn new(params: SurfParams) -> Result<Self, VisionError> {
        params.validate()?;
        Ok(Self {
            params,
            scratch: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// The parameters.
    pub fn params(&self) -> &SurfParams {
        &self.params
    }

    /// Detect, assign orientations and describe.
    pub fn detect_and_describe(&self, img: &GrayImage) -> Features {
        let ii = IntegralImage::new(img);
        let kps = self.detect(&ii);
        self.describe(&ii, kps)
    }

    /// The response layers of a `width` x `height` image, octave by octave (`n_octave_layers + 2`
    /// per octave): filter size, sampling step and grid. An octave whose largest filter plus one
    /// neighbour sample on each side does not fit is left out, and so are all after it.
    pub fn layer_plan(&self, width: usize, height: usize) -> Vec<Vec<LayerSpec>> {
        let p = &self.params;
        let n_layers = p.n_octave_layers + 2;
        let mut plan = Vec::new();
        for o in 0..p.n_octaves {
            let step = p.init_sample_step << o;
            let top = filter_size(o, n_layers - 1);
            // The largest filter of the octave plus one neighbour sample on each side must fit.
            if top + 2 * step > width || top + 2 * step > height {
                break;
            }
            let rows = (height - 1) / step + 1;
            let cols = (width - 1) / step + 1;
            plan.push(
                (0..n_layers)
                    .map(|k| LayerSpec {
                        size: filter_size(o, k),
                        step,
                        rows,
                        cols,
                    })
                    .collect(),
            );
        }
        plan
    }

    /// [`Self::detect_and_describe`] stage by stage, calling `mark` as each [`SurfStage`] ends
    /// (the orientations of all keypoints, then all descriptors, where the one-pass path
    /// interleaves them per keypoint). The same features, bit for bit: `visnav bench surf
    /// --stages` times the stages with it, the caller holding the clock (no clock in the core).
    pub fn detect_and_describe_staged(
        &self,
        img: &GrayImage,
        mark: &mut dyn FnMut(SurfStage),
    ) -> Features {
        let ii = IntegralImage::new(img);
        mark(SurfStage::Integral);
        let (layers, octaves) = self.responses(&ii);
        mark(SurfStage::Responses);
        let mut kps = self.maxima(&ii, &layers, &octaves);
        self.recycle(layers);
        mark(SurfStage::Extrema);
        let upright = self.params.upright;
        kps.par_iter_mut().with_min_len(16).for_each(|kp| {
            kp.orientation_rad = if upright { 0.0 } else { orientation(&ii, kp) };
        });
        mark(SurfStage::Orientation);
        let kind = self.params.descriptor;
        let stride = kind.stride();
        let mut desc = vec![0f32; kps.len() * stride];
        desc.par_chunks_mut(stride)
            .zip(kps.par_iter())
            .with_min_len(16)
            .for_each(|(d, kp)| describe_one(&ii, kp, kind, upright, d));
        mark(SurfStage::Descriptors);
        Features {
            keypoints: kps,
            descriptors: desc,
            kind,
        }
    }

    /// Fast-Hessian detection; keypoints strongest first (orientation not yet assigned), capped to
    /// `max_features` with an even spread.
    pub fn detect(&self, ii: &IntegralImage) -> Vec<KeyPoint> {
        let (layers, octaves) = self.responses(ii);
        let kps = self.maxima(ii, &layers, &octaves);
        self.recycle(layers);
        kps
    }

    /// Every response layer of [`Self::layer_plan`] (a layer shared with a finer octave
    /// subsampled from it), with each octave's layer indices; the buffers come from the scratch
    /// [`Self::recycle`] returns them to.
    fn responses(&self, ii: &IntegralImage) -> (Vec<Layer>, Vec<Vec<usize>>) {
        let plan = self.layer_plan(ii.width(), ii.height());
        let mut layers: Vec<Layer> = Vec::new();
        // A poisoned lock only means another thread panicked mid-call: start with no buffers.
        let mut spare: Vec<Vec<f32>> = self
            .scratch
            .lock()
            .map(|mut g| std::mem::take(&mut *g))
            .unwrap_or_default();
        let take = |spare: &mut Vec<Vec<f32>>| spare.pop().unwrap_or_default();
        let mut octaves: Vec<Vec<usize>> = Vec::new();
        for specs in &plan {
            let mut idx = Vec::with_capacity(specs.len());
            for s in specs {
                // Reuse a finer layer of the same size by subsampling (octaves overlap).
                let det = match layers
                    .iter()
                    .find(|l| l.size == s.size && s.step.is_multiple_of(l.step))
                {
                    Some(src) => {
                        subsample(src, s.step / src.step, s.rows, s.cols, take(&mut spare))
                    }
                    None => compute_layer(ii, s.size, s.step, s.rows, s.cols, take(&mut spare)),
                };
                layers.push(Layer::new(s, det));
                idx.push(layers.len() - 1);
            }
            octaves.push(idx);
        }
        (layers, octaves)
    }

    /// The response layers' buffers kept for the next image (a poisoned lock drops them).
    fn recycle(&self, layers: Vec<Layer>) {
        if let Ok(mut g) = self.scratch.lock() {
            g.clear();
            g.extend(layers.into_iter().map(|l| l.det));
        }
    }

    /// Extrema of every octave's middle layers, strongest first, capped with an even spread.
    fn maxima(
        &self,
        ii: &IntegralImage,
        layers: &[Layer],
        octaves: &[Vec<usize>],
    ) -> Vec<KeyPoint> {
        let p = &self.params;
        let mut kps: Vec<KeyPoint> = Vec::new();
        for (o, idx) in octaves.iter().enumerate() {
            for k in 1..idx.len() - 1 {
                let (lo, mid, hi) = (&layers[idx[k - 1]], &layers[idx[k]], &layers[idx[k + 1]]);
                kps.extend(find_maxima(ii, lo, mid, hi, p.hessian_threshold, o));
            }
        }
        kps.sort_by(|a, b| b.response.total_cmp(&a.response));
        if let Some(n) = p.max_features {
            kps = select_spread(kps, n, ii.width(), ii.height());
        }
        kps
    }

    /// Assign orientations (unless upright) and compute descriptors; parallel over keypoints.
    pub fn describe(&self, ii: &IntegralImage, mut kps: Vec<KeyPoint>) -> Features {
        let kind = self.params.descriptor;
        let stride = kind.stride();
        let upright = self.params.upright;
        let mut desc = vec![0f32; kps.len() * stride];
        desc.par_chunks_mut(stride)
            .zip(kps.par_iter_mut())
            .with_min_len(16)
            .for_each(|(d, kp)| {
                kp.orientation_rad = if upright { 0.0 } else { orientation(ii, kp) };
                describe_one(ii, kp, kind, upright, d);
            });
        Features {
            keypoints: kps,
            descriptors: desc,
            kind,
        }
    }
}

/// Where SURF features are computed and matched: the CPU ([`CpuFeatures`], the reference) or an
/// accelerator that gives the same features and matches (visnav-gpu's GPU path). The fix engine
/// takes one (`FixEngine::set_feature_backend`); the parameters are always the caller's.
pub trait FeatureBackend: Send + Sync {
    /// Detect and describe `img` with `detector`. An accelerator computes the detectors it has
    /// (SURF: [`super::Detector::as_surf`]) and leaves the others to the CPU; one that fails
    /// computes the frame on the CPU instead (and counts it), so a frame is never lost to it.
    fn detect_and_describe(&self, detector: &dyn super::Detector, img: &GrayImage) -> Features;
    /// [`super::match_features`]: the same matches (an accelerator that fails matches on the
    /// CPU). The CPU's by default.
    fn match_features(
        &self,
        query: &Features,
        train: &Features,
        params: &super::MatchParams,
        predicted_in_train: Option<&[[f32; 2]]>,
    ) -> Result<Vec<super::Match>, VisionError> {
        super::match_features(query, train, params, predicted_in_train)
    }
    /// For logs and benches: `cpu`, or `gpu: <adapter>`.
    fn name(&self) -> String;
}

/// The CPU reference as a [`FeatureBackend`].
#[derive(Debug, Clone, Copy, Default)]
pub struct CpuFeatures;

impl FeatureBackend for CpuFeatures {
    fn detect_and_describe(&self, detector: &dyn super::Detector, img: &GrayImage) -> Features {
        detector.detect_and_describe(img)
    }

    fn name(&self) -> String {
        "cpu".into()
    }
}

/// Filter size of layer `k` in octave `o`: `3 (2^(o+1) (k+1) + 1)`.
pub fn filter_size(o: usize, k: usize) -> usize {
    3 * ((2usize << o) * (k + 1) + 1)
}

/// The box-filter Hessian entries `(Dxx, Dyy, Dxy)` at pixel `(x, y)` for filter size `size`
/// (lobe-area normalised). Requires the filter inside the image: `(size-1)/2 <= x <= w-1-(size-1)/2`,
/// same for `y`. Scalar reference for the vectorised layer computation.
pub fn hessian_at(ii: &IntegralImage, x: usize, y: usize, size: usize) -> (f32, f32, f32) {
    let l = size / 3;
    let h = (size - 1) / 2;
    let m = (l - 1) / 2;
    let inv_a = 1.0 / (l * (2 * l - 1)) as f32;
    let inv_d = 1.0 / (l * l) as f32;
    let b = |x0: usize, y0: usize, x1: usize, y1: usize| ii.box_sum(x0, y0, x1, y1);
    let dyy = b(x + 1 - l, y - h, x + l, y + h + 1).wrapping_sub(3i32.wrapping_mul(b(
        x + 1 - l,
        y - m,
        x + l,
        y + m + 1,
    )));
    let dxx = b(x - h, y + 1 - l, x + h + 1, y + l).wrapping_sub(3i32.wrapping_mul(b(
        x - m,
        y + 1 - l,
        x + m + 1,
        y + l,
    )));
    let dxy = b(x - l, y - l, x, y)
        .wrapping_add(b(x + 1, y + 1, x + l + 1, y + l + 1))
        .wrapping_sub(b(x + 1, y - l, x + l + 1, y))
        .wrapping_sub(b(x - l, y + 1, x, y + l + 1));
    (dxx as f32 * inv_a, dyy as f32 * inv_a, dxy as f32 * inv_d)
}

fn subsample(src: &Layer, f: usize, rows: usize, cols: usize, mut out: Vec<f32>) -> Vec<f32> {
    out.clear();
    out.resize(rows * cols, 0.0);
    for r in 0..rows {
        let sr = r * f;
        if sr >= src.rows {
            break;
        }
        let srow = &src.det[sr * src.cols..(sr + 1) * src.cols];
        for (c, o) in out[r * cols..(r + 1) * cols].iter_mut().enumerate() {
            if let Some(&v) = srow.get(c * f) {
                *o = v;
            }
        }
    }
    out
}

/// `det(H)` for filter `size` on the grid of centres `(c*step, r*step)`; 0 where the filter does
/// not fit. Per output row, three strips of column sums over the needed integral rows are formed,
/// after which every response needs 10 strip reads (vectorised for step 1):
/// `E = S_all - 3 S_mid` gives `Dyy`, `S_x` gives `Dxx`, `D = S_top - S_bottom` gives `Dxy`.
fn compute_layer(
    ii: &IntegralImage,
    size: usize,
    step: usize,
    rows: usize,
    cols: usize,
    buf: Vec<f32>,
) -> Vec<f32> {
    // A recycled buffer keeps its old values: every sample is written below (the filter's
    // responses, and 0 where it does not fit), so only a growth is zeroed here.
    let mut det = buf;
    det.resize(rows * cols, 0.0);
    let (w, h) = (ii.width(), ii.height());
    let hs = (size - 1) / 2;
    if size > w || size > h {
        det.fill(0.0);
        return det;
    }
    let l = size / 3;
    let m = (l - 1) / 2;
    let c0 = hs.div_ceil(step);
    let c1 = (w - 1 - hs) / step;
    let r0 = hs.div_ceil(step);
    let r1 = (h - 1 - hs) / step;
    if c1 < c0 || r1 < r0 {
        det.fill(0.0);
        return det;
    }
    let inv_a = 1.0 / (l * (2 * l - 1)) as f32;
    let inv_d = 1.0 / (l * l) as f32;
    let sw = ii.stride();
    let g = RowGeom {
        step,
        hs,
        l,
        m,
        c0,
        c1,
        inv_a,
        inv_d,
    };
    det.par_chunks_mut(cols)
        .enumerate()
        .with_min_len(8)
        .for_each_init(
            || (vec![0i32; sw], vec![0i32; sw], vec![0i32; sw]),
            |(e, sx, d), (r, out)| {
                if r >= r0 && r <= r1 {
                    out[..c0].fill(0.0);
                    out[(c1 + 1).min(cols)..].fill(0.0);
                    layer_row(ii, &g, r * step, e, sx, d, out);
                } else {
                    out.fill(0.0);
                }
            },
        );
    det
}

/// Geometry of one response layer row (see `compute_layer`).
#[derive(Clone, Copy)]
struct RowGeom {
    step: usize,
    hs: usize,
    l: usize,
    m: usize,
    c0: usize,
    c1: usize,
    inv_a: f32,
    inv_d: f32,
}

/// Responses of one layer row at image row `y` (kept out of line for profiling).
///
/// On x86-64 with AVX2 the same loops run in 256-bit registers ([`layer_row_avx2`]; baseline
/// x86-64 has SSE2, 4 lanes of `i32`): wrapping integer sums are exact in any width and the
/// single-precision products are the same operations in the same order (no FMA), so the
/// responses are bit for bit the baseline's.
#[inline(never)]
fn layer_row(
    ii: &IntegralImage,
    g: &RowGeom,
    y: usize,
    e: &mut [i32],
    sx: &mut [i32],
    d: &mut [i32],
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU was just found to support AVX2, the only feature the function enables.
        return unsafe { layer_row_avx2(ii, g, y, e, sx, d, out) };
    }
    layer_row_body(ii, g, y, e, sx, d, out);
}

/// [`layer_row_body`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn layer_row_avx2(
    ii: &IntegralImage,
    g: &RowGeom,
    y: usize,
    e: &mut [i32],
    sx: &mut [i32],
    d: &mut [i32],
    out: &mut [f32],
) {
    layer_row_body(ii, g, y, e, sx, d, out);
}

/// The responses of one layer row: three strips of column sums of the integral image, then the
/// box filters from them (see the module doc). Inlined into each instruction-set variant.
#[inline(always)]
fn layer_row_body(
    ii: &IntegralImage,
    g: &RowGeom,
    y: usize,
    e: &mut [i32],
    sx: &mut [i32],
    d: &mut [i32],
    out: &mut [f32],
) {
    let RowGeom {
        step,
        hs,
        l,
        m,
        c0,
        c1,
        inv_a,
        inv_d,
    } = *g;
    let n = c1 - c0 + 1;
    {
        let (a1, a0) = (ii.row(y + hs + 1), ii.row(y - hs));
        let (m1, m0) = (ii.row(y + m + 1), ii.row(y - m));
        for ((((ev, &a1), &a0), &m1), &m0) in e.iter_mut().zip(a1).zip(a0).zip(m1).zip(m0) {
            *ev = a1
                .wrapping_sub(a0)
                .wrapping_sub(3i32.wrapping_mul(m1.wrapping_sub(m0)));
        }
        let (x1, x0) = (ii.row(y + l), ii.row(y + 1 - l));
        for ((s, &p1), &p0) in sx.iter_mut().zip(x1).zip(x0) {
            *s = p1.wrapping_sub(p0);
        }
        let (t1, t0) = (ii.row(y), ii.row(y - l));
        let (b1, b0) = (ii.row(y + l + 1), ii.row(y + 1));
        for ((((dv, &t1), &t0), &b1), &b0) in d.iter_mut().zip(t1).zip(t0).zip(b1).zip(b0) {
            *dv = t1.wrapping_sub(t0).wrapping_sub(b1.wrapping_sub(b0));
        }
    }
    if step == 1 {
        let xs = c0;
        let e_hi = &e[xs + l..][..n];
        let e_lo = &e[xs + 1 - l..][..n];
        let sa = &sx[xs + hs + 1..][..n];
        let sb = &sx[xs - hs..][..n];
        let sc = &sx[xs + m + 1..][..n];
        let sd = &sx[xs - m..][..n];
        let d0 = &d[xs..][..n];
        let d1 = &d[xs - l..][..n];
        let d2 = &d[xs + l + 1..][..n];
        let d3 = &d[xs + 1..][..n];
        let out = &mut out[c0..c0 + n];
        for i in 0..n {
            let dyy = e_hi[i].wrapping_sub(e_lo[i]) as f32 * inv_a;
            let dxx = sa[i]
                .wrapping_sub(sb[i])
                .wrapping_sub(3i32.wrapping_mul(sc[i].wrapping_sub(sd[i])))
                as f32
                * inv_a;
            let dxy = d0[i]
                .wrapping_sub(d1[i])
                .wrapping_sub(d2[i])
                .wrapping_add(d3[i]) as f32
                * inv_d;
            out[i] = dxx * dyy - DXY_WEIGHT_SQ * dxy * dxy;
        }
    } else {
        for (c, o) in out.iter_mut().enumerate().take(c1 + 1).skip(c0) {
            let x = c * step;
            let dyy = e[x + l].wrapping_sub(e[x + 1 - l]) as f32 * inv_a;
            let dxx = sx[x + hs + 1]
                .wrapping_sub(sx[x - hs])
                .wrapping_sub(3i32.wrapping_mul(sx[x + m + 1].wrapping_sub(sx[x - m])))
                as f32
                * inv_a;
            let dxy = d[x]
                .wrapping_sub(d[x - l])
                .wrapping_sub(d[x + l + 1])
                .wrapping_add(d[x + 1]) as f32
                * inv_d;
            *o = dxx * dyy - DXY_WEIGHT_SQ * dxy * dxy;
        }
    }
}

/// 3x3x3 non-maximum suppression in the middle layer and quadratic interpolation.
fn find_maxima<'a>(
    ii: &IntegralImage,
    lo: &'a Layer,
    mid: &'a Layer,
    hi: &'a Layer,
    threshold: f32,
    octave: usize,
) -> Vec<KeyPoint> {
    let step = mid.step;
    let cols = mid.cols;
    // Margin: the largest filter must fit at the neighbour samples too.
    let Some(ExtremaWindow {
        c_lo,
        c_hi,
        r_lo,
        r_hi,
    }) = extrema_window(ii.width(), ii.height(), &mid.spec(), &hi.spec())
    else {
        return Vec::new();
    };
    #[cfg(target_arch = "x86_64")]
    let avx = std::arch::is_x86_feature_detected!("avx");
    #[cfg(not(target_arch = "x86_64"))]
    let avx = false;
    (r_lo..r_hi + 1)
        .into_par_iter()
        .with_min_len(4)
        .flat_map_iter(|r| {
            let mut found = Vec::new();
            let rows3 = |l: &'a Layer| -> [&'a [f32]; 3] {
                [-1isize, 0, 1].map(|d| {
                    let rr = (r as isize + d) as usize;
                    &l.det[rr * cols..(rr + 1) * cols]
                })
            };
            let layers3 = [rows3(mid), rows3(lo), rows3(hi)];
            let row = layers3[0][1];
            let mut cands = Vec::new();
            row_candidates(layers3, (c_lo, c_hi), threshold, avx, &mut cands);
            for c in cands {
                let v0 = row[c];
                let at = |l: &Layer, dr: isize, dc: isize| -> f32 {
                    l.det[(r as isize + dr) as usize * cols + (c as isize + dc) as usize]
                };
                let mut is_max = true;
                'outer: for (li, l) in [mid, hi, lo].into_iter().enumerate() {
                    for dr in -1..=1 {
                        for dc in -1..=1 {
                            if li == 0 && dr == 0 && dc == 0 {
                                continue;
                            }
                            if at(l, dr, dc) >= v0 {
                                is_max = false;
                                break 'outer;
                            }
                        }
                    }
                }
                if !is_max {
                    continue;
                }
                let v = |s: isize, dr: isize, dc: isize| -> f64 {
                    let l = match s {
                        -1 => lo,
                        0 => mid,
                        _ => hi,
                    };
                    f64::from(at(l, dr, dc))
                };
                let Some(offset) = interpolate(&v) else {
                    continue;
                };
                let (dxx, dyy, _) = hessian_at(ii, c * step, r * step, mid.size);
                let laplacian = if dxx + dyy < 0.0 { -1 } else { 1 };
                let e = Extremum {
                    cell: [c, r],
                    offset,
                    response: v0,
                    laplacian,
                };
                found.push(keypoint_at(&e, &mid.spec(), lo.size, octave));
            }
            found.into_iter()
        })
        .collect()
}

/// The columns `c_lo..=c_hi` of the middle row of `mid` (rows `r - 1, r, r + 1` of the middle
/// layer; `lo` and `hi` the same rows of the layers below and above) that can be maxima: above
/// `threshold` and above both row neighbours, the test the full 26-neighbour one
/// ([`find_maxima`]) starts from. With `avx` (the caller detected it) the CPU's 8-lane compares
/// (whole groups of 8 columns) also drop the columns any other of the 26 neighbours equals or
/// exceeds, which the full test refuses anyway, so the maxima are the same; in column order.
fn row_candidates(
    [mid, lo, hi]: [[&[f32]; 3]; 3],
    (c_lo, c_hi): (usize, usize),
    threshold: f32,
    avx: bool,
    out: &mut Vec<usize>,
) {
    let row = mid[1];
    let mut c = c_lo;
    #[cfg(target_arch = "x86_64")]
    if avx {
        // SAFETY: the caller found AVX on this CPU, the only feature the function enables.
        c = unsafe { row_candidates_avx([mid, lo, hi], (c_lo, c_hi), threshold, out) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (avx, lo, hi);
    while c <= c_hi {
        let v = row[c];
        if (v > threshold) & (v > row[c - 1]) & (v > row[c + 1]) {
            out.push(c);
        }
        c += 1;
    }
}

/// [`row_candidates`] 8 columns at a time in AVX registers, as far as whole groups of 8 reach;
/// returns the first column left for the scalar loop. Each lane keeps `v > threshold`, `v >
/// left`, `v > right` (ordered compares: NaN fails them, as the scalar `>`), and drops the lane
/// when any other of its 26 neighbours is `>= v` (ordered: a NaN neighbour drops nothing, as the
/// full test's `>=`). The 18 neighbours of the other layers are read only for groups with a lane
/// left.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn row_candidates_avx(
    [mid, lo, hi]: [[&[f32]; 3]; 3],
    (c_lo, c_hi): (usize, usize),
    threshold: f32,
    out: &mut Vec<usize>,
) -> usize {
    use std::arch::x86_64::*;
    let load = |s: &[f32], from: usize| -> __m256 {
        let lanes = &s[from..from + 8];
        // SAFETY: `lanes` is exactly 8 f32 long, what an unaligned 256-bit load reads.
        unsafe { _mm256_loadu_ps(lanes.as_ptr()) }
    };
    let drop_ge = |keep: __m256, rows: &[&[f32]], v: __m256, c: usize| -> __m256 {
        let mut keep = keep;
        for n in rows {
            for from in [c - 1, c, c + 1] {
                keep = _mm256_andnot_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(load(n, from), v), keep);
            }
        }
        keep
    };
    let row = mid[1];
    let len = [mid, lo, hi]
        .iter()
        .flatten()
        .map(|r| r.len())
        .min()
        .unwrap_or(0);
    let thr = _mm256_set1_ps(threshold);
    let mut c = c_lo;
    // Columns c - 1 ..= c + 8 are read: c + 8 <= c_hi + 1, a column of every row (the extrema
    // window keeps c_hi + 1 inside the layer, c_lo >= 1).
    while c + 8 <= c_hi + 1 && c + 9 <= len {
        let v = load(row, c);
        let keep = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GT_OQ>(v, thr),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(v, load(row, c - 1)),
                _mm256_cmp_ps::<_CMP_GT_OQ>(v, load(row, c + 1)),
            ),
        );
        let mut keep = drop_ge(keep, &[mid[0], mid[2]], v, c);
        if _mm256_movemask_ps(keep) != 0 {
            keep = drop_ge(keep, &[lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]], v, c);
        }
        let mut mask = _mm256_movemask_ps(keep) as u32;
        while mask != 0 {
            out.push(c + mask.trailing_zeros() as usize);
            mask &= mask - 1;
        }
        c += 8;
    }
    c
}

/// Solve `A o = -g` for the quadratic fit of `v(ds, dy, dx)` around its centre sample; `None` when
/// singular or the offset exceeds one sample in any dimension.
fn interpolate(v: &impl Fn(isize, isize, isize) -> f64) -> Option<[f64; 3]> {
    let v0 = v(0, 0, 0);
    let gx = (v(0, 0, 1) - v(0, 0, -1)) / 2.0;
    let gy = (v(0, 1, 0) - v(0, -1, 0)) / 2.0;
    let gs = (v(1, 0, 0) - v(-1, 0, 0)) / 2.0;
    let dxx = v(0, 0, 1) - 2.0 * v0 + v(0, 0, -1);
    let dyy = v(0, 1, 0) - 2.0 * v0 + v(0, -1, 0);
    let dss = v(1, 0, 0) - 2.0 * v0 + v(-1, 0, 0);
    let dxy = (v(0, 1, 1) - v(0, 1, -1) - v(0, -1, 1) + v(0, -1, -1)) / 4.0;
    let dxs = (v(1, 0, 1) - v(1, 0, -1) - v(-1, 0, 1) + v(-1, 0, -1)) / 4.0;
    let dys = (v(1, 1, 0) - v(1, -1, 0) - v(-1, 1, 0) + v(-1, -1, 0)) / 4.0;
    let a = nalgebra::Matrix3::new(dxx, dxy, dxs, dxy, dyy, dys, dxs, dys, dss);
    let b = nalgebra::Vector3::new(-gx, -gy, -gs);
    let o = a.lu().solve(&b)?;
    if o.iter().all(|c| c.is_finite() && c.abs() <= 1.0) {
        Some([o[0], o[1], o[2]])
    } else {
        None
    }
}

/// Keep the `n` strongest keypoints with an even spatial spread: the image is cut into about
/// `n / 2` square cells and keypoints are taken round-robin over the cells, strongest first in
/// each cell and each round, so dense textured areas cannot take the whole budget.
/// Input and output are sorted strongest first.
pub fn select_spread(kps: Vec<KeyPoint>, n: usize, width: usize, height: usize) -> Vec<KeyPoint> {
    if kps.len() <= n {
        return kps;
    }
    let cells = (n / 2).max(1) as f64;
    let side = ((width * height) as f64 / cells).sqrt().max(1.0);
    let gx = ((width as f64 / side).ceil() as usize).max(1);
    let gy = ((height as f64 / side).ceil() as usize).max(1);
    let mut buckets: Vec<Vec<KeyPoint>> = vec![Vec::new(); gx * gy];
    let mut sorted = kps;
    sorted.sort_by(|a, b| b.response.total_cmp(&a.response));
    for kp in sorted {
        let cx = ((f64::from(kp.x) / side).max(0.0) as usize).min(gx - 1);
        let cy = ((f64::from(kp.y) / side).max(0.0) as usize).min(gy - 1);
        buckets[cy * gx + cx].push(kp);
    }
    let mut out = Vec::with_capacity(n);
    let mut round = 0;
    while out.len() < n {
        let mut layer: Vec<KeyPoint> = buckets
            .iter()
            .filter_map(|b| b.get(round).copied())
            .collect();
        if layer.is_empty() {
            break;
        }
        layer.sort_by(|a, b| b.response.total_cmp(&a.response));
        let take = (n - out.len()).min(layer.len());
        out.extend_from_slice(&layer[..take]);
        round += 1;
    }
    out.sort_by(|a, b| b.response.total_cmp(&a.response));
    out
}

/// Index of the pixel boundary nearest to continuous coordinate `f` (pixel centres at integers):
/// `floor(f + 1)`, clamped to `[half, n - half]` so a box of half-side `half` fits. Truncation
/// equals floor for non-negative values, and negative ones clamp to `half` anyway; `as` maps NaN
/// to 0 and saturates, so any input is safe. (Avoids `floorf`, a libm call without SSE4.1.)
#[inline(always)]
fn boundary_index(f: f32, half: usize, n: usize) -> usize {
    ((f + 1.0) as i32).clamp(half as i32, (n - half) as i32) as usize
}

/// `atan2(y, x)` within 1e-5 rad (polynomial, Abramowitz & Stegun 4.4.49 style); used only to bin
/// orientation samples, `(0, 0)` maps to 0. Written with selects only (no data-dependent
/// branches: the signs of gradient samples are random, mispredictions dominated the old version).
#[inline(always)]
fn fast_atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let mn = ax.min(ay);
    let mx = ax.max(ay);
    // 0 / tiny = 0 covers (0, 0).
    let a = mn / mx.max(f32::MIN_POSITIVE);
    let t = a * a;
    let r = ((((-0.013_480_47 * t + 0.057_477_31) * t - 0.121_239_07) * t + 0.195_635_93) * t
        - 0.332_994_6)
        * t
        * a
        + 0.999_995_6 * a;
    let r = if ay > ax { FRAC_PI_2 - r } else { r };
    let r = if x < 0.0 { PI - r } else { r };
    if y < 0.0 { -r } else { r }
}

/// Haar wavelet responses `(dx, dy)` of side `2 half` centred at continuous `(fx, fy)`, read from
/// the integral image (9 cells). The box is shifted inside the image near borders.
#[inline(always)]
fn haar(ii: &IntegralImage, fx: f32, fy: f32, half: usize) -> (f32, f32) {
    let (w, h) = (ii.width(), ii.height());
    let half = half.min(w / 2).min(h / 2).max(1);
    if 2 * half > w || 2 * half > h {
        return (0.0, 0.0);
    }
    let xs = boundary_index(fx, half, w);
    let ys = boundary_index(fy, half, h);
    let st = ii.stride();
    let d = ii.data();
    let r0 = (ys - half) * st;
    let r1 = ys * st;
    let r2 = (ys + half) * st;
    let (x0, x1, x2) = (xs - half, xs, xs + half);
    let a00 = d[r0 + x0];
    let a01 = d[r0 + x1];
    let a02 = d[r0 + x2];
    let a10 = d[r1 + x0];
    let a12 = d[r1 + x2];
    let a20 = d[r2 + x0];
    let a21 = d[r2 + x1];
    let a22 = d[r2 + x2];
    let (dx, dy) = haar_from_corners([a00, a01, a02], [a10, a12], [a20, a21, a22]);
    (dx as f32, dy as f32)
}

/// Haar wavelet responses from the integral-image samples at the 3x3 corner grid of a square of
/// side `2 * half` (rows top/middle/bottom, columns left/centre/right; the middle row's centre is
/// not needed). Wrapping arithmetic matches the wrapping integral image.
#[inline(always)]
fn haar_from_corners(top: [i32; 3], mid: [i32; 2], bot: [i32; 3]) -> (i32, i32) {
    let ([a00, a01, a02], [a10, a12], [a20, a21, a22]) = (top, mid, bot);
    // right - left = (a22 - a02 - a21 + a01) - (a21 - a01 - a20 + a00)
    let dx = a22
        .wrapping_sub(a02)
        .wrapping_sub(a21.wrapping_mul(2))
        .wrapping_add(a01.wrapping_mul(2))
        .wrapping_add(a20)
        .wrapping_sub(a00);
    // bottom - top = (a22 - a12 - a20 + a10) - (a12 - a02 - a10 + a00)
    let dy = a22
        .wrapping_sub(a12.wrapping_mul(2))
        .wrapping_sub(a20)
        .wrapping_add(a10.wrapping_mul(2))
        .wrapping_add(a02)
        .wrapping_sub(a00);
    (dx, dy)
}

/// Dominant orientation (Bay sec. 4.1), radians in `(-pi, pi]`.
///
/// The 113 sample points lie on the grid `(kp.x + i s, kp.y + j s)`, `|i|, |j| <= 6`, so the
/// integral-image columns of the 13 grid columns and the rows of the 13 grid rows are computed once
/// per keypoint; every sample then needs only its 8 corner loads (no float-to-index conversion or
/// clamping per sample). The Haar responses are gathered first, their bins computed in a
/// branch-free pass, and they are summed into two interleaved bin arrays (breaking the chains of
/// dependent stores when neighbouring samples fall in the same bin). Same samples and weights as
/// sampling each point with `haar()`; only the summation order differs (the test
/// `orientation_equals_per_sample_reference` bounds the difference).
fn orientation(ii: &IntegralImage, kp: &KeyPoint) -> f32 {
    const N: usize = 13;
    let s = kp.scale;
    let (w, h) = (ii.width(), ii.height());
    // Wavelet side 4s, shrunk for tiny images exactly as `haar()` does.
    let half = ((2.0 * s).round() as usize)
        .max(1)
        .min(w / 2)
        .min(h / 2)
        .max(1);
    if 2 * half > w || 2 * half > h {
        return 0.0;
    }
    let mut cols = [0usize; N];
    let mut rows = [0usize; N];
    for k in 0..N {
        let o = (k as f32 - 6.0) * s;
        cols[k] = boundary_index(kp.x + o, half, w);
        rows[k] = boundary_index(kp.y + o, half, h);
    }
    let st = ii.stride();
    let d = ii.data();
    let t = tables();
    let n = t.ori_idx.len();
    let mut gx = [0f32; 113];
    let mut gy = [0f32; 113];
    for (q, &(ci, cj, _)) in t.ori_idx.iter().enumerate() {
        let y = rows[cj as usize];
        let x = cols[ci as usize];
        let (r0, r1, r2) = ((y - half) * st, y * st, (y + half) * st);
        let (x0, x2) = (x - half, x + half);
        let (dx, dy) = haar_from_corners(
            [d[r0 + x0], d[r0 + x], d[r0 + x2]],
            [d[r1 + x0], d[r1 + x2]],
            [d[r2 + x0], d[r2 + x], d[r2 + x2]],
        );
        gx[q] = dx as f32;
        gy[q] = dy as f32;
    }
    // Bin indices in a branch-free pass (vectorisable), then two interleaved bin arrays so that
    // neighbouring samples of similar direction do not wait on each other's stores.
    let bin_scale = ORI_BINS as f32 / std::f32::consts::TAU;
    let mut bidx = [0u8; 113];
    for q in 0..n {
        // A zero response adds nothing wherever it is binned.
        let a = fast_atan2(gy[q], gx[q]); // [-pi, pi]
        bidx[q] = bin_floor((a + std::f32::consts::PI) * bin_scale).min(ORI_BINS as u32 - 1) as u8;
    }
    let mut bins = [[[0f32; 2]; ORI_BINS]; 2];
    for (q, &(_, _, wt)) in t.ori_idx.iter().enumerate().take(n) {
        let b = &mut bins[q & 1][bidx[q] as usize];
        b[0] += wt * gx[q];
        b[1] += wt * gy[q];
    }
    let mut sum = bins[0];
    for (o, e) in sum.iter_mut().zip(&bins[1]) {
        o[0] += e[0];
        o[1] += e[1];
    }
    best_window(&sum)
}

/// `floor(f)` for `f` in `[0, 2^22)` without a float-to-integer conversion (whose saturation
/// checks kept the binning loop scalar): adding `2^23` rounds to an integer held in the mantissa
/// bits; one is taken off when that rounded up.
#[inline(always)]
fn bin_floor(f: f32) -> u32 {
    const MAGIC: f32 = 8_388_608.0; // 2^23
    let r = f + MAGIC;
    let up = u32::from(r - MAGIC > f);
    (r.to_bits() & 0x007f_ffff) - up
}

/// The sliding `pi/3` window over the orientation bins: direction of the longest sum vector.
fn best_window(bins: &[[f32; 2]; ORI_BINS]) -> f32 {
    let mut sx: f32 = bins[..ORI_WIN_BINS].iter().map(|b| b[0]).sum();
    let mut sy: f32 = bins[..ORI_WIN_BINS].iter().map(|b| b[1]).sum();
    let (mut best, mut bx, mut by) = (sx * sx + sy * sy, sx, sy);
    for start in 1..ORI_BINS {
        let out = bins[start - 1];
        let inn = bins[(start + ORI_WIN_BINS - 1) % ORI_BINS];
        sx += inn[0] - out[0];
        sy += inn[1] - out[1];
        let m = sx * sx + sy * sy;
        if m > best {
            (best, bx, by) = (m, sx, sy);
        }
    }
    orientation_of_window(bx, by)
}

/// Compute one descriptor into `out` (`kind.stride()` floats; padding left at zero).
#[inline(never)]
fn describe_one(
    ii: &IntegralImage,
    kp: &KeyPoint,
    kind: DescriptorKind,
    upright: bool,
    out: &mut [f32],
) {
    let s = kp.scale;
    let half = (s.round() as usize).max(1); // wavelet side 2s
    let n = kind.samples();
    let nsub = kind.subregions();
    let per = n / nsub;
    // Subregion column of each sample column (no integer division in the sample loops).
    let mut sub_of = [0usize; 20];
    for (k, v) in sub_of.iter_mut().enumerate().take(n) {
        *v = k / per;
    }
    let t = tables();
    let weights = if n == 18 { &t.desc18 } else { &t.desc20 };
    let sp = 20.0 / n as f32 * s;
    let c = (n as f32 - 1.0) / 2.0;
    let (si, co) = if upright {
        (0.0, 1.0)
    } else {
        kp.orientation_rad.sin_cos()
    };
    let extended = kind == DescriptorKind::Surf128;
    let vals = if extended { 8 } else { 4 };
    let mut acc = [0f32; 128];
    let (w, h) = (ii.width(), ii.height());
    if upright && 2 * half <= w && 2 * half <= h {
        // Axis-aligned grid: the integral-image columns and rows of every sample are computed once
        // per keypoint (20 + 20 instead of 400 per axis); per sample only 8 loads remain.
        let mut cols = [0usize; 20];
        let mut rows = [0usize; 20];
        for k in 0..n {
            let o = (k as f32 - c) * sp;
            cols[k] = boundary_index(kp.x + o, half, w);
            rows[k] = boundary_index(kp.y + o, half, h);
        }
        let st = ii.stride();
        let d = ii.data();
        for j in 0..n {
            let y = rows[j];
            let r0 = &d[(y - half) * st..][..st];
            let r1 = &d[y * st..][..st];
            let r2 = &d[(y + half) * st..][..st];
            let wrow = &weights[j * n..][..n];
            let mut rxs = [0f32; 20];
            let mut rys = [0f32; 20];
            for i in 0..n {
                let x = cols[i];
                let (x0, x2) = (x - half, x + half);
                let (dx, dy) = haar_from_corners(
                    [r0[x0], r0[x], r0[x2]],
                    [r1[x0], r1[x2]],
                    [r2[x0], r2[x], r2[x2]],
                );
                rxs[i] = wrow[i] * dx as f32;
                rys[i] = wrow[i] * dy as f32;
            }
            accumulate_row(
                &mut acc,
                &rxs[..n],
                &rys[..n],
                sub_of[j] * nsub,
                nsub,
                extended,
            );
        }
        finish(&acc[..kind.len()], out);
        return;
    }
    // The fixed-point cell grid needs coordinates far from the i64 range (any keypoint of a real
    // image); anything else takes the per-sample path, which clamps whatever it gets.
    let sane = kp.x.abs() < 1e7 && kp.y.abs() < 1e7 && s < 1e5 && kp.orientation_rad.is_finite();
    // SURF-128 keeps the per-sample path: its sign-split sums lost 2-5 points of matching score
    // with the cell grid on the protocol pairs (SURF-36/64 stayed within +-1 point).
    if !upright && kind != DescriptorKind::Surf128 && half <= w && half <= h && sane {
        describe_rotated(ii, kp, kind, &sub_of, weights, &mut acc);
        finish(&acc[..kind.len()], out);
        return;
    }
    // Per-sample fallback (upright keypoints on images smaller than the wavelet).
    for j in 0..n {
        let v = (j as f32 - c) * sp;
        let row_sub = sub_of[j] * nsub;
        for i in 0..n {
            let u = (i as f32 - c) * sp;
            let wt = weights[j * n + i];
            let (fx, fy) = if upright {
                (kp.x + u, kp.y + v)
            } else {
                (kp.x + co * u - si * v, kp.y + si * u + co * v)
            };
            let (dx, dy) = haar(ii, fx, fy, half);
            let rx = wt * (co * dx + si * dy);
            let ry = wt * (co * dy - si * dx);
            accumulate(
                &mut acc[(row_sub + sub_of[i]) * vals..][..vals],
                rx,
                ry,
                extended,
            );
        }
    }
    finish(&acc[..kind.len()], out);
}

/// Rotated descriptor window sampled as a grid of cells (OpenCV's patch scheme without the warp).
///
/// The `20s` window, rotated by the keypoint orientation, is covered by `(n+1) x (n+1)` cells of
/// spacing `sp = 20s/n` centred at `(k - n/2) sp` along the keypoint axes `u = (cos, sin)`,
/// `v = (-sin, cos)`. Each cell is the sum of the axis-aligned `c x c` pixel box (`c = round(s)`)
/// nearest to its centre: 4 integral-image loads, no per-sample warp or interpolation. The Haar
/// responses of side `2c` at the `n x n` sample points (the cell corners' centres
/// `(i - (n-1)/2) sp`) are then differences of the four neighbouring cells, directly along `u`
/// and `v`: `dx = (right pair) - (left pair)`, `dy = (lower pair) - (upper pair)`, which are the
/// wavelets of the paper evaluated in the keypoint frame (OpenCV samples a rotated patch the same
/// way). At orientation 0 with integer `s` this equals the upright path exactly. Cells whose box
/// would leave the image are shifted inside it (the same rule as `haar()`); a window entirely
/// inside the image skips those clamps.
fn describe_rotated(
    ii: &IntegralImage,
    kp: &KeyPoint,
    kind: DescriptorKind,
    sub_of: &[usize; 20],
    weights: &[f32],
    acc: &mut [f32; 128],
) {
    const M: usize = 21;
    let n = kind.samples();
    let m = n + 1;
    let nsub = kind.subregions();
    let extended = kind == DescriptorKind::Surf128;
    let s = kp.scale;
    let sp = 20.0 / n as f32 * s;
    let c = (s.round() as usize).max(1);
    let (w, h) = (ii.width(), ii.height());
    let (si, co) = kp.orientation_rad.sin_cos();
    let (ux, uy) = (sp * co, sp * si);
    let (vx, vy) = (-sp * si, sp * co);
    let half_n = n as f32 / 2.0;
    // Top-left pixel of cell (k, l)'s box: floor(centre + 1 - c/2) (see `boundary_index`).
    let off = 1.0 - c as f32 / 2.0;
    let ox = kp.x + off - half_n * (ux + vx);
    let oy = kp.y + off - half_n * (uy + vy);
    // Box origins in 48.16 fixed point: floor is an arithmetic shift, no float-to-integer
    // conversion (with its saturation checks) per cell.
    const FX: f32 = 65536.0;
    let fix = |v: f32| (f64::from(v) * f64::from(FX)).round() as i64;
    let (ox, oy, ux, uy, vx, vy) = (fix(ox), fix(oy), fix(ux), fix(uy), fix(vx), fix(vy));
    let (xm, ym) = ((w - c) as i64, (h - c) as i64);
    let ni = n as i64;
    let inside = [(0, 0), (ni, 0), (0, ni), (ni, ni)].iter().all(|&(k, l)| {
        let x = (ox + k * ux + l * vx) >> 16;
        let y = (oy + k * uy + l * vy) >> 16;
        (0..=xm).contains(&x) && (0..=ym).contains(&y)
    });
    let st = ii.stride();
    let d = ii.data();
    let (cs, ce) = (c * st, c * st + c);
    let mut cells = [0f32; M * M];
    for l in 0..m {
        let li = l as i64;
        let (rx, ry) = (ox + li * vx, oy + li * vy);
        let row = &mut cells[l * m..][..m];
        for (k, cell) in row.iter_mut().enumerate() {
            let ki = k as i64;
            let mut x = (rx + ki * ux) >> 16;
            let mut y = (ry + ki * uy) >> 16;
            if !inside {
                x = x.clamp(0, xm);
                y = y.clamp(0, ym);
            }
            let i0 = y as usize * st + x as usize;
            *cell = d[i0 + ce]
                .wrapping_sub(d[i0 + cs])
                .wrapping_sub(d[i0 + c])
                .wrapping_add(d[i0]) as f32;
        }
    }
    let mut rxs = [0f32; 20];
    let mut rys = [0f32; 20];
    for j in 0..n {
        let r0 = &cells[j * m..][..m];
        let r1 = &cells[(j + 1) * m..][..m];
        let wrow = &weights[j * n..][..n];
        for i in 0..n {
            let (a, b, p, q) = (r0[i], r0[i + 1], r1[i], r1[i + 1]);
            rxs[i] = wrow[i] * ((b + q) - (a + p));
            rys[i] = wrow[i] * ((p + q) - (a + b));
        }
        accumulate_row(acc, &rxs[..n], &rys[..n], sub_of[j] * nsub, nsub, extended);
    }
}

/// Add one row of weighted, rotated responses to the subregion sums of descriptor row `row_sub`
/// (`row_sub / nsub`). SURF-36/64 sum each subregion's samples in registers first and touch the
/// accumulator once per subregion (no chain of dependent stores); SURF-128 splits by sign per
/// sample.
#[inline(always)]
fn accumulate_row(
    acc: &mut [f32; 128],
    rxs: &[f32],
    rys: &[f32],
    row_sub: usize,
    nsub: usize,
    extended: bool,
) {
    let per = rxs.len() / nsub;
    if extended {
        for (i, (&rx, &ry)) in rxs.iter().zip(rys).enumerate() {
            let k = (row_sub + i / per) * 8;
            accumulate(&mut acc[k..k + 8], rx, ry, true);
        }
        return;
    }
    for b in 0..nsub {
        let (xs, ys) = (&rxs[b * per..][..per], &rys[b * per..][..per]);
        let (mut s0, mut s1, mut s2, mut s3) = (0f32, 0f32, 0f32, 0f32);
        for (&rx, &ry) in xs.iter().zip(ys) {
            s0 += rx;
            s1 += ry;
            s2 += rx.abs();
            s3 += ry.abs();
        }
        let a = &mut acc[(row_sub + b) * 4..][..4];
        a[0] += s0;
        a[1] += s1;
        a[2] += s2;
        a[3] += s3;
    }
}

/// Add one rotated, weighted response to its subregion's sums (4 or 8 values, OpenCV's order).
#[inline(always)]
fn accumulate(a: &mut [f32], rx: f32, ry: f32, extended: bool) {
    if extended {
        if ry >= 0.0 {
            a[0] += rx;
            a[1] += rx.abs();
        } else {
            a[2] += rx;
            a[3] += rx.abs();
        }
        if rx >= 0.0 {
            a[4] += ry;
            a[5] += ry.abs();
        } else {
            a[6] += ry;
            a[7] += ry.abs();
        }
    } else {
        a[0] += rx;
        a[1] += ry;
        a[2] += rx.abs();
        a[3] += ry.abs();
    }
}

/// L2-normalise `acc` into `out` (all zeros stay zeros).
fn finish(acc: &[f32], out: &mut [f32]) {
    let norm2: f32 = acc.iter().map(|v| v * v).sum();
    let inv = if norm2 > 0.0 { 1.0 / norm2.sqrt() } else { 0.0 };
    for (o, a) in out.iter_mut().zip(acc) {
        *o = a * inv;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob_image(w: usize, h: usize, blobs: &[(f32, f32, f32, f32)]) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| {
            let mut v = 128.0;
            for &(bx, by, sigma, amp) in blobs {
                let r2 = (x as f32 - bx).powi(2) + (y as f32 - by).powi(2);
                v += amp * (-r2 / (2.0 * sigma * sigma)).exp();
            }
            v
        })
    }

    /// The AVX candidates are the scalar ones less only those another of the 26 neighbours
    /// equals or exceeds (which the full test refuses), on rows with many ties, a NaN and every
    /// alignment of the window.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx_row_candidates_drop_only_what_the_full_test_refuses() {
        if !std::arch::is_x86_feature_detected!("avx") {
            eprintln!("SKIP avx_row_candidates_drop_only_what_the_full_test_refuses: no AVX");
            return;
        }
        let mut s = 4242u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % 7) as f32 * 50.0
        };
        let mut dropped = 0;
        for trial in 0..200 {
            let cols = 20 + trial % 29;
            let mut rows: Vec<Vec<f32>> = (0..9)
                .map(|_| (0..cols).map(|_| next()).collect())
                .collect();
            if trial % 5 == 0 {
                rows[trial % 9][cols / 2] = f32::NAN;
            }
            let (c_lo, c_hi) = (1 + trial % 4, cols - 2 - trial % 3);
            let r3 = |k: usize| [&rows[k][..], &rows[k + 1][..], &rows[k + 2][..]];
            let refs = [r3(0), r3(3), r3(6)];
            let (mut scalar, mut avx) = (Vec::new(), Vec::new());
            row_candidates(refs, (c_lo, c_hi), 120.0, false, &mut scalar);
            row_candidates(refs, (c_lo, c_hi), 120.0, true, &mut avx);
            // Rows 0-2 the middle layer's (row 1 the candidates'), 3-5 and 6-8 the others.
            let refused = |c: usize| {
                let v = rows[1][c];
                (0..9).any(|k| (c - 1..=c + 1).any(|cc| (k, cc) != (1, c) && rows[k][cc] >= v))
            };
            assert!(avx.iter().all(|c| scalar.contains(c)), "trial {trial}");
            assert!(avx.windows(2).all(|w| w[0] < w[1]), "trial {trial}");
            for c in scalar.iter().filter(|c| !avx.contains(c)) {
                assert!(refused(*c), "trial {trial}: column {c} dropped");
            }
            dropped += scalar.len() - avx.len();
        }
        assert!(dropped > 100, "{dropped}");
    }

    /// The staged path gives the one-pass path's features bit for bit, every mode and
    /// descriptor, and marks each stage once, in order.
    #[test]
    fn the_staged_path_gives_the_same_features_and_marks_every_stage() {
        let mut s = 99u64;
        let img = GrayImage::from_fn(160, 120, |x, y| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let blob = ((x as f32 / 9.0).sin() * (y as f32 / 7.0).cos() + 1.0) * 90.0;
            blob + ((s >> 33) % 40) as f32
        });
        for upright in [true, false] {
            for descriptor in [
                DescriptorKind::Surf36,
                DescriptorKind::Surf64,
                DescriptorKind::Surf128,
            ] {
                let surf = Surf::new(SurfParams {
                    upright,
                    descriptor,
                    ..SurfParams::default()
                })
                .unwrap();
                let one = surf.detect_and_describe(&img);
                let mut marks = Vec::new();
                let staged = surf.detect_and_describe_staged(&img, &mut |st| marks.push(st));
                assert_eq!(marks, SurfStage::ALL, "{upright} {descriptor:?}");
                assert!(one.len() > 10, "{}", one.len());
                assert_eq!(one.len(), staged.len());
                for (a, b) in one.keypoints.iter().zip(&staged.keypoints) {
                    assert_eq!(a.x.to_bits(), b.x.to_bits());
                    assert_eq!(a.y.to_bits(), b.y.to_bits());
                    assert_eq!(a.orientation_rad.to_bits(), b.orientation_rad.to_bits());
                    assert_eq!(a.response.to_bits(), b.response.to_bits());
                }
                let bits = |f: &Features| -> Vec<u32> {
                    f.descriptors.iter().map(|v| v.to_bits()).collect()
                };
                assert_eq!(bits(&one), bits(&staged), "{upright} {descriptor:?}");
            }
        }
    }

    /// A recycled buffer (any length, stale values) gives the layer a fresh one gives, also
    /// where the filter does not fit at all.
    #[test]
    fn a_recycled_layer_buffer_leaves_no_stale_sample() {
        let img = GrayImage::from_fn(70, 45, |x, y| ((x * 7 + y * 13) % 200) as f32);
        let ii = IntegralImage::new(&img);
        for (size, step) in [(9, 1), (27, 2), (51, 4), (99, 1)] {
            let rows = (45 - 1) / step + 1;
            let cols = (70 - 1) / step + 1;
            let fresh = compute_layer(&ii, size, step, rows, cols, Vec::new());
            for stale_len in [0, rows * cols / 2, rows * cols, rows * cols * 3] {
                let stale = vec![f32::NAN; stale_len];
                let got = compute_layer(&ii, size, step, rows, cols, stale);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&fresh), "{size} {step} {stale_len}");
            }
        }
    }

    #[test]
    fn filter_sizes_follow_the_paper() {
        let o0: Vec<_> = (0..4).map(|k| filter_size(0, k)).collect();
        let o1: Vec<_> = (0..4).map(|k| filter_size(1, k)).collect();
        let o2: Vec<_> = (0..4).map(|k| filter_size(2, k)).collect();
        assert_eq!(o0, [9, 15, 21, 27]);
        assert_eq!(o1, [15, 27, 39, 51]);
        assert_eq!(o2, [27, 51, 75, 99]);
    }

    #[test]
    fn layer_matches_scalar_reference() {
        let mut s = 12345u64;
        let img = GrayImage::from_fn(61, 47, |_, _| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % 256) as f32
        });
        let ii = IntegralImage::new(&img);
        for (size, step) in [(9, 1), (15, 1), (27, 2), (21, 1), (51, 4)] {
            let rows = (47 - 1) / step + 1;
            let cols = (61 - 1) / step + 1;
            let det = compute_layer(&ii, size, step, rows, cols, Vec::new());
            let hs = (size - 1) / 2;
            for r in 0..rows {
                for c in 0..cols {
                    let (x, y) = (c * step, r * step);
                    let want = if x >= hs && y >= hs && x + hs < 61 && y + hs < 47 {
                        let (a, b, d) = hessian_at(&ii, x, y, size);
                        a * b - 0.81 * d * d
                    } else {
                        0.0
                    };
                    let got = det[r * cols + c];
                    assert!(
                        (got - want).abs() <= 1e-3 * want.abs().max(1.0),
                        "{size} {step} {r} {c}: {got} vs {want}"
                    );
                }
            }
        }
    }

    /// The AVX2 response rows are the baseline's to the bit, for every filter size and step of
    /// the octaves and rows of every kind (from the top margin to the bottom one).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_rows_have_the_baselines_bits() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            eprintln!("SKIP avx2_rows_have_the_baselines_bits: this CPU has no AVX2");
            return;
        }
        let mut s = 777u64;
        let img = GrayImage::from_fn(203, 97, |_, _| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % 256) as f32
        });
        let ii = IntegralImage::new(&img);
        let sw = ii.stride();
        for (size, step) in [(9, 1), (15, 1), (21, 1), (27, 2), (39, 2), (51, 4), (75, 4)] {
            let (hs, l) = ((size - 1) / 2, size / 3);
            let g = RowGeom {
                step,
                hs,
                l,
                m: (l - 1) / 2,
                c0: hs.div_ceil(step),
                c1: (203 - 1 - hs) / step,
                inv_a: 1.0 / (l * (2 * l - 1)) as f32,
                inv_d: 1.0 / (l * l) as f32,
            };
            let cols = (203 - 1) / step + 1;
            for y in (hs..97 - hs).step_by(step) {
                let bufs = || (vec![0i32; sw], vec![0i32; sw], vec![0i32; sw]);
                let ((mut e, mut sx, mut d), mut want) = (bufs(), vec![0f32; cols]);
                layer_row_body(&ii, &g, y, &mut e, &mut sx, &mut d, &mut want);
                let ((mut e, mut sx, mut d), mut got) = (bufs(), vec![0f32; cols]);
                // SAFETY: AVX2 was found above.
                unsafe { layer_row_avx2(&ii, &g, y, &mut e, &mut sx, &mut d, &mut got) };
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "size {size} step {step} row {y}");
            }
        }
    }

    #[test]
    fn bin_floor_is_floor() {
        for k in 0..=720_000u32 {
            let f = k as f32 * 1e-4;
            assert_eq!(bin_floor(f), f.floor() as u32, "{f}");
        }
        for f in [0.0f32, 0.5, 1.5, 2.5, 71.999_99, 72.0, 4_000_000.5] {
            assert_eq!(bin_floor(f), f.floor() as u32, "{f}");
        }
    }

    #[test]
    fn fast_atan2_is_accurate() {
        for k in 0..3600 {
            let a = (k as f32 / 10.0 - 180.0).to_radians();
            for r in [0.001f32, 1.0, 1000.0] {
                let (y, x) = (r * a.sin(), r * a.cos());
                let d = (fast_atan2(y, x) - y.atan2(x)).abs();
                assert!(
                    d < 2e-5 || (d - std::f32::consts::TAU).abs() < 2e-5,
                    "{a} {d}"
                );
            }
        }
        assert_eq!(fast_atan2(0.0, 0.0), 0.0);
    }

    fn noise_image(w: usize, h: usize, seed: u64) -> GrayImage {
        let mut s = seed;
        GrayImage::from_fn(w, h, |x, y| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) % 64) as f32 + (x + y) as f32 * 0.5
        })
    }

    fn test_kp(x: f32, y: f32, scale: f32, orientation_rad: f32) -> KeyPoint {
        KeyPoint {
            x,
            y,
            size: scale * 7.5,
            scale,
            response: 1.0,
            orientation_rad,
            laplacian: 1,
            octave: 0,
        }
    }

    /// The previous implementation: every sample through `haar()`, binned on the fly.
    fn orientation_reference(ii: &IntegralImage, kp: &KeyPoint) -> f32 {
        let s = kp.scale;
        let half = ((2.0 * s).round() as usize).max(1);
        let mut bins = [[0f32; 2]; ORI_BINS];
        let bin_scale = ORI_BINS as f32 / std::f32::consts::TAU;
        for &(ci, cj, wt) in &tables().ori_idx {
            let (i, j) = (f32::from(ci) - 6.0, f32::from(cj) - 6.0);
            let (dx, dy) = haar(ii, kp.x + i * s, kp.y + j * s, half);
            if dx == 0.0 && dy == 0.0 {
                continue;
            }
            let a = fast_atan2(dy, dx);
            let b = (((a + std::f32::consts::PI) * bin_scale) as usize).min(ORI_BINS - 1);
            bins[b][0] += wt * dx;
            bins[b][1] += wt * dy;
        }
        best_window(&bins)
    }

    /// The previous rotated descriptor: axis-aligned Haar at each rotated sample, response rotated.
    fn descriptor_reference(ii: &IntegralImage, kp: &KeyPoint, kind: DescriptorKind) -> Vec<f32> {
        let s = kp.scale;
        let half = (s.round() as usize).max(1);
        let (n, nsub) = (kind.samples(), kind.subregions());
        let per = n / nsub;
        let t = tables();
        let weights = if n == 18 { &t.desc18 } else { &t.desc20 };
        let sp = 20.0 / n as f32 * s;
        let c = (n as f32 - 1.0) / 2.0;
        let (si, co) = kp.orientation_rad.sin_cos();
        let extended = kind == DescriptorKind::Surf128;
        let vals = if extended { 8 } else { 4 };
        let mut acc = [0f32; 128];
        for j in 0..n {
            let v = (j as f32 - c) * sp;
            for i in 0..n {
                let u = (i as f32 - c) * sp;
                let (fx, fy) = (kp.x + co * u - si * v, kp.y + si * u + co * v);
                let (dx, dy) = haar(ii, fx, fy, half);
                let wt = weights[j * n + i];
                let rx = wt * (co * dx + si * dy);
                let ry = wt * (co * dy - si * dx);
                let idx = ((j / per) * nsub + i / per) * vals;
                accumulate(&mut acc[idx..idx + vals], rx, ry, extended);
            }
        }
        let mut out = vec![0f32; kind.stride()];
        finish(&acc[..kind.len()], &mut out);
        out
    }

    fn cosine(a: &[f32], b: &[f32]) -> f32 {
        let dot: f32 = a.iter().zip(b).map(|(p, q)| p * q).sum();
        let na: f32 = a.iter().map(|p| p * p).sum::<f32>().sqrt();
        let nb: f32 = b.iter().map(|p| p * p).sum::<f32>().sqrt();
        dot / (na * nb).max(1e-12)
    }

    #[test]
    fn orientation_equals_per_sample_reference() {
        let img = noise_image(150, 110, 7);
        let ii = IntegralImage::new(&img);
        let mut n = 0;
        for y in [0.0f32, 3.3, 20.0, 55.5, 90.25, 109.0] {
            for x in [0.0f32, 2.7, 31.0, 75.5, 120.1, 149.0] {
                for sc in [1.2f32, 1.6, 2.5, 4.0, 7.3] {
                    let kp = test_kp(x, y, sc, 0.0);
                    let (a, b) = (orientation(&ii, &kp), orientation_reference(&ii, &kp));
                    // Same samples, bins and weights; only the summation order differs.
                    let d = (a - b).abs();
                    assert!(
                        d < 1e-4 || (d - std::f32::consts::TAU).abs() < 1e-4,
                        "{x} {y} {sc}: {a} vs {b}"
                    );
                    n += 1;
                }
            }
        }
        assert_eq!(n, 180);
        // Images smaller than the wavelet.
        let tiny = IntegralImage::new(&noise_image(5, 4, 3));
        let kp = test_kp(2.0, 2.0, 3.0, 0.0);
        assert_eq!(orientation(&tiny, &kp), orientation_reference(&tiny, &kp));
    }

    #[test]
    fn rotated_descriptor_equals_upright_at_zero_for_integer_scales() {
        let ii = IntegralImage::new(&noise_image(120, 100, 99));
        for kind in [DescriptorKind::Surf64, DescriptorKind::Surf128] {
            for (x, y, sc) in [
                // Windows inside the image (at the border the two paths shift boxes differently).
                (60.0f32, 50.0f32, 2.0f32),
                (40.3, 50.2, 3.0),
                (60.5, 48.7, 4.0),
                (47.6, 52.2, 1.0),
            ] {
                let kp = test_kp(x, y, sc, 0.0);
                let mut a = vec![0f32; kind.stride()];
                let mut b = vec![0f32; kind.stride()];
                describe_one(&ii, &kp, kind, true, &mut a);
                describe_one(&ii, &kp, kind, false, &mut b);
                for (p, q) in a.iter().zip(&b) {
                    assert!((p - q).abs() < 1e-5, "{kind:?} {x} {y} {sc}");
                }
            }
        }
    }

    #[test]
    fn rotated_descriptor_agrees_with_the_per_sample_reference() {
        // Same window, same Gaussian, Haar boxes in the keypoint frame instead of rotated
        // axis-aligned responses: the descriptors stay close (cosine similarity).
        let img = blob_image(
            160,
            140,
            &[
                (70.0, 60.0, 5.0, 90.0),
                (85.0, 75.0, 3.0, -70.0),
                (60.0, 80.0, 8.0, 40.0),
            ],
        );
        let ii = IntegralImage::new(&img);
        let mut worst = 1.0f32;
        for kind in [
            DescriptorKind::Surf36,
            DescriptorKind::Surf64,
            DescriptorKind::Surf128,
        ] {
            for deg in [0.0f32, 17.0, 45.0, 90.0, 133.0, -60.0, 180.0] {
                for sc in [1.6f32, 2.5, 3.3] {
                    let kp = test_kp(75.0, 70.0, sc, deg.to_radians());
                    let mut a = vec![0f32; kind.stride()];
                    describe_one(&ii, &kp, kind, false, &mut a);
                    let b = descriptor_reference(&ii, &kp, kind);
                    worst = worst.min(cosine(&a, &b));
                }
            }
        }
        assert!(worst > 0.95, "worst cosine {worst}");
    }

    #[test]
    fn rotated_descriptor_near_the_border_is_finite_and_normalised() {
        let ii = IntegralImage::new(&noise_image(64, 48, 5));
        for (x, y) in [(0.0f32, 0.0f32), (63.0, 47.0), (-5.0, 20.0), (30.0, 60.0)] {
            for deg in [0.0f32, 30.0, 200.0] {
                let kp = test_kp(x, y, 3.1, deg.to_radians());
                let mut a = vec![0f32; DescriptorKind::Surf64.stride()];
                describe_one(&ii, &kp, DescriptorKind::Surf64, false, &mut a);
                let n: f32 = a.iter().map(|v| v * v).sum();
                assert!(a.iter().all(|v| v.is_finite()));
                assert!((n - 1.0).abs() < 1e-4, "{x} {y} {deg}: norm {n}");
            }
        }
        // Smaller than a cell: all zeros, no panic.
        let tiny = IntegralImage::new(&noise_image(3, 3, 1));
        let mut a = vec![0f32; DescriptorKind::Surf64.stride()];
        describe_one(
            &tiny,
            &test_kp(1.0, 1.0, 6.0, 0.5),
            DescriptorKind::Surf64,
            false,
            &mut a,
        );
        assert!(a.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn hessian_of_linear_ramp_is_zero() {
        let img = GrayImage::from_fn(40, 40, |x, y| (2 * x + 3 * y) as f32);
        let ii = IntegralImage::new(&img);
        let (a, b, c) = hessian_at(&ii, 20, 20, 15);
        assert_eq!((a, b, c), (0.0, 0.0, 0.0));
    }

    #[test]
    fn detects_gaussian_blobs_at_their_scale_and_sign() {
        // A bright blob (sigma 4) and a dark blob (sigma 8).
        let img = blob_image(
            200,
            160,
            &[(50.0, 60.0, 4.0, 100.0), (130.0, 80.0, 8.0, -100.0)],
        );
        let surf = Surf::new(SurfParams {
            hessian_threshold: 50.0,
            ..SurfParams::default()
        })
        .unwrap();
        let f = surf.detect_and_describe(&img);
        let near = |x: f32, y: f32| {
            f.keypoints
                .iter()
                .filter(|k| (k.x - x).hypot(k.y - y) < 2.0)
                .max_by(|a, b| a.response.total_cmp(&b.response))
                .copied()
        };
        let b = near(50.0, 60.0).expect("bright blob found");
        let d = near(130.0, 80.0).expect("dark blob found");
        assert_eq!(b.laplacian, -1);
        assert_eq!(d.laplacian, 1);
        // The box filter approximates sigma = 1.2 L / 9 = s; blob of sigma t peaks at about s = t.
        assert!(
            (b.scale / 4.0 - 1.0).abs() < 0.35,
            "bright scale {}",
            b.scale
        );
        assert!((d.scale / 8.0 - 1.0).abs() < 0.35, "dark scale {}", d.scale);
        for i in 0..f.len() {
            let n: f32 = f.descriptor(i).iter().map(|v| v * v).sum();
            assert!((n - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn orientation_follows_rotation() {
        // An elongated asymmetric pattern; rotating the image rotates the orientation.
        let make = |ang: f32| {
            let (s, c) = ang.sin_cos();
            GrayImage::from_fn(128, 128, |x, y| {
                let (dx, dy) = (x as f32 - 64.0, y as f32 - 64.0);
                // Rotate back into the pattern frame.
                let u = c * dx + s * dy;
                let v = -s * dx + c * dy;
                // A step along u plus an off-centre blob: one dominant gradient direction.
                let step = 60.0 * (u / 6.0).tanh() * (-(u * u + v * v) / 800.0).exp();
                let blob = 30.0 * (-((u - 6.0).powi(2) + (v - 4.0).powi(2)) / 30.0).exp();
                120.0 + step + blob
            })
        };
        let ii0 = IntegralImage::new(&make(0.0));
        let kp = KeyPoint {
            x: 64.0,
            y: 64.0,
            size: 27.0,
            scale: 3.6,
            response: 1.0,
            orientation_rad: 0.0,
            laplacian: -1,
            octave: 0,
        };
        let a0 = orientation(&ii0, &kp);
        assert!(a0.abs() < 0.3, "unrotated orientation {a0}");
        for deg in [30.0f32, 90.0, 135.0, -100.0] {
            let r = deg.to_radians();
            let a = orientation(&IntegralImage::new(&make(r)), &kp);
            let mut diff = a - a0 - r;
            while diff > std::f32::consts::PI {
                diff -= std::f32::consts::TAU;
            }
            while diff < -std::f32::consts::PI {
                diff += std::f32::consts::TAU;
            }
            assert!(diff.abs() < 0.15, "rotation {deg}: orientation {a} vs {a0}");
        }
    }

    #[test]
    fn spread_selection_covers_the_image() {
        // 200 strong keypoints in one corner, 50 weak ones spread out: a cap of 60 keeps some of both.
        let mut kps = Vec::new();
        for i in 0..200 {
            kps.push(KeyPoint {
                x: (i % 20) as f32,
                y: (i / 20) as f32,
                size: 9.0,
                scale: 1.2,
                response: 1000.0 + i as f32,
                orientation_rad: 0.0,
                laplacian: 1,
                octave: 0,
            });
        }
        for i in 0..50 {
            kps.push(KeyPoint {
                x: 100.0 + 15.0 * (i % 10) as f32,
                y: 100.0 + 15.0 * (i / 10) as f32,
                size: 9.0,
                scale: 1.2,
                response: 200.0 + i as f32,
                orientation_rad: 0.0,
                laplacian: 1,
                octave: 0,
            });
        }
        let sel = select_spread(kps, 60, 256, 256);
        assert_eq!(sel.len(), 60);
        let far = sel.iter().filter(|k| k.x >= 100.0).count();
        assert!(far >= 20, "spread keeps {far} far keypoints");
        assert!(sel.windows(2).all(|w| w[0].response >= w[1].response));
    }

    #[test]
    fn params_are_validated() {
        assert!(
            Surf::new(SurfParams {
                n_octaves: 0,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            Surf::new(SurfParams {
                hessian_threshold: f32::NAN,
                ..Default::default()
            })
            .is_err()
        );
        assert!(
            Surf::new(SurfParams {
                max_features: Some(0),
                ..Default::default()
            })
            .is_err()
        );
    }

    #[test]
    fn tiny_and_flat_images_give_no_features() {
        let surf = Surf::new(SurfParams::default()).unwrap();
        let f = surf.detect_and_describe(&GrayImage::from_fn(5, 5, |_, _| 3.0));
        assert!(f.is_empty());
        let f = surf.detect_and_describe(&GrayImage::from_fn(100, 80, |_, _| 77.0));
        assert!(f.is_empty());
    }
}
