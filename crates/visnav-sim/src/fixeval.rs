//! Evaluation of the vision fix against rendered frames with the renderer's truth. Two sites:
//!
//! * **NAIP** (the default): cross-date, frames rendered from the 2014
//!   orthophoto (640x480, 60 deg HFOV, 1200-2500 m above ground, tilt up to 20 deg, any heading)
//!   matched to a reference built from the 2009 orthophoto over flat ground. Priors (what a
//!   navigation filter in GPS-denied cruise would give): position 100 m off (1 sigma, stated
//!   150 m), altitude 20 m off (stated 30 m), attitude 0.3 deg off per axis (stated 0.5 deg;
//!   `NaipEval::attitude_prior_error_rad` changes the error, not the stated sigma).
//! * **Autzen** ([`NaipEval::autzen`]): drone scale, 80-300 m above the lidar surface model
//!   (`agl_range_m`), a multirotor's camera (1280 x 960, 80 deg), the frames ray-cast on that
//!   surface (roofs, trees, stands) from one degraded copy of the orthophoto
//!   ([`AUTZEN_CAMERA_COPY`]) and photometrically perturbed, the map built from another
//!   ([`AUTZEN_MAP_COPY`]: one date only, so each has its own light, shadows and compression and
//!   no frame is matched against the image it was rendered from) on the surface model or on a
//!   constant height ([`MapHeights`]). Priors: position 20 m off per axis (stated 30 m), altitude
//!   5 m off (stated 10 m), attitude as NAIP.
//!
//! Used by `tests/fix_naip.rs`, `tests/fix_autzen.rs` and `visnav bench fix`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{UnitQuaternion, Vector3, Vector6};
use serde::Serialize;

use super::render::degrade::{DegradeSpec, SunShadow, degrade};
use super::render::{
    ColourMode, RenderPose, RenderSpec, Renderer, Scene, drone_camera, grid_convergence_rad,
    vga_camera,
};
use visnav_core::camera::{Attitude, Camera, Mount};
use visnav_core::fix::engine::Attempt;
use visnav_core::fix::{
    AltitudePrior, AttitudePriorNed, FixEngine, FixParams, FixPrior, FixReport, PositionPriorGeo,
};
use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::Raster;
use visnav_core::rng::Rng;
use visnav_core::vision::{GrayImage, SurfParams};
use visnav_io::geo::geotiff::load_geotiff;
use visnav_io::geo::geotiff_write::write_geotiff;
use visnav_io::map::MapReference;
use visnav_io::map::{BuildSpec, HeightSource};

/// Why the fix bench could not set up or run a case (a missing map or data file, a frame that
/// cannot be rendered, a prior that cannot be formed), in words naming the file or the frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct FixBenchError(pub String);

impl From<String> for FixBenchError {
    fn from(reason: String) -> Self {
        Self(reason)
    }
}

impl From<&str> for FixBenchError {
    fn from(reason: &str) -> Self {
        Self(reason.to_owned())
    }
}

/// Ground height of the bundled NAIP area, metres AMSL (flat prairie, see sitl/maps/README.md).
pub const NAIP_GROUND_M: f64 = 580.0;

/// The Autzen map's copy of the orthophoto: another survey's light (cooler white balance,
/// brighter, the sun low in the south-east casting the surface model's shadows, a slow haze
/// field), resampled and JPEG-compressed as a map tile server delivers it.
pub const AUTZEN_MAP_COPY: DegradeSpec = DegradeSpec {
    seed: 101,
    gain_rgb: [0.92, 0.97, 1.08],
    offset_dn: 6.0,
    gamma: 1.1,
    field_amplitude: 0.12,
    field_wavelength_m: 120.0,
    blur_sigma_px: 0.6,
    noise_dn: 2.0,
    jpeg_quality: 75,
    shadow: Some(SunShadow {
        azimuth_deg: 115.0,
        elevation_deg: 30.0,
        darkening: 0.45,
    }),
};

/// The Autzen camera's copy (the world the camera sees today): warmer light, the sun high in the
/// south-west with its own shadows, another haze field. The renderer adds the camera's own
/// exposure, blur and noise.
pub const AUTZEN_CAMERA_COPY: DegradeSpec = DegradeSpec {
    seed: 202,
    gain_rgb: [1.06, 1.0, 0.9],
    offset_dn: -4.0,
    gamma: 0.92,
    field_amplitude: 0.1,
    field_wavelength_m: 80.0,
    blur_sigma_px: 0.0,
    noise_dn: 0.0,
    jpeg_quality: 0,
    shadow: Some(SunShadow {
        azimuth_deg: 235.0,
        elevation_deg: 48.0,
        darkening: 0.5,
    }),
};

/// The height sigmas of the Autzen surface model as a map states them: its 1 m cells under the
/// 0.3 m orthophoto put the textured edges of roofs, stands and crowns (where the features are)
/// above the gridded, smoothed surface, about a cell's height of error shared by what a footprint
/// sees (config/drone-autzen.toml states the same; docs/map-format.md, "Height uncertainty").
pub const AUTZEN_SURFACE_HEIGHTS: HeightSigmas = HeightSigmas {
    offset_m: Some(1.0),
    slope: None,
    point_m: None,
};

/// The heights an Autzen evaluation's map is built on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MapHeights {
    /// The lidar surface model the frames are ray-cast on, with these height sigmas stated at the
    /// build ([`AUTZEN_SURFACE_HEIGHTS`] is what its 1 m cells under the 0.3 m orthophoto call
    /// for).
    SurfaceModel(HeightSigmas),
    /// One constant height, the surface model's median (what a user without a DEM would take),
    /// with these height sigmas stated at the build.
    Constant(HeightSigmas),
}

