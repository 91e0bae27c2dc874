//! The DTM navigator on a frame sequence: each frame paired with an earlier one far enough away,
//! their flow over the terrain solved ([`super::solve`]) and the newer frame's pose handed to
//! the navigation filter as an absolute pose measurement ([`PoseFix`], like the map fix's
//! image-only pose).
//!
//! Per frame, with the navigation filter's pose at its capture time (a [`FixPrior`]):
//! 1. the pose in the map frame (as the visual odometry's, `vo::odometer`: grid x east, y
//!    north, height AMSL, `R_map_cam = Rz(gamma) R_enu_ned R_ned_cam`);
//! 2. the partner: the newest kept frame at least `min_baseline_agl_fraction` of the height above
//!    ground away and at most `max_pair_span_s` older. The baseline is what fixes the position:
//!    one pair 20 m apart from 550 m above ground leaves 76 m of horizontal sigma, 100 m apart
//!    38 m (10 m with the attitude known) (`docs/dtm.md`). No partner yet: the frame is kept and
//!    nothing is measured ([`DtmStep::Waiting`]);
//! 3. the relief screen on the terrain model alone (the rays of a [`FOOTPRINT_GRID`] x
//!    [`FOOTPRINT_GRID`] grid over the partner's image onto the DEM, their heights' spread against
//!    `min_relief_agl_fraction` of the height above them, as the solver's own screen): flat
//!    ground is refused before any flow is computed;
//! 4. the flow from the partner to this frame ([`super::flow::terrain_flow`], each corner started
//!    at the filter's prediction over the terrain), undistorted;
//! 5. the solve from the two filter poses, with the partner's height and tilt sigma as the guess
//!    check ([`super::GuessSigma`]);
//! 6. this frame's solved pose (the second of the pair: the newest, so the filter fuses it with
//!    the least delay) to geodetic / NED: grid convergence removed, horizontal grid metres divided
//!    by the projection's point scale factor, height AMSL plus the geoid; its `[phi, C]`
//!    covariance rotated into NED and reordered `[position, attitude]`, the terrain model's height
//!    variance added to the vertical (a height error of the model moves the solved height with
//!    it).
//!
//! Each pair's images are its own, so consecutive measurements share no flow; they share the
//! terrain model's errors, which the filter's `vision_error_corr_time_s` accounts for as it
//! does for the map fixes.

use std::collections::VecDeque;
use std::sync::Arc;

use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3};

use super::flow::{predict_px, terrain_flow};
use super::{DtmInput, DtmNavConfig, GuessSigma, solve};
use crate::camera::Camera;
use crate::camera::frames::{r_enu_ned, rot_z};
use crate::fix::{FixPrior, Reference};
use crate::geo::geoid::geoid_undulation_m;
use crate::nav::{Measurement, PoseFix, PositionFix};
use crate::pose::ImageGeometry;
use crate::vision::GrayImage;
use crate::vo::TrackPair;
use crate::vo::odometer::{FramePose, frame_pose, ground_below, undistorted_px};

/// Frames kept for pairing: at 5 Hz, 3 s of them (a pair's partner is the newest far enough away,
/// so only the last few are ever used; the cap bounds the memory when the aircraft hovers).
const MAX_KEPT_FRAMES: usize = 16;

/// Rays per image side of the relief screen before the flow: 7 x 7 = 49 ground points, enough
/// for the spread of heights to within a few tens of per cent.
pub const FOOTPRINT_GRID: usize = 7;

/// What one frame gave.
#[derive(Debug, Clone, PartialEq)]
pub enum DtmStep {
    /// Kept: no earlier frame is far enough away (or recent enough) to pair with yet.
    Waiting,
    /// The frame's pose from its pair.
    Fix(Box<DtmPoseFix>),
    /// No pose from this frame, and why.
    Refused(DtmRefusal),
}

