//! Visual odometry measured (`visnav bench vo`): on a rendered VGA sequence with a known
//! flight ([`vga_vo`], timed per frame), and against real frames with measured poses ([`ngi_vo`]):
//! NGI 3324C strip 05, frames 0182 -> 0184 (`../shared/data/ngi_3324c`: Intergraph DMC frames at 640 x
//! 1152 px, poses from aerial triangulation, a 24 m DEM). The camera moved 2.6 km west at about
//! 4.8 km above a valley of 150-780 m, so the frames overlap in a strip of about a third of each.
//!
//! The previous pose is frame 0182's measured one (what a filter would hold); the features are
//! SURF matched between the frames (a 2.6 km baseline is far beyond a tracker's reach without a
//! prediction); [`visnav_core::vo::frame_motion`] casts them onto the DEM and solves frame 0184's
//! pose from the images alone (no gyro rotation: the frames are half a minute apart). The
//! displacement is compared with the measured one: the angle between the two (the baseline's
//! direction) and the length difference in percent.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::{Vector2, Vector3};
use serde::Serialize;

use visnav_core::camera::Opk;
use visnav_core::pose::{ImageGeometry, Pose};
use visnav_core::stats::percentile;
use visnav_core::vision::{
    Features, GrayImage, Match, MatchParams, Surf, SurfParams, match_features,
};
use visnav_core::vo::{FrameMotion, TrackPair, VoConfig, VoInput, frame_motion};
use visnav_io::image_file::GrayImageFile;

/// The frames and their measured poses.
pub(crate) const PREV_FRAME: &str = "frame_05_0182.png";
pub(crate) const NEXT_FRAME: &str = "frame_05_0184.png";

/// NGI camera (README): f = 120 mm on a 92.16 x 165.888 mm sensor at 640 x 1152 px, no distortion.
const NGI_FOCAL_PX: f64 = 120.0 / 92.16 * 640.0;

/// Height uncertainty of the previous pose above the DEM, m: the aerial triangulation's height is
/// decimetres, the 24 m DEM's error over a valley with 600 m of relief some metres; 10 m is taken.
const PREV_HEIGHT_SIGMA_M: f64 = 10.0;

/// Tilt uncertainty of the previous pose, rad: aerial triangulation, 0.01 deg.
const PREV_TILT_SIGMA_RAD: f64 = 1.745e-4;

/// Feature noise of SURF keypoints between frames 2.6 km apart (relief parallax changes each
/// blob's shape), px: twice a tracker's.
const SURF_TRACK_SIGMA_PX: f64 = 1.0;

/// Errors of the evaluation (missing or unreadable data).
#[derive(Debug, thiserror::Error)]
pub enum VoEvalError {
    /// A data file is missing or unreadable, or its data gave no result.
    #[error("{path}: {reason}")]
    Data {
        /// The file.
        path: PathBuf,
        /// What went wrong, in words.
        reason: String,
    },
    /// The vision code (SURF, matching, tracking, the flat ground) refused its input.
    #[error("vision: {0}")]
    Vision(String),
    /// The data were read but the solver refused them (a measured outcome, not a fault).
    #[error("{path}: {reason}")]
    Refused {
        /// The file of the refused frame.
        path: PathBuf,
        /// The solver's refusal, in words.
        reason: String,
    },
}

/// The NGI figures (`visnav bench vo --json`: the `ngi_*` keys).
#[derive(Debug, Clone, Serialize)]
pub struct NgiVo {
    /// SURF features in frame 0182.
    pub features_prev: usize,
    /// SURF features in frame 0184.
    pub features_next: usize,
    /// Mutual nearest-neighbour matches between the two.
    pub matches: usize,
    /// Matches whose ray from the previous pose met the DEM.
    pub on_ground: usize,
    /// Matches kept as inliers by the motion solver.
    pub inliers: usize,
    /// Measured displacement (aerial triangulation), map grid (east, north, up), m.
    pub truth_dp_m: [f64; 3],
    /// Estimated displacement, map grid (east, north, up), m.
    pub dp_m: [f64; 3],
    /// Angle between the estimated and the measured displacement, deg.
    pub dir_err_deg: f64,
    /// (estimated - measured) / measured length, %.
    pub len_err_pct: f64,
    /// Claimed 1-sigma of the displacement along the baseline (horizontal), m.
    pub sigma_along_m: f64,
    /// Claimed 1-sigma of the displacement across the baseline (horizontal), m.
    pub sigma_across_m: f64,
    /// Reprojection RMS of the inliers, px.
    pub rms_px: f64,
    /// Time of the brute-force matching and the motion (SURF excluded), ms.
    pub ms_match_and_motion: f64,
}

