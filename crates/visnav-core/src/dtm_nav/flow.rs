//! The DTM navigator's optical flow: corners of the first frame tracked into the second by
//! pyramidal Lucas-Kanade (Bouguet 2000, OpenCV's `calcOpticalFlowPyrLK` semantics:
//! [`crate::vision::klt`]) with the forward-backward check (Kalal et al. 2010), each corner
//! started where the navigation's guess predicts it ([`predict_px`]: its ray onto the terrain
//! from the first guessed pose, projected with the second). The guess leaves tens of pixels to
//! find, the pyramid ([`FLOW_MAX_LEVEL`]) the rest; the prediction is what lets two frames tens
//! to hundreds of metres apart be tracked directly, without the frames between.
//!
//! Pixels here are the camera's own (distorted) pixels; the caller's `predict` maps between them.

use nalgebra::{Vector2, Vector3};

use crate::camera::Camera;
use crate::geo::dem::Dem;
use crate::pose::Pose;
use crate::vision::klt::{FeatureParams, Pyramid, SpreadGrid, TrackParams, track_checked};
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
/// tracked point in `b`). Each corner starts at `predict(corner)` in `b`; a corner without a
/// prediction (its ray misses the terrain, or it leaves the second frame) is not tracked.
pub fn terrain_flow(
    a: &GrayImage,
    b: &GrayImage,
    predict: impl Fn([f32; 2]) -> Option<[f32; 2]>,
) -> Result<(usize, Vec<TrackPair>), VisionError> {
    let params = TrackParams {
        max_level: FLOW_MAX_LEVEL,
        ..TrackParams::default()
    };
    let pa = Pyramid::new(a, params.max_level, params.win_size_px)?;
    let pb = Pyramid::new(b, params.max_level, params.win_size_px)?;
    let corners = pa.good_features(&FeatureParams {
        max_corners: MAX_CORNERS,
        min_distance_px: CORNER_MIN_DISTANCE_PX,
        spread: Some(SPREAD),
        ..FeatureParams::default()
    })?;
    let (pts, guesses): (Vec<[f32; 2]>, Vec<[f32; 2]>) = corners
        .iter()
        .filter_map(|&p| predict(p).map(|g| (p, g)))
        .unzip();
    let tracks = track_checked(&pa, &pb, &pts, Some(&guesses), &params)?;
    let pairs = pts
        .iter()
        .zip(&tracks)
        .filter(|(_, t)| t.is_tracked())
        .map(|(p, t)| TrackPair {
            prev_px: Vector2::new(f64::from(p[0]), f64::from(p[1])),
            next_px: Vector2::new(f64::from(t.point[0]), f64::from(t.point[1])),
        })
        .collect();
    Ok((corners.len(), pairs))
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
