//! DTM navigation measured (`visnav bench dtm`): the first frame's pose from the optical
//! flow between two frames and the terrain model alone ([`visnav_core::dtm_nav::solve`]).
//!
//! * Real frames ([`ngi_dtm`]): NGI 3324C strip 05, frames 0182 -> 0184 (`../shared/data/ngi_3324c`:
//!   Intergraph DMC frames at 640 x 1152 px, poses from aerial triangulation, a 24 m DEM of a
//!   valley of 150-780 m, the camera about 4.8 km above it, 2.6 km between the frames). Corners of
//!   frame 0182 are tracked into frame 0184 by pyramidal Lucas-Kanade with the forward-backward
//!   check, each started where the first guess predicts it (its ray onto the DEM from the guessed
//!   first pose, projected with the guessed second pose: the INS's prediction). The first guess
//!   is the measured poses moved by a navigation error ([`NGI_GUESS`]: a shift and a turn common
//!   to both frames, as an INS's error is, and an error of the motion). No orthophoto is read. The solution's first pose against the
//!   measured one, beside its own covariance.
//! * Flat ground ([`flat_dtm`]): the VGA sequence of `visnav bench vo` (a real NAIP photo of the
//!   North Dakota area, laid flat, rendered for a known flight at 300 m above it), frame pairs
//!   [`FLAT_PAIR_GAP`] frames apart, the same flow and solver over flat terrain: every pair must be
//!   refused, with the default relief screen and without it (then by the conditioning check).

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::{Rotation3, Vector3};
use serde::Serialize;

use visnav_core::camera::{Camera, Intrinsics};
use visnav_core::dtm_nav::flow::{predict_px, terrain_flow};
use visnav_core::dtm_nav::{DtmFix, DtmInput, DtmNavConfig, DtmRejection, GuessSigma, solve};
use visnav_core::geo::dem::Dem;
use visnav_core::pose::{ImageGeometry, Pose};
use visnav_core::stats::percentile;
use visnav_core::vision::GrayImage;
use visnav_core::vo::TrackPair;
use visnav_io::image_file::GrayImageFile;

use crate::vo_eval::{
    NEXT_FRAME, NgiPair, PREV_FRAME, VoEvalError, render_flat, vga_image, vga_poses,
};

/// A first guess's navigation error: common to both frames, map east, north, up, m, and a turn
/// (roll, pitch, yaw about the world axes), deg; and the guessed motion's own error, m.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GuessError {
    /// Position error common to both frames, map east, north, up, m.
    pub offset_m: [f64; 3],
    /// Attitude error common to both frames: roll, pitch, yaw about the world axes, deg.
    pub turn_deg: [f64; 3],
    /// Error of the guessed motion (added to the second frame's position), east, north, up, m.
    pub motion_err_m: [f64; 3],
}

/// The bench's NGI guess: an INS some minutes after losing GPS (the motion: 2.6 km flown in
/// about 30 s with a velocity error of 0.5 m/s).
pub const NGI_GUESS: GuessError = GuessError {
    offset_m: [150.0, -100.0, 30.0],
    turn_deg: [0.3, -0.2, 1.0],
    motion_err_m: [12.0, -8.0, 3.0],
};

/// How good the NGI guesses' height and tilt are said to be: a baro-aided height (50 m at 5 km
/// above sea level) and an INS's roll and pitch (0.5 deg).
pub const NGI_GUESS_SIGMA: GuessSigma = GuessSigma {
    height_m: 50.0,
    tilt_rad: 0.5 * std::f64::consts::PI / 180.0,
    horizontal_m: NGI_GUESS_SIGMA_H_M,
};

/// The NGI guesses' horizontal sigma, m: an INS some minutes into a GPS outage (the bench's
/// guess is 183 m off, its sweep goes to 600 m: 2 sigma).
pub const NGI_GUESS_SIGMA_H_M: f64 = 300.0;

/// The flat pairs' guess: the NGI guess's kind of error at 300 m instead of 4.8 km.
const FLAT_GUESS: GuessError = GuessError {
    offset_m: [30.0, -20.0, 6.0],
    turn_deg: [0.3, -0.2, 1.0],
    motion_err_m: [0.5, -0.3, 0.1],
};

/// Flat pairs: frames this far apart in the VGA sequence (4 m per frame: 32 m at 300 m).
pub const FLAT_PAIR_GAP: usize = 8;