/// A frame's measured pose from `frames_truth.csv`.
fn truth_pose(dir: &Path, frame: &str) -> Result<Pose, VoEvalError> {
    let path = dir.join("frames_truth.csv");
    let err = |reason: String| VoEvalError::Data {
        path: path.clone(),
        reason,
    };
    let text = std::fs::read_to_string(&path).map_err(|e| err(e.to_string()))?;
    let line = text
        .lines()
        .find(|l| l.split(',').next() == Some(frame))
        .ok_or_else(|| err(format!("no line for {frame}")))?;
    let v: Vec<f64> = line
        .split(',')
        .skip(1)
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| err(format!("{frame}: {e}")))?;
    let [x, y, z, omega, phi, kappa] = v[..] else {
        return Err(err(format!(
            "{frame}: expected 6 numbers, found {}",
            v.len()
        )));
    };
    Ok(Pose {
        r_world_cam: Opk::from_deg(omega, phi, kappa).r_world_cam(),
        c_world: Vector3::new(x, y, z),
    })
}

fn load_frame(dir: &Path, frame: &str) -> Result<GrayImage, VoEvalError> {
    let path = dir.join(frame);
    GrayImage::load(&path).map_err(|e| VoEvalError::Data {
        path,
        reason: e.to_string(),
    })
}

/// The NGI frames 0182 and 0184 with their measured poses, the DEM and the camera.
pub(crate) struct NgiPair {
    pub prev: Pose,
    pub next: Pose,
    pub img_a: GrayImage,
    pub img_b: GrayImage,
    pub dem: visnav_core::geo::dem::Dem,
    pub image: ImageGeometry,
}

impl NgiPair {
    pub(crate) fn load(dir: &Path) -> Result<Self, VoEvalError> {
        let dem_path = dir.join("dem.tif");
        let dem =
            visnav_io::geo::dem::load_dem(&dem_path, None).map_err(|e| VoEvalError::Data {
                path: dem_path.clone(),
                reason: e.to_string(),
            })?;
        let img_a = load_frame(dir, PREV_FRAME)?;
        let image = ImageGeometry {
            fx_px: NGI_FOCAL_PX,
            fy_px: NGI_FOCAL_PX,
            cx_px: (img_a.width() as f64 - 1.0) / 2.0,
            cy_px: (img_a.height() as f64 - 1.0) / 2.0,
            width_px: img_a.width() as u32,
            height_px: img_a.height() as u32,
        };
        Ok(Self {
            prev: truth_pose(dir, PREV_FRAME)?,
            next: truth_pose(dir, NEXT_FRAME)?,
            img_b: load_frame(dir, NEXT_FRAME)?,
            img_a,
            dem,
            image,
        })
    }
}

