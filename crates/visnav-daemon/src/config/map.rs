//! `[map]`: the reference map the fixes are computed against, or the orthophotos and terrain
//! to build one from at start, and the checks of those files.

use super::*;

/// `[map]`: the georeferenced imagery and terrain the fixes are computed against. The default
/// (no map) is what an absent key means; a configuration must still name a map.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MapConfig {
    /// The reference map (`.vnm`, built by `visnav map build`, or a tiled map's folder, built
    /// with `--tile-m`: its tiles are paged in flight within `memory_mb`), relative to the config
    /// file's folder unless absolute. With it, `ortho` may be empty and `dem` /
    /// `ground_height_amsl_m` are optional (they override the map's own terrain; a tiled map built
    /// on a DEM carries its heights tile by tile, one built before they were written needs
    /// `dem`).
    #[serde(default)]
    pub file: Option<PathBuf>,
    /// With a tiled map (`file` a folder): the memory its tiles may take, MB (default 512). The
    /// tiles near the aircraft and ahead of it are loaded in the background, the least recently
    /// used dropped beyond it (docs/maps.md, "In flight").
    #[serde(default)]
    pub memory_mb: Option<u64>,
    /// Orthophoto GeoTIFF file(s), relative to the config file's folder unless absolute. Without
    /// `file`, the daemon extracts their features in memory at start (small areas).
    #[serde(default)]
    pub ortho: Vec<PathBuf>,
    /// Elevation model GeoTIFF (heights AMSL). Exactly one of `dem` and `ground_height_amsl_m`.
    #[serde(default)]
    pub dem: Option<PathBuf>,
    /// Constant ground height AMSL for flat areas without a DEM.
    #[serde(default)]
    pub ground_height_amsl_m: Option<f64>,
    /// CRS to assume for rasters whose GeoKeys are missing or not understood.
    #[serde(default)]
    pub crs_override: Option<Crs>,
    /// With `ortho`: extract the finest level's features at 1, 2 or 4 times the orthophotos'
    /// resolution (cubic interpolation before SURF; default 1). It pays off when the camera's
    /// ground pixel is finer than the map's (docs/map-format.md, "Upsampling"). A `.vnm` file
    /// keeps the setting it was built with (`visnav map build --upsample`).
    #[serde(default)]
    pub upsample: Option<usize>,
    /// With `ortho`: how far the surface the camera sees (roofs, trees, relief) may be from the
    /// heights, 1 sigma, metres (default 10 with `ground_height_amsl_m`, 0 with `dem`). A `.vnm`
    /// file keeps the figure it was built with (`visnav map build --height-sigma-m`).
    #[serde(default)]
    pub height_sigma_m: Option<f64>,
    /// With `ortho`: how fast that height error changes across a footprint, metres per metre
    /// (default 0.01 with `ground_height_amsl_m`, 0 with `dem`; docs/map-format.md, "Height
    /// uncertainty"). A `.vnm` file keeps the figure it was built with.
    #[serde(default)]
    pub height_slope_sigma: Option<f64>,
    /// With `ortho`: the height error left per point, metres (default 2 with
    /// `ground_height_amsl_m`, `height_sigma_m` with `dem`). A `.vnm` file keeps the figure it
    /// was built with.
    #[serde(default)]
    pub height_point_sigma_m: Option<f64>,
}

/// Smallest `[map] memory_mb`: a few tiles of 2 000 px.
pub const MIN_MAP_MEMORY_MB: u64 = 16;
/// Largest `[map] memory_mb` (1 TB: a bound, not a recommendation).
pub const MAX_MAP_MEMORY_MB: u64 = 1 << 20;

