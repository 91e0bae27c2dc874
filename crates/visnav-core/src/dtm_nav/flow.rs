//! The DTM navigator's optical flow: corners of the first frame tracked into the second by
//! pyramidal Lucas-Kanade (Bouguet 2000, OpenCV's `calcOpticalFlowPyrLK` semantics:
//! [`crate::vision::klt`]) with the forward-backward check (Kalal et al. 2010), the second frame
//! first warped into the first's pixels by the navigation's guess ([`GroundHomography`] fitted to
//! [`predict_px`]: a pixel's ray onto the terrain from the first guessed pose, projected with the
//! second). The guess leaves tens of pixels to find, the pyramid ([`FLOW_MAX_LEVEL`]) the rest;
//! the prediction is what lets two frames tens to hundreds of metres apart, rotated against each
//! other, be tracked directly, without the frames between.
//!
//! Pixels here are the camera's own (distorted) pixels; the caller's `predict` maps between them.

use nalgebra::{Matrix3, Vector2, Vector3};

use crate::camera::Camera;
use crate::geo::dem::Dem;
use crate::pose::Pose;
use crate::vision::klt::{FeatureParams, Pyramid, SpreadGrid, Track, TrackParams, track_checked};
use crate::vision::{GrayImage, VisionError};
use crate::vo::TrackPair;

/// Corners detected in the first frame (strongest first, spread over a grid so the whole overlap
/// is covered): many flow vectors, as the paper's dense flow.
pub const MAX_CORNERS: usize = 1500;
/// Closest two corners, px (as OpenCV's `minDistance`).
const CORNER_MIN_DISTANCE_PX: f32 = 6.0;
/// Corners per grid cell: 8 x 12 cells of at most 40 keep a textured corner from taking them all.
const SPREAD: SpreadGrid = SpreadGrid {
    cols: 8,
    rows: 12,
    max_per_cell: 40,
};
/// Pyramid levels for the flow: the guess leaves tens of pixels to find (2^4 x half a window).
pub const FLOW_MAX_LEVEL: usize = 4;

/// The flow from `a` to `b`: how many corners `a` gave, and the pairs kept (corner in `a`,
/// tracked point in `b`). `predict` maps a pixel of `a` to where the guess puts it in `b`
/// (`None` off the terrain or outside `b`); a corner without a prediction is not tracked.
///
/// `b` is first resampled into `a`'s pixels by the homography that best explains the guess's
/// predictions ([`GroundHomography`]: the ground's mean plane seen from the two guessed poses).
/// Between two frames a bank reversal apart the ground is seen rotated by tens of degrees and
/// at another slant; Lucas-Kanade's translation-only window would match a distorted patch, with
/// errors correlated over the whole image that more tracks do not average out (measured on the
/// moving replica flight, docs/dtm.md). After the homography, what is left in each window is
/// the relief's parallax and the guess's error, nearly a translation. The homography is smooth:
/// it does not impose the guess's relief parallax on the image (a guess hundreds of metres off
/// would scramble a per-pixel terrain warp at the relief's scale); each corner still starts at
/// its own terrain prediction, carried through the homography. Corners are detected only where
/// the homography lands inside `b` (the predicted overlap, so the corner budget is spent
/// there). Too few predictions for a homography: the frames are tracked as they are.
pub fn terrain_flow(
    a: &GrayImage,
    b: &GrayImage,
    predict: impl Fn([f32; 2]) -> Option<[f32; 2]>,
) -> Result<(usize, Vec<TrackPair>), VisionError> {
    let params = TrackParams {
        max_level: FLOW_MAX_LEVEL,
        ..TrackParams::default()
    };
    // The first frame's pyramid first: it refuses an empty or non-finite frame.
    let pa = Pyramid::new(a, params.max_level, params.win_size_px)?;
    let corner_params = FeatureParams {
        max_corners: MAX_CORNERS,
        min_distance_px: CORNER_MIN_DISTANCE_PX,
        spread: Some(SPREAD),
        ..FeatureParams::default()
    };
    let half_window_px = (params.win_size_px / 2) as f64;
    let warp = GroundHomography::fit(a.width(), a.height(), &predict).filter(|h| {
        h.distortion_px(a.width(), a.height(), half_window_px) > MAX_DIRECT_DISTORTION_PX
    });
    let Some(h) = warp else {
        let pb = Pyramid::new(b, params.max_level, params.win_size_px)?;
        let corners = pa.good_features(&corner_params)?;
        let (pts, guesses) = predicted(&corners, &predict);
        let tracks = track_checked(&pa, &pb, &pts, Some(&guesses), &params)?;
        return Ok((corners.len(), tracked_pairs(&pts, &tracks, Some)));
    };
    let b_in_a = h.resample(b, a.width(), a.height())?;
    let pw = Pyramid::new(&b_in_a, params.max_level, params.win_size_px)?;
    let in_b = |q: [f32; 2]| inside(q, b.width(), b.height());
    let corners = pa.good_features_where(&corner_params, |p| h.map(p).is_some_and(in_b))?;
    let (pts, guesses) = predicted(&corners, |p| h.unmap(predict(p)?));
    let tracks = track_checked(&pa, &pw, &pts, Some(&guesses), &params)?;
    Ok((corners.len(), tracked_pairs(&pts, &tracks, |q| h.map(q))))
}