/// The height sigmas a map's build states (`None`: the build's default for its height source;
/// `visnav map build --height-sigma-m`, `--height-slope-sigma`, `--height-point-sigma-m`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HeightSigmas {
    /// The offset shared by a footprint, m.
    pub offset_m: Option<f64>,
    /// The slope across a footprint, m/m.
    pub slope: Option<f64>,
    /// What is left per point, m.
    pub point_m: Option<f64>,
}

impl HeightSigmas {
    /// Stated on `spec`.
    fn apply(&self, spec: &mut BuildSpec) {
        spec.height_sigma_m = self.offset_m;
        spec.height_slope_sigma = self.slope;
        spec.height_point_sigma_m = self.point_m;
    }
}

/// The position / altitude prior an evaluation draws: errors (1 sigma per horizontal axis, and
/// vertical) and the sigmas the prior states.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionPriorSpec {
    /// The prior's drawn horizontal error, 1 sigma per axis, m.
    pub error_h_m: f64,
    /// The horizontal sigma the prior states, m.
    pub sigma_h_m: f64,
    /// The prior's drawn altitude error, 1 sigma, m.
    pub error_v_m: f64,
    /// The altitude sigma the prior states, m.
    pub sigma_v_m: f64,
}

/// What differs between the evaluation sites besides their data.
struct Site {
    agl_range_m: (f64, f64),
    max_tilt_deg: f64,
    margin_m: f64,
    position_prior: PositionPriorSpec,
}

/// The evaluation set-up: the 2009 reference, the fix engine and the 2014 renderer.
pub struct NaipEval {
    /// The orthophoto the map is built from (its first one; the Autzen map's degraded copy).
    pub map_raster: Raster,
    /// The fix engine under test, on the map.
    pub engine: FixEngine,
    /// The camera's scene: the camera-year orthophoto on the rendered surface.
    pub scene: Scene,
    /// The frames' renderer (the engine's camera).
    pub renderer: Renderer,
    /// The map's CRS.
    pub crs: Crs,
    /// Standard deviation of the prior attitude's error per axis, radians (default 0.3 deg; the
    /// prior states 0.5 deg whatever this is). The random draws do not depend on it, so runs
    /// with different values see the same frames.
    pub attitude_prior_error_rad: f64,
    /// Heights above ground the frames are drawn from, uniform in `[lo, hi]` metres (default
    /// 1200-2500 m, the acceptance envelope).
    pub agl_range_m: (f64, f64),
    /// Largest tilt of the body from level, degrees (uniform in `[0, max]`; default 20).
    pub max_tilt_deg: f64,
    /// A heading error of this size (degrees) added to the prior's heading on top of the random
    /// attitude error, positive on even frames and negative on odd ones (a compass-derived or
    /// drifted heading after a GPS loss). Default 0.
    pub yaw_error_deg: f64,
    /// The heading sigma the prior states, degrees (default: the same 0.5 deg as the tilt).
    pub yaw_sigma_deg: f64,
    /// What attitude the prior carries.
    pub attitude_mode: AttitudeMode,
    /// Diagnostic only (never an accuracy claim): the frames are rendered from the map's own
    /// orthophoto, so what remains is the solver's error, not the cross-date matching's.
    pub same_imagery: bool,
    /// Without the position prior ([`Self::run_with`]), the prior's altitude is still given (a
    /// barometer's); false: nothing of the position at all.
    pub altitude_without_position: bool,
    /// The map's own orthophoto as a scene (for `same_imagery`).
    map_scene: Scene,
    /// The surface the frames are rendered on (the truth's ground height).
    terrain: Dem,
    /// Frames' nadir points stay this far inside the map's bounds, metres.
    margin_m: f64,
    /// The position prior's errors and stated sigmas.
    pub position_prior: PositionPriorSpec,
}

/// The attitude the evaluation's prior carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AttitudeMode {
    /// Roll, pitch and heading (with the errors and sigmas above).
    Full,
    /// Roll and pitch only: the heading is unknown (stated sigma 180 deg).
    TiltOnly,
    /// No attitude at all.
    None,
}

/// An accepted fix further than this from the truth (3-D) is a wrong fix, metres, whatever
/// sigma it claims: a user steering by it would be lost.
pub const WRONG_FIX_M: f64 = 50.0;
/// An accepted fix beyond this many of its own sigmas on any NED axis is a wrong fix: the
/// autopilot's filter gates and weighs by the sigma it is told, so a fix outside its 3-sigma
/// bound is as harmful as one far away.
pub const WRONG_FIX_SIGMAS: f64 = 3.0;
/// The horizontal error's squared Mahalanobis distance (its own 2x2 covariance) beyond which a
/// fix is wrong: the chi-square (2 dof) quantile of the 3-sigma probability 0.9973, so an
/// error along a narrow axis of a tilted ellipse counts as the per-axis test would on its axes.
pub const WRONG_FIX_CHI2_H: f64 = 11.829;

/// One random frame of the acceptance envelope.
#[derive(Debug, Clone, Copy)]
pub struct Case {
    /// The true camera pose the frame is rendered from, map grid.
    pub pose: RenderPose,
    /// The true vehicle attitude (body to NED).
    pub attitude: Attitude,
    /// Grid convergence at the place (bearing of grid north clockwise from true north), rad.
    pub grid_convergence_rad: f64,
}

/// One frame of a bench run ([`NaipEval::draw`]).
struct Drawn {
    x_m: f64,
    y_m: f64,
    case: Case,
    img: GrayImage,
    prior: FixPrior,
}

