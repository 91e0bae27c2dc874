//! The odometer: visual odometry on a camera's frame sequence against a map's terrain, each
//! frame's motion turned into the navigation filter's measurement ([`VoFix`], NED).
//!
//! Per frame, with the navigation filter's pose at its capture time (a [`FixPrior`] with
//! position and attitude, as the absolute fix gets):
//! 1. the pose in the map frame (grid x east, y north, height AMSL; `R_map_cam = Rz(gamma)
//!    R_enu_ned R_ned_cam`, gamma the grid convergence, as the fix engine's rectification);
//! 2. the live features followed from the previous frame ([`super::tracker`]), each one's guess
//!    its previous ray cast onto the plane of the ground below and projected from this frame's
//!    prior pose (the filter's rotation and motion between the frames: tens of pixels at camera
//!    rate become a fraction of one);
//! 3. the pairs undistorted and solved by [`super::frame_motion`] from the previous frame's pose,
//!    with the caller's [`GyroDelta`] (the body's rotation between the frames as the gyros
//!    measured it, without the filter's corrections in between) as the [`RotationPrior`];
//! 4. the displacement from the map grid to NED: grid convergence removed, horizontal grid metres
//!    divided by the projection's point scale factor;
//! 5. with a [`GyroDelta`], the images' relative rotation against the gyros' about the mean line
//!    of sight ([`VoRotation`]: the one axis the images fix on their own; the filter fuses it
//!    as the gyro bias along that axis).
//!
//! The previous frame's height sigma is not passed to the motion's covariance: the filter carries
//! its own height error as a state ([`VoFix`]); the terrain model's is [`VoFix::terrain_sigma_m`]
//! (the map's [`Reference::height_sigma_m`]), correlated over
//! [`VoConfig::terrain_error_corr_dist_m`].
//!
//! A frame without a usable prior, or more than [`VO_MAX_SPAN_S`] after the previous one,
//! restarts the sequence; a frame whose motion is refused still becomes the previous frame (its
//! tracks are followed on), so one bad frame costs two measurements, not the sequence.

use std::sync::Arc;

use nalgebra::{Matrix3, Point2, Rotation3, Vector2, Vector3};

use super::tracker::{RawTrack, Tracker};
use super::{FrameMotion, RotationPrior, TrackPair, VoConfig, VoInput, VoRejection, frame_motion};
use crate::camera::Camera;
use crate::camera::frames::{r_enu_ned, rot_z};
use crate::fix::{FixPrior, Reference};
use crate::nav::{VO_MAX_SPAN_S, VoFix, VoRotation};
use crate::pose::{ImageGeometry, Pose};
use crate::vision::GrayImage;

/// The body's rotation between the previous frame and this one as the gyros measured it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GyroDelta {
    /// `R_b0_b1`: vectors of the body at this frame into the body at the previous one.
    pub r_body_prev_next: Rotation3<f64>,
    /// 1-sigma of its error per axis (the gyros' noise and residual bias over the interval), rad.
    pub sigma_rad: f64,
    /// The part of `sigma_rad` that is not the gyros' bias: what integrating sampled rates leaves
    /// unknown (a turn's onset between two samples), rad. The rotation measurement
    /// ([`VoRotation`]) carries it as noise; the bias is the filter's state.
    pub sampling_sigma_rad: f64,
}

/// What one frame gave.
#[derive(Debug, Clone, PartialEq)]
pub enum VoStep {
    /// The first frame of a sequence (features detected, no motion yet).
    Started,
    /// The motion since the previous frame.
    Motion(Box<VoMotion>),
    /// No motion from this frame, and why.
    Refused(VoRefusal),
}

/// Why a frame gave no motion: a typed outcome with its numbers as fields; people read its
/// `Display`, counters count its [`VoRefusal::class`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VoRefusal {
    /// The frame's pose prior is unusable.
    #[error("{0}")]
    Prior(VoRejection),
    /// The frame is not after the previous one (the sequence restarts).
    #[error("frame at {t_us} us is not after the previous one ({prev_us} us)")]
    NotAfter {
        /// This frame's capture time (the prior's `t_capture_us`), us.
        t_us: u64,
        /// The previous frame's capture time, us.
        prev_us: u64,
    },
    /// Too long since the previous frame (the sequence restarts).
    #[error("{span_s:.2} s since the previous frame (at most {max_s} s)")]
    Gap {
        /// Time since the previous frame, s.
        span_s: f64,
        /// The longest span a motion may cover (`nav::VO_MAX_SPAN_S`), s.
        max_s: f64,
    },
    /// The frame could not be prepared for tracking (its message).
    #[error("frame: {0}")]
    Frame(String),
    /// The tracker failed (its message).
    #[error("tracking: {0}")]
    Tracking(String),
    /// The motion's solve refused.
    #[error("{0}")]
    Motion(VoRejection),
    /// The odometer panicked (the daemon's worker caught it).
    #[error("odometer panicked")]
    Panicked,
}