/// Frame 0182 -> 0184 from the images and the DEM (module doc).
pub fn ngi_vo(dir: &Path) -> Result<NgiVo, VoEvalError> {
    let NgiPair {
        prev,
        next,
        img_a,
        img_b,
        dem,
        image,
    } = NgiPair::load(dir)?;
    let surf = Surf::new(SurfParams::default()).map_err(|e| VoEvalError::Vision(e.to_string()))?;
    let (fa, fb) = (
        surf.detect_and_describe(&img_a),
        surf.detect_and_describe(&img_b),
    );
    let t0 = Instant::now();
    let params = MatchParams {
        mutual: true,
        ..MatchParams::default()
    };
    let matches =
        match_features(&fa, &fb, &params, None).map_err(|e| VoEvalError::Vision(e.to_string()))?;
    let tracks = match_pairs(&fa, &fb, &matches);
    let cfg = VoConfig {
        track_sigma_px: SURF_TRACK_SIGMA_PX,
        ..VoConfig::default()
    };
    let input = VoInput {
        tracks: &tracks,
        image: &image,
        prev,
        prev_height_sigma_m: PREV_HEIGHT_SIGMA_M,
        prev_tilt_sigma_rad: PREV_TILT_SIGMA_RAD,
        rotation_prior: None,
    };
    let m = frame_motion(&input, &dem, &cfg).map_err(|e| VoEvalError::Data {
        path: dir.join(NEXT_FRAME),
        reason: format!("no motion: {e}"),
    })?;
    let ms_match_and_motion = t0.elapsed().as_secs_f64() * 1e3;
    let truth = next.c_world - prev.c_world;
    let dp = m.dp_world_m;
    let dir_err_deg = (dp.dot(&truth) / (dp.norm() * truth.norm()))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    let along = Vector2::new(truth.x, truth.y).normalize();
    let across = Vector2::new(-along.y, along.x);
    let h = m.cov_dp_world_m2.fixed_view::<2, 2>(0, 0).into_owned();
    Ok(NgiVo {
        features_prev: fa.len(),
        features_next: fb.len(),
        matches: matches.len(),
        on_ground: m.on_ground,
        inliers: m.inliers,
        truth_dp_m: [truth.x, truth.y, truth.z],
        dp_m: [dp.x, dp.y, dp.z],
        dir_err_deg,
        len_err_pct: (dp.norm() - truth.norm()) / truth.norm() * 100.0,
        sigma_along_m: along.dot(&(h * along)).sqrt(),
        sigma_across_m: across.dot(&(h * across)).sqrt(),
        rms_px: m.rms_px,
        ms_match_and_motion,
    })
}

/// Matched features as track pairs (query in the previous frame, train in the next).
fn match_pairs(prev: &Features, next: &Features, matches: &[Match]) -> Vec<TrackPair> {
    matches
        .iter()
        .map(|m| {
            let (a, b) = (&prev.keypoints[m.query], &next.keypoints[m.train]);
            TrackPair {
                prev_px: Vector2::new(f64::from(a.x), f64::from(a.y)),
                next_px: Vector2::new(f64::from(b.x), f64::from(b.y)),
            }
        })
        .collect()
}

/// The VGA sequence of the timing bench: a real NAIP photo (`../shared/data/bench`, 1280 x 960)
/// laid on flat ground at `TEXTURE_GSD_M` per pixel, seen by a nadir VGA camera (60 deg wide) at
/// `VGA_AGL_M` flying `VGA_STEP_M` per frame (20 m/s at 5 Hz, climbing) while it turns by
/// `VGA_YAW_STEP_DEG` and pitches by up to `VGA_PITCH_DEG`. Each frame is rendered from the photo
/// for its true pose (rays onto the ground, bilinear samples). Not a map: nothing is matched
/// against the photo; it gives the tracker real texture under a known motion.
const VGA_AGL_M: f64 = 300.0;
const VGA_STEP_M: [f64; 3] = [3.2, 2.4, 0.3];
const VGA_YAW_STEP_DEG: f64 = 0.5;
const VGA_PITCH_DEG: f64 = 0.3;
/// The photo's ground sampling: the VGA camera's at 300 m (0.54 m/px), so the photo covers twice
/// the frame's footprint each way and the sequence never sees its edge.
const TEXTURE_GSD_M: f64 = VGA_AGL_M / VGA_FOCAL_PX;
/// VGA with a 60 deg horizontal field of view: fx = 320 / tan(30 deg).
const VGA_FOCAL_PX: f64 = 554.256;
/// Gyro noise over the 0.2 s between frames, deg (a consumer MEMS gyro: bias 20 deg/h and
/// 0.3 deg/sqrt(h) of random walk give about 0.001 deg; 0.01 deg is taken).
const VGA_GYRO_SIGMA_DEG: f64 = 0.01;
/// Tracks kept alive from frame to frame; new corners are detected when fewer remain.
const VGA_MAX_CORNERS: usize = 300;
const VGA_REPLENISH_BELOW: usize = 200;
/// New corners keep this distance from live tracks, px.
const VGA_NEW_CORNER_DISTANCE_PX: f32 = 10.0;