/// Errors of one fix against the truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Score {
    /// Horizontal distance from the true camera centre, m.
    pub err_h_m: f64,
    /// Absolute vertical error against the true camera centre, m.
    pub err_v_m: f64,
    /// Largest per-axis (N, E, D) error in units of the fix's own sigma.
    pub err_sigma: f64,
    /// Horizontal error's squared Mahalanobis distance with the fix's N-E covariance (chi-square
    /// 2 dof when honest).
    pub chi2_h: f64,
    /// Distance from the truth, 3-D, metres.
    pub err_3d_m: f64,
    /// Normalised error squared of the image-only pose (position and attitude against the
    /// truth, with its 6x6 covariance): chi-square with 6 dof when the covariance is honest.
    pub nees6: Option<f64>,
    /// Horizontal error of the ground point under the image centre (boresight cast onto the
    /// ground plane at the truth's ground height): the map registration part of the error, free of
    /// the position/tilt ambiguity.
    pub ground_err_m: f64,
    /// Tilt error of the fix's attitude (angle between the estimated and true body z axes), deg.
    pub tilt_err_deg: f64,
}

impl Score {
    /// A wrong fix: more than [`WRONG_FIX_M`] from the truth in 3-D, or beyond 3 sigma on any
    /// NED axis ([`WRONG_FIX_SIGMAS`]) or horizontally jointly ([`WRONG_FIX_CHI2_H`]). NaN
    /// errors (a report without a finite position or covariance) are wrong too.
    pub fn is_wrong(&self) -> bool {
        self.is_far() || self.is_beyond_sigma()
    }

    /// More than [`WRONG_FIX_M`] off in 3-D (or not finite).
    pub fn is_far(&self) -> bool {
        self.err_3d_m.is_nan() || self.err_3d_m > WRONG_FIX_M
    }

    /// Outside its 3 sigma on an axis or jointly horizontally (or not finite).
    pub fn is_beyond_sigma(&self) -> bool {
        self.err_sigma.is_nan()
            || self.chi2_h.is_nan()
            || self.err_sigma > WRONG_FIX_SIGMAS
            || self.chi2_h > WRONG_FIX_CHI2_H
    }
}

/// Median, 90th percentile and maximum.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// The median (NaN when empty).
    pub median: f64,
    /// The 90th percentile.
    pub p90: f64,
    /// The largest value.
    pub max: f64,
}

impl Stats {
    /// Of a sample (NaN when empty).
    pub fn of(v: &[f64]) -> Self {
        Self {
            median: percentile(v, 0.5),
            p90: percentile(v, 0.9),
            max: percentile(v, 1.0),
        }
    }
}

use visnav_core::stats::percentile;

/// The mean, NaN for an empty sample (as [`percentile`]: JSON prints null, not a number no fix
/// had).
fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.iter().sum::<f64>() / v.len() as f64
}

/// Summary of an evaluation run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// Frames tried.
    pub frames: usize,
    /// Fixes the engine accepted.
    pub accepted: usize,
    /// Accepted over tried.
    pub fix_rate: f64,
    /// Horizontal error of the accepted fixes against the true camera centre, m.
    pub err_h_m: Stats,
    /// Absolute vertical error of the accepted fixes, m.
    pub err_v_m: Stats,
    /// Median horizontal error in map pixels.
    pub median_err_map_px: f64,
    /// Accepted fixes beyond 3 sigma on a NED axis.
    pub beyond_3_sigma: usize,
    /// Wrong fixes ([`Score::is_wrong`]): more than [`WRONG_FIX_M`] off the truth in 3-D, or
    /// beyond 3 sigma on an axis or jointly horizontally.
    pub wrong_fixes: usize,
    /// Of the wrong fixes: those more than [`WRONG_FIX_M`] off (3-D); a fix can count here and in
    /// `wrong_beyond_sigma`.
    pub wrong_far: usize,
    /// Of the wrong fixes: those outside their 3 sigma (on an axis or jointly horizontally).
    pub wrong_beyond_sigma: usize,
    /// Mean 6-dof NEES of the accepted fixes' image-only poses (= `vision_only_nees6_mean`;
    /// NaN, JSON null, without an accepted fix, as the error statistics).
    pub nees6_mean: f64,
    /// Image-only pose of the accepted fixes: mean 6-dof NEES (6 when honest).
    pub vision_only_nees6_mean: f64,
    /// Image-only poses of the accepted fixes beyond the chi-square(6) 99 % quantile (16.8; about
    /// 1 % when honest).
    pub vision_only_beyond_chi2_99: usize,
    /// Frame-to-fix wall time over all frames, milliseconds: the median.
    pub ms_p50: f64,
    /// The 95th percentile of that time, milliseconds.
    pub ms_p95: f64,
    /// Rejections by class (the whole reason in words without its numbers), most frequent
    /// first, each with its latest reason.
    pub rejections: Vec<visnav_core::reasons::ReasonCount>,
}

/// Median of `dem` over `bounds` on a 10 m grid (valid cells only), metres.
fn median_height_m(
    dem: &Dem,
    bounds: &visnav_core::geo::raster::Bounds,
) -> Result<f64, FixBenchError> {
    let mut h = Vec::new();
    let mut y = bounds.min_y_m;
    while y <= bounds.max_y_m {
        let mut x = bounds.min_x_m;
        while x <= bounds.max_x_m {
            h.extend(dem.height_at(x, y).filter(|v| v.is_finite()));
            x += 10.0;
        }
        y += 10.0;
    }
    let m = percentile(&h, 0.5);
    if m.is_finite() {
        Ok(m)
    } else {
        Err("the surface model has no valid height over the orthophoto".into())
    }
}

