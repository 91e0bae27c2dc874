//! Wiring the configuration to the algorithms: the fix engine a configuration describes (its map
//! opened or built, its DEM loaded) and the engine as the daemon's [`FrameFixer`]. The algorithm
//! modules know nothing of the application's configuration; this is where the two meet.

use std::sync::Arc;

use crate::config::Config;
use crate::config::vision::VisionBackend;
use crate::fixer::FrameFixer;
use visnav_core::camera::CameraError;
use visnav_core::fix::{FixEngine, FixError, FixPrior, FixReport, Reference};
use visnav_core::geo::dem::{Dem, DemError};
use visnav_core::vision::GrayImage;
use visnav_io::geo::dem::DemFileError;
use visnav_io::map::MapReference;
use visnav_io::map::MapReferenceError;
use visnav_io::map::paged::{LoadMode, PagedMap};

/// Why the configuration's fix engine could not be built; each names the section and key.
#[derive(Debug, thiserror::Error)]
pub enum WiringError {
    /// `[camera]` is not usable.
    #[error("[camera]: {0}")]
    Camera(CameraError),
    /// The `[map] dem` file is not usable.
    #[error("[map] dem {}: {error}", .path.display())]
    Dem {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        error: Box<DemFileError>,
    },
    /// `[map] ground_height_amsl_m` is not usable.
    #[error("[map] ground_height_amsl_m: {0}")]
    GroundHeight(DemError),
    /// The `[map] file` could not be opened.
    #[error("[map] file: {0}")]
    MapFile(MapReferenceError),
    /// `[map]` names no terrain.
    #[error("[map]: give file, or ortho with dem or ground_height_amsl_m")]
    NoTerrain,
    /// The map could not be built from `[map] ortho`.
    #[error("[map] ortho: {0}")]
    MapBuild(MapReferenceError),
    /// `[fix]` is not usable.
    #[error("[fix]: {0}")]
    Fix(FixError),
}

/// The engine a configuration describes: the `.vnm` map of `[map] file` (terrain overridden by
/// `dem` / `ground_height_amsl_m` when given), or, without one, a map built at start into a
/// temporary file from `[map] ortho` (small areas); the camera of `[camera]`; `[fix]` settings.
/// Paths must already be resolved (as `Config::load` does).
pub fn engine_from_config(cfg: &Config) -> Result<FixEngine, WiringError> {
    Ok(engine_and_pages(cfg, LoadMode::Background)?.0)
}

/// The frame path's fixer a configuration describes: [`engine_from_config`]'s engine, or, when
/// `[map] file` is a tiled map's folder, the engine over its paged tiles with the pager that asks
/// for them ahead of each frame (`crate::paging`).
pub fn fixer_from_config(cfg: &Config) -> Result<Arc<dyn FrameFixer>, WiringError> {
    fixer_from_config_with(cfg, LoadMode::Background)
}

/// [`fixer_from_config`] with a tiled map's tiles loaded as `tiles` says (the lock-step
/// simulator loads them inline, so every run of a seed meets the same tiles).
pub fn fixer_from_config_with(
    cfg: &Config,
    tiles: LoadMode,
) -> Result<Arc<dyn FrameFixer>, WiringError> {
    Ok(match engine_and_pages(cfg, tiles)? {
        (engine, Some(map)) => Arc::new(crate::paging::PagedFixer::new(engine, map)),
        (engine, None) => Arc::new(engine),
    })
}

/// Default `[map] memory_mb`: tiles of 2 000 px are a few MB, so 512 MB holds a hundred of them,
/// several times the squares a footprint and its look-ahead touch, on a 4-8 GB companion board.
pub const DEFAULT_MAP_MEMORY_MB: u64 = 512;

