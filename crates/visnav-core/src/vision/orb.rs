//! ORB-like binary features: FAST-9 corners ranked by the Harris measure, the intensity-centroid
//! orientation and a steered BRIEF-256 descriptor (Rublee, Rabaud, Konolige, Bradski, "ORB: an
//! efficient alternative to SIFT or SURF", ICCV 2011; Rosten & Drummond, "Machine learning for
//! high-speed corner detection", ECCV 2006; Calonder et al., "BRIEF", ECCV 2010).
//!
//! It is the second detector behind [`super::detector::Detector`]: small, fast, and of another
//! family (binary, compared by Hamming distance) than SURF, so the seam is exercised by something
//! that shares nothing with SURF but the keypoint type. It is not tuned for the fix (SURF is the
//! default, docs/surf.md); its accuracy is measured, not promised.
//!
//! * **Pyramid**: level `k` is the image resampled by `1 / scale_factor^k` (bilinear), `n_levels`
//!   levels; keypoints are reported in level-0 pixels.
//! * **FAST-9** (radius-3 Bresenham circle of 16 pixels): a pixel is a corner when 9 contiguous
//!   circle pixels are all brighter than it by more than `fast_threshold` or all darker by more.
//!   Candidates are ranked by the Harris measure `det(M) - 0.04 trace(M)^2` of the 7 x 7 structure
//!   tensor of central differences, and kept when they are the maximum of their 3 x 3
//!   neighbourhood.
//! * **Orientation**: `atan2(m01, m10)` of the intensity moments over a disc of radius
//!   [`PATCH_RADIUS`]; 0 in upright mode (rectified frames, as upright SURF).
//! * **Descriptor**: 256 tests `I(p) < I(q)` on the 5 x 5 box means (integral image) of point pairs
//!   drawn once from an isotropic Gaussian (sigma = patch size / 5, clipped to the patch) by the
//!   project's seeded generator, rotated by the keypoint's orientation and scaled by its level.
//!   The bits are packed into 8 words of 32 bits ([`super::DescriptorKind::Binary256`]).
//!
//! Keypoint fields: `size` = the patch diameter at level 0 scale, `scale` = `1.2 size / 9` (the
//! SURF convention, so scale ratios mean the same for both families), `laplacian` = 0 (no blob
//! sign: the Laplacian gate passes every pair), `octave` = the pyramid level.

use std::sync::OnceLock;

use rayon::prelude::*;

use super::surf::select_spread;
use super::{DescriptorKind, Features, GrayImage, IntegralImage, KeyPoint, VisionError};

/// Radius of the oriented patch (ORB's 31 x 31 patch).
pub const PATCH_RADIUS: usize = 15;
/// Half side of the box a test point averages (5 x 5, ORB's smoothing of the tests).
const TEST_BOX_HALF: i64 = 2;
/// Test points are drawn within this radius, so their boxes stay inside the patch.
const TEST_RADIUS: f64 = (PATCH_RADIUS as i64 - TEST_BOX_HALF) as f64;
/// Number of binary tests (bits).
const N_TESTS: usize = 256;
/// Seed of the test pattern: fixed, so maps and frames always share the pattern.
const PATTERN_SEED: u64 = 0x0b_2011;
/// Harris's `k` (Harris & Stephens 1988; ORB's value).
const HARRIS_K: f32 = 0.04;
/// Half side of the Harris window (7 x 7).
const HARRIS_HALF: usize = 3;
/// Contiguous circle pixels a FAST-9 corner needs.
const FAST_ARC: usize = 9;
/// The 16 pixels of the radius-3 Bresenham circle, clockwise from the top.
const CIRCLE: [(i64, i64); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// ORB settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrbParams {
    /// FAST threshold, intensity units (0..255 scale; ORB's default 20).
    pub fast_threshold: f32,
    /// Pyramid levels (ORB's default 8; aerial frames rectified to the map's scale need few).
    pub n_levels: usize,
    /// Scale between pyramid levels (ORB's default 1.2).
    pub scale_factor: f32,
    /// Skip the orientation (rectified, north-up frames).
    pub upright: bool,
    /// Keep at most this many keypoints, with an even spread ([`select_spread`]); `None` keeps
    /// all.
    pub max_features: Option<usize>,
}

impl Default for OrbParams {
    fn default() -> Self {
        Self {
            fast_threshold: 20.0,
            n_levels: 4,
            scale_factor: 1.3,
            upright: true,
            max_features: None,
        }
    }
}