/// Every value [`VoRefusal::class`] returns besides the resection's
/// ([`crate::fix::rejection::CLASSES`]' `pose_*`).
pub const VO_CLASSES: &[&str] = &[
    "invalid_input",
    "few_tracks",
    "few_on_ground",
    "too_uncertain",
    "time_not_after",
    "time_gap",
    "bad_frame",
    "tracking",
    "internal",
];

impl VoRefusal {
    /// The class for counting and metric labels: a name without numbers.
    pub fn class(&self) -> &'static str {
        match self {
            VoRefusal::Prior(r) | VoRefusal::Motion(r) => r.class(),
            VoRefusal::NotAfter { .. } => "time_not_after",
            VoRefusal::Gap { .. } => "time_gap",
            VoRefusal::Frame(_) => "bad_frame",
            VoRefusal::Tracking(_) => "tracking",
            VoRefusal::Panicked => "internal",
        }
    }
}

/// A frame's motion as the filter's measurement, with the numbers behind it.
#[derive(Debug, Clone, PartialEq)]
pub struct VoMotion {
    /// The displacement (NED) and rotation between the two capture times, for the filter.
    pub fix: VoFix,
    /// Tracks followed into this frame.
    pub tracks: usize,
    /// Tracks whose previous-frame ray met the terrain.
    pub on_ground: usize,
    /// Inliers of the resection.
    pub inliers: usize,
    /// Reprojection RMS of the inliers, px.
    pub rms_px: f64,
}

/// The previous frame as the odometer keeps it.
#[derive(Debug, Clone, Copy)]
struct PrevFrame {
    t_us: u64,
    pose: Pose,
    tilt_sigma_rad: f64,
    /// Grid convergence at the camera, rad.
    gamma_rad: f64,
    /// Height of the ground below, AMSL, m (the guesses' plane).
    ground_amsl_m: f64,
}

/// A frame's pose from its prior (also the DTM navigator's, `crate::dtm_nav::navigator`).
#[derive(Debug, Clone, Copy)]
pub(crate) struct FramePose {
    pub(crate) pose: Pose,
    pub(crate) tilt_sigma_rad: f64,
    /// Grid convergence (rad) and point scale factor at the camera.
    pub(crate) gamma_rad: f64,
    pub(crate) scale: f64,
}

/// Visual odometry over a frame sequence (module doc).
pub struct Odometer {
    camera: Camera,
    reference: Arc<dyn Reference>,
    cfg: VoConfig,
    tracker: Tracker,
    prev: Option<PrevFrame>,
}

impl Odometer {
    /// An odometer for `camera` over `reference`'s terrain.
    pub fn new(camera: Camera, reference: Arc<dyn Reference>, cfg: VoConfig) -> Self {
        let tracker = Tracker::new(cfg.tracking.clone());
        Self {
            camera,
            reference,
            cfg,
            tracker,
            prev: None,
        }
    }

    /// Forget the sequence (the next frame starts a new one).
    pub fn reset(&mut self) {
        self.tracker.reset();
        self.prev = None;
    }

    /// One frame with the filter's pose at its capture time (`prior`) and the gyros' rotation
    /// since the previous frame (`None`: the images alone give the rotation).
    pub fn frame(&mut self, image: GrayImage, prior: &FixPrior, gyro: Option<GyroDelta>) -> VoStep {
        let fp = match self.frame_pose(prior) {
            Ok(p) => p,
            Err(why) => {
                self.reset();
                return VoStep::Refused(VoRefusal::Prior(why));
            }
        };
        let t_us = prior.t_capture_us;
        let restart = match self.prev {
            None => Some(None),
            Some(p) if t_us <= p.t_us => Some(Some(VoRefusal::NotAfter {
                t_us,
                prev_us: p.t_us,
            })),
            Some(p) if (t_us - p.t_us) as f64 * 1e-6 > VO_MAX_SPAN_S => {
                Some(Some(VoRefusal::Gap {
                    span_s: (t_us - p.t_us) as f64 * 1e-6,
                    max_s: VO_MAX_SPAN_S,
                }))
            }
            Some(_) => None,
        };
        if restart.is_some() {
            self.tracker.reset();
        }
        let pyr = match self.tracker.pyramid(image) {
            Ok(p) => p,
            Err(e) => {
                self.reset();
                return VoStep::Refused(VoRefusal::Frame(e.to_string()));
            }
        };
        let prev = self.prev;
        let camera = &self.camera;
        let predict = |p: [f32; 2]| match prev {
            Some(pv) => predict(camera, &pv, &fp.pose, p).unwrap_or(p),
            None => p,
        };
        let pairs = match self.tracker.advance(pyr, predict) {
            Ok(p) => p,
            Err(e) => {
                self.reset();
                return VoStep::Refused(VoRefusal::Tracking(e.to_string()));
            }
        };
        let ground_amsl_m = self.ground_below(&fp.pose);
        self.prev = Some(PrevFrame {
            t_us,
            pose: fp.pose,
            tilt_sigma_rad: fp.tilt_sigma_rad,
            gamma_rad: fp.gamma_rad,
            ground_amsl_m,
        });
        match (restart, prev, pairs) {
            (Some(Some(why)), _, _) => VoStep::Refused(why),
            (None, Some(pv), Some(pairs)) => self.motion(&pv, &fp, t_us, &pairs, gyro),
            _ => VoStep::Started,
        }
    }