/// A frame's solved pose as the filter's measurement, with the numbers behind it.
#[derive(Debug, Clone, PartialEq)]
pub struct DtmPoseFix {
    /// The pose at this frame's capture time (`fix.position.t_capture_us`).
    pub fix: PoseFix,
    /// Capture time of the partner (older) frame, µs.
    pub t_first_us: u64,
    /// Distance between the two frames' camera centres as the filter gave them, m.
    pub baseline_m: f64,
    /// Flow vectors tracked.
    pub tracks: usize,
    /// Vectors on the terrain at the first guess.
    pub on_ground: usize,
    /// Inliers at the solution.
    pub inliers: usize,
    /// Reprojection RMS over the inliers, px.
    pub rms_px: f64,
    /// What the relief alone fixes (horizontal 1-sigma given the attitude), m.
    pub sigma_h_given_attitude_m: f64,
    /// Mean height of the partner frame's centre above the inliers' ground points, m.
    pub agl_m: f64,
    /// Standard deviation of those ground points' heights, m.
    pub relief_std_m: f64,
}

/// Why a frame gave no pose: a typed outcome with its numbers as fields; people read its
/// `Display`, counters count its [`DtmRefusal::class`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DtmRefusal {
    /// The frame's pose prior is unusable.
    #[error("{0}")]
    Prior(crate::vo::VoRejection),
    /// Too few of the screen's rays reach the terrain model.
    #[error("{hits} of {rays} rays of the frame reach the terrain model")]
    OffTerrain {
        /// Rays that met the terrain model.
        hits: usize,
        /// Rays cast ([`FOOTPRINT_GRID`] x [`FOOTPRINT_GRID`] over the partner frame's image).
        rays: usize,
    },
    /// The flow could not be computed (a blank or malformed frame; its message).
    #[error("flow: {0}")]
    Flow(String),
    /// The solver refused (its screen, conditioning or integrity checks).
    #[error(transparent)]
    Solve(super::DtmRejection),
    /// The solved position has no geodetic coordinates or geoid height (its message).
    #[error("solved position: {0}")]
    Geodetic(String),
    /// The pose fails the filter measurement's own check.
    #[error("solved pose unusable: {0}")]
    Unusable(&'static str),
    /// The navigator panicked (the daemon's worker caught it).
    #[error("DTM navigator panicked")]
    Panicked,
}

/// Every value [`DtmRefusal::class`] returns besides the resection's
/// ([`crate::fix::rejection::CLASSES`]' `pose_*`, through a prior the odometer's checks refuse).
pub const DTM_CLASSES: &[&str] = &[
    "invalid_input",
    "inconsistent_with_guess",
    "far_from_guess",
    "few_tracks",
    "few_on_ground",
    "flat_ground",
    "ill_conditioned",
    "unobservable",
    "not_converged",
    "few_inliers",
    "poor_fit",
    "too_uncertain",
    "off_terrain",
    "flow",
    "geodesy",
    "unusable_pose",
    "internal",
];

impl DtmRefusal {
    /// The class for counting and metric labels: a name without numbers.
    pub fn class(&self) -> &'static str {
        match self {
            DtmRefusal::Prior(r) => r.class(),
            DtmRefusal::OffTerrain { .. } => "off_terrain",
            DtmRefusal::Flow(_) => "flow",
            DtmRefusal::Solve(r) => r.class(),
            DtmRefusal::Geodetic(_) => "geodesy",
            DtmRefusal::Unusable(_) => "unusable_pose",
            DtmRefusal::Panicked => "internal",
        }
    }
}

/// A frame kept for pairing.
struct KeptFrame {
    t_us: u64,
    image: GrayImage,
    fp: FramePose,
    sigma_v_m: f64,
    sigma_h_m: f64,
}

/// Called with each frame's capture time (µs) and step (an evaluation's recorder: the simulator
/// scores the poses against its truth).
pub type DtmObserver = Box<dyn FnMut(u64, &DtmStep) + Send>;

/// The DTM navigator over a frame sequence (module doc).
pub struct DtmNavigator {
    camera: Camera,
    reference: Arc<dyn Reference>,
    cfg: DtmNavConfig,
    kept: VecDeque<KeptFrame>,
    observer: Option<DtmObserver>,
}

impl DtmNavigator {
    /// A navigator for `camera` over `reference`'s terrain model (its orthophoto is not used).
    pub fn new(camera: Camera, reference: Arc<dyn Reference>, cfg: DtmNavConfig) -> Self {
        Self {
            camera,
            reference,
            cfg,
            kept: VecDeque::new(),
            observer: None,
        }
    }

    /// This navigator reporting every step to `observer` as well.
    pub fn with_observer(mut self, observer: DtmObserver) -> Self {
        self.observer = Some(observer);
        self
    }