impl OrbParams {
    /// The largest keypoint scale these settings give, level-0 pixels (`1.2 size / 9` at the
    /// coarsest pyramid level).
    pub fn largest_scale_px(&self) -> f64 {
        let size = (2 * PATCH_RADIUS + 1) as f64
            * f64::from(self.scale_factor).powi(self.n_levels.saturating_sub(1) as i32);
        1.2 * size / 9.0
    }
    /// How far from a keypoint the detector reads pixels, level-0 pixels: the patch and the
    /// corner tests' border at the coarsest level (a map tile's margin).
    pub fn reach_px(&self) -> usize {
        let s = f64::from(self.scale_factor).powi(self.n_levels.saturating_sub(1) as i32);
        ((PATCH_RADIUS + 4) as f64 * s).ceil() as usize + 1
    }
    /// Check ranges; names the offending field.
    pub fn validate(&self) -> Result<(), VisionError> {
        let bad = |name, reason: &str| {
            Err(VisionError::InvalidParam {
                detector: "ORB",
                name,
                reason: reason.to_string(),
            })
        };
        if !(self.fast_threshold.is_finite() && self.fast_threshold > 0.0) {
            return bad("fast_threshold", "must be finite and > 0");
        }
        if !(1..=12).contains(&self.n_levels) {
            return bad("n_levels", "must be in 1..=12");
        }
        if !(self.scale_factor.is_finite() && (1.05..=2.0).contains(&self.scale_factor)) {
            return bad("scale_factor", "must be in 1.05..=2");
        }
        if self.max_features == Some(0) {
            return bad("max_features", "must be positive when set");
        }
        Ok(())
    }
}

/// A configured ORB extractor.
#[derive(Debug, Clone)]
pub struct Orb {
    params: OrbParams,
}

/// The 256 test pairs `[x1, y1, x2, y2]` (pixels at level scale 1, orientation 0).
fn pattern() -> &'static [[f32; 4]; N_TESTS] {
    static P: OnceLock<[[f32; 4]; N_TESTS]> = OnceLock::new();
    P.get_or_init(|| {
        let mut rng = crate::rng::Rng::new(PATTERN_SEED);
        let sigma = (2 * PATCH_RADIUS + 1) as f64 / 5.0;
        let mut point = || loop {
            let (x, y) = (rng.normal() * sigma, rng.normal() * sigma);
            if x.hypot(y) <= TEST_RADIUS {
                return [x as f32, y as f32];
            }
        };
        let mut out = [[0f32; 4]; N_TESTS];
        for t in &mut out {
            let (a, b) = (point(), point());
            *t = [a[0], a[1], b[0], b[1]];
        }
        out
    })
}

impl Orb {
    /// Validate the parameters and build the extractor.
    pub fn new(params: OrbParams) -> Result<Self, VisionError> {
        params.validate()?;
        Ok(Self { params })
    }

    /// The settings.
    pub fn params(&self) -> &OrbParams {
        &self.params
    }

    /// Detect and describe: keypoints strongest first, with their binary descriptors.
    pub fn detect_and_describe(&self, img: &GrayImage) -> Features {
        let p = &self.params;
        let mut per_level: Vec<(usize, f32, GrayImage)> = Vec::with_capacity(p.n_levels);
        let mut s = 1f32;
        for level in 0..p.n_levels {
            let (w, h) = (
                (img.width() as f32 / s).round() as usize,
                (img.height() as f32 / s).round() as usize,
            );
            if w < 2 * (PATCH_RADIUS + 4) || h < 2 * (PATCH_RADIUS + 4) {
                break;
            }
            let im = if level == 0 {
                img.clone()
            } else {
                resample(img, w, h, s)
            };
            per_level.push((level, s, im));
            s *= p.scale_factor;
        }
        let found: Vec<(KeyPoint, [u32; 8])> = per_level
            .par_iter()
            .flat_map_iter(|(level, s, im)| detect_level(im, *level, *s, p).into_iter())
            .collect();
        let (kps, words): (Vec<KeyPoint>, Vec<[u32; 8]>) = found.into_iter().unzip();
        let rows = words.iter().flatten().map(|w| f32::from_bits(*w)).collect();
        let all = Features::from_rows(kps, rows, DescriptorKind::Binary256);
        let kept = match p.max_features {
            Some(cap) => select_spread(all.keypoints.clone(), cap, img.width(), img.height()),
            None => {
                let mut k = all.keypoints.clone();
                k.sort_by(|a, b| b.response.total_cmp(&a.response));
                k
            }
        };
        all.subset(&kept)
    }
}

/// `img` resampled to `w x h` with a pixel of `s` source pixels (bilinear at the centres).
fn resample(img: &GrayImage, w: usize, h: usize, s: f32) -> GrayImage {
    GrayImage::from_fn(w, h, |x, y| {
        let (sx, sy) = ((x as f32 + 0.5) * s - 0.5, (y as f32 + 0.5) * s - 0.5);
        img.sample_bilinear(f64::from(sx), f64::from(sy))
            .unwrap_or_else(|| img.get(sx.round().max(0.0) as usize, sy.round().max(0.0) as usize))
    })
}