fn uni(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.uniform()
}

impl NaipEval {
    /// Loads `naip_nd_2009.tif` (map) and `naip_nd_2014.tif` (camera) from `maps_dir`.
    pub fn new(maps_dir: &Path, params: FixParams) -> Result<Self, FixBenchError> {
        let surf = SurfParams {
            upright: true,
            ..SurfParams::default()
        };
        Self::with_surf(maps_dir, params, surf)
    }

    /// [`Self::new`] with the reference's SURF settings (the query uses the same).
    pub fn with_surf(
        maps_dir: &Path,
        params: FixParams,
        surf: SurfParams,
    ) -> Result<Self, FixBenchError> {
        Self::with_map(
            maps_dir,
            &[maps_dir.join("naip_nd_2009.tif")],
            1,
            params,
            surf,
        )
    }

    /// [`Self::with_surf`] with the map built from `map_orthos` (co-registered orthophotos of the
    /// NAIP area, e.g. several years stacked; never the 2014 camera year). The first one gives the
    /// map's pixel size and the area the frames are drawn from. `upsample` as
    /// [`BuildSpec::upsample`].
    pub fn with_map(
        maps_dir: &Path,
        map_orthos: &[PathBuf],
        upsample: usize,
        params: FixParams,
        surf: SurfParams,
    ) -> Result<Self, FixBenchError> {
        Self::with_map_heights(
            maps_dir,
            map_orthos,
            upsample,
            params,
            surf,
            HeightSigmas::default(),
        )
    }

    /// [`Self::with_map`] with the map's height sigmas stated at its build.
    pub fn with_map_heights(
        maps_dir: &Path,
        map_orthos: &[PathBuf],
        upsample: usize,
        params: FixParams,
        surf: SurfParams,
        heights: HeightSigmas,
    ) -> Result<Self, FixBenchError> {
        let load =
            |path: &Path| load_geotiff(path, None).map_err(|e| format!("{}: {e}", path.display()));
        let first = map_orthos
            .first()
            .ok_or_else(|| "at least one map orthophoto is required".to_string())?;
        let map_raster = load(first)?;
        let cam_path = maps_dir.join("naip_nd_2014.tif");
        let cam_raster = load(&cam_path)?;
        for p in map_orthos {
            let r = if p == first { None } else { Some(load(p)?) };
            let r = r.as_ref().unwrap_or(&map_raster);
            if r.data() == cam_raster.data() {
                return Err(format!(
                    "{}: the map must not be built from the camera's own image (naip_nd_2014.tif)",
                    p.display()
                )
                .into());
            }
        }
        let flat = || Dem::flat(NAIP_GROUND_M).map_err(|e| e.to_string());
        // The product path: a .vnm map built from the map orthophoto(s), memory-mapped.
        let mut spec = BuildSpec::new(
            map_orthos.to_vec(),
            HeightSource::ConstantAmsl(NAIP_GROUND_M),
        );
        spec.surf = surf;
        spec.upsample = upsample;
        heights.apply(&mut spec);
        let reference = MapReference::build_temporary(&spec, None).map_err(|e| e.to_string())?;
        let camera = vga_camera().map_err(|e| format!("camera: {e}"))?;
        let engine = FixEngine::new(Arc::new(reference), camera, params)
            .map_err(|e| format!("engine: {e}"))?;
        let scene = Scene::new(&cam_raster, flat()?, ColourMode::Grey)
            .map_err(|e| format!("scene: {e}"))?;
        let map_scene = Scene::new(&map_raster, flat()?, ColourMode::Grey)
            .map_err(|e| format!("scene of the map image: {e}"))?;
        let renderer = Renderer::new(
            camera,
            RenderSpec {
                seed: 7,
                ..RenderSpec::default()
            },
        )
        .map_err(|e| format!("renderer: {e}"))?;
        Ok(Self::from_parts(
            map_raster,
            engine,
            [scene, map_scene],
            renderer,
            flat()?,
            Site {
                agl_range_m: (1200.0, 2500.0),
                max_tilt_deg: 20.0,
                margin_m: 600.0,
                position_prior: PositionPriorSpec {
                    error_h_m: 100.0,
                    sigma_h_m: 150.0,
                    error_v_m: 20.0,
                    sigma_v_m: 30.0,
                },
            },
        ))
    }

    /// The set-up from its parts, with the defaults every site shares (0.3 deg attitude error,
    /// full attitude prior with a 0.5 deg heading sigma, frames from the camera scene).
    fn from_parts(
        map_raster: Raster,
        engine: FixEngine,
        [scene, map_scene]: [Scene; 2],
        renderer: Renderer,
        terrain: Dem,
        site: Site,
    ) -> Self {
        let crs = map_raster.crs();
        Self {
            map_raster,
            engine,
            scene,
            renderer,
            crs,
            attitude_prior_error_rad: 0.3f64.to_radians(),
            agl_range_m: site.agl_range_m,
            max_tilt_deg: site.max_tilt_deg,
            yaw_error_deg: 0.0,
            yaw_sigma_deg: 0.5,
            attitude_mode: AttitudeMode::Full,
            same_imagery: false,
            altitude_without_position: true,
            map_scene,
            terrain,
            margin_m: site.margin_m,
            position_prior: site.position_prior,
        }
    }

