//! Synthetic aerial scenes for tests and benchmarks of the resection.
//!
//! A smooth analytic terrain (about 240 m of relief) is seen by a pinhole camera 1000-2500 m above
//! it. Inlier correspondences: a random pixel is back-projected onto the terrain (ray marching by
//! fixed-point iteration on the height), then Gaussian pixel noise is added to the observation.
//! Outliers pair a terrain point seen by another random pixel with a random pixel (a wrong match
//! between real features, as a descriptor matcher produces).

use nalgebra::{Rotation3, Vector2, Vector3};

use crate::pose::{Correspondence, ImageGeometry, Pose};
use crate::rng::Rng;

/// Terrain height (metres, world z up) at local horizontal position (x, y) relative to the scene
/// origin.
pub fn terrain_height_m(x_m: f64, y_m: f64) -> f64 {
    200.0
        + 80.0 * (x_m / 500.0).sin() * (y_m / 700.0).cos()
        + 40.0 * (x_m / 230.0 + y_m / 310.0).sin()
}

/// Scene parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneConfig {
    /// Camera height above the terrain below the scene origin, metres.
    pub height_agl_m: f64,
    /// Off-nadir tilt of the optical axis (toward the image top), radians; 0 = nadir.
    pub tilt_rad: f64,
    /// Heading of the image top, radians, from world +y toward +x.
    pub yaw_rad: f64,
    /// Total number of correspondences.
    pub n: usize,
    /// Fraction of outliers (0..1).
    pub outlier_ratio: f64,
    /// 1-sigma pixel noise of the inliers (also reported as the correspondences' sigma).
    pub noise_px: f64,
    /// Image width, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// World coordinates of the scene origin (e.g. UTM-sized numbers to exercise the centring).
    pub origin_world: Vector3<f64>,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            height_agl_m: 1500.0,
            tilt_rad: 0.0,
            yaw_rad: 0.3,
            n: 300,
            outlier_ratio: 0.5,
            noise_px: 1.0,
            width_px: 640,
            height_px: 480,
            hfov_deg: 60.0,
            origin_world: Vector3::new(500_000.0, 4_100_000.0, 0.0),
        }
    }
}

/// A generated scene.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The correspondences, inliers and outliers mixed, world points in absolute coordinates.
    pub corrs: Vec<Correspondence>,
    /// Ground truth inlier flags.
    pub is_inlier: Vec<bool>,
    /// The true camera pose (absolute world coordinates).
    pub truth: Pose,
    /// The synthetic camera's intrinsics and image size.
    pub image: ImageGeometry,
}

/// `R_world_cam` of a camera looking down (tilted toward the image top by `tilt_rad`) with the image
/// top toward heading `yaw_rad`.
pub fn aerial_attitude(yaw_rad: f64, tilt_rad: f64) -> Rotation3<f64> {
    // Rx(pi): cam x = east, cam y (image down) = south, cam z = down. Rz(-yaw) turns the image top
    // from north toward east for positive yaw.
    Rotation3::from_axis_angle(&Vector3::z_axis(), -yaw_rad)
        * Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI + tilt_rad)
}

fn cast(pose_local: &Pose, d_cam: &Vector3<f64>) -> Option<Vector3<f64>> {
    let d = pose_local.r_world_cam * d_cam;
    if d.z >= -1e-3 {
        return None;
    }
    let c = pose_local.c_world;
    let mut t = (terrain_height_m(c.x, c.y) - c.z) / d.z;
    for _ in 0..200 {
        let p = c + d * t;
        let t_new = (terrain_height_m(p.x, p.y) - c.z) / d.z;
        if (t_new - t).abs() < 1e-9 * t.abs().max(1.0) {
            let p = c + d * t_new;
            return (t_new > 0.0).then_some(p);
        }
        t = t_new;
    }
    None
}

/// Generate a scene. Deterministic for a given `rng` state.
pub fn make_scene(cfg: &SceneConfig, rng: &mut Rng) -> Scene {
    let f = (cfg.width_px as f64 / 2.0) / (cfg.hfov_deg.to_radians() / 2.0).tan();
    let image = ImageGeometry {
        fx_px: f,
        fy_px: f,
        cx_px: (cfg.width_px as f64 - 1.0) / 2.0,
        cy_px: (cfg.height_px as f64 - 1.0) / 2.0,
        width_px: cfg.width_px,
        height_px: cfg.height_px,
    };
    let c_local = Vector3::new(
        rng.range(-50.0, 50.0),
        rng.range(-50.0, 50.0),
        terrain_height_m(0.0, 0.0) + cfg.height_agl_m,
    );
    let pose_local = Pose {
        r_world_cam: aerial_attitude(cfg.yaw_rad, cfg.tilt_rad),
        c_world: c_local,
    };
    let n_out = ((cfg.n as f64) * cfg.outlier_ratio).round() as usize;
    let mut corrs = Vec::with_capacity(cfg.n);
    let mut is_inlier = Vec::with_capacity(cfg.n);
    let random_pixel = |rng: &mut Rng| {
        Vector2::new(
            rng.range(-0.5, cfg.width_px as f64 - 0.5),
            rng.range(-0.5, cfg.height_px as f64 - 0.5),
        )
    };
    let norm = |px: &Vector2<f64>| Vector2::new((px.x - image.cx_px) / f, (px.y - image.cy_px) / f);
    let mut guard = 0;
    while corrs.len() < cfg.n && guard < 100 * cfg.n + 1000 {
        guard += 1;
        let outlier = corrs.len() < n_out;
        let px = random_pixel(rng);
        let nrm = norm(&px);
        let Some(p) = cast(&pose_local, &Vector3::new(nrm.x, nrm.y, 1.0)) else {
            continue;
        };
        let obs_px = if outlier {
            random_pixel(rng)
        } else {
            px + Vector2::new(rng.normal(), rng.normal()) * cfg.noise_px
        };
        corrs.push(Correspondence {
            point_world: p + cfg.origin_world,
            obs_norm: norm(&obs_px),
            sigma_px: cfg.noise_px.max(1e-3),
        });
        is_inlier.push(!outlier);
    }
    // Shuffle so that outliers are not grouped.
    for i in (1..corrs.len()).rev() {
        let j = rng.below(i + 1);
        corrs.swap(i, j);
        is_inlier.swap(i, j);
    }
    let truth = Pose {
        r_world_cam: pose_local.r_world_cam,
        c_world: c_local + cfg.origin_world,
    };
    Scene {
        corrs,
        is_inlier,
        truth,
        image,
    }
}