    /// Forget the kept frames.
    pub fn reset(&mut self) {
        self.kept.clear();
    }

    /// One frame with the filter's pose at its capture time.
    pub fn frame(&mut self, image: GrayImage, prior: &FixPrior) -> DtmStep {
        let step = self.step(image, prior);
        if let Some(o) = self.observer.as_mut() {
            o(prior.t_capture_us, &step);
        }
        step
    }

    fn step(&mut self, image: GrayImage, prior: &FixPrior) -> DtmStep {
        let fp = match frame_pose(&self.camera, self.reference.as_ref(), prior) {
            Ok(p) => p,
            Err(e) => return DtmStep::Refused(DtmRefusal::Prior(e)),
        };
        let t_us = prior.t_capture_us;
        let span_us = (self.cfg.max_pair_span_s * 1e6) as u64;
        self.kept
            .retain(|k| k.t_us < t_us && t_us - k.t_us <= span_us);
        let agl_m = fp.pose.c_world.z - ground_below(&self.reference.dem(), &fp.pose);
        let need_m = self.cfg.min_baseline_agl_fraction * agl_m.max(0.0);
        let partner = self
            .kept
            .iter()
            .rev()
            .find(|k| (k.fp.pose.c_world - fp.pose.c_world).norm() >= need_m);
        let step = match partner {
            None => DtmStep::Waiting,
            Some(first) => match self.pair(first, &image, &fp, t_us) {
                Ok(f) => DtmStep::Fix(Box::new(f)),
                Err(why) => DtmStep::Refused(why),
            },
        };
        self.kept.push_back(KeptFrame {
            t_us,
            image,
            fp,
            sigma_v_m: prior.position.map_or(f64::INFINITY, |p| p.sigma_v_m),
            sigma_h_m: prior
                .position
                .map_or(f64::INFINITY, |p| p.sigma_h_m)
                .max(f64::MIN_POSITIVE),
        });
        while self.kept.len() > MAX_KEPT_FRAMES {
            self.kept.pop_front();
        }
        step
    }

    /// The pair's flow and solution; this frame's pose as the filter's measurement.
    fn pair(
        &self,
        first: &KeptFrame,
        image: &GrayImage,
        fp: &FramePose,
        t_us: u64,
    ) -> Result<DtmPoseFix, DtmRefusal> {
        let dem = self.reference.dem();
        let (guess1, guess2) = (first.fp.pose, fp.pose);
        let range = self.cfg.max_range_m;
        self.screen_footprint(&guess1)?;
        let (_, raw) = terrain_flow(&first.image, image, |p| {
            predict_px(p, &self.camera, &guess1, &guess2, &dem, range)
        })
        .map_err(|e| DtmRefusal::Flow(e.to_string()))?;
        let f32px = |v: nalgebra::Vector2<f64>| [v.x as f32, v.y as f32];
        let tracks: Vec<TrackPair> = raw
            .iter()
            .filter_map(|t| {
                Some(TrackPair {
                    prev_px: undistorted_px(&self.camera, f32px(t.prev_px))?,
                    next_px: undistorted_px(&self.camera, f32px(t.next_px))?,
                })
            })
            .collect();
        let geometry = ImageGeometry::from(&self.camera.intrinsics);
        let guess_sigma = first.sigma_v_m.is_finite().then_some(GuessSigma {
            height_m: first.sigma_v_m,
            tilt_rad: first.fp.tilt_sigma_rad,
            horizontal_m: first.sigma_h_m,
        });
        let input = DtmInput {
            tracks: &tracks,
            image: &geometry,
            guess_first: guess1,
            guess_second: guess2,
            guess_sigma,
        };
        // The terrain model's errors are one displacement shared by every pose over the same
        // model: as each pose's own noise the filter would both average them down and weigh
        // every pose less, and the guess check would let more wrong minima through (the replica
        // flights with them in: 7.7-12.4 m largest error over five seeds, poses outside 3 sigma
        // in the moving one; without: 5.6-8.4 m, none). The solver leaves them out here; the
        // pose takes the map's stated height error on its vertical (`pose_fix`); the pose's own
        // report (`DtmFix::cov`, `visnav bench dtm`) keeps them.
        let cfg = DtmNavConfig {
            dem_offset_sigma_m: 0.0,
            dem_shift_sigma_cells: 0.0,
            ..self.cfg.clone()
        };
        let sol = solve(&input, &dem, &cfg).map_err(DtmRefusal::Solve)?;
        let fix = self.pose_fix(&sol.second, &sol.second_cov(), fp, t_us)?;
        Ok(DtmPoseFix {
            fix,
            t_first_us: first.t_us,
            baseline_m: (guess2.c_world - guess1.c_world).norm(),
            tracks: sol.tracks,
            on_ground: sol.on_ground,
            inliers: sol.inliers,
            rms_px: sol.rms_px,
            sigma_h_given_attitude_m: sol.sigma_h_given_attitude_m,
            agl_m: sol.agl_m,
            relief_std_m: sol.relief_std_m,
        })
    }