/// The VGA figures (`visnav bench vo --json`: the `vga` keys).
#[derive(Debug, Clone, Serialize)]
pub struct VgaVo {
    /// Frame pairs solved.
    pub frames: usize,
    /// Per frame on one thread: the new frame's pyramid, tracking forward and backward, the
    /// motion, and new corners when the tracks run low: the median, ms.
    pub ms_p50: f64,
    /// The 95th percentile of that time, ms.
    pub ms_p95: f64,
    /// The minimum of that time, ms.
    pub ms_min: f64,
    /// Median time of the new frame's pyramid, ms.
    pub ms_pyramid: f64,
    /// Median time of tracking forward and backward, ms.
    pub ms_track: f64,
    /// Median time of the motion solve, ms.
    pub ms_motion: f64,
    /// Median time of topping up the tracks (new corners when they run low), ms.
    pub ms_replenish: f64,
    /// Frames on which new corners were detected.
    pub replenished: usize,
    /// Mean tracks going into the motion per frame.
    pub tracks_mean: f64,
    /// Mean inliers coming out per frame.
    pub inliers_mean: f64,
    /// Per step: displacement error against the true step, m, the median.
    pub step_err_m_p50: f64,
    /// The largest of those errors, m.
    pub step_err_m_max: f64,
    /// Per step: the displacement error's Mahalanobis distance under its claimed covariance,
    /// the median.
    pub step_err_over_sigma_p50: f64,
    /// The true step, m.
    pub step_m: f64,
    /// Visual odometry alone (each motion chained onto the last estimate, no filter): distance
    /// flown, m.
    pub distance_m: f64,
    /// The chained estimate's position error at the end, m.
    pub chained_err_m: f64,
}

/// The frame `pose` sees of the photo laid on the ground (z = 0, centred on the origin, north up,
/// `TEXTURE_GSD_M` per pixel): each pixel's ray onto the ground, bilinear sample (0 off the photo).
pub(crate) fn render_flat(texture: &GrayImage, image: &ImageGeometry, pose: &Pose) -> GrayImage {
    let (cx, cy) = (
        (texture.width() as f64 - 1.0) / 2.0,
        (texture.height() as f64 - 1.0) / 2.0,
    );
    GrayImage::from_fn(image.width_px as usize, image.height_px as usize, |x, y| {
        let d = pose.r_world_cam
            * Vector3::new(
                (x as f64 - image.cx_px) / image.fx_px,
                (y as f64 - image.cy_px) / image.fy_px,
                1.0,
            );
        if d.z >= 0.0 {
            return 0.0;
        }
        let g = pose.c_world + d * (-pose.c_world.z / d.z);
        texture
            .sample_bilinear(cx + g.x / TEXTURE_GSD_M, cy - g.y / TEXTURE_GSD_M)
            .unwrap_or(0.0)
    })
}

/// The VGA camera of the sequence: 640 x 480, 60 deg wide, no distortion.
pub(crate) fn vga_image() -> ImageGeometry {
    ImageGeometry {
        fx_px: VGA_FOCAL_PX,
        fy_px: VGA_FOCAL_PX,
        cx_px: 319.5,
        cy_px: 239.5,
        width_px: 640,
        height_px: 480,
    }
}

/// The true poses of the VGA sequence (`VGA_*`), centred on the photo.
pub(crate) fn vga_poses(frames: usize) -> Vec<Pose> {
    let step = Vector3::from(VGA_STEP_M);
    let start = Vector3::new(0.0, 0.0, VGA_AGL_M) - step * (frames as f64 / 2.0);
    (0..frames)
        .map(|k| {
            let kf = k as f64;
            Pose::nadir(
                start + step * kf,
                0.3 + (VGA_YAW_STEP_DEG * kf).to_radians(),
                (VGA_PITCH_DEG * (0.7 * kf).sin()).to_radians(),
            )
        })
        .collect()
}

