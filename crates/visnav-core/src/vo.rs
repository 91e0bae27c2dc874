//! Visual odometry: the camera's motion between two frames from features seen in both, the
//! previous frame's pose (the navigation filter's) and the terrain.
//!
//! # Method
//! 1. Every feature of the previous frame is cast as a ray from the previous pose onto the terrain
//!    ([`Dem::intersect_ray`]: a DEM / surface model, or flat ground at a known height): a 3-D point.
//! 2. The next frame's pose is the space resection ([`crate::pose::resect`]: LO-RANSAC over P3P,
//!    Levenberg-Marquardt, covariance) of those points against the features' positions in the next
//!    frame. When the gyros' rotation between the frames is given ([`RotationPrior`]) it is fused
//!    as the next frame's attitude prior: one frame cannot tell a small tilt from a sideways shift,
//!    the gyros over a fraction of a second can.
//! 3. The motion is the difference of the two poses: the displacement of the projection centre
//!    `dp_world_m = C_next - C_prev`, from the pose with the gyros' rotation fused, and the relative
//!    rotation `R_prev_next = R_world_prev^T R_world_next` (takes next-camera vectors into the
//!    previous camera frame), from the images alone (`vision_pose`: a filter that propagates with
//!    the same gyros must not be handed their rotation back as a measurement).
//!
//! This is the similarity model of the nadir case (Chan 2022, NPS thesis: pixel shift, rotation
//! and scale turned into metric motion with the height) and the homography of a tilted camera over
//! a plane, generalised: the terrain model gives the scale, any camera tilt and any relief are
//! handled by the ray casting, and the outliers by the same RANSAC and integrity checks as the
//! absolute fix. The previous pose is an estimate; how its errors reach the motion (first order,
//! flat ground; exact for yaw):
//! * horizontal position error: every ground point moves with it, so does the next centre: the
//!   displacement does not change;
//! * a yaw error rotates the whole back-projected scene about the previous centre: the
//!   displacement comes out rotated by it (`dp = Rz(dyaw) dp_true`), the relative rotation
//!   does not change. A filter that fuses `dp_world_m` expresses it in its own heading frame of
//!   the previous instant (the heading this pose was given with), where the yaw error cancels;
//! * a tilt error shifts the ground points sideways by about `AGL * dtilt` and the next centre with
//!   them; for a camera looking `theta` off the vertical it also changes the range to the ground,
//!   so the displacement is scaled by about `1 + tan(theta) dtilt` (first order: zero for a nadir
//!   camera, 1.5 % at 60 deg and 0.5 deg). In the covariance as
//!   `(sigma_tilt tan(theta))^2 dp dp^T` with the caller's tilt sigma of the previous pose. Over
//!   relief the yaw statement is approximate too (a turned ray bundle meets other heights);
//! * a height error `dh` scales the scene: the displacement is wrong by the factor `1 + dh / AGL`.
//!   This is in the covariance: `(sigma_h / AGL)^2 dp dp^T` with `sigma_h` the caller's height
//!   uncertainty of the previous pose (filter plus terrain model).
//!
//! The covariance of the displacement is the resection's position covariance of the next frame
//! (conservative: a-posteriori, floored at the a-priori; with the gyros' rotation fused when
//! given) with the observations' sigma `sqrt(2) track_sigma_px` (both frames' feature noise, the
//! previous frame's reaching the ground points) plus the two scale terms above. The rotation's
//! covariance is the image-only resection's attitude covariance expressed in the previous camera
//! frame. Not yet passed on: the part of the displacement that follows the gyros' error
//! (`Fix::prior_dependence`, about AGL x the gyro error: 5 cm at 300 m for 0.01 deg).
//!
//! # What it refuses
//! Too few tracks, too few of them on the terrain (sky, outside the DEM, holes), no consensus or a
//! failed integrity check of the resection, a result with non-finite numbers, and a motion whose
//! horizontal or vertical sigma exceeds [`VoConfig::max_sigma_agl_fraction`] of the height above
//! ground or whose image-only attitude sigma exceeds the resection's `max_attitude_sigma_deg`
//! (flat or repetitive texture, features clustered in a corner). Tracks that did not move at all are
//! legitimate (a hovering aircraft), but the caller must not feed a frozen camera (an identical
//! frame gives zero motion; the daemon drops such frames before tracking).
//!
//! # Conventions
//! World frame: the terrain model's map frame (x grid east, y grid north, z up, metres), as in
//! [`crate::pose`]. Camera frame `_cam`: x right, y down, z forward. Pixels: undistorted, OpenCV's
//! convention (x right, y down, pixel centres at integer coordinates).

use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::geo::dem::Dem;
use crate::pose::{
    AttitudePrior, Correspondence, ImageGeometry, IntegrityConfig, Pose, Priors, Rejection,
    ResectionConfig, resect, rotate_cov3,
};
use crate::validate::{Problems, Validate};

pub mod odometer;
pub mod tracker;

pub use odometer::{GyroDelta, Odometer, VO_CLASSES, VoMotion, VoRefusal, VoStep};
pub use tracker::{RawTrack, Tracker, TrackingConfig};

/// One feature seen in both frames: its undistorted pixel position in the previous and the next.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPair {
    /// Undistorted pixel position in the previous frame.
    pub prev_px: Vector2<f64>,
    /// Undistorted pixel position in the next frame.
    pub next_px: Vector2<f64>,
}

/// Visual-odometry settings (`[vo]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VoConfig {
    /// Run visual odometry on every frame (the daemon; the absolute fix runs on the frames its
    /// workers are free for).
    pub enabled: bool,
    /// Fewest tracks on the terrain to try a solution.
    pub min_tracks: usize,
    /// 1-sigma position noise of a tracked feature in one frame, px.
    pub track_sigma_px: f64,
    /// Longest ray to the terrain, m (beyond it a feature is dropped: near-horizontal rays).
    pub max_range_m: f64,
    /// Largest accepted horizontal 1-sigma of the displacement as a fraction of the height above
    /// ground (the motion of a camera whose features say little is refused, not guessed).
    pub max_sigma_agl_fraction: f64,
    /// The next frame's resection (RANSAC, adjustment, integrity).
    pub resection: ResectionConfig,
    /// Distance over which the terrain model's height error stays the same, m: the scale error it
    /// gives the displacements is one error over this distance, not one per frame
    /// (`nav::VoFix`).
    pub terrain_error_corr_dist_m: f64,
    /// Feature detection and tracking.
    pub tracking: TrackingConfig,
}