/// The corners with a guess, and their guesses.
fn predicted(
    corners: &[[f32; 2]],
    guess: impl Fn([f32; 2]) -> Option<[f32; 2]>,
) -> (Vec<[f32; 2]>, Vec<[f32; 2]>) {
    corners
        .iter()
        .filter_map(|&p| guess(p).map(|g| (p, g)))
        .unzip()
}

/// The tracked points' pairs, each tracked point mapped into the second frame by `to_b`.
fn tracked_pairs(
    pts: &[[f32; 2]],
    tracks: &[Track],
    to_b: impl Fn([f32; 2]) -> Option<[f32; 2]>,
) -> Vec<TrackPair> {
    let as_f64 = |p: [f32; 2]| Vector2::new(f64::from(p[0]), f64::from(p[1]));
    pts.iter()
        .zip(tracks)
        .filter(|(_, t)| t.is_tracked())
        .filter_map(|(p, t)| {
            Some(TrackPair {
                prev_px: as_f64(*p),
                next_px: as_f64(to_b(t.point)?),
            })
        })
        .collect()
}

/// Largest distortion of a tracking window by the guessed motion for tracking the frames as
/// they are, px at the window's edge ([`GroundHomography::distortion_px`]): twice the
/// forward-backward tolerance (`TrackParams::max_fb_error_px`, 0.5 px). Resampling the second
/// frame costs some of its sharpness (on the real NGI pair, 0.4 px of distortion, it lost a third
/// of the tracks), worth paying only when a translation-only window is clearly wrong: a straight
/// flight stays at 0.02-0.6 px, a bank reversal between the frames reaches 1.5-3.8 px (the
/// replica flights, docs/dtm.md).
pub const MAX_DIRECT_DISTORTION_PX: f64 = 1.0;

/// Spacing of the predictions the homography is fitted to, px: 20 x 12 rays for a 640 x 390
/// frame, a small fraction of the corners' own.
pub const HOMOGRAPHY_GRID_PX: usize = 32;

/// Fewest predictions for a homography: 8 unknowns, 2 equations each; a fifth of a VGA grid
/// (the frames overlap in less than that: track them as they are).
const MIN_HOMOGRAPHY_POINTS: usize = 48;