/// The engine, and the paged map under it when `[map] file` is a tiled map's folder.
fn engine_and_pages(
    cfg: &Config,
    tiles: LoadMode,
) -> Result<(FixEngine, Option<Arc<PagedMap>>), WiringError> {
    let camera = cfg.camera.build().map_err(WiringError::Camera)?;
    let dem = match (&cfg.map.dem, cfg.map.ground_height_amsl_m) {
        (Some(p), _) => Some(
            visnav_io::geo::dem::load_dem(p, cfg.map.crs_override).map_err(|error| {
                WiringError::Dem {
                    path: p.clone(),
                    error: Box::new(error),
                }
            })?,
        ),
        (None, Some(h)) => Some(Dem::flat(h).map_err(WiringError::GroundHeight)?),
        (None, None) => None,
    };
    let mut pages = None;
    let reference: Arc<dyn Reference> = match &cfg.map.file {
        Some(f) if f.is_dir() => {
            let memory_mb = cfg.map.memory_mb.unwrap_or(DEFAULT_MAP_MEMORY_MB);
            let map = Arc::new(
                PagedMap::open_with(f, memory_mb, dem, tiles).map_err(WiringError::MapFile)?,
            );
            pages = Some(Arc::clone(&map));
            map
        }
        Some(f) => Arc::new(MapReference::open(f, dem).map_err(WiringError::MapFile)?),
        None => {
            let spec = cfg.map.build_spec().ok_or(WiringError::NoTerrain)?;
            Arc::new(MapReference::build_temporary(&spec, dem).map_err(WiringError::MapBuild)?)
        }
    };
    let mut engine =
        FixEngine::new(reference, camera, cfg.fix.clone()).map_err(WiringError::Fix)?;
    if let Some(backend) = feature_backend(cfg.vision.backend) {
        engine.set_feature_backend(backend);
    }
    Ok((engine, pages))
}

/// The feature backend for `[vision] backend` (None: the CPU), saying what was chosen and why.
#[cfg(feature = "gpu")]
fn feature_backend(b: VisionBackend) -> Option<Arc<dyn visnav_core::vision::FeatureBackend>> {
    use visnav_gpu::{AdapterPolicy, GpuSurf};
    let policy = match b {
        VisionBackend::Cpu => return None,
        VisionBackend::Gpu => AdapterPolicy::AllowSoftware,
        VisionBackend::Auto => AdapterPolicy::HardwareOnly,
    };
    match GpuSurf::new(policy) {
        Ok(g) => {
            if g.adapter().software {
                tracing::warn!(
                    "vision: SURF on {} as [vision] backend = \"gpu\" asks; a software adapter is slower than the CPU",
                    g.adapter()
                );
            } else {
                tracing::info!("vision: SURF on the GPU, {}", g.adapter());
            }
            Some(Arc::new(g))
        }
        Err(e) if b == VisionBackend::Gpu => {
            tracing::warn!("vision: [vision] backend = \"gpu\": {e}; SURF runs on the CPU");
            None
        }
        Err(e) => {
            tracing::info!("vision: [vision] backend = \"auto\": {e}; SURF runs on the CPU");
            None
        }
    }
}

/// Without the GPU path compiled in: the CPU, with a warning when the GPU was asked for.
#[cfg(not(feature = "gpu"))]
fn feature_backend(b: VisionBackend) -> Option<Arc<dyn visnav_core::vision::FeatureBackend>> {
    if b == VisionBackend::Gpu {
        tracing::warn!(
            "vision: [vision] backend = \"gpu\": this visnav is built without the GPU path (cargo build --release --features gpu); SURF runs on the CPU"
        );
    }
    None
}

impl FrameFixer for FixEngine {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport {
        FixEngine::fix(self, image, prior)
    }

    fn odometer(&self, cfg: &visnav_core::vo::VoConfig) -> Option<visnav_core::vo::Odometer> {
        Some(visnav_core::vo::Odometer::new(
            *self.camera(),
            self.reference().clone(),
            cfg.clone(),
        ))
    }

    fn dtm_navigator(
        &self,
        cfg: &visnav_core::dtm_nav::DtmNavConfig,
    ) -> Option<visnav_core::dtm_nav::DtmNavigator> {
        Some(visnav_core::dtm_nav::DtmNavigator::new(
            *self.camera(),
            self.reference().clone(),
            cfg.clone(),
        ))
    }
}