/// Largest deviation of a given rotation from orthonormality (`|R R^T - I|` elementwise): rounding
/// of products of rotations is 1e-15 to 1e-8; more is not a rotation.
const MAX_ROTATION_DRIFT: f64 = 1e-6;

/// Orthonormal within [`MAX_ROTATION_DRIFT`] and proper (determinant +1, not a reflection).
fn is_rotation(r: &Rotation3<f64>) -> bool {
    let m = r.matrix();
    (m * m.transpose() - Matrix3::identity()).amax() <= MAX_ROTATION_DRIFT && m.determinant() > 0.0
}

/// Default fewest tracks: three times the P3P sample, so RANSAC has a consensus to find and the
/// adjustment a redundancy.
const DEFAULT_MIN_TRACKS: usize = 12;
/// Default track noise: a pyramidal Lucas-Kanade track converges to about 0.1 px on texture;
/// blur, rolling shutter and relief parallax inside the window make it several times that.
const DEFAULT_TRACK_SIGMA_PX: f64 = 0.5;
/// Default longest ray, m: 20 km covers any height a small aircraft flies at a tilted camera.
const DEFAULT_MAX_RANGE_M: f64 = 20_000.0;
/// Default largest horizontal sigma over the height above ground: 5 % (50 m at 1000 m AGL) is
/// already a motion the IMU knows better over a fifth of a second.
const DEFAULT_MAX_SIGMA_AGL_FRACTION: f64 = 0.05;

/// Default terrain error correlation distance: published semivariograms of SRTM-class and
/// photogrammetric DEM errors reach their sill at about 0.5-2 km; a map whose heights are off by
/// a datum (or a flat-ground assumption) is off everywhere: set it to the map's size then.
const DEFAULT_TERRAIN_ERROR_CORR_DIST_M: f64 = 1000.0;

impl Default for VoConfig {
    fn default() -> Self {
        Self {
            enabled: false,
            terrain_error_corr_dist_m: DEFAULT_TERRAIN_ERROR_CORR_DIST_M,
            tracking: TrackingConfig::default(),
            min_tracks: DEFAULT_MIN_TRACKS,
            track_sigma_px: DEFAULT_TRACK_SIGMA_PX,
            max_range_m: DEFAULT_MAX_RANGE_M,
            max_sigma_agl_fraction: DEFAULT_MAX_SIGMA_AGL_FRACTION,
            resection: ResectionConfig {
                integrity: vo_integrity(),
                ..ResectionConfig::default()
            },
        }
    }
}

/// The absolute fix's integrity checks, adapted to two frames that overlap only in part: the
/// features of the next frame sit where the previous one saw ground (a strip of the image when the
/// camera moves fast), so the image-coverage checks are those of a strip, and the sigma limits
/// are [`VoConfig::max_sigma_agl_fraction`]'s (metres do not scale with height).
fn vo_integrity() -> IntegrityConfig {
    IntegrityConfig {
        // One column (or row) of the 3 x 3 grid: a 30 % overlap.
        min_grid_cells: 3,
        min_hull_area_fraction: 0.02,
        min_spread_eig_ratio: 0.05,
        max_horizontal_sigma_m: 1e6,
        max_vertical_sigma_m: 1e6,
        max_attitude_sigma_deg: 5.0,
        ..IntegrityConfig::default()
    }
}

impl Validate for VoConfig {
    fn validate(&self, p: &mut Problems) {
        if self.min_tracks < 6 {
            p.push(
                "min_tracks",
                format!(
                    "{} is below 6 (a pose has 6 unknowns; RANSAC needs a consensus beyond its 3-point sample)",
                    self.min_tracks
                ),
            );
        }
        if !(self.track_sigma_px.is_finite() && self.track_sigma_px > 0.0) {
            p.push(
                "track_sigma_px",
                format!("{} must be finite and > 0", self.track_sigma_px),
            );
        }
        if !(self.max_range_m.is_finite() && self.max_range_m > 0.0) {
            p.push(
                "max_range_m",
                format!("{} must be finite and > 0", self.max_range_m),
            );
        }
        if !(self.max_sigma_agl_fraction.is_finite() && self.max_sigma_agl_fraction > 0.0) {
            p.push(
                "max_sigma_agl_fraction",
                format!("{} must be finite and > 0", self.max_sigma_agl_fraction),
            );
        }
        if !(self.terrain_error_corr_dist_m.is_finite()
            && (0.0..=1e7).contains(&self.terrain_error_corr_dist_m))
        {
            p.push(
                "terrain_error_corr_dist_m",
                format!("{} must be in 0..=1e7", self.terrain_error_corr_dist_m),
            );
        }
        p.section("resection", |p| self.resection.validate(p));
        p.section("tracking", |p| self.tracking.validate(p));
    }
}

/// Why no motion came out of a frame pair.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VoRejection {
    /// Unusable input, settings or result (non-finite, not a rotation, bad camera); says which.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// Fewer tracks than [`VoConfig::min_tracks`].
    #[error("{tracks} tracks, need {min}")]
    TooFewTracks {
        /// Tracks given.
        tracks: usize,
        /// [`VoConfig::min_tracks`].
        min: usize,
    },
    /// Fewer tracks whose previous-frame ray meets the terrain than [`VoConfig::min_tracks`].
    #[error("{on_ground} of {tracks} tracks reach the terrain, need {min}")]
    TooFewOnGround {
        /// Tracks whose ray meets the terrain within [`VoConfig::max_range_m`].
        on_ground: usize,
        /// Tracks given.
        tracks: usize,
        /// [`VoConfig::min_tracks`].
        min: usize,
    },
    /// The next frame's resection failed or was rejected by its integrity checks.
    #[error("next frame's resection: {0}")]
    Resection(Rejection),
    /// The displacement's horizontal or vertical 1-sigma exceeds
    /// [`VoConfig::max_sigma_agl_fraction`] of the height above ground.
    #[error(
        "sigma {sigma_m:.1} m is over {max_fraction} of the height above ground ({agl_m:.0} m)"
    )]
    TooUncertain {
        /// The larger of the horizontal and vertical sigma, m.
        sigma_m: f64,
        /// Height of the previous centre above the inlier ground points, m.
        agl_m: f64,
        /// [`VoConfig::max_sigma_agl_fraction`].
        max_fraction: f64,
    },
}