/// The VGA camera and the sequence it sees of the photo at `texture_path` (`VGA_*`), with the
/// solver of its motions.
fn vga_sequence(
    texture_path: &Path,
    frames: usize,
) -> Result<(VgaSolver<'_>, Vec<GrayImage>), VoEvalError> {
    let texture = GrayImage::load(texture_path).map_err(|e| VoEvalError::Data {
        path: texture_path.to_path_buf(),
        reason: e.to_string(),
    })?;
    let image = vga_image();
    let poses = vga_poses(frames.max(2));
    let imgs = poses
        .iter()
        .map(|p| render_flat(&texture, &image, p))
        .collect();
    let dem =
        visnav_core::geo::dem::Dem::flat(0.0).map_err(|e| VoEvalError::Vision(e.to_string()))?;
    let solver = VgaSolver {
        image,
        poses,
        dem,
        cfg: VoConfig::default(),
        path: texture_path,
    };
    Ok((solver, imgs))
}

/// Frame `k`'s motion input: its pairs, the chained estimate of frame `k - 1`, and the gyros'
/// rotation between the true poses off by `VGA_GYRO_SIGMA_DEG` (always the same way).
fn vga_input<'a>(
    pairs: &'a [TrackPair],
    image: &'a ImageGeometry,
    est: &Pose,
    poses: &[Pose],
    k: usize,
) -> VoInput<'a> {
    let gyro_err = nalgebra::Rotation3::from_axis_angle(
        &nalgebra::Unit::new_normalize(Vector3::new(1.0, -1.0, 0.5)),
        VGA_GYRO_SIGMA_DEG.to_radians(),
    );
    VoInput {
        tracks: pairs,
        image,
        prev: *est,
        // The chained estimate drifts: its height and tilt as far as the bench goes (about 1 % of
        // the distance, the gyros' 0.01 deg per frame).
        prev_height_sigma_m: 0.01 * (est.c_world - poses[0].c_world).norm(),
        prev_tilt_sigma_rad: (VGA_GYRO_SIGMA_DEG * k as f64).to_radians(),
        rotation_prior: Some(visnav_core::vo::RotationPrior {
            r_prev_next: poses[k - 1].r_world_cam.inverse() * poses[k].r_world_cam * gyro_err,
            cov_prev_rad2: nalgebra::Matrix3::identity() * VGA_GYRO_SIGMA_DEG.to_radians().powi(2),
        }),
    }
}

/// What both VGA benches solve each motion with: the camera, the true poses, flat ground and the
/// VO settings; `path` (the photo) names the bench in errors.
struct VgaSolver<'a> {
    image: ImageGeometry,
    poses: Vec<Pose>,
    dem: visnav_core::geo::dem::Dem,
    cfg: VoConfig,
    path: &'a Path,
}

impl VgaSolver<'_> {
    /// Frame `k`'s motion from `pairs` (set up by [`vga_input`]) and the chained estimate `est`
    /// moved by it; `what` names the method in the error.
    fn solve_and_chain(
        &self,
        pairs: &[TrackPair],
        est: &Pose,
        k: usize,
        what: &str,
    ) -> Result<(FrameMotion, Pose), VoEvalError> {
        let input = vga_input(pairs, &self.image, est, &self.poses, k);
        let m = frame_motion(&input, &self.dem, &self.cfg).map_err(|e| VoEvalError::Data {
            path: self.path.to_path_buf(),
            reason: format!("frame {k}{what}: no motion: {e}"),
        })?;
        let mut r = est.r_world_cam * m.r_prev_next;
        r.renormalize();
        let next = Pose {
            r_world_cam: r,
            c_world: est.c_world + m.dp_world_m,
        };
        Ok((m, next))
    }
}