/// Whether 9 contiguous circle pixels around `(x, y)` are all brighter or all darker by `t`.
fn is_fast_corner(im: &GrayImage, x: usize, y: usize, t: f32) -> bool {
    let c = im.get(x, y);
    let mut states = [0i8; 16];
    for (i, (dx, dy)) in CIRCLE.iter().enumerate() {
        let v = im.get((x as i64 + dx) as usize, (y as i64 + dy) as usize);
        states[i] = if v > c + t {
            1
        } else if v < c - t {
            -1
        } else {
            0
        };
    }
    for want in [1i8, -1] {
        let mut run = 0;
        // Twice round the circle, so an arc across the start counts whole.
        for i in 0..32 {
            if states[i % 16] == want {
                run += 1;
                if run >= FAST_ARC {
                    return true;
                }
            } else {
                run = 0;
            }
        }
    }
    false
}

/// The Harris measure of the 7 x 7 structure tensor at `(x, y)`.
fn harris(im: &GrayImage, x: usize, y: usize) -> f32 {
    let (mut a, mut b, mut c) = (0f32, 0f32, 0f32);
    for v in y - HARRIS_HALF..=y + HARRIS_HALF {
        for u in x - HARRIS_HALF..=x + HARRIS_HALF {
            let gx = 0.5 * (im.get(u + 1, v) - im.get(u - 1, v));
            let gy = 0.5 * (im.get(u, v + 1) - im.get(u, v - 1));
            a += gx * gx;
            b += gy * gy;
            c += gx * gy;
        }
    }
    a * b - c * c - HARRIS_K * (a + b) * (a + b)
}

/// The intensity-centroid angle over the patch disc at `(x, y)`.
fn centroid_angle(im: &GrayImage, x: usize, y: usize) -> f32 {
    let r = PATCH_RADIUS as i64;
    let (mut m10, mut m01) = (0f32, 0f32);
    for dy in -r..=r {
        for dx in -r..=r {
            if dx * dx + dy * dy > r * r {
                continue;
            }
            let v = im.get((x as i64 + dx) as usize, (y as i64 + dy) as usize);
            m10 += dx as f32 * v;
            m01 += dy as f32 * v;
        }
    }
    m01.atan2(m10)
}

/// Keypoints and descriptors of one pyramid level (`s`: its pixel in level-0 pixels).
fn detect_level(im: &GrayImage, level: usize, s: f32, p: &OrbParams) -> Vec<(KeyPoint, [u32; 8])> {
    let (w, h) = (im.width(), im.height());
    let border = PATCH_RADIUS + 2;
    let mut score = vec![f32::NEG_INFINITY; w * h];
    for y in border..h - border {
        for x in border..w - border {
            if im.get(x, y).is_finite() && is_fast_corner(im, x, y, p.fast_threshold) {
                let r = harris(im, x, y);
                if r.is_finite() && r > 0.0 {
                    score[y * w + x] = r;
                }
            }
        }
    }
    let integral = IntegralImage::new(im);
    let mut out = Vec::new();
    for y in border..h - border {
        for x in border..w - border {
            let v = score[y * w + x];
            if v == f32::NEG_INFINITY {
                continue;
            }
            let local_max = (-1i64..=1).all(|dy| {
                (-1i64..=1).all(|dx| {
                    let n = score[(y as i64 + dy) as usize * w + (x as i64 + dx) as usize];
                    (dx == 0 && dy == 0) || n < v || (n == v && (dy, dx) > (0, 0))
                })
            });
            if !local_max {
                continue;
            }
            let angle = if p.upright {
                0.0
            } else {
                centroid_angle(im, x, y)
            };
            let size = (2 * PATCH_RADIUS + 1) as f32 * s;
            let kp = KeyPoint {
                x: (x as f32 + 0.5) * s - 0.5,
                y: (y as f32 + 0.5) * s - 0.5,
                size,
                scale: 1.2 * size / 9.0,
                response: v,
                orientation_rad: angle,
                laplacian: 0,
                octave: level as u8,
            };
            out.push((kp, describe(&integral, x, y, angle)));
        }
    }
    out
}