impl VoRejection {
    /// The check's class for counting and metric labels (a name without numbers; the
    /// resection's are [`Rejection::class`]'s).
    pub fn class(&self) -> &'static str {
        match self {
            VoRejection::InvalidInput(_) => "invalid_input",
            VoRejection::TooFewTracks { .. } => "few_tracks",
            VoRejection::TooFewOnGround { .. } => "few_on_ground",
            VoRejection::Resection(r) => r.class(),
            VoRejection::TooUncertain { .. } => "too_uncertain",
        }
    }
}

/// The camera's motion between two frames.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMotion {
    /// `C_next - C_prev`, world frame, m.
    pub dp_world_m: Vector3<f64>,
    /// Its covariance, world frame, m^2.
    pub cov_dp_world_m2: Matrix3<f64>,
    /// `R_world_prev^T R_world_next` from the images alone (the gyros' rotation not fused):
    /// next-camera vectors into the previous camera frame.
    pub r_prev_next: Rotation3<f64>,
    /// Covariance of that relative rotation as a rotation vector in the previous camera frame,
    /// applied on the left, rad^2.
    pub cov_rot_prev_rad2: Matrix3<f64>,
    /// The next frame's pose as solved, with the gyros' rotation fused when given (world frame).
    pub next: Pose,
    /// Mean height of the previous centre above the resection's inlier ground points, m.
    pub agl_m: f64,
    /// Mean line of sight from the next centre to the inlier ground points, world frame, m.
    pub look_world_m: Vector3<f64>,
    /// Tracks given.
    pub tracks: usize,
    /// Tracks whose previous-frame ray met the terrain.
    pub on_ground: usize,
    /// Inliers of the next frame's resection.
    pub inliers: usize,
    /// Reprojection RMS over the inliers, px.
    pub rms_px: f64,
    /// With the gyros' rotation fused: how the next centre (so the displacement) moved with an
    /// error of it, `d C_world / d phi` (m/rad, world frame, `phi` the world-frame rotation vector
    /// of the prior's error: [`crate::pose::Fix::prior_dependence`]).
    pub rotation_sensitivity_world: Option<Matrix3<f64>>,
}

/// The camera's rotation between the two frames as the gyros measured it: `R_prev_next`
/// (next-camera vectors into the previous camera frame) and the covariance of its error as a
/// rotation vector in the previous camera frame, applied on the left (`R_true = Exp(psi_prev)
/// R_prev_next`), rad^2 (gyro noise and bias over the interval, not the filter's attitude
/// uncertainty: a common attitude error cancels, see the module doc). A gyro integrator's error is
/// naturally on the right, in the next frame: `Exp(R_prev_next psi_next) R_prev_next`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotationPrior {
    /// The gyros' `R_prev_next`: next-camera vectors into the previous camera frame.
    pub r_prev_next: Rotation3<f64>,
    /// Covariance of its error, rotation vector in the previous camera frame (left), rad^2.
    pub cov_prev_rad2: Matrix3<f64>,
}

/// What a frame pair's motion is solved from besides the terrain.
#[derive(Debug, Clone, Copy)]
pub struct VoInput<'a> {
    /// Features seen in both frames, undistorted pixels.
    pub tracks: &'a [TrackPair],
    /// The camera's focal lengths, principal point and image size.
    pub image: &'a ImageGeometry,
    /// The previous frame's camera pose (the filter's, world frame).
    pub prev: Pose,
    /// 1-sigma of its height above the terrain model: the filter's vertical sigma and the
    /// model's own error, m.
    pub prev_height_sigma_m: f64,
    /// 1-sigma of its tilt (roll and pitch), rad: it scales the displacement of an oblique camera
    /// (module doc).
    pub prev_tilt_sigma_rad: f64,
    /// The gyros' rotation between the frames, when known. A single frame's resection cannot
    /// tell a small tilt from a sideways shift (at 500 m, 0.05 deg is 0.4 m); the gyros' relative
    /// rotation over a fraction of a second removes that ambiguity from the displacement.
    pub rotation_prior: Option<RotationPrior>,
}

/// The motion between two frames: see the module documentation.
pub fn frame_motion(
    input: &VoInput<'_>,
    dem: &Dem,
    cfg: &VoConfig,
) -> Result<FrameMotion, VoRejection> {
    let VoInput {
        tracks,
        image,
        prev,
        prev_height_sigma_m,
        prev_tilt_sigma_rad,
        rotation_prior,
    } = *input;
    let prev = &prev;
    check_inputs(
        tracks,
        image,
        prev,
        [prev_height_sigma_m, prev_tilt_sigma_rad],
        cfg,
    )?;
    let (corrs, agl_m) = ground_points(tracks, image, prev, dem, cfg)?;
    let (priors, resection) = next_attitude_prior(prev, rotation_prior.as_ref(), cfg)?;
    let outcome = resect(&corrs, image, &priors, &resection);
    let fix = match (outcome.accepted(), outcome.rejection()) {
        (Some(f), _) => f.clone(),
        (None, Some(r)) => return Err(VoRejection::Resection(r.clone())),
        (None, None) => {
            return Err(VoRejection::InvalidInput(
                "the resection gave neither a fix nor a reason".into(),
            ));
        }
    };
    // The height above the ground the scale came from: the inliers' (an outlier's ray may have
    // met other ground).
    let agl_m = inlier_agl_m(&corrs, &fix.inliers, prev.c_world.z).unwrap_or(agl_m);
    // The displacement from the pose with the gyros' rotation fused; the rotation from the
    // images alone (module doc).
    let next = fix.pose;
    let look_world_m = inlier_look_m(&corrs, &fix.inliers, &next.c_world)
        .unwrap_or_else(|| Vector3::new(0.0, 0.0, -agl_m));
    let dp = next.c_world - prev.c_world;
    // The optical axis's angle off the vertical.
    let axis_down = -(prev.r_world_cam * Vector3::z()).z;
    let tan_off_nadir = (1.0 - axis_down * axis_down).max(0.0).sqrt() / axis_down.max(1e-3);
    let scale_var =
        (prev_height_sigma_m / agl_m).powi(2) + (prev_tilt_sigma_rad * tan_off_nadir).powi(2);
    let cov_dp = fix.covariance.position_world_m2() + dp * dp.transpose() * scale_var;
    let r_prev_world = prev.r_world_cam.inverse();
    let vision_att = fix.vision_covariance.attitude_world_rad2();
    check_attitude_sigma(&vision_att, cfg)?;
    let motion = FrameMotion {
        dp_world_m: dp,
        cov_dp_world_m2: 0.5 * (cov_dp + cov_dp.transpose()),
        r_prev_next: r_prev_world * fix.vision_pose.r_world_cam,
        cov_rot_prev_rad2: rotate_cov3(&vision_att, &r_prev_world),
        next,
        agl_m,
        look_world_m,
        tracks: tracks.len(),
        on_ground: corrs.len(),
        inliers: fix.inliers.len(),
        rms_px: fix.quality.reprojection_rms_px,
        rotation_sensitivity_world: fix.prior_dependence.map(|d| d.d_position_d_prior_att),
    };
    check_motion(&motion, cfg)?;
    Ok(motion)
}

