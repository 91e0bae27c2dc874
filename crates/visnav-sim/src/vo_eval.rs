//! Visual odometry against real frames with measured poses (`visnav bench vo`, issue 22): NGI 3324C
//! strip 05, frames 0182 -> 0184 (`../shared/data/ngi_3324c`: Intergraph DMC frames at 640 x
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
use visnav_core::vision::{GrayImage, MatchParams, Surf, SurfParams, match_features};
use visnav_core::vo::{TrackPair, VoConfig, VoInput, frame_motion};
use visnav_io::image_file::GrayImageFile;

/// The frames and their measured poses.
const PREV_FRAME: &str = "frame_05_0182.png";
const NEXT_FRAME: &str = "frame_05_0184.png";

/// NGI camera (README): f = 120 mm on a 92.16 x 165.888 mm sensor at 640 x 1152 px, no distortion.
const NGI_FOCAL_PX: f64 = 120.0 / 92.16 * 640.0;

/// Height uncertainty of the previous pose above the DEM, m: the aerial triangulation's height is
/// decimetres, the 24 m DEM's error over a valley with 600 m of relief some metres; 10 m is taken.
const PREV_HEIGHT_SIGMA_M: f64 = 10.0;

/// Feature noise of SURF keypoints between frames 2.6 km apart (relief parallax changes each
/// blob's shape), px: twice a tracker's.
const SURF_TRACK_SIGMA_PX: f64 = 1.0;

/// Errors of the evaluation (missing or unreadable data).
#[derive(Debug, thiserror::Error)]
pub enum VoEvalError {
    #[error("{path}: {reason}")]
    Data { path: PathBuf, reason: String },
    #[error("SURF: {0}")]
    Vision(String),
}

/// The NGI figures (`visnav bench vo --json`: the `ngi_*` keys).
#[derive(Debug, Clone, Serialize)]
pub struct NgiVo {
    pub features_prev: usize,
    pub features_next: usize,
    pub matches: usize,
    pub on_ground: usize,
    pub inliers: usize,
    /// Measured and estimated displacement, map grid (east, north, up), m.
    pub truth_dp_m: [f64; 3],
    pub dp_m: [f64; 3],
    /// Angle between the estimated and the measured displacement, deg.
    pub dir_err_deg: f64,
    /// (estimated - measured) / measured length, %.
    pub len_err_pct: f64,
    /// 1-sigma of the displacement along and across the baseline (horizontal), m.
    pub sigma_along_m: f64,
    pub sigma_across_m: f64,
    /// Reprojection RMS of the inliers, px.
    pub rms_px: f64,
    /// Time of matching and motion (SURF excluded), ms.
    pub ms_motion: f64,
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

/// Frame 0182 -> 0184 from the images and the DEM (module doc).
pub fn ngi_vo(dir: &Path) -> Result<NgiVo, VoEvalError> {
    let prev = truth_pose(dir, PREV_FRAME)?;
    let next = truth_pose(dir, NEXT_FRAME)?;
    let (img_a, img_b) = (load_frame(dir, PREV_FRAME)?, load_frame(dir, NEXT_FRAME)?);
    let dem_path = dir.join("dem.tif");
    let dem = visnav_io::geo::dem::load_dem(&dem_path, None).map_err(|e| VoEvalError::Data {
        path: dem_path.clone(),
        reason: e.to_string(),
    })?;
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
    let tracks: Vec<TrackPair> = matches
        .iter()
        .map(|m| {
            let (a, b) = (&fa.keypoints[m.query], &fb.keypoints[m.train]);
            TrackPair {
                prev_px: Vector2::new(f64::from(a.x), f64::from(a.y)),
                next_px: Vector2::new(f64::from(b.x), f64::from(b.y)),
            }
        })
        .collect();
    let image = ImageGeometry {
        fx_px: NGI_FOCAL_PX,
        fy_px: NGI_FOCAL_PX,
        cx_px: (img_a.width() as f64 - 1.0) / 2.0,
        cy_px: (img_a.height() as f64 - 1.0) / 2.0,
        width_px: img_a.width() as u32,
        height_px: img_a.height() as u32,
    };
    let cfg = VoConfig {
        track_sigma_px: SURF_TRACK_SIGMA_PX,
        ..VoConfig::default()
    };
    let input = VoInput {
        tracks: &tracks,
        image: &image,
        prev,
        prev_height_sigma_m: PREV_HEIGHT_SIGMA_M,
        rotation_prior: None,
    };
    let m = frame_motion(&input, &dem, &cfg).map_err(|e| VoEvalError::Data {
        path: dir.join(NEXT_FRAME),
        reason: format!("no motion: {e}"),
    })?;
    let ms_motion = t0.elapsed().as_secs_f64() * 1e3;
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
        ms_motion,
    })
}