/// SURF matched between consecutive frames instead of tracked (the other candidate method), on
/// the same VGA sequence (`visnav bench vo --json`: the `vga_surf` keys).
#[derive(Debug, Clone, Serialize)]
pub struct VgaSurfVo {
    /// Frame pairs solved.
    pub frames: usize,
    /// Per frame on one thread: SURF on the new frame (the previous frame's features kept),
    /// matching with the spatial gate, the motion: the median, ms.
    pub ms_p50: f64,
    /// The 95th percentile of that time, ms.
    pub ms_p95: f64,
    /// Median time of SURF on the new frame, ms.
    pub ms_surf: f64,
    /// Median time of the gated matching, ms.
    pub ms_match: f64,
    /// Median time of the motion solve, ms.
    pub ms_motion: f64,
    /// Mean matches going into the motion per frame.
    pub matches_mean: f64,
    /// Mean inliers coming out per frame.
    pub inliers_mean: f64,
    /// Per step: displacement error against the true step, m, the median.
    pub step_err_m_p50: f64,
    /// The largest of those errors, m.
    pub step_err_m_max: f64,
}

/// Radius of the spatial gate for SURF between consecutive frames, px: the VGA sequence moves
/// about 7 px per frame; a generous gate leaves the descriptors to decide.
const VGA_SURF_GATE_PX: f32 = 40.0;

/// Visual odometry over the VGA sequence with SURF matched between consecutive frames (mutual
/// nearest neighbours, ratio test, the spatial gate around each feature's previous position),
/// each motion solved as in [`vga_vo`]; timed per frame on the calling thread.
pub fn vga_surf_vo(texture_path: &Path, frames: usize) -> Result<VgaSurfVo, VoEvalError> {
    let vision = |e: String| VoEvalError::Vision(e);
    let (solver, imgs) = vga_sequence(texture_path, frames)?;
    let poses = &solver.poses;
    let surf = Surf::new(SurfParams::default()).map_err(|e| vision(e.to_string()))?;
    let params = MatchParams {
        mutual: true,
        spatial_radius_px: Some(VGA_SURF_GATE_PX),
        ..MatchParams::default()
    };
    let mut prev = surf.detect_and_describe(&imgs[0]);
    let mut est = poses[0];
    let (mut total, mut t_surf, mut t_match, mut t_mot, mut errs) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut matches_n, mut inliers_n) = (0usize, 0usize);
    for k in 1..poses.len() {
        let t0 = Instant::now();
        let next = surf.detect_and_describe(&imgs[k]);
        let t1 = Instant::now();
        let at: Vec<[f32; 2]> = prev.keypoints.iter().map(|p| [p.x, p.y]).collect();
        let matches =
            match_features(&prev, &next, &params, Some(&at)).map_err(|e| vision(e.to_string()))?;
        let pairs = match_pairs(&prev, &next, &matches);
        let t2 = Instant::now();
        let (m, moved) = solver.solve_and_chain(&pairs, &est, k, " (SURF)")?;
        let t3 = Instant::now();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        total.push(ms(t0, t3));
        t_surf.push(ms(t0, t1));
        t_match.push(ms(t1, t2));
        t_mot.push(ms(t2, t3));
        errs.push((m.dp_world_m - (poses[k].c_world - poses[k - 1].c_world)).norm());
        matches_n += pairs.len();
        inliers_n += m.inliers;
        est = moved;
        prev = next;
    }
    let n = total.len();
    Ok(VgaSurfVo {
        frames: n,
        ms_p50: percentile(&total, 0.5),
        ms_p95: percentile(&total, 0.95),
        ms_surf: percentile(&t_surf, 0.5),
        ms_match: percentile(&t_match, 0.5),
        ms_motion: percentile(&t_mot, 0.5),
        matches_mean: matches_n as f64 / n as f64,
        inliers_mean: inliers_n as f64 / n as f64,
        step_err_m_p50: percentile(&errs, 0.5),
        step_err_m_max: errs.iter().copied().fold(0.0, f64::max),
    })
}

