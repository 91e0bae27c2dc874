//! Wiring the configuration to the algorithms: the fix engine a configuration describes (its map
//! opened or built, its DEM loaded) and the engine as the daemon's [`FrameFixer`]. The algorithm
//! modules know nothing of the application's configuration; this is where the two meet.

use std::sync::Arc;

use super::FrameFixer;
use super::app_config::Config;
use crate::fix::{FixEngine, FixPrior, FixReport, MapReference, Reference};
use crate::geo::dem::Dem;
use crate::map::{BuildSpec, HeightSource};
use crate::vision::GrayImage;

/// The engine a configuration describes: the `.vnm` map of `[map] file` (terrain overridden by
/// `dem` / `ground_height_amsl_m` when given), or, without one, a map built at start into a
/// temporary file from `[map] ortho` (small areas); the camera of `[camera]`; `[fix]` settings.
/// Paths must already be resolved (as `Config::load` does).
pub fn engine_from_config(cfg: &Config) -> Result<FixEngine, String> {
    let camera = cfg.camera.build().map_err(|e| format!("[camera]: {e}"))?;
    let dem = match (&cfg.map.dem, cfg.map.ground_height_amsl_m) {
        (Some(p), _) => Some(
            Dem::load_geotiff(p, cfg.map.crs_override)
                .map_err(|e| format!("[map] dem {}: {e}", p.display()))?,
        ),
        (None, Some(h)) => {
            Some(Dem::flat(h).map_err(|e| format!("[map] ground_height_amsl_m: {e}"))?)
        }
        (None, None) => None,
    };
    let reference: Arc<dyn Reference> = match &cfg.map.file {
        Some(f) => Arc::new(MapReference::open(f, dem).map_err(|e| format!("[map] file: {e}"))?),
        None => {
            let height = match (&cfg.map.dem, cfg.map.ground_height_amsl_m) {
                (Some(p), _) => HeightSource::Dem(p.clone()),
                (None, Some(h)) => HeightSource::ConstantAmsl(h),
                (None, None) => {
                    return Err(
                        "[map]: give file, or ortho with dem or ground_height_amsl_m".into(),
                    );
                }
            };
            let mut spec = BuildSpec::new(cfg.map.ortho.clone(), height);
            spec.crs_override = cfg.map.crs_override;
            spec.upsample = cfg.map.upsample.unwrap_or(1);
            spec.height_sigma_m = cfg.map.height_sigma_m;
            Arc::new(
                MapReference::build_temporary(&spec, dem)
                    .map_err(|e| format!("[map] ortho: {e}"))?,
            )
        }
    };
    FixEngine::new(reference, camera, cfg.fix.clone()).map_err(|e| format!("[fix]: {e}"))
}

impl FrameFixer for FixEngine {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport {
        FixEngine::fix(self, image, prior)
    }
}