    fn frame_pose(&self, prior: &FixPrior) -> Result<FramePose, VoRejection> {
        frame_pose(&self.camera, self.reference.as_ref(), prior)
    }

    fn ground_below(&self, pose: &Pose) -> f64 {
        ground_below(&self.reference.dem(), pose)
    }

    /// The motion from the previous frame to this one as the filter's measurement.
    fn motion(
        &self,
        prev: &PrevFrame,
        next: &FramePose,
        t_us: u64,
        pairs: &[RawTrack],
        gyro: Option<GyroDelta>,
    ) -> VoStep {
        let tracks: Vec<TrackPair> = pairs.iter().filter_map(|t| self.undistort(t)).collect();
        let image = ImageGeometry::from(&self.camera.intrinsics);
        // The body's rotation in camera axes: `R_c0_c1 = R_bc^T R_b0_b1 R_bc`.
        let r_body_cam = self
            .camera
            .mount
            .r_ned_cam(&crate::camera::frames::Attitude::new(0.0, 0.0, 0.0));
        let rotation_prior = gyro.map(|g| {
            let r = camera_rotation_in_grid(
                &g.r_body_prev_next,
                &r_body_cam,
                &prev.pose.r_world_cam,
                next.gamma_rad - prev.gamma_rad,
            );
            RotationPrior {
                r_prev_next: r,
                cov_prev_rad2: Matrix3::identity() * g.sigma_rad.powi(2),
            }
        });
        let input = VoInput {
            tracks: &tracks,
            image: &image,
            prev: prev.pose,
            prev_height_sigma_m: 0.0,
            prev_tilt_sigma_rad: prev.tilt_sigma_rad,
            rotation_prior,
        };
        let m = match frame_motion(&input, &self.reference.dem(), &self.cfg) {
            Ok(m) => m,
            Err(e) => return VoStep::Refused(VoRefusal::Motion(e)),
        };
        let rotation = rotation_prior
            .zip(gyro)
            .and_then(|(r, g)| rotation_about_los(&m, &r, &prev.pose, g.sampling_sigma_rad));
        // Map grid to NED: v_map = Rz(gamma) v_enu; horizontal grid metres are `scale` true ones.
        let unscale =
            Matrix3::from_diagonal(&Vector3::new(1.0 / next.scale, 1.0 / next.scale, 1.0));
        let r: Matrix3<f64> =
            r_enu_ned().inverse().matrix() * unscale * rot_z(-next.gamma_rad).matrix();
        // A NED rotation vector `e` on the next camera is `M e` in the grid (`R_world_cam =
        // M R_ned_cam`, `M = Rz(gamma) R_enu_ned`), and moves the grid displacement by `G M e`.
        let m_world_ned: Matrix3<f64> = (rot_z(next.gamma_rad) * r_enu_ned()).into_inner();
        let fix = VoFix {
            t_prev_us: prev.t_us,
            t_next_us: t_us,
            dp_ned_m: r * m.dp_world_m,
            cov_ned_m2: r * m.cov_dp_world_m2 * r.transpose(),
            agl_m: m.agl_m,
            terrain_sigma_m: self.reference.height_sigma_m(),
            terrain_corr_dist_m: self.cfg.terrain_error_corr_dist_m,
            look_ned_m: r * m.look_world_m,
            rotation,
            rotation_sensitivity_ned: m
                .rotation_sensitivity_world
                .map(|g| r * g * m_world_ned)
                .filter(|g| g.iter().all(|v| v.is_finite())),
        };
        let fix = VoFix {
            cov_ned_m2: 0.5 * (fix.cov_ned_m2 + fix.cov_ned_m2.transpose()),
            ..fix
        };
        VoStep::Motion(Box::new(VoMotion {
            fix,
            tracks: m.tracks,
            on_ground: m.on_ground,
            inliers: m.inliers,
            rms_px: m.rms_px,
        }))
    }

    /// A raw track in undistorted pixels (`None` where the distortion cannot be inverted).
    fn undistort(&self, t: &RawTrack) -> Option<TrackPair> {
        Some(TrackPair {
            prev_px: undistorted_px(&self.camera, t.prev_px)?,
            next_px: undistorted_px(&self.camera, t.next_px)?,
        })
    }
}

/// A pixel of `camera` where the distortion-free camera with the same intrinsics sees it
/// (`None` where the distortion cannot be inverted).
pub(crate) fn undistorted_px(camera: &Camera, px: [f32; 2]) -> Option<Vector2<f64>> {
    let k = &camera.intrinsics;
    let ray = camera.unproject(&Point2::new(f64::from(px[0]), f64::from(px[1])))?;
    let n = ray.xy() / ray.z;
    Some(Vector2::new(
        k.cx_px + k.fx_px * n.x,
        k.cy_px + k.fy_px * n.y,
    ))
}