/// Mean height of a camera at `z_m` above the inliers' ground points; `None` without inliers or
/// when not positive.
fn inlier_agl_m(corrs: &[Correspondence], inliers: &[usize], z_m: f64) -> Option<f64> {
    let heights: Vec<f64> = inliers
        .iter()
        .filter_map(|&i| corrs.get(i))
        .map(|c| z_m - c.point_world.z)
        .collect();
    let agl = heights.iter().sum::<f64>() / heights.len() as f64;
    (!heights.is_empty() && agl.is_finite() && agl > 0.0).then_some(agl)
}

/// Mean vector from a camera at `c` to the inliers' ground points; `None` without inliers.
fn inlier_look_m(
    corrs: &[Correspondence],
    inliers: &[usize],
    c: &Vector3<f64>,
) -> Option<Vector3<f64>> {
    let pts: Vec<Vector3<f64>> = inliers
        .iter()
        .filter_map(|&i| corrs.get(i))
        .map(|k| k.point_world - c)
        .collect();
    let mean = pts.iter().sum::<Vector3<f64>>() / pts.len().max(1) as f64;
    (!pts.is_empty() && mean.iter().all(|v| v.is_finite())).then_some(mean)
}

/// The next frame's attitude prior (the previous attitude turned by the gyros' rotation, with
/// the rotation's covariance in the world frame) and the resection settings that fuse it.
fn next_attitude_prior(
    prev: &Pose,
    rotation: Option<&RotationPrior>,
    cfg: &VoConfig,
) -> Result<(Priors, ResectionConfig), VoRejection> {
    let Some(r) = rotation else {
        return Ok((Priors::default(), cfg.resection.clone()));
    };
    let finite = r
        .r_prev_next
        .matrix()
        .iter()
        .chain(r.cov_prev_rad2.iter())
        .all(|v| v.is_finite());
    let c = &r.cov_prev_rad2;
    let symmetric = (c - c.transpose()).amax() <= 1e-9 * c.amax();
    let positive = c.symmetric_eigenvalues().min() > 0.0;
    let rotation = is_rotation(&r.r_prev_next);
    if !(finite && symmetric && positive && rotation) {
        return Err(VoRejection::InvalidInput(
            "the gyros' rotation prior is not finite or not a rotation, or its covariance is not symmetric positive definite"
                .into(),
        ));
    }
    let mut resection = cfg.resection.clone();
    resection.refine.use_attitude_prior = true;
    let mut r_world_next = prev.r_world_cam * r.r_prev_next;
    r_world_next.renormalize();
    let priors = Priors {
        attitude: Some(AttitudePrior {
            r_world_cam: r_world_next,
            cov_rad2: rotate_cov3(&r.cov_prev_rad2, &prev.r_world_cam),
        }),
        position: None,
        map_tilt_sigma_rad: 0.0,
    };
    Ok((priors, resection))
}

/// The pose, the sigma, the configuration and the number of tracks are usable.
fn check_inputs(
    tracks: &[TrackPair],
    image: &ImageGeometry,
    prev: &Pose,
    [height_sigma_m, tilt_sigma_rad]: [f64; 2],
    cfg: &VoConfig,
) -> Result<(), VoRejection> {
    let mut problems = Problems::default();
    cfg.validate(&mut problems);
    if let Some(first) = problems.list.first() {
        return Err(VoRejection::InvalidInput(format!("[vo] {first}")));
    }
    let invalid = |s: String| Err(VoRejection::InvalidInput(s));
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    if !(finite(prev.c_world.as_slice()) && finite(prev.r_world_cam.matrix().as_slice())) {
        return invalid("the previous pose is not finite".into());
    }
    if !is_rotation(&prev.r_world_cam) {
        return invalid("the previous attitude is not a rotation".into());
    }
    // A sigma of the previous pose beyond these is not a pose to cast rays from.
    if !(height_sigma_m.is_finite() && (0.0..=1e5).contains(&height_sigma_m)) {
        return invalid(format!(
            "previous height sigma {height_sigma_m} m must be in 0..=1e5"
        ));
    }
    if !(tilt_sigma_rad.is_finite() && (0.0..=1.0).contains(&tilt_sigma_rad)) {
        return invalid(format!(
            "previous tilt sigma {tilt_sigma_rad} rad must be in 0..=1"
        ));
    }
    let ok = |v: f64| v.is_finite() && v > 0.0;
    if !(ok(image.fx_px) && ok(image.fy_px) && image.cx_px.is_finite() && image.cy_px.is_finite()) {
        return invalid(format!(
            "focal lengths {} / {} px must be finite and > 0, the principal point ({}, {}) finite",
            image.fx_px, image.fy_px, image.cx_px, image.cy_px
        ));
    }
    if tracks.len() < cfg.min_tracks {
        return Err(VoRejection::TooFewTracks {
            tracks: tracks.len(),
            min: cfg.min_tracks,
        });
    }
    Ok(())
}