/// Visual odometry over the VGA sequence (`VGA_*`), timed per frame on the calling thread:
/// tracks carried from frame to frame, replenished when they run low, each motion solved from
/// the previous estimate (chained, no filter) with the gyros' rotation (`VGA_GYRO_SIGMA_DEG` off).
pub fn vga_vo(texture_path: &Path, frames: usize) -> Result<VgaVo, VoEvalError> {
    use visnav_core::vo::{Tracker, TrackingConfig};
    let vision = |e: visnav_core::vision::VisionError| VoEvalError::Vision(e.to_string());
    let (solver, imgs) = vga_sequence(texture_path, frames)?;
    let poses = &solver.poses;
    let mut tracker = Tracker::new(TrackingConfig {
        max_corners: VGA_MAX_CORNERS,
        replenish_below: VGA_REPLENISH_BELOW,
        new_corner_distance_px: VGA_NEW_CORNER_DISTANCE_PX,
        ..TrackingConfig::default()
    });
    let first = tracker.pyramid(imgs[0].clone()).map_err(vision)?;
    tracker.advance(first, |p| p).map_err(vision)?;
    let mut est = poses[0];
    let (mut total, mut t_pyr, mut t_trk, mut t_mot, mut t_rep) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut errs, mut err_sig, mut tracks_n, mut inliers_n) =
        (Vec::new(), Vec::new(), 0usize, 0usize);
    let mut replenished = 0;
    for k in 1..poses.len() {
        let t0 = Instant::now();
        let pyr = tracker.pyramid(imgs[k].clone()).map_err(vision)?;
        let t1 = Instant::now();
        // No prediction: the bench measures the tracker's own reach (4 m at 300 m: 7 px).
        let pairs: Vec<TrackPair> = tracker
            .track(pyr, |p| p)
            .map_err(vision)?
            .unwrap_or_default()
            .iter()
            .map(|t| TrackPair {
                prev_px: Vector2::new(f64::from(t.prev_px[0]), f64::from(t.prev_px[1])),
                next_px: Vector2::new(f64::from(t.next_px[0]), f64::from(t.next_px[1])),
            })
            .collect();
        let t2 = Instant::now();
        let (m, moved) = solver.solve_and_chain(&pairs, &est, k, "")?;
        let t3 = Instant::now();
        if tracker.top_up().map_err(vision)? {
            replenished += 1;
        }
        let t4 = Instant::now();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        total.push(ms(t0, t4));
        t_pyr.push(ms(t0, t1));
        t_trk.push(ms(t1, t2));
        t_mot.push(ms(t2, t3));
        t_rep.push(ms(t3, t4));
        let e = m.dp_world_m - (poses[k].c_world - poses[k - 1].c_world);
        errs.push(e.norm());
        err_sig.push(
            m.cov_dp_world_m2
                .try_inverse()
                .map_or(f64::NAN, |i| e.dot(&(i * e)).sqrt()),
        );
        tracks_n += pairs.len();
        inliers_n += m.inliers;
        est = moved;
    }
    let n = total.len();
    let last = poses.len() - 1;
    Ok(VgaVo {
        frames: n,
        ms_p50: percentile(&total, 0.5),
        ms_p95: percentile(&total, 0.95),
        ms_min: percentile(&total, 0.0),
        ms_pyramid: percentile(&t_pyr, 0.5),
        ms_track: percentile(&t_trk, 0.5),
        ms_motion: percentile(&t_mot, 0.5),
        ms_replenish: percentile(&t_rep, 0.5),
        replenished,
        tracks_mean: tracks_n as f64 / n as f64,
        inliers_mean: inliers_n as f64 / n as f64,
        step_err_m_p50: percentile(&errs, 0.5),
        step_err_m_max: errs.iter().copied().fold(0.0, f64::max),
        step_err_over_sigma_p50: percentile(&err_sig, 0.5),
        step_m: Vector3::from(VGA_STEP_M).norm(),
        distance_m: (poses[last].c_world - poses[0].c_world).norm(),
        chained_err_m: (est.c_world - poses[last].c_world).norm(),
    })
}