    /// The Autzen drone-scale case (module docs) from `data_dir` (`../shared/data/autzen`): the
    /// 0.3 m orthophoto and the 1 m lidar surface model, the map on `heights`. The map is built
    /// from one degraded copy of the orthophoto ([`AUTZEN_MAP_COPY`]) and the frames are rendered
    /// from another ([`AUTZEN_CAMERA_COPY`]): one date only, so neither sees the other's image.
    pub fn autzen(
        data_dir: &Path,
        params: FixParams,
        heights: MapHeights,
    ) -> Result<Self, FixBenchError> {
        let ortho = data_dir.join("autzen_ortho_0p3m_utm10n.tif");
        let dsm = data_dir.join("autzen_dsm_1m_utm10n.tif");
        let original =
            load_geotiff(&ortho, None).map_err(|e| format!("{}: {e}", ortho.display()))?;
        let surface = visnav_io::geo::dem::load_dem(&dsm, Some(original.crs()))
            .map_err(|e| format!("{}: {e}", dsm.display()))?;
        let map_raster = degrade(&original, Some(&surface), &AUTZEN_MAP_COPY)
            .map_err(|e| format!("the map's copy of {}: {e}", ortho.display()))?;
        let cam_raster = degrade(&original, Some(&surface), &AUTZEN_CAMERA_COPY)
            .map_err(|e| format!("the camera's copy of {}: {e}", ortho.display()))?;
        drop(original);
        // The map build reads files: the map's copy goes through a temporary GeoTIFF.
        let dir = tempfile::tempdir().map_err(|e| format!("temporary folder: {e}"))?;
        let map_copy = dir.path().join("autzen_map_copy.tif");
        write_geotiff(&map_raster, &map_copy).map_err(|e| e.to_string())?;
        let mut spec = match heights {
            MapHeights::SurfaceModel(sigmas) => {
                let mut spec =
                    BuildSpec::new(vec![map_copy.clone()], HeightSource::Dem(dsm.clone()));
                sigmas.apply(&mut spec);
                spec
            }
            MapHeights::Constant(sigmas) => {
                let mut spec = BuildSpec::new(
                    vec![map_copy.clone()],
                    HeightSource::ConstantAmsl(median_height_m(&surface, &map_raster.bounds())?),
                );
                sigmas.apply(&mut spec);
                spec
            }
        };
        spec.surf = SurfParams {
            upright: true,
            ..SurfParams::default()
        };
        let reference = MapReference::build_temporary(&spec, None).map_err(|e| e.to_string())?;
        drop(dir);
        let camera = drone_camera().map_err(|e| format!("camera: {e}"))?;
        let engine = FixEngine::new(Arc::new(reference), camera, params)
            .map_err(|e| format!("engine: {e}"))?;
        let scene = Scene::new(&cam_raster, surface.clone(), ColourMode::Grey)
            .map_err(|e| format!("scene: {e}"))?;
        let map_scene = Scene::new(&map_raster, surface.clone(), ColourMode::Grey)
            .map_err(|e| format!("scene of the map image: {e}"))?;
        // The camera's own photometry on top of its copy.
        let mut render = RenderSpec {
            seed: 7,
            ..RenderSpec::default()
        };
        render.exposure.gain = 1.15;
        render.exposure.gamma = 0.8;
        render.exposure.vignetting_corner = 0.15;
        render.blur.sigma_px = 0.7;
        render.noise.read_dn = 2.0;
        let renderer = Renderer::new(camera, render).map_err(|e| format!("renderer: {e}"))?;
        Ok(Self::from_parts(
            map_raster,
            engine,
            [scene, map_scene],
            renderer,
            surface,
            Site {
                agl_range_m: (80.0, 300.0),
                max_tilt_deg: 10.0,
                margin_m: 250.0,
                position_prior: PositionPriorSpec {
                    error_h_m: 20.0,
                    sigma_h_m: 30.0,
                    error_v_m: 5.0,
                    sigma_v_m: 10.0,
                },
            },
        ))
    }

    /// The same evaluation seen through `camera` (the fix engine and the renderer rebuilt with
    /// it; the map, the scenes and every draw stay the same).
    pub fn with_camera(mut self, camera: Camera) -> Result<Self, FixBenchError> {
        self.engine = FixEngine::new(
            self.engine.reference().clone(),
            camera,
            self.engine.params().clone(),
        )
        .map_err(|e| format!("engine: {e}"))?;
        self.renderer =
            Renderer::new(camera, *self.renderer.spec()).map_err(|e| format!("renderer: {e}"))?;
        Ok(self)
    }

    /// Height of the rendered surface at `(x, y)` (the truth's ground), metres AMSL.
    pub fn ground_m(&self, x_m: f64, y_m: f64) -> f64 {
        self.terrain
            .height_at(x_m, y_m)
            .unwrap_or_else(|| self.terrain.height_range_m().0)
    }

    /// Map pixel size, metres.
    pub fn map_gsd_m(&self) -> f64 {
        self.map_raster.transform().pixel_size().0
    }

    /// A random pose of the envelope with its body (nadir point) over `(x, y)`.
    pub fn random_case(&self, rng: &mut Rng, x_m: f64, y_m: f64) -> Case {
        let agl_m = uni(rng, self.agl_range_m.0, self.agl_range_m.1);
        let tilt_deg = uni(rng, 0.0, self.max_tilt_deg);
        let dir = uni(rng, 0.0, std::f64::consts::TAU);
        let attitude = Attitude::from_deg(
            tilt_deg * dir.cos(),
            tilt_deg * dir.sin(),
            uni(rng, -180.0, 180.0),
        );
        let gamma = grid_convergence_rad(&self.crs, x_m, y_m).unwrap_or(0.0);
        let body = Vector3::new(x_m, y_m, self.ground_m(x_m, y_m) + agl_m);
        Case {
            pose: RenderPose::from_body(body, &attitude, &Mount::nadir(), gamma),
            attitude,
            grid_convergence_rad: gamma,
        }
    }