/// The NGI figures (`visnav bench dtm --json`: the `ngi_*` keys).
#[derive(Debug, Clone, Serialize)]
pub struct NgiDtm {
    /// Corners detected in the first frame.
    pub corners: usize,
    /// Flow vectors kept by the forward-backward check.
    pub tracks: usize,
    /// Of those, the ones on the terrain at the first guess.
    pub on_ground: usize,
    /// Inliers of the solution.
    pub inliers: usize,
    /// The first guess's position error, m (what the solution starts from).
    pub guess_err_m: f64,
    /// The solved first position minus the measured one (east, north, up), m.
    pub err_m: [f64; 3],
    /// The length of that error, m.
    pub err_norm_m: f64,
    /// The claimed 1-sigma along the error's direction, m.
    pub sigma_along_err_m: f64,
    /// The error's length in those sigmas.
    pub err_over_sigma: f64,
    /// The position error's squared Mahalanobis distance with the claimed 3x3 covariance
    /// (chi-square, 3 dof, when honest).
    pub err_mahalanobis2: f64,
    /// The largest per-axis error in its own sigmas.
    pub err_axis_sigmas: f64,
    /// Claimed 1-sigma east, north, up, m.
    pub sigma_m: [f64; 3],
    /// Claimed horizontal 1-sigma were the attitudes known (what the relief alone fixes), m.
    pub sigma_h_given_attitude_m: f64,
    /// The solved first attitude against the measured one (rotation angle), deg.
    pub att_err_deg: f64,
    /// The attitude's largest claimed 1-sigma, deg.
    pub att_sigma_deg: f64,
    /// Reprojection RMS over the inliers, px.
    pub rms_px: f64,
    /// A-posteriori sigma0 of the solution.
    pub sigma0: f64,
    /// Standard deviation of the inliers' ground heights, m.
    pub relief_std_m: f64,
    /// Mean height of the first camera centre above the inliers' ground points, m.
    pub agl_m: f64,
    /// The minimiser of the final stage (`gauss_newton`, `levenberg_marquardt`).
    pub method: String,
    /// Iterations of both stages.
    pub iterations: usize,
    /// Flow time (pyramids, corners, tracking both ways) on the calling thread, ms.
    pub ms_flow: f64,
    /// Solve time on the calling thread, ms.
    pub ms_solve: f64,
}

/// The flat-ground figures.
#[derive(Debug, Clone, Serialize)]
pub struct FlatDtm {
    /// Frame pairs tried.
    pub pairs: usize,
    /// Solutions accepted with the default settings (should be 0).
    pub accepted: usize,
    /// Solutions accepted with the relief screen off (should be 0).
    pub accepted_unscreened: usize,
    /// One line per distinct refusal reason (first example of each), both runs.
    pub reasons: Vec<String>,
    /// Mean flow vectors per pair.
    pub tracks_mean: f64,
    /// Solve time per pair with the screen off (the full iterations), median, ms.
    pub ms_solve_p50: f64,
}

/// The flow from `a` to `b` started at the guessed poses' predictions over `dem`
/// ([`visnav_core::dtm_nav::flow`]).
fn flow(
    a: &GrayImage,
    b: &GrayImage,
    camera: &Camera,
    guess: (&Pose, &Pose),
    dem: &Dem,
) -> Result<(usize, Vec<TrackPair>), VoEvalError> {
    let range = DtmNavConfig::default().max_range_m;
    terrain_flow(a, b, |p| {
        predict_px(p, camera, guess.0, guess.1, dem, range)
    })
    .map_err(|e| VoEvalError::Vision(e.to_string()))
}

/// The pinhole camera of an image geometry (the evaluations' frames have no distortion).
fn pinhole(image: &ImageGeometry) -> Result<Camera, VoEvalError> {
    Intrinsics::new(
        image.fx_px,
        image.fy_px,
        image.cx_px,
        image.cy_px,
        image.width_px,
        image.height_px,
    )
    .and_then(Camera::pinhole)
    .map_err(|e| VoEvalError::Vision(e.to_string()))
}

/// The true poses moved by a navigation error (module doc).
fn guess(first: &Pose, second: &Pose, err: &GuessError) -> (Pose, Pose) {
    let [r, p, y] = err.turn_deg.map(f64::to_radians);
    let turn = Rotation3::from_euler_angles(r, p, y);
    let off = Vector3::from(err.offset_m);
    let moved = |pose: &Pose, extra: Vector3<f64>| Pose {
        r_world_cam: turn * pose.r_world_cam,
        c_world: pose.c_world + off + extra,
    };
    (
        moved(first, Vector3::zeros()),
        moved(second, Vector3::from(err.motion_err_m)),
    )
}

fn data_err(path: PathBuf, reason: String) -> VoEvalError {
    VoEvalError::Data { path, reason }
}

/// Which NGI frame is the first of the pair: 0182 (flown order, flow to 0184) or 0184 (flow
/// back to 0182: the same geometry seen the other way, another sample of the flow's errors).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NgiOrder {
    /// Frame 0182 first, flow to 0184 (the flown order).
    Forward,
    /// Frame 0184 first, flow back to 0182.
    Reverse,
}