    /// The relief under the frame at `pose` from the terrain model alone (module doc, step 3).
    fn screen_footprint(&self, pose: &crate::pose::Pose) -> Result<(), DtmRefusal> {
        let k = &self.camera.intrinsics;
        let c = pose.c_world;
        let n = FOOTPRINT_GRID;
        let heights: Vec<f64> = (0..n * n)
            .filter_map(|i| {
                let u = (i % n) as f64 / (n - 1) as f64 * f64::from(k.width_px - 1);
                let v = (i / n) as f64 / (n - 1) as f64 * f64::from(k.height_px - 1);
                let ray = self.camera.unproject(&nalgebra::Point2::new(u, v))?;
                let d = pose.r_world_cam * ray.into_inner();
                let x = self.reference.dem().intersect_ray(
                    [c.x, c.y, c.z],
                    [d.x, d.y, d.z],
                    self.cfg.max_range_m,
                )?;
                Some(x[2])
            })
            .collect();
        if heights.len() < n * n / 2 {
            return Err(DtmRefusal::OffTerrain {
                hits: heights.len(),
                rays: n * n,
            });
        }
        let (agl_m, relief_std_m) = super::agl_and_relief(&heights, c.z);
        let min = self.cfg.min_relief_agl_fraction;
        if agl_m.is_nan() || relief_std_m < min * agl_m {
            return Err(DtmRefusal::Solve(super::DtmRejection::FlatGround {
                relief_std_m,
                agl_m,
                min_fraction: min,
            }));
        }
        Ok(())
    }