    /// The frame of `case` rendered from `scene` (the 2014 scene unless another is given).
    pub fn frame(
        &self,
        case: &Case,
        index: u64,
        scene: Option<&Scene>,
    ) -> Result<GrayImage, FixBenchError> {
        let f = self
            .renderer
            .render(scene.unwrap_or(&self.scene), &case.pose, index)
            .map_err(|e| format!("render: {e}"))?;
        GrayImage::new(f.width, f.height, f.grey()).map_err(|e| FixBenchError(e.to_string()))
    }

    /// The prior a filter would give (see the module doc).
    pub fn prior(&self, rng: &mut Rng, case: &Case, index: u64) -> Result<FixPrior, FixBenchError> {
        let c = case.pose.centre_map_m;
        let pp = self.position_prior;
        let (px, py) = (
            c.x + pp.error_h_m * rng.normal(),
            c.y + pp.error_h_m * rng.normal(),
        );
        let (lat, lon) = self.crs.to_geodetic(px, py).map_err(|e| e.to_string())?;
        // Draw order as before the attitude modes existed (the same frames and priors per seed).
        let alt_amsl_m = c.z + pp.error_v_m * rng.normal();
        let n = self.attitude_prior_error_rad;
        let a = &case.attitude;
        let sign = if index.is_multiple_of(2) { 1.0 } else { -1.0 };
        let yaw_err = sign * self.yaw_error_deg.to_radians();
        let (roll_e, pitch_e, yaw_e) = (n * rng.normal(), n * rng.normal(), n * rng.normal());
        let attitude = Attitude::new(
            a.roll_rad + roll_e,
            a.pitch_rad + pitch_e,
            a.yaw_rad + yaw_e + yaw_err,
        );
        let stated = 0.5f64.to_radians();
        let attitude = match self.attitude_mode {
            AttitudeMode::Full => Some(AttitudePriorNed {
                attitude,
                sigma_rad: stated,
                sigma_yaw_rad: self.yaw_sigma_deg.to_radians(),
            }),
            // The heading is unknown: a heading of 0 with a sigma of half a turn.
            AttitudeMode::TiltOnly => Some(AttitudePriorNed {
                attitude: Attitude::new(attitude.roll_rad, attitude.pitch_rad, 0.0),
                sigma_rad: stated,
                sigma_yaw_rad: std::f64::consts::PI,
            }),
            AttitudeMode::None => None,
        };
        Ok(FixPrior {
            t_capture_us: index,
            position: Some(PositionPriorGeo {
                lat_deg: lat,
                lon_deg: lon,
                alt_amsl_m,
                sigma_h_m: pp.sigma_h_m,
                sigma_v_m: pp.sigma_v_m,
            }),
            attitude,
            altitude: None,
            attitude_from_filter: false,
            widen_heading: true,
        })
    }

    /// Errors of an accepted report against the case's truth.
    pub fn score(&self, r: &FixReport, case: &Case) -> Score {
        let t = case.pose.centre_map_m;
        let (ex, ey, ez) = (r.x_m - t.x, r.y_m - t.y, r.z_m - t.z);
        let (s, c) = case.grid_convergence_rad.sin_cos();
        let e_n = ey * c - ex * s;
        let e_e = ex * c + ey * s;
        let err_sigma = (e_n / r.cov_ned_m2[0][0].sqrt())
            .abs()
            .max((e_e / r.cov_ned_m2[1][1].sqrt()).abs())
            .max((ez / r.cov_ned_m2[2][2].sqrt()).abs());
        let c_h = nalgebra::Matrix2::new(
            r.cov_ned_m2[0][0],
            r.cov_ned_m2[0][1],
            r.cov_ned_m2[1][0],
            r.cov_ned_m2[1][1],
        );
        let e_h = nalgebra::Vector2::new(e_n, e_e);
        // A singular or non-finite covariance claims certainty: infinitely far in its own units.
        let chi2_h = c_h
            .try_inverse()
            .map_or(f64::INFINITY, |ci| (e_h.transpose() * ci * e_h)[(0, 0)]);
        // Boresight (body z of the nadir mount) cast onto the ground plane, in grid axes.
        let down = |a: &Attitude| {
            let d = a.r_ned_body() * Vector3::z();
            // NED -> grid east/north (grid convergence gamma: grid north = true north rotated).
            (d.y * c - d.x * s, d.x * c + d.y * s, d.z)
        };
        let ground = |a: &Attitude, x: f64, y: f64, h: f64| {
            let (de, dn, dd) = down(a);
            (x + de * h / dd, y + dn * h / dd)
        };
        let a_est = Attitude::from_deg(r.roll_deg, r.pitch_deg, r.yaw_deg);
        let ground_m = self.ground_m(t.x, t.y);
        let h_true = t.z - ground_m;
        let g_est = ground(&a_est, r.x_m, r.y_m, r.z_m - ground_m);
        let g_true = ground(&case.attitude, t.x, t.y, h_true);
        let z_est = a_est.r_ned_body() * Vector3::z();
        let z_true = case.attitude.r_ned_body() * Vector3::z();
        Score {
            err_h_m: ex.hypot(ey),
            err_v_m: ez.abs(),
            err_sigma,
            chi2_h: if chi2_h.is_finite() {
                chi2_h
            } else {
                f64::INFINITY
            },
            err_3d_m: (ex * ex + ey * ey + ez * ez).sqrt(),
            nees6: self.nees6(r, case),
            ground_err_m: (g_est.0 - g_true.0).hypot(g_est.1 - g_true.1),
            tilt_err_deg: z_est.angle(&z_true).to_degrees(),
        }
    }