impl NgiOrder {
    /// "0182 -> 0184" or "0184 -> 0182".
    pub fn label(self) -> &'static str {
        match self {
            NgiOrder::Forward => "0182 -> 0184",
            NgiOrder::Reverse => "0184 -> 0182",
        }
    }
}

/// The first frame's pose from the flow to the other frame and the DEM, started from the
/// measured poses moved by `err` (module doc; the bench uses [`NGI_GUESS`]).
pub fn ngi_dtm(dir: &Path, err: &GuessError, order: NgiOrder) -> Result<NgiDtm, VoEvalError> {
    let pair = NgiPair::load(dir)?;
    let (truth1, truth2, img_a, img_b, first_frame) = match order {
        NgiOrder::Forward => (pair.prev, pair.next, pair.img_a, pair.img_b, PREV_FRAME),
        NgiOrder::Reverse => (pair.next, pair.prev, pair.img_b, pair.img_a, NEXT_FRAME),
    };
    let (dem, image) = (pair.dem, pair.image);
    let (guess1, guess2) = guess(&truth1, &truth2, err);
    let t0 = Instant::now();
    let camera = pinhole(&image)?;
    let (corners, tracks) = flow(&img_a, &img_b, &camera, (&guess1, &guess2), &dem)?;
    let t1 = Instant::now();
    let cfg = DtmNavConfig::default();
    let input = DtmInput {
        tracks: &tracks,
        image: &image,
        guess_first: guess1,
        guess_second: guess2,
        guess_sigma: Some(NGI_GUESS_SIGMA),
    };
    let fix = solve(&input, &dem, &cfg).map_err(|e| VoEvalError::Refused {
        path: dir.join(first_frame),
        reason: format!("no pose from {} flow vectors: {e}", tracks.len()),
    })?;
    let t2 = Instant::now();
    Ok(ngi_figures(
        &fix,
        &truth1,
        &guess1,
        corners,
        tracks.len(),
        [t0, t1, t2],
    ))
}

/// One guess of a sweep ([`ngi_sweep`]): where it was and what came of it.
#[derive(Debug, Clone, Serialize)]
pub struct SweepCase {
    /// Which frame was the first.
    pub order: NgiOrder,
    /// The guess's horizontal offset from the truth, m.
    pub offset_m: f64,
    /// The offset's direction, deg from grid east, counter-clockwise.
    pub direction_deg: f64,
    /// The solution's figures when one was accepted.
    pub solved: Option<NgiDtm>,
    /// The solver's refusal in words otherwise.
    pub refused: Option<String>,
}

impl SweepCase {
    /// An accepted pose outside its claimed 3 sigma: on any axis, or jointly (the 3-D
    /// chi-square at the 3-sigma probability, [`WRONG_POSE_CHI2_3D`]).
    pub fn wrong(&self) -> bool {
        self.solved.as_ref().is_some_and(|r| {
            !(r.err_axis_sigmas <= 3.0 && r.err_mahalanobis2 <= WRONG_POSE_CHI2_3D)
        })
    }
}

/// Chi-square (3 dof) at the 3-sigma probability 0.9973: an accepted pose further than this in
/// squared Mahalanobis distance is outside what it claims.
pub const WRONG_POSE_CHI2_3D: f64 = 14.16;

/// First guesses `offsets_m` from the truth in `directions` directions (evenly spread, the first
/// 22.5 deg from grid east so none runs along a grid axis), each with [`NGI_GUESS`]'s turn and
/// motion error and a height error of 8 % of the offset (alternating in sign): the pose of the
/// first frame of `order` from each.
pub fn ngi_sweep(
    dir: &Path,
    order: NgiOrder,
    offsets_m: &[f64],
    directions: usize,
) -> Result<Vec<SweepCase>, VoEvalError> {
    let mut out = Vec::new();
    for &offset_m in offsets_m {
        for k in 0..directions {
            let a = (22.5 + 360.0 * k as f64 / directions.max(1) as f64).to_radians();
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            let g = GuessError {
                offset_m: [
                    offset_m * a.cos(),
                    offset_m * a.sin(),
                    0.08 * offset_m * sign,
                ],
                ..NGI_GUESS
            };
            let (solved, refused) = match ngi_dtm(dir, &g, order) {
                Ok(r) => (Some(r), None),
                Err(VoEvalError::Refused { reason, .. }) => (None, Some(reason)),
                Err(e) => return Err(e),
            };
            out.push(SweepCase {
                order,
                offset_m,
                direction_deg: a.to_degrees(),
                solved,
                refused,
            });
        }
    }
    Ok(out)
}