    /// A solved camera pose (map frame) with its `[phi, C]` covariance as the filter's pose
    /// measurement (module doc, step 5).
    fn pose_fix(
        &self,
        pose: &crate::pose::Pose,
        cov_phi_c: &Matrix6<f64>,
        fp: &FramePose,
        t_us: u64,
    ) -> Result<PoseFix, DtmRefusal> {
        let c = pose.c_world;
        let (lat_deg, lon_deg) = self
            .reference
            .crs()
            .to_geodetic(c.x, c.y)
            .map_err(|e| DtmRefusal::Geodetic(e.to_string()))?;
        let n = geoid_undulation_m(lat_deg, lon_deg)
            .map_err(|e| DtmRefusal::Geodetic(e.to_string()))?;
        // Map grid -> NED: v_map = Rz(gamma) R_enu_ned v_ned; grid metres are `scale` true ones.
        let r_ned_map = (rot_z(fp.gamma_rad) * r_enu_ned()).inverse();
        let unscale = Matrix3::from_diagonal(&Vector3::new(1.0 / fp.scale, 1.0 / fp.scale, 1.0));
        let r_pos = r_ned_map.matrix() * unscale;
        let mut t = Matrix6::<f64>::zeros();
        t.fixed_view_mut::<3, 3>(0, 3).copy_from(&r_pos);
        t.fixed_view_mut::<3, 3>(3, 0).copy_from(r_ned_map.matrix());
        let mut cov6 = t * cov_phi_c * t.transpose();
        cov6[(2, 2)] += self.reference.height_sigma_m().powi(2);
        let cov6 = (cov6 + cov6.transpose()) * 0.5;
        let att = self
            .camera
            .mount
            .attitude_from_r_ned_cam(&(r_ned_map * pose.r_world_cam));
        let fix = PoseFix {
            position: PositionFix {
                t_capture_us: t_us,
                lat_rad: lat_deg.to_radians(),
                lon_rad: lon_deg.to_radians(),
                h_m: c.z + n,
                cov_ned_m2: cov6.fixed_view::<3, 3>(0, 0).into_owned(),
                att_dependence_ned: None,
            },
            q_nb: UnitQuaternion::from_euler_angles(att.roll_rad, att.pitch_rad, att.yaw_rad),
            cov6,
        };
        Measurement::VisionPose(fix)
            .check()
            .map_err(DtmRefusal::Unusable)?;
        Ok(fix)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::frames::Attitude;
    use crate::fix::engine::tests::checkerboard_engine;
    use crate::vo::odometer::tests::{prior, render};

    /// Every refusal's class is a name of the closed set, without a number.
    #[test]
    fn refusal_classes_are_a_closed_set() {
        use crate::dtm_nav::DtmRejection as R;
        let all = [
            DtmRefusal::Prior(crate::vo::VoRejection::InvalidInput("no pose prior".into())),
            DtmRefusal::OffTerrain { hits: 3, rays: 49 },
            DtmRefusal::Flow("blank".into()),
            DtmRefusal::Solve(R::FlatGround {
                relief_std_m: 1.0,
                agl_m: 500.0,
                min_fraction: 0.02,
            }),
            DtmRefusal::Solve(R::FarFromGuess {
                d_m: 250.0,
                sigma_m: 30.0,
                m2: 70.0,
                max: 13.8,
            }),
            DtmRefusal::Solve(R::IllConditioned {
                rcond: 1e-12,
                min: 1e-9,
            }),
            DtmRefusal::Solve(R::NotConverged { iterations: 30 }),
            DtmRefusal::Solve(R::PoorFit {
                sigma0: 4.0,
                max: 3.0,
            }),
            DtmRefusal::Geodetic("x".into()),
            DtmRefusal::Unusable("non-finite"),
            DtmRefusal::Panicked,
        ];
        for r in all {
            let c = r.class();
            assert!(DTM_CLASSES.contains(&c), "{c}: {r}");
            assert!(!c.chars().any(|ch| ch.is_ascii_digit()), "{c}");
        }
    }

    /// Over the checkerboard engine's flat ground: the first frame waits for a partner, frames
    /// closer than the baseline wait too, and the first far enough is refused as flat ground by
    /// the terrain model alone (no flow computed); a frame without a pose prior is refused
    /// without disturbing the kept ones.
    #[test]
    fn flat_ground_is_refused_before_the_flow_and_frames_wait_for_their_baseline() {
        let (engine, crs) = checkerboard_engine();
        let camera = *engine.camera();
        let cfg = DtmNavConfig {
            enabled: true,
            ..DtmNavConfig::default()
        };
        let mut nav = DtmNavigator::new(camera, engine.reference().clone(), cfg);
        // 300 m above the ground: 45 m of baseline needed; 20 m per frame (frame 3 is 60 m from
        // frame 0).
        let at = |k: usize| Vector3::new(300_640.0 + 20.0 * k as f64, 5_199_360.0, 600.0);
        let att = Attitude::from_deg(0.0, 0.0, 90.0);
        let mut steps = Vec::new();
        for k in 0..5 {
            let c = at(k);
            let (lat, lon) = crs.to_geodetic(c.x, c.y).unwrap();
            let img = render(&camera, &crs, c, &att, lat, lon);
            steps.push(nav.frame(img, &prior(&crs, c, att, 400_000 * k as u64)));
        }
        assert_eq!(
            steps[..3],
            [DtmStep::Waiting, DtmStep::Waiting, DtmStep::Waiting]
        );
        for s in &steps[3..] {
            let DtmStep::Refused(why) = s else {
                panic!("{s:?}")
            };
            assert!(why.to_string().starts_with("flat ground"), "{why}");
            assert_eq!(why.class(), "flat_ground");
        }
        let no_prior = FixPrior {
            t_capture_us: 2_000_000,
            position: None,
            altitude: None,
            attitude: None,
            attitude_from_filter: false,
            widen_heading: false,
        };
        let (lat, lon) = crs.to_geodetic(at(6).x, at(6).y).unwrap();
        let img = render(&camera, &crs, at(6), &att, lat, lon);
        let DtmStep::Refused(why) = nav.frame(img, &no_prior) else {
            panic!("a frame without a prior")
        };
        assert!(why.to_string().contains("no pose prior"), "{why}");
        assert_eq!(why.class(), "invalid_input");
        assert_eq!(nav.kept.len(), 5);
    }
}