/// The homography `H` (first frame's pixels to the second's) fitted to the guess's predictions
/// on a grid over the first frame: Hartley's normalised direct linear transform (Hartley and
/// Zisserman 2003, algorithm 4.2), the null vector of `A^T A` as the smallest eigenvector.
#[derive(Debug, Clone, Copy)]
pub struct GroundHomography {
    h: Matrix3<f64>,
    h_inv: Matrix3<f64>,
}

impl GroundHomography {
    /// The fit over a `width` x `height` first frame, or `None` with too few predictions or a
    /// degenerate fit.
    pub fn fit(
        width: usize,
        height: usize,
        predict: &impl Fn([f32; 2]) -> Option<[f32; 2]>,
    ) -> Option<Self> {
        let pairs: Vec<([f64; 2], [f64; 2])> = grid_points(width, height)
            .filter_map(|p| {
                let q = predict(p)?;
                let f = |v: [f32; 2]| [f64::from(v[0]), f64::from(v[1])];
                Some((f(p), f(q)))
            })
            .collect();
        if pairs.len() < MIN_HOMOGRAPHY_POINTS {
            return None;
        }
        let h = dlt(&pairs)?;
        let h_inv = h.try_inverse()?;
        (h.iter().chain(h_inv.iter()).all(|v| v.is_finite())).then_some(Self { h, h_inv })
    }

    /// How far the homography moves a tracking window's edge, `half_window_px` from its centre,
    /// away from where a translation would put it: `|J - I|` (Frobenius) of its Jacobian times
    /// the half window, the median over a grid of the first frame's points that land in a frame
    /// of the same size, px (0 when none does).
    pub fn distortion_px(&self, width: usize, height: usize, half_window_px: f64) -> f64 {
        let d: Vec<f64> = grid_points(width, height)
            .filter_map(|p| {
                let q = self.map(p).filter(|&q| inside(q, width, height))?;
                // The Jacobian by 1 px differences (the map is smooth at that scale).
                let qx = self.map([p[0] + 1.0, p[1]])?;
                let qy = self.map([p[0], p[1] + 1.0])?;
                let jac = [
                    f64::from(qx[0] - q[0]) - 1.0,
                    f64::from(qx[1] - q[1]),
                    f64::from(qy[0] - q[0]),
                    f64::from(qy[1] - q[1]) - 1.0,
                ];
                Some(jac.iter().map(|v| v * v).sum::<f64>().sqrt() * half_window_px)
            })
            .collect();
        // NaN (no point) -> 0.
        crate::stats::percentile(&d, 0.5).max(0.0)
    }

    fn apply(m: &Matrix3<f64>, p: [f32; 2]) -> Option<[f32; 2]> {
        let v = m * Vector3::new(f64::from(p[0]), f64::from(p[1]), 1.0);
        // Points behind either camera's view of the plane have no image.
        (v.z > 0.0 && v.z.is_finite()).then(|| [(v.x / v.z) as f32, (v.y / v.z) as f32])
    }

    /// A first-frame pixel in the second frame.
    pub fn map(&self, p: [f32; 2]) -> Option<[f32; 2]> {
        Self::apply(&self.h, p)
    }

    /// A second-frame pixel in the first frame.
    pub fn unmap(&self, q: [f32; 2]) -> Option<[f32; 2]> {
        Self::apply(&self.h_inv, q)
    }

    /// `b` resampled into the first frame's `width` x `height` pixels (bilinear); where the
    /// homography leaves `b`, `b`'s mean grey (no corner is detected there).
    pub fn resample(
        &self,
        b: &GrayImage,
        width: usize,
        height: usize,
    ) -> Result<GrayImage, VisionError> {
        let n = b.data().len().max(1);
        let mean = (b.data().iter().map(|&v| f64::from(v)).sum::<f64>() / n as f64) as f32;
        let data = (0..width * height)
            .map(|k| {
                self.map([(k % width) as f32, (k / width) as f32])
                    .and_then(|q| b.sample_bilinear(f64::from(q[0]), f64::from(q[1])))
                    .unwrap_or(mean)
            })
            .collect();
        GrayImage::new(width, height, data)
    }
}