/// The figures of an NGI solution against the measured first pose.
fn ngi_figures(
    fix: &DtmFix,
    truth: &Pose,
    guess: &Pose,
    corners: usize,
    tracks: usize,
    [t0, t1, t2]: [Instant; 3],
) -> NgiDtm {
    let e = fix.first.c_world - truth.c_world;
    let cov = fix.position_cov_first_m2();
    let n = e.norm();
    let sigma_along = if n > 0.0 {
        ((e.transpose() * cov * e)[(0, 0)] / (n * n)).sqrt()
    } else {
        cov.trace().sqrt()
    };
    let att = fix.attitude_cov_first_rad2();
    let att_err =
        visnav_core::pose::refine::log_so3(&(fix.first.r_world_cam * truth.r_world_cam.inverse()));
    let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
    NgiDtm {
        corners,
        tracks,
        on_ground: fix.on_ground,
        inliers: fix.inliers,
        guess_err_m: (guess.c_world - truth.c_world).norm(),
        err_m: [e.x, e.y, e.z],
        err_norm_m: n,
        sigma_along_err_m: sigma_along,
        err_over_sigma: n / sigma_along,
        err_mahalanobis2: cov
            .try_inverse()
            .map_or(f64::INFINITY, |ci| (e.transpose() * ci * e)[(0, 0)]),
        err_axis_sigmas: (0..3)
            .map(|i| (e[i] / cov[(i, i)].sqrt()).abs())
            .fold(0.0, f64::max),
        sigma_m: [cov[(0, 0)].sqrt(), cov[(1, 1)].sqrt(), cov[(2, 2)].sqrt()],
        sigma_h_given_attitude_m: fix.sigma_h_given_attitude_m,
        att_err_deg: att_err.norm().to_degrees(),
        att_sigma_deg: att
            .symmetric_eigenvalues()
            .max()
            .max(0.0)
            .sqrt()
            .to_degrees(),
        rms_px: fix.rms_px,
        sigma0: fix.sigma0,
        relief_std_m: fix.relief_std_m,
        agl_m: fix.agl_m,
        method: fix.method.to_string(),
        iterations: fix.iterations,
        ms_flow: ms(t0, t1),
        ms_solve: ms(t1, t2),
    }
}

/// Flat pairs of the VGA sequence over the photo at `texture_path` (module doc): `pairs` pairs,
/// each solved with the default settings and with the relief screen off.
pub fn flat_dtm(texture_path: &Path, pairs: usize) -> Result<FlatDtm, VoEvalError> {
    let texture = GrayImage::load(texture_path)
        .map_err(|e| data_err(texture_path.to_path_buf(), e.to_string()))?;
    let image = vga_image();
    let poses = vga_poses(pairs + FLAT_PAIR_GAP);
    let dem = Dem::flat(0.0).map_err(|e| VoEvalError::Vision(e.to_string()))?;
    let camera = pinhole(&image)?;
    let screened = DtmNavConfig::default();
    let unscreened = DtmNavConfig {
        min_relief_agl_fraction: 0.0,
        ..DtmNavConfig::default()
    };
    let (mut accepted, mut accepted_unscreened, mut n_tracks) = (0, 0, 0);
    let mut reasons: Vec<String> = Vec::new();
    let mut times = Vec::new();
    for k in 0..pairs {
        let (t1, t2) = (&poses[k], &poses[k + FLAT_PAIR_GAP]);
        let a = render_flat(&texture, &image, t1);
        let b = render_flat(&texture, &image, t2);
        let (g1, g2) = guess(t1, t2, &FLAT_GUESS);
        let (_, tracks) = flow(&a, &b, &camera, (&g1, &g2), &dem)?;
        n_tracks += tracks.len();
        let input = DtmInput {
            tracks: &tracks,
            image: &image,
            guess_first: g1,
            guess_second: g2,
            guess_sigma: None,
        };
        let mut note = |r: &DtmRejection, what: &str| {
            let line = format!("{what}: {r}");
            let kind = line.split(':').take(2).collect::<Vec<_>>().join(":");
            if !reasons.iter().any(|l| l.starts_with(&kind)) {
                reasons.push(line);
            }
        };
        match solve(&input, &dem, &screened) {
            Ok(_) => accepted += 1,
            Err(r) => note(&r, "default"),
        }
        let t0 = Instant::now();
        match solve(&input, &dem, &unscreened) {
            Ok(_) => accepted_unscreened += 1,
            Err(r) => note(&r, "screen off"),
        }
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(FlatDtm {
        pairs,
        accepted,
        accepted_unscreened,
        reasons,
        tracks_mean: n_tracks as f64 / pairs.max(1) as f64,
        ms_solve_p50: percentile(&times, 0.5),
    })
}