    /// The report's image-only pose: map grid x, y (m) and its attitude (NED from body).
    fn vision_only_map(&self, r: &FixReport) -> Option<(f64, f64, UnitQuaternion<f64>)> {
        let v = r.vision_only?;
        let (x, y) = self.crs.from_geodetic(v.lat_deg, v.lon_deg).ok()?;
        let q = UnitQuaternion::from_euler_angles(
            v.roll_deg.to_radians(),
            v.pitch_deg.to_radians(),
            v.yaw_deg.to_radians(),
        );
        Some((x, y, q))
    }

    /// 6-dof NEES of the report's image-only pose (None without one).
    fn nees6(&self, r: &FixReport, case: &Case) -> Option<f64> {
        let v = r.vision_only?;
        let t = case.pose.centre_map_m;
        let (x, y, q_meas) = self.vision_only_map(r)?;
        let n = visnav_core::geo::geoid::geoid_undulation_m(v.lat_deg, v.lon_deg).ok()?;
        let (ex, ey, ez) = (x - t.x, y - t.y, v.h_ellip_m - n - t.z);
        let (sg, cg) = case.grid_convergence_rad.sin_cos();
        let q_true = UnitQuaternion::from_rotation_matrix(&case.attitude.r_ned_body());
        let psi = (q_meas * q_true.inverse()).scaled_axis();
        let e = Vector6::new(
            ey * cg - ex * sg,
            ex * cg + ey * sg,
            -ez,
            psi.x,
            psi.y,
            psi.z,
        );
        let inv = v.cov6().try_inverse()?;
        Some((e.transpose() * inv * e)[0])
    }

    /// Horizontal error (m) and tilt error (deg) of the report's image-only pose.
    fn vision_only_errors(&self, r: &FixReport, case: &Case) -> Option<(f64, f64)> {
        let t = case.pose.centre_map_m;
        let (x, y, q_meas) = self.vision_only_map(r)?;
        let z_true = case.attitude.r_ned_body() * Vector3::z();
        let z_est = q_meas * Vector3::z();
        Some(((x - t.x).hypot(y - t.y), z_est.angle(&z_true).to_degrees()))
    }

    /// Number of fine matches whose map point projects within 3 px of the query keypoint
    /// through the true pose.
    pub fn correct_pairs(&self, a: &Attempt, case: &Case) -> usize {
        a.pairs
            .iter()
            .filter(|(px, p)| {
                case.pose
                    .project(self.renderer.camera(), &Vector3::new(p[0], p[1], p[2]))
                    .is_some_and(|q| (q.x - px[0]).hypot(q.y - px[1]) < 3.0)
            })
            .count()
    }

    /// The fix engine under test.
    pub fn engine(&self) -> &FixEngine {
        &self.engine
    }

    /// The fix engine under test, to change its feature backend (the GPU path).
    pub fn engine_mut(&mut self) -> &mut FixEngine {
        &mut self.engine
    }

    /// The map's bounds and the margin the frames keep from them, m (the acceptance run's area).
    pub fn frame_area_m(&self) -> ([f64; 4], f64) {
        let b = self.map_raster.bounds();
        ([b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m], self.margin_m)
    }

    /// The acceptance run: `n` frames with their nadir points at least 600 m inside the map.
    /// `log` receives one line per frame.
    pub fn run(
        &self,
        n: usize,
        seed: u64,
        log: &mut dyn FnMut(String),
    ) -> Result<Summary, FixBenchError> {
        self.run_with(n, seed, true, log)
    }

    /// Frame `i` of a run: a place drawn inside the margin, a pose there, its rendered frame and
    /// the prior (without the position when `position_prior` is false: the altitude alone when
    /// the bench keeps it).
    fn draw(&self, rng: &mut Rng, i: usize, position_prior: bool) -> Result<Drawn, FixBenchError> {
        let b = self.map_raster.bounds();
        let x_m = uni(rng, b.min_x_m + self.margin_m, b.max_x_m - self.margin_m);
        let y_m = uni(rng, b.min_y_m + self.margin_m, b.max_y_m - self.margin_m);
        let case = self.random_case(rng, x_m, y_m);
        let scene = self.same_imagery.then_some(&self.map_scene);
        let img = self.frame(&case, i as u64, scene)?;
        let mut prior = self.prior(rng, &case, i as u64)?;
        if !position_prior {
            prior.altitude = prior
                .position
                .filter(|_| self.altitude_without_position)
                .map(|p| AltitudePrior {
                    alt_amsl_m: p.alt_amsl_m,
                    sigma_m: p.sigma_v_m,
                });
            prior.position = None;
        }
        Ok(Drawn {
            x_m,
            y_m,
            case,
            img,
            prior,
        })
    }