/// The tracks whose previous-frame ray reaches the terrain, as correspondences of that ground point
/// with the next frame's observation, and the mean height of the previous centre above them.
fn ground_points(
    tracks: &[TrackPair],
    image: &ImageGeometry,
    prev: &Pose,
    dem: &Dem,
    cfg: &VoConfig,
) -> Result<(Vec<Correspondence>, f64), VoRejection> {
    let sigma_px = std::f64::consts::SQRT_2 * cfg.track_sigma_px;
    let norm = |px: &Vector2<f64>| {
        Vector2::new(
            (px.x - image.cx_px) / image.fx_px,
            (px.y - image.cy_px) / image.fy_px,
        )
    };
    let c = prev.c_world;
    let mut corrs = Vec::with_capacity(tracks.len());
    let mut agl_sum = 0.0;
    for t in tracks {
        let (a, b) = (norm(&t.prev_px), norm(&t.next_px));
        if !(a.iter().chain(b.iter()).all(|v| v.is_finite())) {
            continue;
        }
        let d = prev.r_world_cam * Vector3::new(a.x, a.y, 1.0);
        let Some(x) = dem.intersect_ray([c.x, c.y, c.z], [d.x, d.y, d.z], cfg.max_range_m) else {
            continue;
        };
        let corr = Correspondence {
            point_world: Vector3::new(x[0], x[1], x[2]),
            obs_norm: b,
            sigma_px,
        };
        if corr.is_valid() {
            agl_sum += c.z - x[2];
            corrs.push(corr);
        }
    }
    if corrs.len() < cfg.min_tracks {
        return Err(VoRejection::TooFewOnGround {
            on_ground: corrs.len(),
            tracks: tracks.len(),
            min: cfg.min_tracks,
        });
    }
    let agl_m = agl_sum / corrs.len() as f64;
    if !(agl_m.is_finite() && agl_m > 0.0) {
        return Err(VoRejection::InvalidInput(format!(
            "the camera is {agl_m} m above its ground points"
        )));
    }
    Ok((corrs, agl_m))
}

/// The image-only attitude sigma within the resection's `max_attitude_sigma_deg` (its own check
/// sees the covariance with the gyros' rotation fused, which always passes).
fn check_attitude_sigma(cov_rad2: &Matrix3<f64>, cfg: &VoConfig) -> Result<(), VoRejection> {
    let sigma_deg = cov_rad2
        .symmetric_eigenvalues()
        .max()
        .max(0.0)
        .sqrt()
        .to_degrees();
    let max_deg = cfg.resection.integrity.max_attitude_sigma_deg;
    if sigma_deg.is_nan() || sigma_deg > max_deg {
        return Err(VoRejection::InvalidInput(format!(
            "the images alone fix the rotation to {sigma_deg:.2} deg (1 sigma), above {max_deg} deg"
        )));
    }
    Ok(())
}