/// The camera's rotation between two frames in the map grid (`R_world_prev^T R_world_next`) from
/// the body's over the local level frame (`r_body_prev_next`, the gyros'), the mount
/// (`r_body_cam`) and the change of the grid convergence `dgamma_rad`: the grid's north turns
/// against the local level frame as the aircraft moves (`R_world_k = Rz(gamma_k) R_enu_ned
/// R_ned_cam`), so `R_world_prev^T Rz(dgamma) R_world_prev = Exp(dgamma R_world_prev^T e_z)`
/// goes on the left: 0.9 deg/h at 25 m/s east at 47 deg, the transport rate's vertical part.
fn camera_rotation_in_grid(
    r_body_prev_next: &Rotation3<f64>,
    r_body_cam: &Rotation3<f64>,
    r_world_prev_cam: &Rotation3<f64>,
    dgamma_rad: f64,
) -> Rotation3<f64> {
    let up_prev = r_world_prev_cam.inverse() * Vector3::z();
    let grid_turn = Rotation3::from_scaled_axis(up_prev * dgamma_rad);
    let mut r = grid_turn * r_body_cam.inverse() * r_body_prev_next * r_body_cam;
    r.renormalize();
    r
}

/// The images' rotation between the frames against the gyros', about the mean line of sight
/// ([`VoRotation`]), from the image-only relative rotation and its covariance, its sigma with the
/// gyros' sampling error (`sampling_sigma_rad`) added; `None` when not finite. Both relative rotations are in the previous camera frame with the images' error on
/// the left (`R_images = Exp(psi) R_gyros`); the previous camera's attitude takes `psi` and its
/// covariance to the world frame, where the line of sight is. The angle about an axis is the
/// same in the map frame and in NED (a proper rotation between them; the projection's scale
/// changes the axis by a part in 10^4).
fn rotation_about_los(
    m: &FrameMotion,
    gyro: &RotationPrior,
    prev: &Pose,
    sampling_sigma_rad: f64,
) -> Option<VoRotation> {
    let psi_prev = (m.r_prev_next * gyro.r_prev_next.inverse()).scaled_axis();
    let r_wp = prev.r_world_cam.matrix();
    let u = m.look_world_m.try_normalize(1e-9)?;
    let about_los_rad = u.dot(&(r_wp * psi_prev));
    let var = (u.transpose() * r_wp * m.cov_rot_prev_rad2 * r_wp.transpose() * u)[(0, 0)];
    let sigma_rad = var.max(0.0).sqrt().hypot(sampling_sigma_rad);
    (about_los_rad.is_finite() && sigma_rad.is_finite() && sigma_rad > 0.0).then_some(VoRotation {
        about_los_rad,
        sigma_rad,
    })
}

/// The frame's camera pose in the map frame from its prior.
pub(crate) fn frame_pose(
    camera: &Camera,
    reference: &dyn Reference,
    prior: &FixPrior,
) -> Result<FramePose, VoRejection> {
    let invalid = |s: String| VoRejection::InvalidInput(s);
    let (Some(pos), Some(att)) = (&prior.position, &prior.attitude) else {
        return Err(invalid(
            "no pose prior (the filter is not initialised, or lost)".into(),
        ));
    };
    let crs = reference.crs();
    let geo = |e: crate::geo::GeoError| invalid(format!("prior position: {e}"));
    let (x, y) = crs.from_geodetic(pos.lat_deg, pos.lon_deg).map_err(geo)?;
    let gamma_rad = crs
        .grid_convergence_deg(pos.lat_deg, pos.lon_deg)
        .map_err(geo)?
        .to_radians();
    let scale = crs
        .point_scale_factor(pos.lat_deg, pos.lon_deg)
        .map_err(geo)?;
    let r = rot_z(gamma_rad) * r_enu_ned() * camera.mount.r_ned_cam(&att.attitude);
    let pose = Pose {
        r_world_cam: r,
        c_world: Vector3::new(x, y, pos.alt_amsl_m),
    };
    let finite = pose.c_world.iter().all(|v| v.is_finite())
        && [gamma_rad, scale, att.sigma_rad]
            .iter()
            .all(|v| v.is_finite())
        && scale > 0.0;
    if !finite {
        return Err(invalid("prior pose is not finite".into()));
    }
    Ok(FramePose {
        pose,
        tilt_sigma_rad: att.sigma_rad.clamp(0.0, 1.0),
        gamma_rad,
        scale,
    })
}

/// Height AMSL of the ground below the camera (the DEM along the optical axis, or straight
/// down, or the DEM's middle height).
pub(crate) fn ground_below(dem: &crate::geo::dem::Dem, pose: &Pose) -> f64 {
    let c = pose.c_world;
    let axis = pose.r_world_cam * Vector3::z();
    if let Some(p) = dem.intersect_ray([c.x, c.y, c.z], [axis.x, axis.y, axis.z], 1e6) {
        return p[2];
    }
    if let Some(h) = dem.height_at(c.x, c.y) {
        return h;
    }
    let (lo, hi) = dem.height_range_m();
    0.5 * (lo + hi)
}