/// The centres of the [`HOMOGRAPHY_GRID_PX`] cells over a `width` x `height` frame.
fn grid_points(width: usize, height: usize) -> impl Iterator<Item = [f32; 2]> {
    let g = HOMOGRAPHY_GRID_PX;
    (0..height.div_ceil(g)).flat_map(move |j| {
        (0..width.div_ceil(g)).map(move |i| [(i * g + g / 2) as f32, (j * g + g / 2) as f32])
    })
}

/// Whether pixel `q` lies in a `width` x `height` frame (its pixel centres, 0 to side - 1).
fn inside(q: [f32; 2], width: usize, height: usize) -> bool {
    (0.0..=width.saturating_sub(1) as f32).contains(&q[0])
        && (0.0..=height.saturating_sub(1) as f32).contains(&q[1])
}

/// Hartley's normalisation: the similarity taking `pts` to centroid 0, mean distance sqrt 2.
fn normaliser(pts: impl Iterator<Item = [f64; 2]> + Clone) -> Option<Matrix3<f64>> {
    let n = pts.clone().count() as f64;
    let (cx, cy) = pts
        .clone()
        .fold((0.0, 0.0), |(x, y), p| (x + p[0] / n, y + p[1] / n));
    let d = pts.map(|p| (p[0] - cx).hypot(p[1] - cy)).sum::<f64>() / n;
    if !(d > 0.0 && d.is_finite()) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / d;
    Some(Matrix3::new(
        s,
        0.0,
        -s * cx,
        0.0,
        s,
        -s * cy,
        0.0,
        0.0,
        1.0,
    ))
}

/// The normalised DLT (the type's doc): `H` with `q ~ H p`, scaled to `H[(2, 2)] = 1`.
fn dlt(pairs: &[([f64; 2], [f64; 2])]) -> Option<Matrix3<f64>> {
    let t1 = normaliser(pairs.iter().map(|x| x.0))?;
    let t2 = normaliser(pairs.iter().map(|x| x.1))?;
    let mut ata = nalgebra::SMatrix::<f64, 9, 9>::zeros();
    for (p, q) in pairs {
        let p = t1 * Vector3::new(p[0], p[1], 1.0);
        let q = t2 * Vector3::new(q[0], q[1], 1.0);
        let (x, y, u, v) = (p.x, p.y, q.x, q.y);
        let rows = [
            [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v],
            [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u],
        ];
        for r in rows {
            let r = nalgebra::SVector::<f64, 9>::from(r);
            ata += r * r.transpose();
        }
    }
    let eig = nalgebra::SymmetricEigen::new(ata);
    let k = eig.eigenvalues.imin();
    let e = eig.eigenvectors.column(k);
    let hn = Matrix3::new(e[0], e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8]);
    let h = t2.try_inverse()? * hn * t1;
    let scale = h[(2, 2)];
    (scale.abs() > f64::EPSILON).then(|| h / scale)
}