impl MapConfig {
    /// The map build `ortho` and the terrain describe (the daemon's map of small areas, built at
    /// start); `None` when no terrain is named.
    pub fn build_spec(&self) -> Option<visnav_io::map::BuildSpec> {
        use visnav_io::map::{BuildSpec, HeightSource};
        let height = match (&self.dem, self.ground_height_amsl_m) {
            (Some(p), _) => HeightSource::Dem(p.clone()),
            (None, Some(h)) => HeightSource::ConstantAmsl(h),
            (None, None) => return None,
        };
        let mut spec = BuildSpec::new(self.ortho.clone(), height);
        spec.crs_override = self.crs_override;
        spec.upsample = self.upsample.unwrap_or(1);
        spec.height_sigma_m = self.height_sigma_m;
        spec.height_slope_sigma = self.height_slope_sigma;
        spec.height_point_sigma_m = self.height_point_sigma_m;
        Some(spec)
    }

    /// Validate; `file` is relative to `file_base` (the current directory when `--map` gave it),
    /// the other paths to `base` (the config file's folder).
    pub(super) fn validate_in(&self, base: &Base, file_base: &Base, p: &mut Problems) {
        if let Some(f) = &self.file {
            if file_base.resolve(f).is_dir() {
                check_file(
                    p,
                    "file",
                    file_base,
                    &f.join(visnav_io::map::tiled::INDEX_FILE),
                );
            } else {
                check_file(p, "file", file_base, f);
            }
        } else if self.ortho.is_empty() {
            p.push(
                "ortho",
                "give a reference map (file) or at least one orthophoto GeoTIFF (ortho)",
            );
        }
        for (i, f) in self.ortho.iter().enumerate() {
            check_file(p, &format!("ortho[{i}]"), base, f);
        }
        match (&self.dem, self.ground_height_amsl_m) {
            (Some(_), Some(_)) => p.push(
                "dem",
                "give either dem or ground_height_amsl_m, not both",
            ),
            (None, None) if self.file.is_some() => {}
            (None, None) => p.push(
                "dem",
                "missing: give a DEM GeoTIFF (dem) or a constant ground height (ground_height_amsl_m)",
            ),
            (Some(f), None) => check_file(p, "dem", base, f),
            (None, Some(h)) => p.range(
                "ground_height_amsl_m",
                h,
                visnav_io::geo::dem::MIN_TERRAIN_HEIGHT_M,
                visnav_io::geo::dem::MAX_TERRAIN_HEIGHT_M,
            ),
        }
        if let Some(mb) = self.memory_mb {
            p.range(
                "memory_mb",
                mb as f64,
                MIN_MAP_MEMORY_MB as f64,
                MAX_MAP_MEMORY_MB as f64,
            );
        }
        if let Some(crs) = &self.crs_override {
            p.section("crs_override", |p| Validate::validate(crs, p));
        }
        match self.upsample {
            None => {}
            Some(_) if self.file.is_some() => p.push(
                "upsample",
                "applies to building from ortho; a map file keeps the setting it was built with (visnav map build --upsample)",
            ),
            Some(1 | 2 | 4) => {}
            Some(n) => p.push("upsample", format!("{n}: must be 1, 2 or 4")),
        }
        match self.height_sigma_m {
            None => {}
            Some(_) if self.file.is_some() => p.push(
                "height_sigma_m",
                "applies to building from ortho; a map file keeps the figure it was built with (visnav map build --height-sigma-m)",
            ),
            Some(s) => p.range(
                "height_sigma_m",
                s,
                0.0,
                visnav_io::map::build::MAX_HEIGHT_SIGMA_M,
            ),
        }
        for (key, value, max) in [
            (
                "height_slope_sigma",
                self.height_slope_sigma,
                visnav_io::map::build::MAX_HEIGHT_SLOPE_SIGMA,
            ),
            (
                "height_point_sigma_m",
                self.height_point_sigma_m,
                visnav_io::map::build::MAX_HEIGHT_SIGMA_M,
            ),
        ] {
            match value {
                None => {}
                Some(_) if self.file.is_some() => p.push(
                    key,
                    "applies to building from ortho; a map file keeps the figure it was built with",
                ),
                Some(s) => p.range(key, s, 0.0, max),
            }
        }
    }
}