    /// [`Self::run`]; without the position prior when `position_prior` is false (global
    /// relocalisation with the attitude prior only).
    pub fn run_with(
        &self,
        n: usize,
        seed: u64,
        position_prior: bool,
        log: &mut dyn FnMut(String),
    ) -> Result<Summary, FixBenchError> {
        let mut rng = Rng::new(seed);
        let (mut eh, mut ev, mut ms) = (Vec::new(), Vec::new(), Vec::new());
        let (mut accepted, mut beyond, mut wrong) = (0, 0, 0);
        let (mut wrong_far, mut wrong_beyond_sigma) = (0, 0);
        let mut nees6 = Vec::new();
        let mut reasons = visnav_core::reasons::ReasonTally::default();
        for i in 0..n {
            let Drawn {
                x_m: x,
                y_m: y,
                case,
                img,
                prior,
            } = self.draw(&mut rng, i, position_prior)?;
            let start = std::time::Instant::now();
            let (mut r, a) = self.engine.fix_with_attempt(&img, &prior);
            r.ms = start.elapsed().as_secs_f64() * 1e3;
            ms.push(r.ms);
            let good = self.correct_pairs(&a, &case);
            if r.accepted {
                let s = self.score(&r, &case);
                accepted += 1;
                eh.push(s.err_h_m);
                ev.push(s.err_v_m);
                if s.err_sigma > 3.0 {
                    beyond += 1;
                }
                let is_wrong = s.is_wrong();
                if is_wrong {
                    wrong += 1;
                    wrong_far += usize::from(s.is_far());
                    wrong_beyond_sigma += usize::from(s.is_beyond_sigma());
                }
                nees6.extend(s.nees6);
                let vo = self
                    .vision_only_errors(&r, &case)
                    .unwrap_or((f64::NAN, f64::NAN));
                let prior_dv_m = prior
                    .position
                    .as_ref()
                    .map_or(f64::NAN, |p| p.alt_amsl_m - case.pose.centre_map_m.z);
                // A placement fix has no resection: no image-only pose, residuals or sigma0.
                let resection = if r.reproj_rms_px.is_finite() {
                    format!(
                        "image-only h {:.1} m tilt {:.2} deg NEES {:.1}, reprojection RMS {:.2} px, sigma0 {:.2}",
                        vo.0,
                        vo.1,
                        s.nees6.unwrap_or(f64::NAN),
                        r.reproj_rms_px,
                        r.sigma0
                    )
                } else {
                    "no resection".to_string()
                };
                log(format!(
                    "frame {i:3}: accepted{} ({}), {} inliers of {} matches ({good} correct, chance {}), error h {:.1} m v {:+.1} m = {:.2} sigma (sigma h {:.1} v {:.1} m; {:.0} m above ground, prior altitude {:+.1} m), ground {:.1} m tilt {:.2} deg, {resection}, covariance factor {:.1}, {:.1} ms",
                    if is_wrong { " WRONG" } else { "" },
                    r.method,
                    r.inliers,
                    r.matches,
                    a.null_matches,
                    s.err_h_m,
                    r.z_m - case.pose.centre_map_m.z,
                    s.err_sigma,
                    r.cov_ned_m2[0][0].max(r.cov_ned_m2[1][1]).sqrt(),
                    r.cov_ned_m2[2][2].sqrt(),
                    case.pose.centre_map_m.z - self.ground_m(x, y),
                    prior_dv_m,
                    s.ground_err_m,
                    s.tilt_err_deg,
                    r.cov_factor,
                    r.ms
                ));
            } else {
                // Reasons that differ only in their numbers count as one.
                let reason = r.reason();
                reasons.add(r.class(), &reason);
                log(format!(
                    "frame {i:3}: {reason} ({} matches, {good} correct, chance {}), {:.1} ms",
                    r.matches, a.null_matches, r.ms
                ));
            }
        }
        let err_h_m = Stats::of(&eh);
        Ok(Summary {
            frames: n,
            accepted,
            fix_rate: accepted as f64 / n.max(1) as f64,
            median_err_map_px: err_h_m.median / self.map_gsd_m(),
            err_h_m,
            err_v_m: Stats::of(&ev),
            beyond_3_sigma: beyond,
            wrong_fixes: wrong,
            wrong_far,
            wrong_beyond_sigma,
            nees6_mean: mean(&nees6),
            vision_only_nees6_mean: mean(&nees6),
            vision_only_beyond_chi2_99: nees6.iter().filter(|&&x| x > 16.81).count(),
            ms_p50: percentile(&ms, 0.5),
            ms_p95: percentile(&ms, 0.95),
            rejections: reasons.counts(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn score(err_3d_m: f64, err_sigma: f64, chi2_h: f64) -> Score {
        Score {
            err_h_m: err_3d_m,
            err_v_m: 0.0,
            err_sigma,
            chi2_h,
            err_3d_m,
            nees6: None,
            ground_err_m: 0.0,
            tilt_err_deg: 0.0,
        }
    }

    /// Wrong: far in 3-D whatever the sigma, or outside 3 sigma on an axis, or jointly
    /// horizontally though inside 3 sigma on each axis; and anything not finite.
    #[test]
    fn a_wrong_fix_is_far_or_outside_its_3_sigma_on_an_axis_or_jointly() {
        assert!(!score(20.0, 2.9, 11.0).is_wrong());
        let far = score(50.1, 1.0, 1.0);
        assert!(far.is_wrong() && far.is_far() && !far.is_beyond_sigma());
        let axis = score(10.0, 3.1, 9.6);
        assert!(axis.is_wrong() && !axis.is_far() && axis.is_beyond_sigma());
        // 2.5 sigma on both axes of a round ellipse: chi-square 12.5, beyond the 3-sigma mass.
        let joint = score(10.0, 2.5, 12.5);
        assert!(joint.is_wrong() && joint.is_beyond_sigma());
        assert!(score(f64::NAN, 1.0, 1.0).is_wrong());
        assert!(score(1.0, f64::NAN, 1.0).is_wrong());
        assert!(score(1.0, 1.0, f64::INFINITY).is_wrong());
    }
}