/// Where a feature of the previous frame should appear in this one: its ray cast onto the
/// horizontal plane of the ground below the previous frame, projected from this frame's prior
/// pose. `None` when the ray misses the plane or the point is behind the camera.
fn predict(camera: &Camera, prev: &PrevFrame, next: &Pose, px: [f32; 2]) -> Option<[f32; 2]> {
    let p = Point2::new(f64::from(px[0]), f64::from(px[1]));
    let ray = prev.pose.r_world_cam * camera.unproject(&p)?.into_inner();
    let c = prev.pose.c_world;
    if ray.z >= -1e-6 {
        return None;
    }
    let s = (prev.ground_amsl_m - c.z) / ray.z;
    let ground = c + ray * s;
    let q = camera.project(&next.to_cam(&ground))?;
    let out = [q.x as f32, q.y as f32];
    out.iter().all(|v| v.is_finite()).then_some(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::camera::frames::Attitude;
    use crate::fix::engine::tests::checkerboard_engine;
    use crate::fix::{AttitudePriorNed, PositionPriorGeo};
    use crate::geo::Crs;
    use crate::nav::earth::ned_offset_m;

    /// Every refusal's class is a name of the closed set (the resection's `pose_*` from the
    /// fix's), without a number.
    #[test]
    fn refusal_classes_are_a_closed_set() {
        let all = [
            VoRefusal::Prior(VoRejection::InvalidInput("no pose prior".into())),
            VoRefusal::NotAfter {
                t_us: 1,
                prev_us: 2,
            },
            VoRefusal::Gap {
                span_s: 2.5,
                max_s: 2.0,
            },
            VoRefusal::Frame("blank".into()),
            VoRefusal::Tracking("x".into()),
            VoRefusal::Motion(VoRejection::TooFewTracks { tracks: 3, min: 8 }),
            VoRefusal::Motion(VoRejection::TooFewOnGround {
                on_ground: 3,
                tracks: 9,
                min: 8,
            }),
            VoRefusal::Motion(VoRejection::Resection(crate::pose::Rejection::Sigma0 {
                sigma0: 3.0,
                max: 2.0,
            })),
            VoRefusal::Motion(VoRejection::TooUncertain {
                sigma_m: 9.0,
                agl_m: 50.0,
                max_fraction: 0.1,
            }),
            VoRefusal::Panicked,
        ];
        for r in all {
            let c = r.class();
            let pose = c.starts_with("pose_") && crate::fix::rejection::CLASSES.contains(&c);
            assert!(VO_CLASSES.contains(&c) || pose, "{c}: {r}");
            assert!(!c.chars().any(|ch| ch.is_ascii_digit()), "{c}");
        }
    }

    /// Flat ground of the checkerboard engine, m AMSL.
    const GROUND_M: f64 = 300.0;

    /// A texture KLT can follow: value noise on a 3 m lattice plus two sines (no repetition over a
    /// footprint), grey levels 20-235.
    fn texture(x: f64, y: f64) -> f32 {
        let hash = |i: i64, j: i64| -> f64 {
            let h = (i.wrapping_mul(73_856_093) ^ j.wrapping_mul(19_349_663)) as u64;
            let h = h.wrapping_mul(0x9E37_79B9_7F4A_7C15);
            (h >> 40) as f64 / (1u64 << 24) as f64
        };
        let (gx, gy) = (x / 3.0, y / 3.0);
        let (i, j) = (gx.floor() as i64, gy.floor() as i64);
        let (fx, fy) = (gx - gx.floor(), gy - gy.floor());
        let n = hash(i, j) * (1.0 - fx) * (1.0 - fy)
            + hash(i + 1, j) * fx * (1.0 - fy)
            + hash(i, j + 1) * (1.0 - fx) * fy
            + hash(i + 1, j + 1) * fx * fy;
        (20.0 + 150.0 * n + 30.0 * (1.0 + (x / 17.0).sin() * (y / 23.0).cos())) as f32
    }

    /// The frame a camera at map position `c` (height AMSL) with `att` sees of the textured flat
    /// ground (rendered from the same convention the odometer uses, not from its code).
    pub(crate) fn render(
        camera: &Camera,
        crs: &Crs,
        c: Vector3<f64>,
        att: &Attitude,
        lat: f64,
        lon: f64,
    ) -> GrayImage {
        let gamma = crs.grid_convergence_deg(lat, lon).unwrap().to_radians();
        let r = rot_z(gamma) * r_enu_ned() * camera.mount.r_ned_cam(att);
        let (w, h) = (camera.width_px() as usize, camera.height_px() as usize);
        GrayImage::from_fn(w, h, |u, v| {
            let ray = r * camera
                .unproject(&Point2::new(u as f64, v as f64))
                .unwrap()
                .into_inner();
            let s = (GROUND_M - c.z) / ray.z;
            texture(c.x + s * ray.x, c.y + s * ray.y)
        })
    }

    /// Map position of the flight at frame `k` (0.2 s apart): 20 m/s on grid bearing 30 deg,
    /// 300 m above the ground, 200 km west of the zone's central meridian (grid convergence
    /// about -1.9 deg, point scale factor 1.0001).
    fn at(k: usize) -> Vector3<f64> {
        let d = 4.0 * k as f64;
        Vector3::new(
            300_640.0 + d * 0.5,
            5_199_360.0 + d * 0.866,
            GROUND_M + 300.0,
        )
    }

    pub(crate) fn prior(crs: &Crs, c: Vector3<f64>, att: Attitude, t_us: u64) -> FixPrior {
        let (lat, lon) = crs.to_geodetic(c.x, c.y).unwrap();
        FixPrior {
            t_capture_us: t_us,
            position: Some(PositionPriorGeo {
                lat_deg: lat,
                lon_deg: lon,
                alt_amsl_m: c.z,
                sigma_h_m: 5.0,
                sigma_v_m: 2.0,
            }),
            altitude: None,
            attitude: Some(AttitudePriorNed {
                attitude: att,
                sigma_rad: 1e-3,
                sigma_yaw_rad: 1e-2,
            }),
            attitude_from_filter: true,
            widen_heading: false,
        }
    }

    /// The true NED displacement between frames `a` and `b`.
    fn truth_ned(crs: &Crs, a: Vector3<f64>, b: Vector3<f64>) -> Vector3<f64> {
        let (la, oa) = crs.to_geodetic(a.x, a.y).unwrap();
        let (lb, ob) = crs.to_geodetic(b.x, b.y).unwrap();
        ned_offset_m(
            (lb.to_radians(), ob.to_radians(), b.z),
            (la.to_radians(), oa.to_radians(), a.z),
        )
    }

    /// Flies the sequence with the prior's heading off by `yaw_err_deg` (the truth's heading is
    /// the grid bearing plus the convergence); returns the steps and the true displacements.
    fn fly(yaw_err_deg: f64, frames: usize) -> (Vec<VoStep>, Vec<Vector3<f64>>) {
        fly_path(yaw_err_deg, frames, at, 0.4, Vector3::zeros())
    }

    /// Straight up from 300 m above the ground at 50 m per frame (a copter's climb at 8 m/s
    /// filmed at 2 Hz, sped up: the height more than quadruples in 20 frames), heading fixed.
    fn climb(k: usize) -> Vector3<f64> {
        Vector3::new(300_640.0, 5_199_360.0, GROUND_M + 300.0 + 50.0 * k as f64)
    }

    fn fly_path(
        yaw_err_deg: f64,
        frames: usize,
        at: fn(usize) -> Vector3<f64>,
        yaw_rate_deg_per_frame: f64,
        gyro_bias_err_rad_s: Vector3<f64>,
    ) -> (Vec<VoStep>, Vec<Vector3<f64>>) {
        let (engine, crs) = checkerboard_engine();
        let camera = *engine.camera();
        let cfg = VoConfig {
            enabled: true,
            ..VoConfig::default()
        };
        let mut odo = Odometer::new(camera, engine.reference().clone(), cfg);
        let (mut steps, mut truth) = (Vec::new(), Vec::new());
        let mut last: Option<Rotation3<f64>> = None;
        for k in 0..frames {
            let c = at(k);
            let (lat, lon) = crs.to_geodetic(c.x, c.y).unwrap();
            let gamma = crs.grid_convergence_deg(lat, lon).unwrap();
            let att =
                Attitude::from_deg(0.5, -0.3, 30.0 - gamma + yaw_rate_deg_per_frame * k as f64);
            let img = render(&camera, &crs, c, &att, lat, lon);
            let seen = Attitude {
                yaw_rad: att.yaw_rad + yaw_err_deg.to_radians(),
                ..att
            };
            let r_nb = att.r_ned_body();
            // Rates compensated with a bias estimate off by `gyro_bias_err_rad_s` (estimate
            // minus truth): the integrated rotation is short of the truth by it over the 0.2 s.
            let bias_turn = Rotation3::from_scaled_axis(-gyro_bias_err_rad_s * 0.2);
            let gyro = last.map(|l| GyroDelta {
                r_body_prev_next: l.inverse() * r_nb * bias_turn,
                sigma_rad: 1e-4,
                sampling_sigma_rad: 0.0,
            });
            last = Some(r_nb);
            steps.push(odo.frame(img, &prior(&crs, c, seen, 200_000 * k as u64), gyro));
            if k > 0 {
                truth.push(truth_ned(&crs, at(k - 1), c));
            }
        }
        (steps, truth)
    }

    fn motions(steps: &[VoStep]) -> Vec<VoMotion> {
        steps
            .iter()
            .filter_map(|s| match s {
                VoStep::Motion(m) => Some((**m).clone()),
                _ => None,
            })
            .collect()
    }

    /// Frame to frame on textured flat ground: the NED displacement of each pair within a few
    /// centimetres and inside 3 sigma; the first frame starts the sequence.
    #[test]
    fn displacements_in_ned_match_the_flight() {
        let (steps, truth) = fly(0.0, 6);
        assert_eq!(steps[0], VoStep::Started);
        let m = motions(&steps[1..]);
        assert_eq!(m.len(), 5, "{steps:?}");
        for (m, t) in m.iter().zip(&truth) {
            let e = m.fix.dp_ned_m - t;
            let sig = m.fix.cov_ned_m2.diagonal().map(f64::sqrt);
            eprintln!(
                "error {:.3?} m, sigma {:.3?} m",
                e.as_slice(),
                sig.as_slice()
            );
            assert!(e.norm() < 0.1, "error {e:?} of {t:?} (sigma {sig:?})");
            assert!(m.inliers > 100, "{}", m.inliers);
            assert!((m.fix.agl_m - 300.0).abs() < 1.0, "{}", m.fix.agl_m);
            let nis = e.dot(&(m.fix.cov_ned_m2.try_inverse().unwrap() * e));
            assert!(nis < 3.0 * 3.0 * 3.0, "nis {nis}");
            assert_eq!(m.fix.t_next_us - m.fix.t_prev_us, 200_000);
        }
    }

    /// A vertical climb: every feature moves towards the image centre and none is lost; the
    /// tracker tops up the edges as they empty, so every motion is measured (straight up), not
    /// refused for the inliers' spread once the height has doubled (ArduCopter SITL: 323 of 451
    /// frames of a climb from 500 to 1800 m were, before).
    #[test]
    fn a_vertical_climb_is_measured() {
        let (steps, truth) = fly_path(0.0, 21, climb, 0.0, Vector3::zeros());
        let m = motions(&steps[1..]);
        assert_eq!(m.len(), 20, "{steps:?}");
        for (m, t) in m.iter().zip(&truth) {
            let e = m.fix.dp_ned_m - t;
            let nis = e.dot(&(m.fix.cov_ned_m2.try_inverse().unwrap() * e));
            eprintln!(
                "AGL {:.0} m: {} tracks, error {:.3?} m, NIS {nis:.2}",
                m.fix.agl_m,
                m.tracks,
                e.as_slice()
            );
            assert!(e.norm() < 1e-3 * m.fix.agl_m, "error {e:?} of {t:?}");
            assert!(nis < 3.0 * 3.0 * 3.0, "nis {nis}");
            assert!(m.inliers > 100, "{}", m.inliers);
        }
    }

    /// The gyro-bias column of the filter (`nav::filter::fuse_vo`) rests on this: a bias error
    /// of the rates the rotation prior was integrated from moves the displacement by
    /// `VoFix::gyro_rotation_sensitivity` times the rotation error it makes, `-C_b^n dbg dt`.
    #[test]
    fn a_gyro_bias_error_moves_the_displacement_as_the_filter_models_it() {
        let db = Vector3::new(2e-3, -1.5e-3, 1e-3); // rad/s, body: 0.02-0.05 deg per frame
        let (clean, _) = fly_path(0.0, 4, at, 0.4, Vector3::zeros());
        let (biased, _) = fly_path(0.0, 4, at, 0.4, db);
        let (_, crs) = checkerboard_engine();
        for (k, (a, b)) in motions(&clean)
            .iter()
            .zip(motions(&biased).iter())
            .enumerate()
        {
            let att = {
                let c = at(k + 1);
                let (lat, lon) = crs.to_geodetic(c.x, c.y).unwrap();
                let gamma = crs.grid_convergence_deg(lat, lon).unwrap();
                Attitude::from_deg(0.5, -0.3, 30.0 - gamma + 0.4 * (k + 1) as f64)
            };
            let c_bn = att.r_ned_body();
            let e_rot = -(c_bn * db) * 0.2;
            let model = b.fix.gyro_rotation_sensitivity() * e_rot;
            let seen = b.fix.dp_ned_m - a.fix.dp_ned_m;
            eprintln!(
                "look {:.1?} m: displacement moved {:.3?} m, model {:.3?} m",
                b.fix.look_ned_m.as_slice(),
                seen.as_slice(),
                model.as_slice()
            );
            assert!(
                (seen - model).norm() < 0.2 * model.norm(),
                "moved {seen:?}, model {model:?}"
            );
            assert!(
                (b.fix.look_ned_m.z - 300.0).abs() < 10.0,
                "{:?}",
                b.fix.look_ned_m
            );
            // The rotation measurement (`VoRotation`) sees the same error about the line of
            // sight, with the sign the filter's row uses: `R_images = Exp(a u) R_gyros`,
            // `R_gyros = Exp(e_rot) R_true`, so `a = -u . e_rot`.
            let u = b.fix.look_ned_m.normalize();
            let rot_model = -u.dot(&e_rot);
            let (ra, rb) = (a.fix.rotation.unwrap(), b.fix.rotation.unwrap());
            let rot_seen = rb.about_los_rad - ra.about_los_rad;
            eprintln!(
                "about the line of sight: {:.5} deg, model {:.5} deg (sigma {:.5} deg)",
                rot_seen.to_degrees(),
                rot_model.to_degrees(),
                rb.sigma_rad.to_degrees()
            );
            // The same images: the difference is the gyros' alone, to first order exact.
            assert!(
                (rot_seen - rot_model).abs() < 0.02 * rot_model.abs(),
                "seen {rot_seen}, model {rot_model}"
            );
            assert!(ra.about_los_rad.abs() < 3.0 * ra.sigma_rad, "{ra:?}");
        }
    }

    /// The gyros' rotation over the local level frame, put into the map grid, is exactly the
    /// grid's relative camera rotation of two frames whose grid convergence differs (the
    /// odometer's frame poses: `Rz(gamma) R_enu_ned R_ned_cam`).
    #[test]
    fn the_gyros_rotation_goes_into_the_grid_with_the_convergence() {
        let camera = *checkerboard_engine().0.camera();
        let mount = camera.mount;
        let r_body_cam = mount.r_ned_cam(&Attitude::new(0.0, 0.0, 0.0));
        let (a0, a1) = (
            Attitude::from_deg(3.0, -2.0, 40.0),
            Attitude::from_deg(-1.0, 4.0, 47.0),
        );
        let (g0, g1) = (0.012, 0.0135); // rad: 1.5 mrad of convergence change
        let world = |a: &Attitude, g: f64| rot_z(g) * r_enu_ned() * mount.r_ned_cam(a);
        let (w0, w1) = (world(&a0, g0), world(&a1, g1));
        let body = a0.r_ned_body().inverse() * a1.r_ned_body();
        let got = camera_rotation_in_grid(&body, &r_body_cam, &w0, g1 - g0);
        let want = w0.inverse() * w1;
        assert!(
            (got.inverse() * want).angle() < 1e-12,
            "{}",
            (got.inverse() * want).angle()
        );
        // Without the convergence the 1.5 mrad is missing.
        let plain = camera_rotation_in_grid(&body, &r_body_cam, &w0, 0.0);
        assert!(((plain.inverse() * want).angle() - 1.5e-3).abs() < 1e-9);
    }

    /// The property the filter's model rests on (`nav::filter::fuse_vo`): a heading error of the
    /// prior rotates the displacement by it, `dp = Rz(dyaw) dp_true` (NED, about down).
    #[test]
    fn a_heading_error_of_the_prior_rotates_the_displacement() {
        let (steps, truth) = fly(3.0, 3);
        for (m, t) in motions(&steps).iter().zip(&truth) {
            let rotated = Rotation3::from_axis_angle(&Vector3::z_axis(), 3f64.to_radians()) * t;
            let e = m.fix.dp_ned_m - rotated;
            assert!(
                e.norm() < 0.1,
                "{:?} vs rotated truth {rotated:?}",
                m.fix.dp_ned_m
            );
        }
    }

    /// Bad input gives no motion: a blank frame, a frame without a pose prior, a frame back in
    /// time; the sequence goes on after them.
    #[test]
    fn blank_frames_missing_priors_and_time_steps_give_no_motion() {
        let (engine, crs) = checkerboard_engine();
        let camera = *engine.camera();
        let mut odo = Odometer::new(camera, engine.reference().clone(), VoConfig::default());
        let att = Attitude::from_deg(0.0, 0.0, 30.0);
        let frame = |k: usize| {
            let (lat, lon) = crs.to_geodetic(at(k).x, at(k).y).unwrap();
            render(&camera, &crs, at(k), &att, lat, lon)
        };
        let blank = GrayImage::from_fn(320, 240, |_, _| 128.0);
        assert_eq!(
            odo.frame(frame(0), &prior(&crs, at(0), att, 0), None),
            VoStep::Started
        );
        let s = odo.frame(blank.clone(), &prior(&crs, at(1), att, 200_000), None);
        assert!(
            matches!(&s, VoStep::Refused(why) if why.class() == "few_tracks"
                && why.to_string().contains("tracks")),
            "{s:?}"
        );
        let mut none = prior(&crs, at(2), att, 400_000);
        none.position = None;
        let s = odo.frame(frame(2), &none, None);
        assert!(
            matches!(&s, VoStep::Refused(why) if why.class() == "invalid_input"
                && why.to_string().contains("no pose prior")),
            "{s:?}"
        );
        assert_eq!(
            odo.frame(frame(3), &prior(&crs, at(3), att, 600_000), None),
            VoStep::Started
        );
        let s = odo.frame(frame(4), &prior(&crs, at(4), att, 500_000), None);
        assert!(
            matches!(
                &s,
                VoStep::Refused(VoRefusal::NotAfter {
                    t_us: 500_000,
                    prev_us: 600_000
                })
            ),
            "{s:?}"
        );
        let s = odo.frame(frame(5), &prior(&crs, at(5), att, 3_000_000), None);
        let VoStep::Refused(why) = &s else {
            panic!("{s:?}")
        };
        assert_eq!(
            (why.to_string().as_str(), why.class()),
            ("2.50 s since the previous frame (at most 2 s)", "time_gap")
        );
        assert!(matches!(
            odo.frame(frame(6), &prior(&crs, at(6), att, 3_200_000), None),
            VoStep::Motion(_)
        ));
    }
}