/// Finite numbers and horizontal and vertical sigmas within the configured fraction of the
/// height.
fn check_motion(m: &FrameMotion, cfg: &VoConfig) -> Result<(), VoRejection> {
    let finite = m
        .dp_world_m
        .iter()
        .chain(m.cov_dp_world_m2.iter())
        .chain(m.cov_rot_prev_rad2.iter())
        .chain(m.r_prev_next.matrix().iter())
        .all(|v| v.is_finite());
    if !finite {
        return Err(VoRejection::InvalidInput(
            "the motion has non-finite numbers".into(),
        ));
    }
    let h = m.cov_dp_world_m2.fixed_view::<2, 2>(0, 0);
    let sigma_h_m = h.symmetric_eigenvalues().max().max(0.0).sqrt();
    let sigma_v_m = m.cov_dp_world_m2[(2, 2)].max(0.0).sqrt();
    let sigma_m = sigma_h_m.max(sigma_v_m);
    if sigma_m > cfg.max_sigma_agl_fraction * m.agl_m {
        return Err(VoRejection::TooUncertain {
            sigma_m,
            agl_m: m.agl_m,
            max_fraction: cfg.max_sigma_agl_fraction,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::Crs;
    use crate::geo::raster::{GeoTransform, Raster, RasterData};
    use crate::pose::log_so3;
    use crate::rng::Rng;

    /// The rotation's angle, rad (robust near the identity: `pose::log_so3`).
    fn angle(r: &Rotation3<f64>) -> f64 {
        log_so3(r).norm()
    }

    fn camera(c: Vector3<f64>, yaw_rad: f64, tilt_rad: f64) -> Pose {
        Pose::nadir(c, yaw_rad, tilt_rad)
    }

    fn vga() -> ImageGeometry {
        ImageGeometry {
            fx_px: 554.3,
            fy_px: 554.3,
            cx_px: 319.5,
            cy_px: 239.5,
            width_px: 640,
            height_px: 480,
        }
    }

    /// Hills: 60 m of relief over 2 km on a 20 m grid (heights 100-160 m).
    fn hills() -> Dem {
        let (w, h) = (200, 200);
        let data: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 * 20.0, (i / w) as f32 * 20.0);
                130.0 + 20.0 * (x / 300.0).sin() + 10.0 * (y / 170.0).cos()
            })
            .collect();
        grid_dem(w, data, -2000.0, 2000.0, 20.0)
    }

    /// A square-cell DEM of `w` columns (rows from `heights.len()`), top-left corner at
    /// (`x0`, `y0`), UTM 33N.
    fn grid_dem(w: usize, heights: Vec<f32>, x0: f64, y0: f64, cell_m: f64) -> Dem {
        let h = heights.len() / w;
        let raster = Raster::new(
            w,
            h,
            1,
            RasterData::F32(heights),
            GeoTransform::north_up(x0, y0, cell_m, cell_m).expect("transform"),
            Crs::Utm {
                zone: 33,
                north: true,
            },
            None,
        )
        .expect("raster");
        Dem::from_raster(&raster).expect("dem")
    }

    /// Tracks of `n` ground points seen from `a` and `b`, pixel noise `noise_px`, a fraction
    /// `outliers` of them replaced by random next positions.
    fn tracks(
        dem: &Dem,
        a: &Pose,
        b: &Pose,
        n: usize,
        noise_px: f64,
        outliers: f64,
        seed: u64,
    ) -> Vec<TrackPair> {
        let img = vga();
        let mut rng = Rng::new(seed);
        let mut out = Vec::new();
        let mut tries = 0;
        while out.len() < n && tries < 100 * n {
            tries += 1;
            let px = Vector2::new(rng.uniform() * 639.0, rng.uniform() * 479.0);
            let d = a.r_world_cam
                * Vector3::new(
                    (px.x - img.cx_px) / img.fx_px,
                    (px.y - img.cy_px) / img.fy_px,
                    1.0,
                );
            let c = a.c_world;
            let Some(x) = dem.intersect_ray([c.x, c.y, c.z], [d.x, d.y, d.z], 1e5) else {
                continue;
            };
            let Some(q) = b.project(&Vector3::new(x[0], x[1], x[2])) else {
                continue;
            };
            let mut next = img.to_pixel(&q);
            if !(0.0..640.0).contains(&next.x) || !(0.0..480.0).contains(&next.y) {
                continue;
            }
            if rng.uniform() < outliers {
                next = Vector2::new(rng.uniform() * 639.0, rng.uniform() * 479.0);
            }
            let mut noise = || rng.normal() * noise_px;
            let prev_px = px + Vector2::new(noise(), noise());
            let next_px = next + Vector2::new(noise(), noise());
            out.push(TrackPair { prev_px, next_px });
        }
        out
    }

    /// The gyros' relative rotation between `a` and `b` with a 0.01 deg sigma.
    fn gyro(a: &Pose, b: &Pose) -> RotationPrior {
        RotationPrior {
            r_prev_next: a.r_world_cam.inverse() * b.r_world_cam,
            cov_prev_rad2: Matrix3::identity() * 0.01f64.to_radians().powi(2),
        }
    }

    fn solve(
        t: &[TrackPair],
        prev: &Pose,
        height_sigma_m: f64,
        rotation_prior: Option<RotationPrior>,
        dem: &Dem,
    ) -> Result<FrameMotion, VoRejection> {
        let image = vga();
        let input = VoInput {
            tracks: t,
            image: &image,
            prev: *prev,
            prev_height_sigma_m: height_sigma_m,
            prev_tilt_sigma_rad: 0.0,
            rotation_prior,
        };
        frame_motion(&input, dem, &VoConfig::default())
    }

    /// Squared Mahalanobis distance of the displacement error.
    fn d2(m: &FrameMotion, truth: &Vector3<f64>) -> f64 {
        let e = m.dp_world_m - truth;
        e.dot(&(m.cov_dp_world_m2.try_inverse().expect("inverse") * e))
    }

    /// Chi-square, 3 dof, 99.9 %.
    const CHI2_3_999: f64 = 16.27;

    #[test]
    fn the_motion_over_flat_ground_is_the_true_one_within_its_sigma() {
        let dem = Dem::flat(100.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 600.0), 0.3, 0.0);
        let b = camera(Vector3::new(3.0, 4.5, 600.4), 0.32, 0.01);
        let truth = b.c_world - a.c_world;
        let t = tracks(&dem, &a, &b, 200, 0.3, 0.0, 1);
        // The images alone: a small tilt and a sideways shift trade off (decimetres at 500 m).
        let m = solve(&t, &a, 0.0, None, &dem).expect("motion");
        assert!(
            d2(&m, &truth) < CHI2_3_999,
            "images alone: d2 {}",
            d2(&m, &truth)
        );
        assert!((m.dp_world_m - truth).norm() < 1.5);
        let dr = angle(&(m.r_prev_next.inverse() * (a.r_world_cam.inverse() * b.r_world_cam)));
        assert!(
            dr.to_degrees() < 0.1,
            "rotation error {} deg",
            dr.to_degrees()
        );
        assert!((m.agl_m - 500.0).abs() < 30.0, "agl {}", m.agl_m);
        assert_eq!(m.tracks, 200);
        // With the gyros' rotation: centimetres, and the sigma says so.
        let g = solve(&t, &a, 0.0, Some(gyro(&a, &b)), &dem).expect("motion");
        let e = (g.dp_world_m - truth).norm();
        assert!(e < 0.1, "with the gyros: error {e} m");
        assert!(
            d2(&g, &truth) < CHI2_3_999,
            "with the gyros: d2 {}",
            d2(&g, &truth)
        );
        assert!(g.cov_dp_world_m2.trace() < m.cov_dp_world_m2.trace() / 4.0);
    }

    #[test]
    fn relief_and_a_tilted_camera_with_outliers() {
        let dem = hills();
        let a = camera(Vector3::new(-200.0, 100.0, 900.0), -1.2, 0.35);
        let b = camera(Vector3::new(-195.0, 96.0, 901.0), -1.19, 0.36);
        let truth = b.c_world - a.c_world;
        let t = tracks(&dem, &a, &b, 250, 0.5, 0.3, 2);
        let m = solve(&t, &a, 0.0, Some(gyro(&a, &b)), &dem).expect("motion");
        let e = (m.dp_world_m - truth).norm();
        assert!(e < 0.2, "error {e} m");
        assert!(d2(&m, &truth) < CHI2_3_999, "d2 {}", d2(&m, &truth));
        assert!(m.inliers < 200, "outliers kept: {} inliers", m.inliers);
    }

    #[test]
    fn a_gyro_rotation_the_images_contradict_is_refused() {
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 400.0), 0.0, 0.0);
        let b = camera(Vector3::new(5.0, 0.0, 400.0), 0.1, 0.0);
        let t = tracks(&dem, &a, &b, 150, 0.2, 0.0, 10);
        let mut wrong = gyro(&a, &b);
        wrong.r_prev_next *= Rotation3::from_axis_angle(&Vector3::z_axis(), 0.05);
        assert!(matches!(
            solve(&t, &a, 0.0, Some(wrong), &dem),
            Err(VoRejection::Resection(_))
        ));
        let mut drifted = gyro(&a, &b);
        drifted.r_prev_next =
            Rotation3::from_matrix_unchecked(drifted.r_prev_next.matrix() * (1.0 + 1e-8));
        assert!(
            solve(&t, &a, 0.0, Some(drifted), &dem).is_ok(),
            "rounding drift refused"
        );
        let mut scaled = gyro(&a, &b);
        scaled.r_prev_next = Rotation3::from_matrix_unchecked(scaled.r_prev_next.matrix() * 1.01);
        assert!(matches!(
            solve(&t, &a, 0.0, Some(scaled), &dem),
            Err(VoRejection::InvalidInput(_))
        ));
        let mut reflected = gyro(&a, &b);
        reflected.r_prev_next = Rotation3::from_matrix_unchecked(
            reflected.r_prev_next.matrix() * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0)),
        );
        assert!(matches!(
            solve(&t, &a, 0.0, Some(reflected), &dem),
            Err(VoRejection::InvalidInput(_))
        ));
        let mut singular = gyro(&a, &b);
        singular.cov_prev_rad2 = Matrix3::zeros();
        assert!(matches!(
            solve(&t, &a, 0.0, Some(singular), &dem),
            Err(VoRejection::InvalidInput(_))
        ));
    }

    #[test]
    fn an_anisotropic_gyro_prior_is_applied_about_the_right_axes() {
        // Tight about the previous camera's x and y axes, loose about its optical axis, given
        // 0.3 deg wrong about that axis only (1.7 sigma): the images correct it. Had the prior's
        // frame been converted the wrong way, the error would sit on a tight axis and stay (or
        // fail the prior-consistency gate).
        let dem = hills();
        let a = camera(Vector3::new(-300.0, 200.0, 900.0), 1.0, 0.3);
        let b = camera(Vector3::new(-296.0, 203.0, 900.5), 1.02, 0.31);
        let t = tracks(&dem, &a, &b, 250, 0.3, 0.0, 11);
        let wrong = Rotation3::from_axis_angle(&Vector3::z_axis(), 0.3f64.to_radians());
        let prior = RotationPrior {
            r_prev_next: wrong * (a.r_world_cam.inverse() * b.r_world_cam),
            cov_prev_rad2: Matrix3::from_diagonal(&Vector3::new(1e-10, 1e-10, 1e-5)),
        };
        let m = solve(&t, &a, 0.0, Some(prior), &dem).expect("motion");
        let err_deg = angle(&(m.next.r_world_cam.inverse() * b.r_world_cam)).to_degrees();
        assert!(err_deg < 0.05, "fused attitude {err_deg} deg off");
        assert!((m.dp_world_m - (b.c_world - a.c_world)).norm() < 0.2);
        // The rotation handed out is the images' own: the same with and without the prior.
        let alone = solve(&t, &a, 0.0, None, &dem).expect("motion");
        assert!(angle(&(m.r_prev_next.inverse() * alone.r_prev_next)) < 1e-9);
        assert!((m.cov_rot_prev_rad2 - alone.cov_rot_prev_rad2).amax() < 1e-15);
        // In the previous camera frame the images fix the rotation about the optical axis best.
        let c = m.cov_rot_prev_rad2;
        assert!(c[(2, 2)] < 0.5 * c[(0, 0)].min(c[(1, 1)]), "{c:?}");
    }

    #[test]
    fn a_tilt_sigma_scales_an_oblique_cameras_displacement_only() {
        let dem = Dem::flat(0.0).expect("flat");
        let g = |a: &Pose, b: &Pose| Some(gyro(a, b));
        let run = |tilt: f64, sigma: f64| {
            let a = camera(Vector3::new(0.0, 0.0, 500.0), 0.0, tilt);
            let b = camera(Vector3::new(0.0, 10.0, 500.0), 0.0, tilt);
            let t = tracks(&dem, &a, &b, 150, 0.2, 0.0, 12);
            let image = vga();
            let input = VoInput {
                tracks: &t,
                image: &image,
                prev: a,
                prev_height_sigma_m: 0.0,
                prev_tilt_sigma_rad: sigma,
                rotation_prior: g(&a, &b),
            };
            frame_motion(&input, &dem, &VoConfig::default()).expect("motion")
        };
        let sigma = 0.5f64.to_radians();
        let added = |tilt: f64| {
            (run(tilt, sigma).cov_dp_world_m2[(1, 1)] - run(tilt, 0.0).cov_dp_world_m2[(1, 1)])
                .sqrt()
        };
        // Nadir: nothing; 45 deg: 10 m x tan(45 deg) x 0.5 deg = 8.7 cm.
        assert!(added(0.0) < 1e-6, "{}", added(0.0));
        assert!(
            (added(45f64.to_radians()) - 0.0873).abs() < 0.003,
            "{}",
            added(45f64.to_radians())
        );
    }

    #[test]
    fn a_yaw_error_of_the_previous_pose_rotates_the_displacement_only() {
        // The property the fusion relies on (module doc): over flat ground the displacement comes
        // out rotated by the yaw error, the relative rotation unchanged.
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 400.0), 0.0, 0.0);
        let b = camera(Vector3::new(5.0, 0.0, 400.0), 0.0, 0.0);
        let t = tracks(&dem, &a, &b, 150, 0.0, 0.0, 3);
        let dyaw = 10f64.to_radians();
        let wrong = Pose {
            r_world_cam: Rotation3::from_axis_angle(&Vector3::z_axis(), dyaw) * a.r_world_cam,
            ..a
        };
        let m = solve(&t, &wrong, 0.0, None, &dem).expect("motion");
        let expected =
            Rotation3::from_axis_angle(&Vector3::z_axis(), dyaw) * (b.c_world - a.c_world);
        assert!(
            (m.dp_world_m - expected).norm() < 1e-3,
            "{:?}",
            m.dp_world_m
        );
        assert!(angle(&m.r_prev_next) < 1e-6);
    }

    #[test]
    fn the_height_sigma_scales_the_displacement_covariance() {
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 500.0), 0.0, 0.0);
        let b = camera(Vector3::new(0.0, 10.0, 500.0), 0.0, 0.0);
        let t = tracks(&dem, &a, &b, 150, 0.2, 0.0, 4);
        let g = Some(gyro(&a, &b));
        let m0 = solve(&t, &a, 0.0, g, &dem).expect("motion");
        let m1 = solve(&t, &a, 25.0, g, &dem).expect("motion");
        // 25 m of 500 m: 5 % of 10 m along the motion (north).
        let added = m1.cov_dp_world_m2[(1, 1)] - m0.cov_dp_world_m2[(1, 1)];
        assert!(
            (added.sqrt() - 0.5).abs() < 0.03,
            "added sigma {}",
            added.sqrt()
        );
        // A height error of that size scales the displacement by it.
        let high = Pose {
            c_world: a.c_world + Vector3::new(0.0, 0.0, 25.0),
            ..a
        };
        let m2 = solve(&t, &high, 0.0, g, &dem).expect("motion");
        let ratio = m2.dp_world_m.y / m0.dp_world_m.y;
        assert!((ratio - 1.05).abs() < 0.01, "ratio {ratio}");
    }

    #[test]
    fn no_texture_no_ground_no_consensus_give_reasons_not_motion() {
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 300.0), 0.0, 0.0);
        let b = camera(Vector3::new(2.0, 0.0, 300.0), 0.0, 0.0);
        let t = tracks(&dem, &a, &b, 5, 0.2, 0.0, 5);
        assert!(matches!(
            solve(&t, &a, 0.0, None, &dem),
            Err(VoRejection::TooFewTracks { tracks: 5, .. })
        ));
        // The camera looking at the sky: nothing on the ground.
        let up = camera(Vector3::new(0.0, 0.0, 300.0), 0.0, std::f64::consts::PI);
        let t = tracks(&dem, &a, &b, 50, 0.2, 0.0, 6);
        assert!(matches!(
            solve(&t, &up, 0.0, None, &dem),
            Err(VoRejection::TooFewOnGround { on_ground: 0, .. })
        ));
        // Random next positions: no consensus.
        let t = tracks(&dem, &a, &b, 60, 0.2, 1.0, 7);
        assert!(matches!(
            solve(&t, &a, 0.0, None, &dem),
            Err(VoRejection::Resection(_))
        ));
    }

    #[test]
    fn bad_numbers_are_refused() {
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 300.0), 0.0, 0.0);
        let b = camera(Vector3::new(2.0, 0.0, 300.0), 0.0, 0.0);
        let t = tracks(&dem, &a, &b, 50, 0.2, 0.0, 8);
        let nan_pose = Pose {
            c_world: Vector3::new(f64::NAN, 0.0, 300.0),
            ..a
        };
        assert!(matches!(
            solve(&t, &nan_pose, 0.0, None, &dem),
            Err(VoRejection::InvalidInput(_))
        ));
        assert!(matches!(
            solve(&t, &a, f64::NAN, None, &dem),
            Err(VoRejection::InvalidInput(_))
        ));
        let mut nan_tracks = t.clone();
        for p in nan_tracks.iter_mut().take(45) {
            p.next_px.x = f64::NAN;
        }
        assert!(matches!(
            solve(&nan_tracks, &a, 0.0, None, &dem),
            Err(VoRejection::TooFewOnGround { on_ground: 5, .. })
        ));
        let bad = VoConfig {
            track_sigma_px: 0.0,
            ..VoConfig::default()
        };
        let image = vga();
        let input = VoInput {
            tracks: &t,
            image: &image,
            prev: a,
            prev_height_sigma_m: 0.0,
            prev_tilt_sigma_rad: 0.0,
            rotation_prior: None,
        };
        assert!(matches!(
            frame_motion(&input, &dem, &bad),
            Err(VoRejection::InvalidInput(_))
        ));
    }

    /// Relief on a 1 m grid: flat ground at 100 m with crowns 6-16 m tall and 4-8 m across
    /// (half the ground covered, like a wood's edge), 600 x 600 m.
    fn canopy(seed: u64) -> Dem {
        let n = 600;
        let mut h = vec![100.0f32; n * n];
        let mut rng = Rng::new(seed);
        for _ in 0..9000 {
            let (cx, cy) = (rng.uniform() * n as f64, rng.uniform() * n as f64);
            let (r, top) = (2.0 + 2.0 * rng.uniform(), 6.0 + 10.0 * rng.uniform());
            let (x0, x1) = ((cx - r).max(0.0) as usize, ((cx + r) as usize).min(n - 1));
            let (y0, y1) = ((cy - r).max(0.0) as usize, ((cy + r) as usize).min(n - 1));
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let d2 = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / (r * r);
                    if d2 < 1.0 {
                        let c = &mut h[y * n + x];
                        *c = c.max((100.0 + top * (1.0 - d2).sqrt()) as f32);
                    }
                }
            }
        }
        grid_dem(n, h, -300.0, 300.0, 1.0)
    }

    /// The displacement's dependence on the gyros' rotation (what the filter's gyro-bias column
    /// of a motion rests on) is the resection's own, checked against re-solving with the
    /// gyros' rotation turned. High over flat ground the images tell a tilt from a shift least
    /// and the displacement follows the gyros most (towards the rays' lever arm, `[look x]`);
    /// 100 m over crowns the relief tells them apart better and it follows them less.
    #[test]
    fn the_displacement_follows_the_gyros_as_far_as_the_images_leave_it() {
        let turn = Vector3::new(0.04, -0.03, 0.0f64).map(f64::to_radians); // world frame
        let cases = [
            (
                "high over flat ground",
                Dem::flat(100.0).expect("flat"),
                1600.0,
                0.0,
            ),
            ("100 m over crowns", canopy(5), 200.0, 0.52),
        ];
        let mut ratio = Vec::new();
        for (name, dem, z, tilt) in cases {
            let a = camera(Vector3::new(-20.0, 10.0, z), 0.4, tilt);
            let b = camera(a.c_world + Vector3::new(1.6, 3.7, 0.1), 0.404, tilt + 0.005);
            let t = tracks(&dem, &a, &b, 250, 0.3, 0.0, 21);
            let g = RotationPrior {
                r_prev_next: a.r_world_cam.inverse() * b.r_world_cam,
                cov_prev_rad2: Matrix3::identity() * 0.03f64.to_radians().powi(2),
            };
            // The same rotation turned by `turn` in the world frame (on the left of the next
            // camera's attitude): `R_prev^T Exp(turn) R_prev R_prev_next`.
            let turned = RotationPrior {
                r_prev_next: a.r_world_cam.inverse()
                    * Rotation3::from_scaled_axis(turn)
                    * a.r_world_cam
                    * g.r_prev_next,
                ..g
            };
            let m0 = solve(&t, &a, 0.0, Some(g), &dem).expect("motion");
            let m1 = solve(&t, &a, 0.0, Some(turned), &dem).expect("motion");
            let seen = m1.dp_world_m - m0.dp_world_m;
            let model = m0.rotation_sensitivity_world.expect("with the gyros") * turn;
            let lever = m0.look_world_m.cross(&turn);
            eprintln!(
                "{name}: moved {:.4?} m, model {:.4?}, lever arm {:.4?}",
                seen.as_slice(),
                model.as_slice(),
                lever.as_slice()
            );
            assert!(
                (seen - model).norm() < 0.15 * seen.norm() + 2e-4,
                "{name}: moved {seen:?}, model {model:?}"
            );
            ratio.push(model.norm() / lever.norm());
        }
        // Measured: 0.65 and 0.48 of the lever arm with a 0.03 deg gyro sigma; the lever arm
        // alone would have put a third more of every motion's error into the gyro bias over the
        // crowns.
        assert!(ratio[1] < 0.6, "crowns: {ratio:?} of the lever arm");
        assert!(ratio[1] < ratio[0], "{ratio:?} of the lever arm");
    }

    #[test]
    fn a_camera_that_did_not_move_gives_zero_motion_with_a_sigma() {
        let dem = Dem::flat(0.0).expect("flat");
        let a = camera(Vector3::new(0.0, 0.0, 300.0), 0.5, 0.0);
        let t = tracks(&dem, &a, &a, 100, 0.2, 0.0, 9);
        let m = solve(&t, &a, 1.0, Some(gyro(&a, &a)), &dem).expect("motion");
        assert!(m.dp_world_m.norm() < 0.05, "{:?}", m.dp_world_m);
        assert!(m.cov_dp_world_m2[(0, 0)] > 0.0);
    }
}
