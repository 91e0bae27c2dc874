//! The `.vnm` reference map as the fix engine's [`Reference`]: the memory-mapped map file
//! ([`ReferenceMap`]) with the terrain its features were placed on, for ray casting. Opening finds
//! the terrain the map was built from (its constant ground height, or its DEM file next to the map
//! or at the recorded path); [`MapReference::build_temporary`] builds a map from orthophotos into a
//! temporary file first (small areas given as images).

use std::path::{Path, PathBuf};

use visnav_core::fix::reference::{MapImage, RefSelection, Reference};
use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::vision::FeatureSpec;

use super::{BuildSpec, HeightInfo, MapError, ReferenceMap, build_map};
use crate::geo::dem::load_dem;

/// A `.vnm` reference map (memory-mapped) with the terrain for ray casting.
pub struct MapReference {
    map: ReferenceMap,
    dem: Dem,
}

/// Why a map reference could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum MapReferenceError {
    /// The map file could not be opened or built.
    #[error(transparent)]
    Map(#[from] MapError),
    /// The DEM the map names is not where the map says.
    #[error(
        "{map}: the DEM it was built from ({dem}) was not found next to the map or at that path; give the DEM explicitly"
    )]
    DemNotFound {
        /// The map file.
        map: String,
        /// The DEM file the map names.
        dem: String,
    },
    /// The DEM the map names could not be used.
    #[error("{map}: DEM {dem}: {reason}")]
    Dem {
        /// The map file.
        map: String,
        /// The DEM file the map names.
        dem: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// Building the temporary map failed (`build_temporary`).
    #[error("map build: {0}")]
    Build(MapError),
}

/// The flat terrain of a map built on a constant ground height (`map` names it in the error).
pub(crate) fn constant_terrain(map: &Path, amsl_m: f64) -> Result<Dem, MapReferenceError> {
    Dem::flat(amsl_m).map_err(|e| MapReferenceError::Dem {
        map: map.display().to_string(),
        dem: format!("constant {amsl_m} m"),
        reason: e.to_string(),
    })
}

/// The DEM a map file at `map` was built on, as its header records it (`recorded`): looked up
/// next to the map first (maps travel with their DEM), then as recorded.
pub(crate) fn find_dem(map: &Path, recorded: &str) -> Option<PathBuf> {
    let recorded = PathBuf::from(recorded);
    let beside = map
        .parent()
        .unwrap_or(Path::new("."))
        .join(recorded.file_name().unwrap_or_default());
    [beside, recorded].into_iter().find(|p| p.is_file())
}

impl MapReference {
    /// Opens `path`. The terrain: `dem` when given, otherwise the map's constant ground height,
    /// or the DEM file it was built from (looked up next to the map first, then as recorded).
    pub fn open(path: &Path, dem: Option<Dem>) -> Result<Self, MapReferenceError> {
        let map = ReferenceMap::open(path)?;
        let dem = match (dem, &map.header().height) {
            (Some(d), _) => d,
            (None, HeightInfo::Constant { amsl_m }) => constant_terrain(path, *amsl_m)?,
            (None, HeightInfo::Dem { file, .. }) => {
                let found = find_dem(path, file).ok_or_else(|| MapReferenceError::DemNotFound {
                    map: path.display().to_string(),
                    dem: file.clone(),
                })?;
                load_dem(&found, Some(map.header().crs)).map_err(|e| MapReferenceError::Dem {
                    map: path.display().to_string(),
                    dem: found.display().to_string(),
                    reason: e.to_string(),
                })?
            }
        };
        Ok(Self { map, dem })
    }

    /// Builds a map from `spec` into a temporary file, maps it and unlinks it (the mapping keeps
    /// the data alive): the in-memory path for small areas given as orthophotos. `dem` as in
    /// [`Self::open`].
    pub fn build_temporary(spec: &BuildSpec, dem: Option<Dem>) -> Result<Self, MapReferenceError> {
        // Process, call count and time: threads building at once never share a file.
        static CALLS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let call = CALLS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = std::env::temp_dir().join(format!(
            "visnav-{}-{call}-{}.vnm",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos())
        ));
        build_map(spec, &tmp, &mut |_| {}).map_err(MapReferenceError::Build)?;
        let r = Self::open(&tmp, dem);
        let _ = std::fs::remove_file(&tmp);
        r
    }

    /// The underlying map file.
    pub fn map(&self) -> &ReferenceMap {
        &self.map
    }
}

impl Reference for MapReference {
    fn crs(&self) -> Crs {
        self.map.header().crs
    }
    fn level_gsd_m(&self) -> Vec<f64> {
        self.map.header().levels.iter().map(|l| l.gsd_m).collect()
    }
    fn ortho_pixel_m(&self) -> f64 {
        let h = self.map.header();
        h.orthos
            .first()
            .map(|o| o.pixel_size_m)
            .or_else(|| h.levels.first().map(|l| l.gsd_m))
            .unwrap_or(0.0)
    }
    fn feature_spec(&self) -> FeatureSpec {
        self.map.header().feature_spec()
    }
    fn bounds_m(&self) -> [f64; 4] {
        let b = &self.map.header().bounds;
        [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m]
    }
    fn height_amsl_m(&self, x_m: f64, y_m: f64) -> Option<f64> {
        self.dem.height_at(x_m, y_m)
    }
    fn dem(&self) -> visnav_core::fix::reference::DemRef<'_> {
        visnav_core::fix::reference::DemRef::Borrowed(&self.dem)
    }
    fn height_sigma_m(&self) -> f64 {
        self.map.header().height_sigma_m
    }
    fn height_errors(&self) -> visnav_core::fix::reference::HeightErrors {
        self.map.header().height_errors()
    }
    fn level_image(&self, level: usize) -> Option<MapImage<'_>> {
        let (info, data) = self.map.level_image(level)?;
        Some(MapImage {
            data,
            width: info.width_px as usize, // ok: the image lies in the mapped file
            height: info.height_px as usize, // ok: as above
            origin_x_m: info.origin_x_m,
            origin_y_m: info.origin_y_m,
            gsd_m: self.map.header().levels.get(level)?.gsd_m,
        })
    }
    fn select(&self, level: usize, rect_m: [f64; 4]) -> RefSelection {
        super::paged::ref_selection(
            self.map
                .select(level, rect_m[0], rect_m[1], rect_m[2], rect_m[3]),
        )
    }
}