/// The 256 box-mean comparisons of the steered pattern at `(x, y)`, packed low bit first.
fn describe(ii: &IntegralImage, x: usize, y: usize, angle: f32) -> [u32; 8] {
    let (sn, cs) = angle.sin_cos();
    let (w, h) = (ii.width() as i64, ii.height() as i64);
    let box_at = |px: f32, py: f32| -> i32 {
        let u = (x as f32 + cs * px - sn * py).round() as i64;
        let v = (y as f32 + sn * px + cs * py).round() as i64;
        let (x0, y0) = (
            (u - TEST_BOX_HALF).clamp(0, w),
            (v - TEST_BOX_HALF).clamp(0, h),
        );
        let (x1, y1) = (
            (u + TEST_BOX_HALF + 1).clamp(0, w),
            (v + TEST_BOX_HALF + 1).clamp(0, h),
        );
        ii.box_sum(x0 as usize, y0 as usize, x1 as usize, y1 as usize)
    };
    let mut words = [0u32; 8];
    for (i, t) in pattern().iter().enumerate() {
        if box_at(t[0], t[1]) < box_at(t[2], t[3]) {
            words[i / 32] |= 1 << (i % 32);
        }
    }
    words
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::{MatchParams, match_features};

    /// A textured image: blobs and lines of several sizes, deterministic.
    fn texture(w: usize, h: usize) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| {
            let (x, y) = (x as f32, y as f32);
            let v = 128.0
                + 50.0 * ((0.21 * x).sin() * (0.17 * y).cos())
                + 40.0 * ((0.047 * x + 0.031 * y).sin()).signum()
                + 30.0 * ((0.013 * x * y / 40.0).sin());
            v.clamp(0.0, 255.0)
        })
    }

    #[test]
    fn finds_corners_with_binary_descriptors() {
        let img = texture(240, 200);
        let orb = Orb::new(OrbParams::default()).unwrap();
        let f = orb.detect_and_describe(&img);
        assert!(f.len() > 50, "{} keypoints", f.len());
        assert_eq!(f.kind(), DescriptorKind::Binary256);
        assert!(
            f.keypoints
                .windows(2)
                .all(|k| k[0].response >= k[1].response)
        );
        // Not all descriptors alike: the tests see different patches.
        let distinct: std::collections::HashSet<[u32; 8]> =
            (0..f.len()).map(|i| f.binary_descriptor(i)).collect();
        assert!(distinct.len() > f.len() / 2);
    }

    #[test]
    fn a_shifted_image_matches_itself_by_hamming_distance() {
        let img = texture(300, 260);
        let shifted = img.crop(7, 11, 280, 240).unwrap();
        let orb = Orb::new(OrbParams::default()).unwrap();
        let (a, b) = (
            orb.detect_and_describe(&shifted),
            orb.detect_and_describe(&img),
        );
        let m = match_features(&a, &b, &MatchParams::default(), None).unwrap();
        assert!(m.len() > 30, "{} matches", m.len());
        let good = m
            .iter()
            .filter(|m| {
                let (q, t) = (&a.keypoints[m.query], &b.keypoints[m.train]);
                (q.x + 7.0 - t.x).abs() < 1.5 && (q.y + 11.0 - t.y).abs() < 1.5
            })
            .count();
        // The coarser levels are resampled at another phase in the crop and the texture repeats,
        // so not every match is at the shift: measured 396 of 529.
        assert!(
            good >= 100 && good * 10 >= m.len() * 7,
            "{good} of {} at the shift",
            m.len()
        );
        // Hamming distances are whole numbers of bits.
        assert!(
            m.iter()
                .all(|m| m.distance.fract() == 0.0 && m.distance <= 256.0)
        );
    }

    #[test]
    fn oriented_descriptors_follow_a_turned_image() {
        let img = texture(260, 260);
        // The image turned by 90 degrees: (x, y) -> (h - 1 - y, x).
        let n = img.width();
        let turned = GrayImage::from_fn(n, n, |x, y| img.get(y, n - 1 - x));
        let orb = Orb::new(OrbParams {
            upright: false,
            ..OrbParams::default()
        })
        .unwrap();
        let (a, b) = (
            orb.detect_and_describe(&img),
            orb.detect_and_describe(&turned),
        );
        let m = match_features(&a, &b, &MatchParams::default(), None).unwrap();
        let good = m
            .iter()
            .filter(|m| {
                let (q, t) = (&a.keypoints[m.query], &b.keypoints[m.train]);
                ((n as f32 - 1.0 - q.y) - t.x).abs() < 2.0 && (q.x - t.y).abs() < 2.0
            })
            .count();
        assert!(
            good >= 20,
            "{good} of {} matches at the turned place",
            m.len()
        );
    }

    #[test]
    fn bad_settings_are_named() {
        let e = Orb::new(OrbParams {
            n_levels: 0,
            ..OrbParams::default()
        })
        .unwrap_err();
        assert!(e.to_string().contains("n_levels"), "{e}");
    }
}