/// Where pixel `px` of `camera` at pose `first` lands in the same camera at `second` over `dem`
/// (its ray onto the terrain within `max_range_m`, projected), inside the image; `None`
/// otherwise.
pub fn predict_px(
    px: [f32; 2],
    camera: &Camera,
    first: &Pose,
    second: &Pose,
    dem: &Dem,
    max_range_m: f64,
) -> Option<[f32; 2]> {
    let p = nalgebra::Point2::new(f64::from(px[0]), f64::from(px[1]));
    let d: Vector3<f64> = first.r_world_cam * camera.unproject(&p)?.into_inner();
    let c = first.c_world;
    let x = dem.intersect_ray([c.x, c.y, c.z], [d.x, d.y, d.z], max_range_m)?;
    let q = camera.project(&second.to_cam(&Vector3::new(x[0], x[1], x[2])))?;
    let out = [q.x as f32, q.y as f32];
    (out.iter().all(|v| v.is_finite()) && camera.intrinsics.contains(&q)).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Aerial-like texture: value noise at 4, 9 and 23 px (bilinear between random grid values).
    fn texture(w: usize, h: usize, seed: u64) -> GrayImage {
        let mut rng = Rng::new(seed);
        let layers: Vec<(f64, usize, Vec<f64>)> = [4.0, 9.0, 23.0]
            .iter()
            .map(|&cell: &f64| {
                let cols = (w as f64 / cell) as usize + 2;
                let rows = (h as f64 / cell) as usize + 2;
                let v = (0..cols * rows).map(|_| rng.range(-1.0, 1.0)).collect();
                (cell, cols, v)
            })
            .collect();
        GrayImage::from_fn(w, h, |x, y| {
            let v: f64 = layers
                .iter()
                .map(|(cell, cols, v)| {
                    let (fx, fy) = (x as f64 / cell, y as f64 / cell);
                    let (i, j) = (fx as usize, fy as usize);
                    let (u, t) = (fx - i as f64, fy - j as f64);
                    let g = |a: usize, b: usize| v[b * cols + a];
                    let top = g(i, j) * (1.0 - u) + g(i + 1, j) * u;
                    let bottom = g(i, j + 1) * (1.0 - u) + g(i + 1, j + 1) * u;
                    top * (1.0 - t) + bottom * t
                })
                .sum();
            (128.0 + 30.0 * v) as f32
        })
    }

    /// The second frame: the scene turned by `angle_deg` about the frame centre (and shifted by
    /// `shift_px`), sampled from a larger texture; `truth(p)` is where pixel `p` of the first
    /// frame lands in it.
    struct Turned {
        a: GrayImage,
        b: GrayImage,
        angle_rad: f64,
        shift_px: [f64; 2],
        centre: [f64; 2],
    }

    impl Turned {
        fn new(angle_deg: f64, shift_px: [f64; 2]) -> Self {
            let (w, h) = (320usize, 240usize);
            let big = texture(2 * w, 2 * h, 7);
            let off = [w as f64 / 2.0, h as f64 / 2.0];
            let centre = [(w - 1) as f64 / 2.0, (h - 1) as f64 / 2.0];
            let a = GrayImage::from_fn(w, h, |x, y| big.get(x + w / 2, y + h / 2));
            let mut t = Self {
                a,
                b: GrayImage::from_fn(1, 1, |_, _| 0.0),
                angle_rad: angle_deg.to_radians(),
                shift_px,
                centre,
            };
            // b(q) = a(truth^-1(q)), read from the big texture (no edge fill).
            t.b = GrayImage::from_fn(w, h, |x, y| {
                let p = t.inverse([x as f64, y as f64]);
                big.sample_bilinear(p[0] + off[0], p[1] + off[1])
                    .unwrap_or(128.0)
            });
            t
        }

        fn truth(&self, p: [f64; 2]) -> [f64; 2] {
            let (s, c) = self.angle_rad.sin_cos();
            let (dx, dy) = (p[0] - self.centre[0], p[1] - self.centre[1]);
            [
                self.centre[0] + c * dx - s * dy + self.shift_px[0],
                self.centre[1] + s * dx + c * dy + self.shift_px[1],
            ]
        }

        fn inverse(&self, q: [f64; 2]) -> [f64; 2] {
            let (s, c) = self.angle_rad.sin_cos();
            let (dx, dy) = (
                q[0] - self.shift_px[0] - self.centre[0],
                q[1] - self.shift_px[1] - self.centre[1],
            );
            [
                self.centre[0] + c * dx + s * dy,
                self.centre[1] - s * dx + c * dy,
            ]
        }

        /// The guess: the truth moved by `err_px`, inside the second frame.
        fn predict(&self, err_px: [f64; 2]) -> impl Fn([f32; 2]) -> Option<[f32; 2]> + '_ {
            move |p| {
                let q = self.truth([f64::from(p[0]), f64::from(p[1])]);
                let q = [(q[0] + err_px[0]) as f32, (q[1] + err_px[1]) as f32];
                let inside = (0.0..=(self.b.width() - 1) as f32).contains(&q[0])
                    && (0.0..=(self.b.height() - 1) as f32).contains(&q[1]);
                inside.then_some(q)
            }
        }

        /// Median and 90th percentile of the flow's points' distances from the truth, px.
        fn errors(&self, pairs: &[TrackPair]) -> (f64, f64) {
            let mut e: Vec<f64> = pairs
                .iter()
                .map(|t| {
                    let q = self.truth([t.prev_px.x, t.prev_px.y]);
                    (t.next_px.x - q[0]).hypot(t.next_px.y - q[1])
                })
                .collect();
            e.sort_by(f64::total_cmp);
            (e[e.len() / 2], e[e.len() * 9 / 10])
        }
    }

    #[test]
    fn the_homography_of_the_predictions_is_recovered_and_its_distortion_measured() {
        for (angle_deg, distorted) in [(0.0, false), (2.0, false), (25.0, true)] {
            let t = Turned::new(angle_deg, [6.0, -4.0]);
            let predict = t.predict([0.0, 0.0]);
            let h = GroundHomography::fit(320, 240, &predict).unwrap();
            for p in [[10.0f32, 10.0], [160.0, 120.0], [300.0, 200.0]] {
                let q = h.map(p).unwrap();
                let want = t.truth([f64::from(p[0]), f64::from(p[1])]);
                assert!((f64::from(q[0]) - want[0]).hypot(f64::from(q[1]) - want[1]) < 1e-3);
                let back = h.unmap(q).unwrap();
                assert!((back[0] - p[0]).hypot(back[1] - p[1]) < 1e-3);
            }
            // A turn by theta moves a window's edge 10 px out by 2 sin(theta / 2) sqrt 2 x 10 px.
            let d = h.distortion_px(320, 240, 10.0);
            let want = 2.0 * (angle_deg.to_radians() / 2.0).sin() * 2f64.sqrt() * 10.0;
            assert!(
                (d - want).abs() < 1e-2,
                "{angle_deg} deg: {d} px, {want} px"
            );
            assert_eq!(
                d > MAX_DIRECT_DISTORTION_PX,
                distorted,
                "{angle_deg} deg: {d} px"
            );
        }
    }

    #[test]
    fn too_few_predictions_give_no_homography() {
        let none = |_: [f32; 2]| None;
        assert!(GroundHomography::fit(320, 240, &none).is_none());
        let corner = |p: [f32; 2]| (p[0] < 40.0 && p[1] < 40.0).then_some(p);
        assert!(GroundHomography::fit(320, 240, &corner).is_none());
    }

    /// The flow between the frames of `t` from a guess (3, -2.5) px off: most corners tracked,
    /// onto the truth to a small fraction of a pixel.
    fn assert_tracked(t: &Turned) {
        let (corners, pairs) = terrain_flow(&t.a, &t.b, t.predict([3.0, -2.5])).unwrap();
        let (median, p90) = t.errors(&pairs);
        assert!(pairs.len() * 2 > corners, "{} of {corners}", pairs.len());
        assert!(
            median < 0.05 && p90 < 0.2,
            "median {median} px, p90 {p90} px"
        );
    }

    /// A frame turned by 25 deg against the first: tracked through the warp.
    #[test]
    fn a_turned_frame_is_tracked_through_the_warp() {
        assert_tracked(&Turned::new(25.0, [6.0, -4.0]));
    }

    /// A translation only: tracked as the frames are (no resampling), just as well.
    #[test]
    fn a_shifted_frame_is_tracked_as_it_is() {
        assert_tracked(&Turned::new(0.0, [7.3, -5.6]));
    }
}
