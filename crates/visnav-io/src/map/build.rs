//! `build_map`: orthophoto(s) + heights -> `.vnm` reference map, tile by tile.
//!
//! For every orthophoto and pyramid level (see the conventions in `map`), the level image is cut
//! into square tile cores of `tile_px` level pixels (rounded up to a multiple of the coarsest SURF
//! sampling step) on a grid anchored at the ortho's top-left pixel. Each tile is read with a margin
//! ([`tile_margin_px`]: the largest box filter plus the neighbour samples and the interpolation
//! offset, or the descriptor window of the largest scale, whichever is larger, also a multiple of
//! the coarsest step) so that every keypoint whose centre lies in the core is detected and
//! described exactly as in the whole image: tile origins are multiples of every octave's sampling
//! step, so the SURF sample grids coincide, and the integral image is exact. Only keypoints whose
//! centre lies in the core are kept, so the result does not depend on the tiling (up to float
//! rounding of coordinates); the per-tile cap (`max_features_per_tile`, SURF's even-spread
//! selection over the core) is the one tiling-dependent step.
//!
//! Keypoints whose descriptor window touches a missing pixel (nodata) are dropped, as are those
//! without a DEM height. Features go to a spill file while per-cell counters are kept; the final
//! file is laid out cell by cell (the index cells are the tile cores of the first ortho).
//!
//! Memory: an orthophoto whose decoded samples exceed [`BuildSpec::whole_decode_max_bytes`]
//! (default [`WHOLE_DECODE_MAX_BYTES`], 256 MiB) is never decoded whole. Each tile window (core +
//! margin, in level pixels) is read through `geo::window::GeoTiffWindowReader`, which decodes only
//! the strips/tiles under it (in parallel on rayon's threads) and keeps a bounded LRU cache of
//! decoded chunks ([`ORTHO_CACHE_BYTES`]); a tile of level `L` (each level pixel the mean of a
//! `2^L x 2^L` block of level-0 pixels) is averaged from level-0 row bands of about
//! [`BAND_BYTES`], so a level-5 tile never needs its 32x larger level-0 footprint at once; the
//! columns a tile's window shares with its left neighbour's are reused, not read again. Add one
//! tile's working set (grey, integral image, SURF response layers: a few tens of MB at the default
//! 1024 px tiles), the DEM's part under the orthophotos (`geo::dem::load_dem_covering`), and
//! 8 bytes per index cell. Peak memory thus no longer grows with the orthophoto size
//! (docs/map-format.md has measurements). The price is decoding time: the window margins overlap
//! vertically and every level reads the level-0 pixels again, so each chunk is decoded about
//! 1.5-2 times per level. Smaller orthophotos are decoded whole once (fastest). The features are
//! the same either way: the level windows are bit-identical.

use std::io::{Read, Seek};
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use super::format::SpillWriter;
use super::{
    HeightInfo, IndexGrid, LevelImageInfo, LevelInfo, MapError, MapFeature, MapHeader, OrthoInfo,
};
use crate::geo::geotiff::{GeoTiffError, GeoTiffInfo, crs_equivalent, describe_crs, load_geotiff};
use crate::geo::window::{GeoTiffWindowReader, open_geotiff_window};
use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::{Bounds, GeoTransform, Raster, RasterData};
use visnav_core::vision::{
    DescriptorKind, Features, GrayImage, IntegralImage, KeyPoint, Orb, OrbParams, Surf, SurfParams,
    VisionError,
};

/// Rec. 601 luma weights (as `vision::file::GrayImageFile::from_dynamic` and the renderer).
const LUMA: [f32; 3] = [0.299, 0.587, 0.114];
/// Auto level count: keep halving while the short side stays at or above this many pixels.
const AUTO_MIN_SIDE_PX: f64 = 256.0;
/// Auto level count: at most this many levels.
const AUTO_MAX_LEVELS: usize = 6;
/// Default [`BuildSpec::whole_decode_max_bytes`].
pub const WHOLE_DECODE_MAX_BYTES: usize = 256 << 20;
/// Bound of each orthophoto reader's decoded-chunk cache, bytes (it keeps the chunks shared by
/// neighbouring tile windows).
pub const ORTHO_CACHE_BYTES: usize = 16 << 20;
/// Target size of one band of level-0 samples read to average a window of a coarser level, bytes.
pub const BAND_BYTES: usize = 16 << 20;

/// Where the feature heights come from.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum HeightSource {
    /// A one-band GeoTIFF DEM in the orthos' CRS (heights in its own vertical datum).
    Dem(PathBuf),
    /// A constant ground height, metres AMSL.
    ConstantAmsl(f64),
}

/// What to build (a tiled map's plan stores it, `map::tiled::TilePlan`).
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct BuildSpec {
    /// Orthophotos (GeoTIFF, north-up, square pixels, one CRS, one pixel size).
    pub orthos: Vec<PathBuf>,
    /// Where the features' heights come from.
    pub height: HeightSource,
    /// CRS for files whose GeoKeys are missing or not understood.
    pub crs_override: Option<Crs>,
    /// Number of pyramid levels; `None`: halve while the short side stays >= 256 px, at most 6.
    pub levels: Option<usize>,
    /// SURF parameters (`max_features` is ignored: the cap is per tile).
    pub surf: SurfParams,
    /// Build ORB-like binary features of these settings instead of SURF (the detector seam's
    /// second family, docs/surf.md; `max_features` is ignored). None: SURF.
    pub orb: Option<OrbParams>,
    /// Tile core side in level pixels (rounded up to a multiple of the coarsest SURF step).
    pub tile_px: usize,
    /// Keep at most this many features per tile core (even spread), per level.
    pub max_features_per_tile: usize,
    /// Orthophotos whose decoded samples take at most this many bytes are decoded whole once
    /// (fastest; memory grows with the orthophoto); larger ones are read tile window by tile window
    /// (bounded memory, more decoding). 0: always windows; `usize::MAX`: always whole. Same
    /// features either way.
    pub whole_decode_max_bytes: usize,
    /// Build the finest level at this many times the orthophotos' resolution (1, 2 or 4): the
    /// orthophoto is interpolated (Keys cubic) before SURF, as Lowe doubles the image for SIFT, so
    /// blobs under SURF's smallest filter (9 px, sigma 1.2) become features. It pays off when the
    /// camera's ground pixel is finer than the map's (a 5 m map seen from 1000 m: 23 -> 66 % of the
    /// frames fixed, docs/map-format.md). Levels finer than the orthophoto are interpolated from it
    /// (x4: levels 0 and 1); the others are the orthophoto's own block means. The automatic level
    /// count adds the interpolated levels to the plain build's.
    pub upsample: usize,
    /// Standard deviation of the heights against the surface the camera sees, metres
    /// ([`MapHeader::height_sigma_m`]); `None`: [`DEFAULT_CONSTANT_HEIGHT_SIGMA_M`] for a constant
    /// height, [`DEFAULT_DEM_HEIGHT_SIGMA_M`] for a DEM.
    pub height_sigma_m: Option<f64>,
    /// How fast the height error changes across a footprint, metres per metre
    /// ([`MapHeader::height_slope_sigma`]); `None`: [`DEFAULT_CONSTANT_HEIGHT_SLOPE_SIGMA`] for a
    /// constant height, 0 for a DEM.
    pub height_slope_sigma: Option<f64>,
    /// The height error per point, metres ([`MapHeader::height_point_sigma_m`]); `None`: the
    /// height sigma (what a constant height or a DEM does not hold varies per point too: roofs,
    /// trees, relief).
    pub height_point_sigma_m: Option<f64>,
    /// Build only the part of the orthophotos inside this area (map coordinates in their CRS),
    /// its edges moved out to the coarsest level's pixel grid of the first orthophoto; `None`:
    /// all of them. The features are the whole build's that lie inside the area (x in
    /// `[min, max)`, y in `(min, max]`), so the parts of a partition hold the whole build's
    /// features, each once; the automatic level count follows the area's size, so parts meant
    /// to go together state `levels`. Not stored in a plan (its squares are the areas).
    #[serde(skip)]
    pub area: Option<Bounds>,
    /// Read a part (`area`) from its area alone: every tile core is cut at the area (moved out
    /// to the coarsest SURF sampling step) and read with the detector's margin around the cut,
    /// so a part costs its own area at every level, where whole cores at the coarse levels span
    /// tens of kilometres (a tiled map's squares are built so). A feature inside the area is
    /// detected and described as in the whole build (its windows lie inside the cut core's
    /// margin); the per-core cap ([`BuildSpec::max_features_per_tile`]) is scaled to the cut
    /// core's share of a whole one, so where the cap binds the part keeps the same density but
    /// not always the same features as the whole build. `false`: whole cores (the parts of a
    /// partition then hold exactly the whole build's features).
    pub area_local: bool,
    /// The build time the header records, seconds since 1970; `None`: now. A tiled map's tiles
    /// record 0, so the same settings write the same bytes on any machine at any time.
    pub built_unix_s: Option<u64>,
}

/// Height slope sigma of a map built on a constant ground height when the build does not state
/// one, metres per metre: a constant is chosen for ground its user takes as flat, where the
/// ground still falls or rises by about a metre per 100 m (river terraces, fields, prairie
/// swells; steeper ground needs a DEM). Over a footprint this tilts the points by about 0.6 deg.
pub const DEFAULT_CONSTANT_HEIGHT_SLOPE_SIGMA: f64 = 0.01;

/// Largest accepted height slope sigma (45 deg).
pub const MAX_HEIGHT_SLOPE_SIGMA: f64 = 1.0;

/// Height sigma of a map built on a constant ground height when the build does not state one, m:
/// a constant stands for ground the build knows nothing about; buildings and trees are 4-12 m
/// (as measured over Autzen: 12 m vertical error at a claimed 0.09 m), and the
/// relief under a footprint a few metres more.
pub const DEFAULT_CONSTANT_HEIGHT_SIGMA_M: f64 = 10.0;

/// Height sigma of a map built on a DEM when the build does not state one, m: the DEM is taken
/// as the surface the camera sees (a lidar surface model); give a bare-earth or coarse DEM its
/// own figure (SRTM / Copernicus 30 m: 4-10 m, more under trees and buildings).
pub const DEFAULT_DEM_HEIGHT_SIGMA_M: f64 = 0.0;

/// Largest accepted height sigma, m.
pub const MAX_HEIGHT_SIGMA_M: f64 = 1000.0;

impl BuildSpec {
    /// Defaults: upright SURF-64 (U-SURF), threshold 100, 4 octaves; 1024 px tiles, 4000
    /// features per tile; automatic level count.
    pub fn new(orthos: Vec<PathBuf>, height: HeightSource) -> Self {
        Self {
            orthos,
            height,
            crs_override: None,
            levels: None,
            surf: SurfParams {
                upright: true,
                ..SurfParams::default()
            },
            orb: None,
            tile_px: 1024,
            max_features_per_tile: 4000,
            whole_decode_max_bytes: WHOLE_DECODE_MAX_BYTES,
            upsample: 1,
            height_sigma_m: None,
            height_slope_sigma: None,
            height_point_sigma_m: None,
            area: None,
            area_local: false,
            built_unix_s: None,
        }
    }

    /// The height sigma the map will carry ([`Self::height_sigma_m`] or the source's default).
    pub fn resolved_height_sigma_m(&self) -> f64 {
        self.height_sigma_m.unwrap_or(match self.height {
            HeightSource::ConstantAmsl(_) => DEFAULT_CONSTANT_HEIGHT_SIGMA_M,
            HeightSource::Dem(_) => DEFAULT_DEM_HEIGHT_SIGMA_M,
        })
    }

    /// The height slope sigma the map will carry ([`Self::height_slope_sigma`] or the source's
    /// default).
    pub fn resolved_height_slope_sigma(&self) -> f64 {
        self.height_slope_sigma.unwrap_or(match self.height {
            HeightSource::ConstantAmsl(_) => DEFAULT_CONSTANT_HEIGHT_SLOPE_SIGMA,
            HeightSource::Dem(_) => 0.0,
        })
    }

    /// The per-point height sigma the map will carry ([`Self::height_point_sigma_m`] or the
    /// source's default).
    pub fn resolved_height_point_sigma_m(&self) -> f64 {
        self.height_point_sigma_m
            .unwrap_or_else(|| self.resolved_height_sigma_m())
    }
}

/// Progress report, after every tile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildProgress {
    /// Index of the orthophoto being processed.
    pub ortho: usize,
    /// The pyramid level being processed.
    pub level: usize,
    /// Tiles done so far, over all orthophotos and levels.
    pub tiles_done: u64,
    /// Tiles in all.
    pub tiles_total: u64,
    /// Features written so far.
    pub features: u64,
}

/// Outcome of a build.
#[derive(Clone, Debug)]
pub struct BuildSummary {
    /// The header as written.
    pub header: MapHeader,
    /// Size of the file written, bytes.
    pub file_bytes: u64,
    /// Keypoints dropped because their descriptor window touched nodata.
    pub dropped_nodata: u64,
    /// Keypoints dropped because the DEM has no height there.
    pub dropped_no_height: u64,
    /// Tiles processed.
    pub tiles: u64,
    /// Wall time of the build, seconds.
    pub elapsed_s: f64,
}

/// Margin around a tile core, level pixels: enough for every keypoint in the core to be detected
/// and described as in the whole image; a multiple of the coarsest sampling step.
pub fn tile_margin_px(p: &SurfParams) -> usize {
    let n_layers = p.n_octave_layers + 2;
    let mut m = 0usize;
    for o in 0..p.n_octaves {
        let step = p.init_sample_step << o;
        // Filter size of layer k in octave o: 3 (2^(o+1) (k+1) + 1) (Bay sec. 3.3; vision::surf).
        let top = 3 * ((2usize << o) * n_layers + 1);
        // Half the largest filter at a neighbour sample, plus the refinement offset (one step).
        let det = (top - 1) / 2 + 3 * step;
        let s = 1.2 * top as f64 / 9.0;
        m = m
            .max(det)
            .max(descriptor_radius_px(s as f32, p.upright).ceil() as usize);
    }
    m.div_ceil(max_step(p)) * max_step(p)
}

/// Half-side of the square that holds every sample of a keypoint's orientation and descriptor
/// windows (20s window, Haar side 2s, rotated by up to 45 deg unless upright), pixels.
fn descriptor_radius_px(scale: f32, upright: bool) -> f32 {
    if upright {
        10.5 * scale + 2.0
    } else {
        14.5 * scale + 2.0
    }
}

/// The build's extractors: SURF (its settings also fix the tiles' alignment) and, for a map of
/// binary features, ORB; the descriptors they write and the tiles' margin.
struct Detectors {
    surf_params: SurfParams,
    surf: Surf,
    orb: Option<Orb>,
    kind: DescriptorKind,
    margin: usize,
}

impl Detectors {
    fn of(spec: &BuildSpec) -> Result<Self, MapError> {
        let param = |name, e: VisionError| MapError::Param {
            name,
            reason: e.to_string(),
        };
        let surf_params = SurfParams {
            max_features: None,
            ..spec.surf.clone()
        };
        let surf = Surf::new(surf_params.clone()).map_err(|e| param("surf", e))?;
        let orb = match &spec.orb {
            Some(p) => Some(
                Orb::new(OrbParams {
                    max_features: None,
                    ..p.clone()
                })
                .map_err(|e| param("orb", e))?,
            ),
            None => None,
        };
        let (kind, margin) = match &orb {
            Some(o) => (DescriptorKind::Binary256, o.params().reach_px()),
            None => (surf_params.descriptor, tile_margin_px(&surf_params)),
        };
        Ok(Self {
            surf_params,
            surf,
            orb,
            kind,
            margin,
        })
    }
}

/// Sampling step of the coarsest octave.
fn max_step(p: &SurfParams) -> usize {
    p.init_sample_step << (p.n_octaves - 1)
}

/// Geometry of one ortho, read in the first pass.
#[derive(Clone)]
struct OrthoGeom {
    path: PathBuf,
    width: usize,
    height: usize,
    bands: usize,
    gsd_m: f64,
    bounds: Bounds,
    transform: GeoTransform,
    /// Bytes per decoded sample (as `Raster` stores them: 1, 2 or 4).
    sample_bytes: usize,
}

impl OrthoGeom {
    /// What the header records of the ortho.
    fn info(&self) -> OrthoInfo {
        OrthoInfo {
            file: self.path.display().to_string(),
            width_px: self.width as u64,
            height_px: self.height as u64,
            bands: self.bands as u32,
            pixel_size_m: self.gsd_m,
        }
    }

    /// The same ortho on a grid `2^shift` times finer (same outer edges).
    fn upsampled(&self, shift: usize) -> Result<Self, MapError> {
        if shift == 0 {
            return Ok(self.clone());
        }
        let k = f64::from(1u32 << shift);
        let c = self.transform.coeffs();
        let transform = GeoTransform::new([c[0], c[1] / k, c[2] / k, c[3], c[4] / k, c[5] / k])
            .map_err(|e| MapError::Input {
                path: self.path.clone(),
                reason: format!("upsampled geotransform: {e}"),
            })?;
        let too_big = || MapError::Input {
            path: self.path.clone(),
            reason: format!("too large to upsample by {k}"),
        };
        Ok(Self {
            width: self.width.checked_mul(1 << shift).ok_or_else(too_big)?,
            height: self.height.checked_mul(1 << shift).ok_or_else(too_big)?,
            gsd_m: self.gsd_m / k,
            transform,
            ..self.clone()
        })
    }
}

fn check_ortho(path: &Path, r: &GeoTiffInfo, crs: Option<Crs>) -> Result<OrthoGeom, MapError> {
    let bad = |reason: String| MapError::Input {
        path: path.to_path_buf(),
        reason,
    };
    if matches!(r.crs, Crs::Geographic) {
        return Err(bad(geographic_advice(&r.bounds())));
    }
    let t = &r.transform;
    if !t.is_axis_aligned() {
        return Err(bad(
            "the orthophoto is rotated (geotransform has rotation terms); warp it north-up first"
                .into(),
        ));
    }
    let c = t.coeffs();
    if !(c[1] > 0.0 && c[5] < 0.0) {
        return Err(bad(format!(
            "the orthophoto is not north-up (pixel steps {} x {}, expected positive x, negative y)",
            c[1], c[5]
        )));
    }
    let (px, py) = t.pixel_size();
    if (px - py).abs() > 1e-3 * px {
        return Err(bad(format!(
            "pixels are not square ({px} x {py} m); resample the orthophoto"
        )));
    }
    if let Some(c0) = crs
        && !crs_equivalent(&c0, &r.crs)
    {
        return Err(bad(format!(
            "CRS {} differs from the first orthophoto's {}; all orthophotos of a map must share one CRS",
            describe_crs(&r.crs),
            describe_crs(&c0)
        )));
    }
    Ok(OrthoGeom {
        path: path.to_path_buf(),
        width: r.width,
        height: r.height,
        bands: r.bands,
        gsd_m: px,
        bounds: r.bounds(),
        transform: r.transform,
        sample_bytes: match r.bits_per_sample {
            0..=8 => 1,
            9..=16 => 2,
            _ => 4,
        },
    })
}

/// What to do with an orthophoto in geographic coordinates (EPSG:4326, pixel steps in degrees):
/// the map, its index and its pixel sizes are in metres, so it must be reprojected first. Names
/// the UTM zone of the image's centre (`bounds` in degrees: x longitude, y latitude).
pub fn geographic_advice(bounds: &Bounds) -> String {
    let lon = 0.5 * (bounds.min_x_m + bounds.max_x_m);
    let lat = 0.5 * (bounds.min_y_m + bounds.max_y_m);
    let target = if lon.is_finite() && lat.is_finite() && (-180.0..=180.0).contains(&lon) {
        let zone = (((lon + 180.0) / 6.0).floor() as i64).clamp(0, 59) + 1; // ok: clamped
        let epsg = if lat >= 0.0 {
            32600 + zone
        } else {
            32700 + zone
        };
        format!("EPSG:{epsg}")
    } else {
        "EPSG:326zz".to_string()
    };
    format!(
        "the orthophoto is in geographic coordinates (EPSG:4326, pixel steps in degrees); a map \
         needs a projected CRS in metres: reproject it, e.g. to its UTM zone with \
         `gdalwarp -t_srs {target} -r cubic IN.tif OUT.tif` (EPSG:326zz north, 327zz south of \
         the equator), and the DEM to the same CRS"
    )
}

/// Builds the map `out` from `spec`. `progress` is called after every tile.
pub fn build_map(
    spec: &BuildSpec,
    out: &Path,
    progress: &mut dyn FnMut(BuildProgress),
) -> Result<BuildSummary, MapError> {
    let t0 = Instant::now();
    let sigmas = HeightSigmas::checked(spec)?;
    let d = Detectors::of(spec)?;
    let (geoms, crs) = read_geometry(spec)?;
    let up_shift = upsample_shift(spec.upsample)?;
    // The level-0 grid of every ortho: its own pixels, or `upsample` times finer.
    let vgeoms = geoms
        .iter()
        .map(|g| g.upsampled(up_shift))
        .collect::<Result<Vec<_>, _>>()?;
    let union = union_bounds(&geoms);
    let (bounds, n_levels) = build_area(spec, &union, &vgeoms[0], up_shift)?;
    let heights = Heights::load(spec, &crs, &bounds)?;
    let plan = LevelPlan::new(spec, &d, &bounds, &vgeoms, n_levels);
    tracing::info!(
        orthos = geoms.len(),
        levels = plan.n_levels,
        gsd_m = plan.gsd0_m,
        upsample = spec.upsample,
        core_px = plan.core,
        margin_px = d.margin,
        tiles = plan.tiles_total,
        "building reference map"
    );

    let spill_path = out.with_extension("vnm.spill");
    let writer = SpillWriter::new(&spill_path, d.kind, plan.grids.clone())?
        .with_images(plan.image_levels(&bounds))?;
    let mut sink = Sink {
        writer,
        st: Stats::default(),
    };
    let pass = OrthoPass {
        spec,
        plan: &plan,
        d: &d,
        dem: &heights.dem,
        bounds: &bounds,
        up_shift,
        area: spec.area,
        area_local: spec.area_local,
        step: max_step(&d.surf_params),
    };
    // Pass 2, last ortho first (the order of the features in the file depends on it).
    for oi in (0..geoms.len()).rev() {
        pass.run(oi, &geoms[oi], &vgeoms[oi], &mut sink, progress)?;
    }

    let header = MapHeader {
        version: super::FORMAT_VERSION,
        crs,
        surf: d.surf_params.clone(),
        orb: d.orb.as_ref().map(|o| o.params().clone()),
        levels: plan.level_infos(),
        bounds,
        height: heights.info,
        height_sigma_m: sigmas.sigma_m,
        height_slope_sigma: Some(sigmas.slope),
        height_point_sigma_m: Some(sigmas.point_sigma_m),
        vertical_datum: heights.datum,
        orthos: geoms.iter().map(OrthoGeom::info).collect(),
        tile_px: plan.core as u32,
        max_features_per_tile: spec.max_features_per_tile.min(u32::MAX as usize) as u32,
        built_unix_s: spec.built_unix_s.unwrap_or_else(|| {
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs())
        }),
        built_by: format!("visnav {}", env!("CARGO_PKG_VERSION")),
    };
    let Sink { writer, st } = sink;
    if st.features == 0 {
        return Err(MapError::NoFeatures {
            orthos: spec
                .orthos
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            threshold: header.surf.hessian_threshold,
            dropped_nodata: st.dropped_nodata,
            dropped_no_height: st.dropped_no_height,
        });
    }
    let (header, file_bytes) = writer.finish(header, out)?;
    Ok(BuildSummary {
        header,
        file_bytes,
        dropped_nodata: st.dropped_nodata,
        dropped_no_height: st.dropped_no_height,
        tiles: st.tiles,
        elapsed_s: t0.elapsed().as_secs_f64(),
    })
}

fn param_error(name: &'static str, reason: &str) -> MapError {
    MapError::Param {
        name,
        reason: reason.to_string(),
    }
}

/// The map's height error model, each part checked against its bounds.
struct HeightSigmas {
    sigma_m: f64,
    slope: f64,
    point_sigma_m: f64,
}

impl HeightSigmas {
    /// Checks the spec's counts and sizes and resolves its height sigmas.
    fn checked(spec: &BuildSpec) -> Result<Self, MapError> {
        if spec.orthos.is_empty() {
            return Err(param_error("orthos", "at least one orthophoto is required"));
        }
        if spec.orthos.len() > 255 {
            return Err(param_error("orthos", "at most 255 orthophotos per map"));
        }
        if !(64..=16384).contains(&spec.tile_px) {
            return Err(param_error("tile_px", "must be in 64..=16384"));
        }
        if spec.max_features_per_tile == 0 {
            return Err(param_error("max_features_per_tile", "must be positive"));
        }
        if let Some(n) = spec.levels
            && !(1..=12).contains(&n)
        {
            return Err(param_error("levels", "must be in 1..=12"));
        }
        upsample_shift(spec.upsample)?;
        let bounded = |name, v: f64, max: f64, unit: &str| {
            if v.is_finite() && (0.0..=max).contains(&v) {
                Ok(v)
            } else {
                Err(param_error(name, &format!("{v} must be 0 to {max}{unit}")))
            }
        };
        Ok(Self {
            sigma_m: bounded(
                "height_sigma_m",
                spec.resolved_height_sigma_m(),
                MAX_HEIGHT_SIGMA_M,
                " m",
            )?,
            slope: bounded(
                "height_slope_sigma",
                spec.resolved_height_slope_sigma(),
                MAX_HEIGHT_SLOPE_SIGMA,
                "",
            )?,
            point_sigma_m: bounded(
                "height_point_sigma_m",
                spec.resolved_height_point_sigma_m(),
                MAX_HEIGHT_SIGMA_M,
                " m",
            )?,
        })
    }
}

/// log2 of the build's upsampling factor.
fn upsample_shift(upsample: usize) -> Result<usize, MapError> {
    match upsample {
        1 => Ok(0),
        2 => Ok(1),
        4 => Ok(2),
        _ => Err(param_error("upsample", "must be 1, 2 or 4")),
    }
}

/// What a whole build of `spec` would cover: the orthophotos' union (headers only), their CRS,
/// the level-0 ground pixel and the level count (`spec.levels`, or the automatic count over a
/// square of `part_m` metres clipped to the union, or over the union without one): what the
/// parts of a tiled map share.
pub(crate) fn extent_of(
    spec: &BuildSpec,
    part_m: Option<f64>,
) -> Result<(Bounds, Crs, f64, usize), MapError> {
    HeightSigmas::checked(spec)?;
    let (geoms, crs) = read_geometry(spec)?;
    let up_shift = upsample_shift(spec.upsample)?;
    let g0 = geoms[0].upsampled(up_shift)?;
    let union = union_bounds(&geoms);
    let sized = match part_m {
        None => union,
        Some(t) => Bounds {
            min_x_m: 0.0,
            min_y_m: 0.0,
            max_x_m: t.min(union.max_x_m - union.min_x_m),
            max_y_m: t.min(union.max_y_m - union.min_y_m),
        },
    };
    let levels = level_count(spec, &sized, g0.gsd_m, up_shift);
    Ok((union, crs, g0.gsd_m, levels))
}

/// The map's bounds and level count: the orthophotos' union, or the part of it in
/// `BuildSpec::area` with its edges moved out to the coarsest level's pixel grid of the first
/// orthophoto (`g0`, on the level-0 grid), so that a part's level images are the whole build's
/// pixels.
fn build_area(
    spec: &BuildSpec,
    union: &Bounds,
    g0: &OrthoGeom,
    up_shift: usize,
) -> Result<(Bounds, usize), MapError> {
    let inside = |a: &Bounds| Bounds {
        min_x_m: a.min_x_m.max(union.min_x_m),
        min_y_m: a.min_y_m.max(union.min_y_m),
        max_x_m: a.max_x_m.min(union.max_x_m),
        max_y_m: a.max_y_m.min(union.max_y_m),
    };
    let part = match &spec.area {
        None => *union,
        Some(a) => {
            let p = inside(a);
            if !(p.max_x_m > p.min_x_m && p.max_y_m > p.min_y_m) {
                return Err(param_error(
                    "area",
                    "the area does not overlap the orthophotos (or is not a finite box)",
                ));
            }
            p
        }
    };
    let n_levels = level_count(spec, &part, g0.gsd_m, up_shift);
    if spec.area.is_none() {
        return Ok((part, n_levels));
    }
    // The coarsest level's pixel grid through the first ortho's top-left corner.
    let c = g0.transform.coeffs();
    let step = g0.gsd_m * f64::from(1u32 << (n_levels - 1));
    let down = |v: f64, o: f64| o + ((v - o) / step).floor() * step;
    let up = |v: f64, o: f64| o + ((v - o) / step).ceil() * step;
    let snapped = Bounds {
        min_x_m: down(part.min_x_m, c[0]),
        max_x_m: up(part.max_x_m, c[0]),
        min_y_m: down(part.min_y_m, c[3]),
        max_y_m: up(part.max_y_m, c[3]),
    };
    Ok((inside(&snapped), n_levels))
}

/// `spec.levels`, or halving while the short side of `bounds` stays at or above
/// [`AUTO_MIN_SIDE_PX`]: the automatic count keeps the coarsest level of a plain build, the
/// interpolated levels come on top of the cap.
fn level_count(spec: &BuildSpec, bounds: &Bounds, gsd0_m: f64, up_shift: usize) -> usize {
    let short_px =
        ((bounds.max_x_m - bounds.min_x_m).min(bounds.max_y_m - bounds.min_y_m)) / gsd0_m;
    spec.levels.unwrap_or_else(|| {
        (1..AUTO_MAX_LEVELS + up_shift)
            .take_while(|&l| short_px / f64::from(1u32 << l) >= AUTO_MIN_SIDE_PX)
            .count()
            + 1
    })
}

/// Whether tile `(tx, ty)` of level `level` (cores of `core` level pixels) of an ortho of
/// level-0 size and transform `g` overlaps `area` (always, without one).
fn core_in_area(
    g: (usize, usize, &GeoTransform),
    level: usize,
    core: usize,
    (tx, ty): (usize, usize),
    area: Option<&Bounds>,
) -> bool {
    let Some(a) = area else {
        return true;
    };
    let (w, h, t) = g;
    let f = 1usize << level;
    let (lw, lh) = (w >> level, h >> level);
    let (x0, y0) = (tx * core, ty * core);
    let (x1, y1) = ((x0 + core).min(lw), (y0 + core).min(lh));
    let corners =
        [(x0 * f, y0 * f), (x1 * f, y1 * f)].map(|(c, r)| t.pixel_to_map(c as f64, r as f64));
    let (min_x, max_x) = (
        corners[0].0.min(corners[1].0),
        corners[0].0.max(corners[1].0),
    );
    let (min_y, max_y) = (
        corners[0].1.min(corners[1].1),
        corners[0].1.max(corners[1].1),
    );
    min_x < a.max_x_m && max_x > a.min_x_m && min_y < a.max_y_m && max_y > a.min_y_m
}

/// Pass 1: the geometry of every ortho (headers only), checked to share one CRS and pixel size.
fn read_geometry(spec: &BuildSpec) -> Result<(Vec<OrthoGeom>, Crs), MapError> {
    let mut geoms: Vec<OrthoGeom> = Vec::new();
    let mut crs: Option<Crs> = None;
    for path in &spec.orthos {
        let r = open_geotiff_window(path, spec.crs_override)?;
        let g = check_ortho(path, r.info(), crs)?;
        if let Some(g0) = geoms.first()
            && (g.gsd_m - g0.gsd_m).abs() > 1e-3 * g0.gsd_m
        {
            return Err(MapError::Input {
                path: path.clone(),
                reason: format!(
                    "pixel size {} m differs from the first orthophoto's {} m; resample to one pixel size",
                    g.gsd_m, g0.gsd_m
                ),
            });
        }
        crs.get_or_insert(r.info().crs);
        geoms.push(g);
    }
    let crs = crs.ok_or_else(|| param_error("orthos", "no orthophoto loaded"))?;
    Ok((geoms, crs))
}

/// The bounds that hold every ortho (`geoms` is not empty: checked before).
fn union_bounds(geoms: &[OrthoGeom]) -> Bounds {
    geoms.iter().skip(1).fold(geoms[0].bounds, |b, g| Bounds {
        min_x_m: b.min_x_m.min(g.bounds.min_x_m),
        min_y_m: b.min_y_m.min(g.bounds.min_y_m),
        max_x_m: b.max_x_m.max(g.bounds.max_x_m),
        max_y_m: b.max_y_m.max(g.bounds.max_y_m),
    })
}

/// The features' heights: the terrain model, what the header says of it and its datum.
struct Heights {
    dem: Dem,
    info: HeightInfo,
    datum: String,
}

impl Heights {
    fn load(spec: &BuildSpec, crs: &Crs, area: &Bounds) -> Result<Self, MapError> {
        match &spec.height {
            HeightSource::ConstantAmsl(h) => Self::constant(*h),
            HeightSource::Dem(p) => Self::dem(p, spec.crs_override, crs, area),
        }
    }

    fn constant(h: f64) -> Result<Self, MapError> {
        use crate::geo::dem::{MAX_TERRAIN_HEIGHT_M, MIN_TERRAIN_HEIGHT_M};
        if !(MIN_TERRAIN_HEIGHT_M..=MAX_TERRAIN_HEIGHT_M).contains(&h) {
            return Err(param_error(
                "ground_height",
                &format!(
                    "{h} m is not a terrain height (expected {MIN_TERRAIN_HEIGHT_M} to \
                     {MAX_TERRAIN_HEIGHT_M} m above mean sea level)"
                ),
            ));
        }
        Ok(Self {
            dem: Dem::flat(h).map_err(|e| param_error("ground_height", &e.to_string()))?,
            info: HeightInfo::Constant { amsl_m: h },
            datum: "constant ground height, metres AMSL".to_string(),
        })
    }

    /// The DEM's part under the map (`area`, the orthophotos' bounds): a DEM of a whole region is
    /// not decoded whole. Its CRS is checked from the header first, so that the window is taken
    /// in the orthophotos' coordinates.
    fn dem(
        p: &Path,
        crs_override: Option<Crs>,
        crs: &Crs,
        area: &Bounds,
    ) -> Result<Self, MapError> {
        let dem_err = |source: crate::geo::dem::DemFileError| MapError::Dem {
            path: p.to_path_buf(),
            cause: Box::new(source),
        };
        let header_crs = open_geotiff_window(p, crs_override)
            .map_err(|e| dem_err(e.into()))?
            .info()
            .crs;
        let differs = |dc: &Crs| MapError::Input {
            path: p.to_path_buf(),
            reason: format!(
                "DEM CRS {} differs from the orthophotos' {}; reproject the DEM to the orthophotos' CRS",
                describe_crs(dc),
                describe_crs(crs)
            ),
        };
        if !crs_equivalent(&header_crs, crs) {
            return Err(differs(&header_crs));
        }
        let d = crate::geo::dem::load_dem_covering(p, crs_override, area).map_err(dem_err)?;
        if let Some(dc) = d.crs()
            && !crs_equivalent(&dc, crs)
        {
            return Err(differs(&dc));
        }
        let (lo, hi) = d.height_range_m();
        Ok(Self {
            dem: d,
            info: HeightInfo::Dem {
                file: p.display().to_string(),
                min_m: lo,
                max_m: hi,
            },
            datum: "the DEM's vertical datum (orthometric heights, ~AMSL, unless the DEM says \
                    otherwise)"
                .to_string(),
        })
    }
}

/// The pyramid: how many levels, the tile core and the index grid of each level.
struct LevelPlan {
    n_levels: usize,
    /// Ground pixel of level 0, m.
    gsd0_m: f64,
    /// Tile core side, level pixels.
    core: usize,
    grids: Vec<IndexGrid>,
    tiles_total: u64,
}

impl LevelPlan {
    fn new(
        spec: &BuildSpec,
        d: &Detectors,
        bounds: &Bounds,
        vgeoms: &[OrthoGeom],
        n_levels: usize,
    ) -> Self {
        let gsd0_m = vgeoms[0].gsd_m;
        let step = max_step(&d.surf_params);
        let core = spec.tile_px.div_ceil(step) * step;
        let grids = (0..n_levels)
            .map(|l| {
                let cell_m = core as f64 * gsd0_m * f64::from(1u32 << l);
                let cols = ((bounds.max_x_m - bounds.min_x_m) / cell_m).ceil().max(1.0);
                let rows = ((bounds.max_y_m - bounds.min_y_m) / cell_m).ceil().max(1.0);
                IndexGrid {
                    origin_x_m: bounds.min_x_m,
                    origin_y_m: bounds.max_y_m,
                    cell_m,
                    cols: cols.min(f64::from(u32::MAX)) as u32, // ok: clamped
                    rows: rows.min(f64::from(u32::MAX)) as u32, // ok: clamped
                }
            })
            .collect();
        let area = spec.area;
        let tiles_total = vgeoms
            .iter()
            .map(|g| {
                (0..n_levels)
                    .map(|l| {
                        let (w, h) = (g.width >> l, g.height >> l);
                        let cores = (0..h.div_ceil(core))
                            .flat_map(|ty| (0..w.div_ceil(core)).map(move |tx| (tx, ty)));
                        cores
                            .filter(|&(tx, ty)| {
                                core_in_area(
                                    (g.width, g.height, &g.transform),
                                    l,
                                    core,
                                    (tx, ty),
                                    area.as_ref(),
                                )
                            })
                            .count() as u64
                    })
                    .sum::<u64>()
            })
            .sum();
        Self {
            n_levels,
            gsd0_m,
            core,
            grids,
            tiles_total,
        }
    }

    fn gsd_m(&self, level: usize) -> f64 {
        self.gsd0_m * f64::from(1u32 << level)
    }

    /// Level images on one grid over the union bounds, row 0 north (docs/map-format.md).
    fn image_levels(&self, bounds: &Bounds) -> Vec<LevelImageInfo> {
        (0..self.n_levels)
            .map(|l| {
                let gsd = self.gsd_m(l);
                LevelImageInfo {
                    offset: 0,
                    width_px: (((bounds.max_x_m - bounds.min_x_m) / gsd).ceil().max(1.0)) as u64,
                    height_px: (((bounds.max_y_m - bounds.min_y_m) / gsd).ceil().max(1.0)) as u64,
                    origin_x_m: bounds.min_x_m,
                    origin_y_m: bounds.max_y_m,
                }
            })
            .collect()
    }

    /// The header's levels, their offsets and counts left for the writer to fill in.
    fn level_infos(&self) -> Vec<LevelInfo> {
        (0..self.n_levels)
            .map(|l| LevelInfo {
                gsd_m: self.gsd_m(l),
                n_features: 0,
                grid: self.grids[l],
                cells_offset: 0,
                records_offset: 0,
                descriptors_offset: 0,
                image: None,
            })
            .collect()
    }
}

/// Where the tiles' features and images go, and their counts.
struct Sink {
    writer: SpillWriter,
    st: Stats,
}

/// Pass 2 over one ortho: every level, tile by tile.
struct OrthoPass<'a> {
    spec: &'a BuildSpec,
    plan: &'a LevelPlan,
    d: &'a Detectors,
    dem: &'a Dem,
    bounds: &'a Bounds,
    up_shift: usize,
    /// The area a part-build keeps (`BuildSpec::area` as given: its features split at the
    /// given edges, its images reach out to the pixel grid).
    area: Option<Bounds>,
    /// Cut the cores at the area ([`BuildSpec::area_local`]).
    area_local: bool,
    /// The coarsest SURF sampling step: a cut core's edges stay on its grid.
    step: usize,
}

impl OrthoPass<'_> {
    /// Ortho `oi` (its file's geometry `g0`, its level-0 grid `g`) into `sink`.
    fn run(
        &self,
        oi: usize,
        g0: &OrthoGeom,
        g: &OrthoGeom,
        sink: &mut Sink,
        progress: &mut dyn FnMut(BuildProgress),
    ) -> Result<(), MapError> {
        let mut source = self.open(g0)?;
        for level in 0..self.plan.n_levels {
            let decoded_before = source.chunks_decoded();
            let ctx = TileCtx {
                width: g.width,
                height: g.height,
                transform: g.transform,
                level,
                core: self.plan.core,
                margin: self.d.margin,
                surf: &self.d.surf,
                orb: self.d.orb.as_ref(),
                cap: self.spec.max_features_per_tile,
                dem: self.dem,
                source: oi as u8, // ok: <= 255 orthos checked
                area: self.area,
                clip: self.clip(g, level),
            };
            self.level(&ctx, source.as_mut(), sink, &mut |st: &Stats| {
                progress(BuildProgress {
                    ortho: oi,
                    level,
                    tiles_done: st.tiles,
                    tiles_total: self.plan.tiles_total,
                    features: st.features,
                })
            })?;
            tracing::debug!(
                ortho = oi,
                level,
                chunks_decoded = source.chunks_decoded() - decoded_before,
                "level done"
            );
        }
        Ok(())
    }

    /// The area in level pixels of the ortho whose level-0 grid is `g`, moved out to whole
    /// pixels and to the sampling step, when cores are cut at it.
    fn clip(&self, g: &OrthoGeom, level: usize) -> Option<PxRect> {
        let a = self.area.filter(|_| self.area_local)?;
        let c = g.transform.coeffs();
        let px_m = g.gsd_m * f64::from(1u32 << level);
        let (lw, lh) = (g.width >> level, g.height >> level);
        let step = self.step as f64;
        let down = |v: f64, n: usize| ((v / step).floor() * step).clamp(0.0, n as f64) as usize; // ok: clamped
        let up = |v: f64, n: usize| ((v / step).ceil() * step).clamp(0.0, n as f64) as usize; // ok: clamped
        Some(PxRect {
            x0: down((a.min_x_m - c[0]) / px_m, lw),
            x1: up((a.max_x_m - c[0]) / px_m, lw),
            y0: down((c[3] - a.max_y_m) / px_m, lh),
            y1: up((c[3] - a.min_y_m) / px_m, lh),
        })
    }

    /// The ortho's pixels: decoded whole when small enough, else window by window; upsampled
    /// when the build asks for it.
    fn open(&self, g0: &OrthoGeom) -> Result<Box<dyn LevelSource>, MapError> {
        let decoded_bytes = g0
            .width
            .saturating_mul(g0.height)
            .saturating_mul(g0.bands)
            .saturating_mul(g0.sample_bytes);
        let whole = decoded_bytes <= self.spec.whole_decode_max_bytes;
        tracing::debug!(path = %g0.path.display(), decoded_bytes, whole, "reading the orthophoto");
        let crs_override = self.spec.crs_override;
        let mut source: Box<dyn LevelSource> = if whole {
            Box::new(load_geotiff(&g0.path, crs_override)?)
        } else {
            let mut r = open_geotiff_window(&g0.path, crs_override)?;
            r.set_cache_bytes(ORTHO_CACHE_BYTES);
            r.set_decode_threads(rayon::current_num_threads())?;
            Box::new(r)
        };
        if source.dims() != (g0.width, g0.height) {
            return Err(MapError::Input {
                path: g0.path.clone(),
                reason: "the file changed during the build".into(),
            });
        }
        if self.up_shift > 0 {
            source = Box::new(Upsampled {
                inner: source,
                shift: self.up_shift,
            });
        }
        Ok(source)
    }

    /// One level of one ortho, row of tiles by row of tiles.
    fn level(
        &self,
        ctx: &TileCtx,
        source: &mut dyn LevelSource,
        sink: &mut Sink,
        progress: &mut dyn FnMut(&Stats),
    ) -> Result<(), MapError> {
        let core = ctx.core;
        let (lw, lh) = (ctx.width >> ctx.level, ctx.height >> ctx.level);
        for ty in 0..lh.div_ceil(core) {
            let mut prev: Option<LevelPatch> = None;
            for tx in 0..lw.div_ceil(core) {
                if !core_in_area(
                    (ctx.width, ctx.height, &ctx.transform),
                    ctx.level,
                    core,
                    (tx, ty),
                    self.area.as_ref(),
                ) {
                    prev = None;
                    continue;
                }
                let Some(win) = TileWindow::new(ctx, tx * core, ty * core) else {
                    prev = None;
                    continue;
                };
                let (grey, valid) = read_reusing(source, ctx.level, &win, prev.take())?;
                // Keep the columns the next tile's window starts with.
                let next_x0 = ((tx + 1) * core)
                    .saturating_sub(ctx.margin)
                    .clamp(win.x0, win.x0 + win.w);
                prev = Some(LevelPatch::columns(&win, &grey, &valid, next_x0));
                push_core_image(ctx, &win, &grey, &valid, self.bounds, &mut sink.writer)?;
                process_tile(ctx, &win, grey, &valid, &mut sink.writer, &mut sink.st)?;
                sink.st.tiles += 1;
                progress(&sink.st);
            }
        }
        Ok(())
    }
}

#[derive(Default)]
struct Stats {
    tiles: u64,
    features: u64,
    dropped_nodata: u64,
    dropped_no_height: u64,
}

struct TileCtx<'a> {
    /// Level-0 size and transform of the ortho.
    width: usize,
    height: usize,
    transform: GeoTransform,
    level: usize,
    core: usize,
    margin: usize,
    surf: &'a Surf,
    /// ORB-like binary features instead of SURF ([`BuildSpec::orb`]).
    orb: Option<&'a Orb>,
    cap: usize,
    dem: &'a Dem,
    source: u8,
    /// Keep only the features inside this area (`BuildSpec::area`).
    area: Option<Bounds>,
    /// Cut the cores at this rectangle of level pixels (`BuildSpec::area_local`).
    clip: Option<PxRect>,
}

/// A rectangle of level pixels, `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug)]
struct PxRect {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

/// A tile of a level image: core `(cx0, cy0)`, `cw x ch`, inside the window `(x0, y0)`, `w x h`
/// (the core plus the margin, clipped to the level image), level pixels.
struct TileWindow {
    cx0: usize,
    cy0: usize,
    cw: usize,
    ch: usize,
    /// The core's share of the area of the core it was cut from (below 1 where a part's area
    /// cuts it): the cap of a cut core is scaled by it.
    share: f64,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
}

impl TileWindow {
    /// The window of the core at `(cx0, cy0)`, cut at `ctx.clip`; `None` when the cut leaves
    /// nothing.
    fn new(ctx: &TileCtx, cx0: usize, cy0: usize) -> Option<Self> {
        let (lw, lh) = (ctx.width >> ctx.level, ctx.height >> ctx.level);
        let (cw, ch) = (ctx.core.min(lw - cx0), ctx.core.min(lh - cy0));
        let (cx0, cy0, cw, ch, share) = match ctx.clip {
            None => (cx0, cy0, cw, ch, 1.0),
            Some(r) => {
                let (x0, y0) = (cx0.max(r.x0), cy0.max(r.y0));
                let (x1, y1) = ((cx0 + cw).min(r.x1), (cy0 + ch).min(r.y1));
                if x1 <= x0 || y1 <= y0 {
                    return None;
                }
                let share = ((x1 - x0) * (y1 - y0)) as f64 / (cw * ch) as f64;
                (x0, y0, x1 - x0, y1 - y0, share)
            }
        };
        let x0 = cx0.saturating_sub(ctx.margin);
        let y0 = cy0.saturating_sub(ctx.margin);
        let x1 = (cx0 + cw + ctx.margin).min(lw);
        let y1 = (cy0 + ch + ctx.margin).min(lh);
        Some(Self {
            cx0,
            cy0,
            cw,
            ch,
            share,
            x0,
            y0,
            w: x1 - x0,
            h: y1 - y0,
        })
    }

    /// The cap of this core: `cap` scaled by its share of the core it was cut from (at least 1),
    /// so a part cut at an area keeps the whole build's density.
    fn cap(&self, cap: usize) -> usize {
        if self.share >= 1.0 {
            cap
        } else {
            ((cap as f64 * self.share).ceil() as usize).max(1) // ok: 0 < share < 1
        }
    }
}

/// Part of a level window: `w x h` level pixels at `(x0, y0)`, grey values and validity.
struct LevelPatch {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    grey: Vec<f32>,
    valid: Vec<bool>,
}

impl LevelPatch {
    /// Columns `from ..` of the window `win` (grey / valid as read for it).
    fn columns(win: &TileWindow, grey: &[f32], valid: &[bool], from: usize) -> Self {
        let (off, w) = (from - win.x0, win.x0 + win.w - from);
        let rows = |y: usize| y * win.w + off..y * win.w + off + w;
        Self {
            x0: from,
            y0: win.y0,
            w,
            h: win.h,
            grey: (0..win.h)
                .flat_map(|y| grey[rows(y)].iter().copied())
                .collect(),
            valid: (0..win.h)
                .flat_map(|y| valid[rows(y)].iter().copied())
                .collect(),
        }
    }
}

/// The level window of `win` (grey, valid), reusing the columns it shares with `prev`, kept from
/// the window of the tile to its left (the two margins): only the new columns are read. Level
/// pixels do not depend on the window they are read in, so the result is the same as reading the
/// whole window.
fn read_reusing(
    source: &mut dyn LevelSource,
    level: usize,
    win: &TileWindow,
    prev: Option<LevelPatch>,
) -> Result<(Vec<f32>, Vec<bool>), MapError> {
    let shared = match &prev {
        Some(p)
            if p.y0 == win.y0
                && p.h == win.h
                && p.x0 <= win.x0
                && win.x0 < p.x0 + p.w
                && p.x0 + p.w <= win.x0 + win.w =>
        {
            p.x0 + p.w - win.x0
        }
        _ => 0,
    };
    let (x0, y0, w, h) = (win.x0, win.y0, win.w, win.h);
    match prev {
        Some(p) if shared > 0 => {
            let new_w = w - shared;
            let (g_new, v_new) = if new_w > 0 {
                source.level_window(level, x0 + shared, y0, new_w, h)?
            } else {
                (Vec::new(), Vec::new())
            };
            let off = x0 - p.x0;
            let mut grey = Vec::with_capacity(w * h);
            let mut valid = Vec::with_capacity(w * h);
            for y in 0..h {
                grey.extend_from_slice(&p.grey[y * p.w + off..y * p.w + off + shared]);
                grey.extend_from_slice(&g_new[y * new_w..(y + 1) * new_w]);
                valid.extend_from_slice(&p.valid[y * p.w + off..y * p.w + off + shared]);
                valid.extend_from_slice(&v_new[y * new_w..(y + 1) * new_w]);
            }
            Ok((grey, valid))
        }
        _ => source.level_window(level, x0, y0, w, h),
    }
}

/// Where a build reads level windows from: a whole decoded ortho or a windowed reader.
trait LevelSource {
    /// Level-0 width and height.
    fn dims(&self) -> (usize, usize);
    /// Chunks decoded so far (0 for a decoded image).
    fn chunks_decoded(&self) -> u64 {
        0
    }
    /// As [`level_window`].
    fn level_window(
        &mut self,
        level: usize,
        x0: usize,
        y0: usize,
        w: usize,
        h: usize,
    ) -> Result<(Vec<f32>, Vec<bool>), MapError>;
}

/// A level source seen `2^shift` times finer. Level `l < shift` is the source's level 0
/// interpolated by `2^(shift - l)` with Keys' cubic convolution (a = -0.5; output pixel centre `x`
/// samples the source at `u = (x + 0.5) / f - 0.5`, edges replicated); a pixel is valid when its
/// 16 taps are. Level `l >= shift` is the source's level `l - shift` (block means of the real
/// pixels, not of the interpolated ones).
struct Upsampled {
    inner: Box<dyn LevelSource>,
    shift: usize,
}

/// Keys' cubic convolution weights (a = -0.5) of the taps at -1, 0, 1, 2 for fraction `t`.
fn keys_weights(t: f32) -> [f32; 4] {
    let a = -0.5f32;
    let near = |x: f32| ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0;
    let far = |x: f32| ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a;
    [far(1.0 + t), near(t), near(1.0 - t), far(2.0 - t)]
}

/// Taps (source indices, clamped to `0..n`) and weights of output pixels `x0..x0 + w` upsampled by `f`.
fn keys_taps(x0: usize, w: usize, f: usize, n: usize) -> Vec<([usize; 4], [f32; 4])> {
    (x0..x0 + w)
        .map(|x| {
            let u = (x as f64 + 0.5) / f as f64 - 0.5;
            let i = u.floor();
            let wts = keys_weights((u - i) as f32);
            let i = i as i64;
            let idx = [-1, 0, 1, 2].map(|d| (i + d).clamp(0, n as i64 - 1) as usize);
            (idx, wts)
        })
        .collect()
}

impl LevelSource for Upsampled {
    fn dims(&self) -> (usize, usize) {
        let (w, h) = self.inner.dims();
        (w << self.shift, h << self.shift)
    }
    fn chunks_decoded(&self) -> u64 {
        self.inner.chunks_decoded()
    }
    fn level_window(
        &mut self,
        level: usize,
        x0: usize,
        y0: usize,
        w: usize,
        h: usize,
    ) -> Result<(Vec<f32>, Vec<bool>), MapError> {
        if level >= self.shift {
            return self.inner.level_window(level - self.shift, x0, y0, w, h);
        }
        let f = 1usize << (self.shift - level);
        let (sw, sh) = self.inner.dims();
        let tx = keys_taps(x0, w, f, sw);
        let ty = keys_taps(y0, h, f, sh);
        let (Some(first_x), Some(last_x), Some(first_y), Some(last_y)) =
            (tx.first(), tx.last(), ty.first(), ty.last())
        else {
            return Ok((Vec::new(), Vec::new()));
        };
        let (sx0, sx1) = (first_x.0[0], last_x.0[3] + 1);
        let (sy0, sy1) = (first_y.0[0], last_y.0[3] + 1);
        let (swin, shwin) = (sx1 - sx0, sy1 - sy0);
        let (src, src_valid) = self.inner.level_window(0, sx0, sy0, swin, shwin)?;
        // Horizontal pass: source rows sy0..sy1 at the output columns.
        let mut rows = vec![0f32; shwin * w];
        let mut rows_valid = vec![false; shwin * w];
        rows.par_chunks_mut(w)
            .zip(rows_valid.par_chunks_mut(w))
            .enumerate()
            .for_each(|(r, (out, ok))| {
                let s = &src[r * swin..(r + 1) * swin];
                let v = &src_valid[r * swin..(r + 1) * swin];
                for (x, (idx, wts)) in tx.iter().enumerate() {
                    let mut acc = 0f32;
                    let mut all = true;
                    for k in 0..4 {
                        acc += wts[k] * s[idx[k] - sx0];
                        all &= v[idx[k] - sx0];
                    }
                    out[x] = acc;
                    ok[x] = all;
                }
            });
        // Vertical pass.
        let mut grey = vec![0f32; w * h];
        let mut valid = vec![false; w * h];
        grey.par_chunks_mut(w)
            .zip(valid.par_chunks_mut(w))
            .zip(ty.par_iter())
            .for_each(|((out, ok), (idx, wts))| {
                for x in 0..w {
                    let mut acc = 0f32;
                    let mut all = true;
                    for k in 0..4 {
                        let r = idx[k] - sy0;
                        acc += wts[k] * rows[r * w + x];
                        all &= rows_valid[r * w + x];
                    }
                    if all {
                        out[x] = acc;
                        ok[x] = true;
                    }
                }
            });
        Ok((grey, valid))
    }
}

impl LevelSource for Raster {
    fn dims(&self) -> (usize, usize) {
        (self.width(), self.height())
    }
    fn level_window(
        &mut self,
        level: usize,
        x0: usize,
        y0: usize,
        w: usize,
        h: usize,
    ) -> Result<(Vec<f32>, Vec<bool>), MapError> {
        Ok(level_window(self, level, x0, y0, w, h))
    }
}

impl<R: Read + Seek + Send> LevelSource for GeoTiffWindowReader<R> {
    fn dims(&self) -> (usize, usize) {
        (self.info().width, self.info().height)
    }
    fn chunks_decoded(&self) -> u64 {
        GeoTiffWindowReader::chunks_decoded(self)
    }
    fn level_window(
        &mut self,
        level: usize,
        x0: usize,
        y0: usize,
        w: usize,
        h: usize,
    ) -> Result<(Vec<f32>, Vec<bool>), MapError> {
        Ok(level_window_from_reader(
            self, level, x0, y0, w, h, BAND_BYTES,
        )?)
    }
}

/// Writes the core of the tile `win` into the level image: grey rounded into `1..=255`, 0 where
/// invalid, at the ortho's place on the image grid (its level pixel offset from the union bounds'
/// north-west corner, rounded: orthos of one map share the pixel size, and those whose grids are
/// not aligned with the first one's are placed to the nearest level pixel).
fn push_core_image(
    ctx: &TileCtx,
    win: &TileWindow,
    grey: &[f32],
    valid: &[bool],
    bounds: &Bounds,
    writer: &mut SpillWriter,
) -> Result<(), MapError> {
    let c = ctx.transform.coeffs();
    let gsd = c[1] * f64::from(1u32 << ctx.level);
    let ox = ((c[0] - bounds.min_x_m) / gsd).round() as i64;
    let oy = ((bounds.max_y_m - c[3]) / gsd).round() as i64;
    let mut px = vec![0u8; win.cw * win.ch];
    for y in 0..win.ch {
        for x in 0..win.cw {
            let i = (win.cy0 - win.y0 + y) * win.w + win.cx0 - win.x0 + x;
            if valid[i] {
                px[y * win.cw + x] = grey[i].round().clamp(1.0, 255.0) as u8; // ok: clamped
            }
        }
    }
    writer.push_image_block(
        ctx.level,
        ox + win.cx0 as i64,
        oy + win.cy0 as i64,
        win.cw,
        win.ch,
        &px,
    )
}

/// Extracts the features of the tile `win` from its level window `grey` / `valid`: the
/// detector's keypoints whose centre lies in the tile's core and whose descriptor window holds no
/// missing pixel, the strongest `cap` of them with an even spread, with their descriptors.
fn process_tile(
    ctx: &TileCtx,
    win: &TileWindow,
    grey: Vec<f32>,
    valid: &[bool],
    writer: &mut SpillWriter,
    st: &mut Stats,
) -> Result<(), MapError> {
    if !valid.iter().any(|&v| v) {
        return Ok(());
    }
    let holes = Holes::of(valid, win.w, win.h);
    let img = GrayImage::new(win.w, win.h, grey).map_err(|e| MapError::Param {
        name: "tile",
        reason: e.to_string(),
    })?;
    let feats = match ctx.orb {
        // Binary features are described with the detection (one pass over the pyramid); the
        // keypoints kept pick their rows.
        Some(orb) => {
            let all = orb.detect_and_describe(&img);
            // The patch grows with the pyramid level: half the keypoint's size.
            let kept = keep_in_core(
                ctx,
                win,
                &holes,
                all.keypoints.clone(),
                |kp| 0.5 * f64::from(kp.size) + 1.0,
                st,
            );
            all.subset(&kept)
        }
        None => {
            let ii = IntegralImage::new(&img);
            let upright = ctx.surf.params().upright;
            let kept = keep_in_core(
                ctx,
                win,
                &holes,
                ctx.surf.detect(&ii),
                |kp| f64::from(descriptor_radius_px(kp.scale, upright)),
                st,
            );
            ctx.surf.describe(&ii, kept)
        }
    };
    push_features(ctx, win, &feats, writer, st)
}

/// Summed-area table of a window's missing pixels, `(w+1) x (h+1)`.
struct Holes {
    w: usize,
    h: usize,
    sums: Vec<u32>,
}

impl Holes {
    fn of(valid: &[bool], w: usize, h: usize) -> Self {
        let mut sums = vec![0u32; (w + 1) * (h + 1)];
        for y in 0..h {
            let mut run = 0u32;
            for x in 0..w {
                run += u32::from(!valid[y * w + x]);
                sums[(y + 1) * (w + 1) + x + 1] = sums[y * (w + 1) + x + 1] + run;
            }
        }
        Self { w, h, sums }
    }
    fn any(&self) -> bool {
        self.sums[(self.w + 1) * (self.h + 1) - 1] > 0
    }
    /// Whether the square of radius `r` around `(x, y)` (clipped to the window) has a hole.
    fn near(&self, x: i64, y: i64, r: i64) -> bool {
        let cl = |v: i64, n: usize| v.clamp(0, n as i64) as usize;
        let (x0, x1) = (cl(x - r, self.w), cl(x + r + 1, self.w));
        let (y0, y1) = (cl(y - r, self.h), cl(y + r + 1, self.h));
        let s = |xx: usize, yy: usize| i64::from(self.sums[yy * (self.w + 1) + xx]);
        s(x1, y1) - s(x0, y1) - s(x1, y0) + s(x0, y0) > 0
    }
}

/// The keypoints of the window whose centre lies in the tile's core and whose descriptor window
/// (radius `radius_px(kp)`) holds no missing pixel, the strongest `ctx.cap` with an even spread,
/// in window coordinates.
fn keep_in_core(
    ctx: &TileCtx,
    win: &TileWindow,
    holes: &Holes,
    kps: Vec<KeyPoint>,
    radius_px: impl Fn(&KeyPoint) -> f64,
    st: &mut Stats,
) -> Vec<KeyPoint> {
    let (cx0, cy0, cw, ch, wx0, wy0) = (win.cx0, win.cy0, win.cw, win.ch, win.x0, win.y0);
    let any_hole = holes.any();
    let mut kept: Vec<KeyPoint> = Vec::new();
    for kp in kps {
        // Continuous level coordinates (GDAL corner convention) of the keypoint centre.
        let gx = wx0 as f64 + f64::from(kp.x) + 0.5;
        let gy = wy0 as f64 + f64::from(kp.y) + 0.5;
        if !(gx >= cx0 as f64
            && gx < (cx0 + cw) as f64
            && gy >= cy0 as f64
            && gy < (cy0 + ch) as f64)
        {
            continue;
        }
        if any_hole {
            let r = radius_px(&kp).ceil() as i64;
            if holes.near(kp.x.round() as i64, kp.y.round() as i64, r) {
                st.dropped_nodata += 1;
                continue;
            }
        }
        // Core-relative coordinates for the even-spread cap.
        let mut k = kp;
        k.x -= (cx0 - wx0) as f32;
        k.y -= (cy0 - wy0) as f32;
        kept.push(k);
    }
    let mut kept = visnav_core::vision::surf::select_spread(kept, win.cap(ctx.cap), cw, ch);
    for k in &mut kept {
        k.x += (cx0 - wx0) as f32;
        k.y += (cy0 - wy0) as f32;
    }
    kept
}

/// Writes the tile's features with their map position and height.
fn push_features(
    ctx: &TileCtx,
    win: &TileWindow,
    feats: &Features,
    writer: &mut SpillWriter,
    st: &mut Stats,
) -> Result<(), MapError> {
    let (wx0, wy0) = (win.x0, win.y0);
    let f = f64::from(1u32 << ctx.level);
    let t = &ctx.transform;
    for (i, kp) in feats.keypoints.iter().enumerate() {
        let col0 = (wx0 as f64 + f64::from(kp.x) + 0.5) * f;
        let row0 = (wy0 as f64 + f64::from(kp.y) + 0.5) * f;
        let (x_m, y_m) = t.pixel_to_map(col0, row0);
        if let Some(a) = &ctx.area
            && !(x_m >= a.min_x_m && x_m < a.max_x_m && y_m > a.min_y_m && y_m <= a.max_y_m)
        {
            continue;
        }
        let Some(z) = ctx.dem.height_at(x_m, y_m) else {
            st.dropped_no_height += 1;
            continue;
        };
        let mf = MapFeature {
            x_m,
            y_m,
            z_amsl_m: z,
            scale_m: (f64::from(kp.scale) * t.pixel_size().0 * f) as f32,
            response: kp.response,
            laplacian: kp.laplacian,
            level: ctx.level as u8, // ok: <= 12 levels
        };
        writer.push(ctx.level, &mf, feats.descriptor(i), ctx.source)?;
        st.features += 1;
    }
    Ok(())
}

/// Grey values (8-bit scale) and validity of the level-`level` window with top-left level pixel
/// `(x0, y0)` and size `w x h` (inside the level image). A level pixel is the mean of the valid
/// level-0 luma values of its `2^level` block, missing (value 0) when under 3/4 are valid.
pub fn level_window(
    r: &Raster,
    level: usize,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
) -> (Vec<f32>, Vec<bool>) {
    let f = 1usize << level;
    let mut grey = vec![0f32; w * h];
    let mut valid = vec![false; w * h];
    let need = (3 * f * f).div_ceil(4) as u32;
    grey.par_chunks_mut(w)
        .zip(valid.par_chunks_mut(w))
        .enumerate()
        .for_each_init(
            || (vec![0f32; w * f], vec![0f32; w], vec![0u32; w]),
            |(row, sum, cnt), (yy, (g_out, v_out))| {
                sum.iter_mut().for_each(|v| *v = 0.0);
                cnt.iter_mut().for_each(|v| *v = 0);
                for j in 0..f {
                    luma_row(r, (y0 + yy) * f + j, x0 * f, row);
                    for (i, v) in row.iter().enumerate() {
                        if !v.is_nan() {
                            sum[i / f] += v;
                            cnt[i / f] += 1;
                        }
                    }
                }
                for i in 0..w {
                    if cnt[i] >= need {
                        g_out[i] = sum[i] / cnt[i] as f32;
                        v_out[i] = true;
                    }
                }
            },
        );
    (grey, valid)
}

/// [`level_window`] read through a windowed GeoTIFF reader: the level-0 pixels under the level
/// window are read in bands of whole `2^level`-row blocks of about `band_bytes` (at least one
/// block row), each averaged with [`level_window`] itself, so the result is bit-identical to
/// `level_window` on the whole decoded image while only one band is held at a time. When a band
/// holds several chunk rows, band ends fall on chunk-row boundaries so that no strip/tile is
/// needed by two bands (each is decoded once per window even without the cache).
pub fn level_window_from_reader<R: Read + Seek + Send>(
    reader: &mut GeoTiffWindowReader<R>,
    level: usize,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    band_bytes: usize,
) -> Result<(Vec<f32>, Vec<bool>), GeoTiffError> {
    let f = 1usize << level;
    let info = reader.info();
    let sample_bytes = usize::from(info.bits_per_sample).div_ceil(8).max(1);
    // Level-0 bytes of one level row of the window.
    let row_bytes = (w * f)
        .saturating_mul(f)
        .saturating_mul(info.bands)
        .saturating_mul(sample_bytes);
    let rows_per_band = (band_bytes / row_bytes.max(1)).clamp(1, h.max(1));
    // Level rows per aligned unit: lcm(2^level, chunk height) level-0 rows.
    let ch = info.chunk_height.max(1);
    let unit = (f / gcd(f, ch)).saturating_mul(ch) / f;
    let mut grey = Vec::with_capacity(w * h);
    let mut valid = Vec::with_capacity(w * h);
    let mut ya = 0;
    while ya < h {
        let mut n = rows_per_band.min(h - ya);
        if ya + n < h && unit <= rows_per_band {
            // End the band on a unit boundary (absolute level row a multiple of `unit`).
            let end = (y0 + ya + n) / unit * unit;
            if end > y0 + ya {
                n = end - y0 - ya;
            }
        }
        let band = reader.read_window(x0 * f, (y0 + ya) * f, w * f, n * f)?;
        let (g, v) = level_window(&band, level, 0, 0, w, n);
        grey.extend_from_slice(&g);
        valid.extend_from_slice(&v);
        ya += n;
    }
    Ok((grey, valid))
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// Luma of level-0 pixels `c0 .. c0 + out.len()` of `row`, NaN where a used band is missing.
fn luma_row(r: &Raster, row: usize, c0: usize, out: &mut [f32]) {
    let bands = r.bands();
    let start = (row * r.width() + c0) * bands;
    let n = out.len();
    let nodata = r.nodata();
    let rgb = bands >= 3;
    macro_rules! conv {
        ($v:expr, $scale:expr) => {{
            let px = &$v[start..start + n * bands];
            for (o, p) in out.iter_mut().zip(px.chunks_exact(bands)) {
                let miss = |s: f64| s.is_nan() || nodata == Some(s);
                *o = if rgb {
                    let (a, b, c) = (f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                    if miss(a) || miss(b) || miss(c) {
                        f32::NAN
                    } else {
                        (LUMA[0] * a as f32 + LUMA[1] * b as f32 + LUMA[2] * c as f32) * $scale
                    }
                } else {
                    let a = f64::from(p[0]);
                    if miss(a) { f32::NAN } else { a as f32 * $scale }
                };
            }
        }};
    }
    match r.data() {
        RasterData::U8(v) => conv!(v, 1.0f32),
        RasterData::U16(v) => conv!(v, 255.0f32 / 65535.0),
        RasterData::F32(v) => conv!(v, 1.0f32),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn height_sigmas_default_by_source() {
        let constant = BuildSpec::new(vec![], HeightSource::ConstantAmsl(100.0));
        assert_eq!(
            constant.resolved_height_sigma_m(),
            DEFAULT_CONSTANT_HEIGHT_SIGMA_M
        );
        assert_eq!(
            constant.resolved_height_slope_sigma(),
            DEFAULT_CONSTANT_HEIGHT_SLOPE_SIGMA
        );
        assert_eq!(
            constant.resolved_height_point_sigma_m(),
            DEFAULT_CONSTANT_HEIGHT_SIGMA_M
        );
        let mut dem = BuildSpec::new(vec![], HeightSource::Dem(PathBuf::from("d.tif")));
        assert_eq!(
            (
                dem.resolved_height_sigma_m(),
                dem.resolved_height_slope_sigma()
            ),
            (0.0, 0.0)
        );
        dem.height_sigma_m = Some(5.0);
        assert_eq!(
            dem.resolved_height_point_sigma_m(),
            5.0,
            "the point sigma follows"
        );
        dem.height_point_sigma_m = Some(1.0);
        dem.height_slope_sigma = Some(0.002);
        assert_eq!(dem.resolved_height_point_sigma_m(), 1.0);
        assert_eq!(dem.resolved_height_slope_sigma(), 0.002);
    }
    use crate::map::ReferenceMap;
    use visnav_core::geo::raster::GeoTransform;

    const UTM: Crs = Crs::Utm {
        zone: 14,
        north: true,
    };

    fn write_tif(
        path: &Path,
        w: usize,
        h: usize,
        px_m: f64,
        x0: f64,
        y0: f64,
        f: impl Fn(usize, usize) -> u8,
    ) {
        // Minimal GeoTIFF writer via the tiff crate (1 band u8, UTM 14N, pixel-is-area).
        use tiff::encoder::{TiffEncoder, colortype};
        use tiff::tags::Tag;
        let data: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y))
            .collect();
        let file = std::fs::File::create(path).unwrap();
        let mut enc = TiffEncoder::new(file).unwrap();
        let mut img = enc
            .new_image::<colortype::Gray8>(w as u32, h as u32)
            .unwrap();
        img.encoder()
            .write_tag(Tag::ModelPixelScaleTag, &[px_m, px_m, 0.0][..])
            .unwrap();
        img.encoder()
            .write_tag(Tag::ModelTiepointTag, &[0.0, 0.0, 0.0, x0, y0, 0.0][..])
            .unwrap();
        // GeoKeyDirectory: version 1.1.0, 3 keys: model type projected, raster pixel-is-area, EPSG 32614.
        let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32614];
        img.encoder()
            .write_tag(Tag::GeoKeyDirectoryTag, &keys[..])
            .unwrap();
        img.write_data(&data).unwrap();
    }

    #[test]
    fn level_window_averages_blocks_and_marks_holes() {
        let gt = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let data: Vec<u8> = (0..8 * 4).map(|i| (i % 8) as u8 * 10 + 1).collect();
        let mut d = data.clone();
        d[9] = 0; // one nodata pixel in block (0..2, 0..2) of row 1 -> 3/4 valid, still valid
        d[2] = 0;
        d[3] = 0;
        d[10] = 0; // block (2..4) rows 0-1: 3 of 4 missing -> missing
        let r = Raster::new(8, 4, 1, RasterData::U8(d), gt, UTM, Some(0.0)).unwrap();
        let (g, v) = level_window(&r, 1, 0, 0, 4, 2);
        assert!(v[0] && !v[1] && v[2] && v[3]);
        assert!((g[0] - (1.0 + 11.0 + 1.0) / 3.0).abs() < 1e-5, "{}", g[0]);
        assert!((g[2] - (41.0 + 51.0) / 2.0).abs() < 1e-5);
        // RGB luma, 16-bit scaled.
        let r = Raster::new(
            1,
            1,
            3,
            RasterData::U16(vec![65535, 0, 65535]),
            gt,
            UTM,
            None,
        )
        .unwrap();
        let (g, _) = level_window(&r, 0, 0, 0, 1, 1);
        assert!((g[0] - 255.0 * (0.299 + 0.114)).abs() < 1e-3);
    }

    /// A dark Gaussian blob at a known map coordinate: the feature lands on it within a fraction
    /// of a pixel at every level (half-pixel conventions), with the constant height; also on an
    /// upsampled build, whose finest level is twice as fine and whose blob scale is the same.
    #[test]
    fn blob_lands_at_its_map_coordinate() {
        let dir = tempfile::tempdir().unwrap();
        let tif = dir.path().join("blob.tif");
        let (x0, y0, px) = (500_000.0, 4_000_000.0, 2.0);
        // Blob centre at continuous pixel (100.3, 76.6) (off the pixel grid, so that no two SURF
        // samples tie by symmetry) -> map coordinate:
        let (bc, br) = (100.3, 76.6);
        let (bx, by) = (x0 + bc * px, y0 - br * px);
        write_tif(&tif, 200, 160, px, x0, y0, |x, y| {
            let dx = x as f64 + 0.5 - bc;
            let dy = y as f64 + 0.5 - br;
            let s = 5.0;
            (200.0 - 150.0 * (-(dx * dx + dy * dy) / (2.0 * s * s)).exp()) as u8
        });
        let mut scales = Vec::new();
        for (upsample, levels) in [(1usize, 2usize), (2, 3)] {
            let mut spec = BuildSpec::new(vec![tif.clone()], HeightSource::ConstantAmsl(321.0));
            spec.levels = Some(levels);
            spec.surf.n_octaves = 3;
            spec.tile_px = 64;
            spec.upsample = upsample;
            let out = dir.path().join(format!("blob{upsample}.vnm"));
            let summary = build_map(&spec, &out, &mut |_| {}).unwrap();
            assert_eq!(summary.header.levels.len(), levels);
            assert_eq!(summary.header.orthos[0].pixel_size_m, px);
            assert_eq!(summary.header.orthos[0].width_px, 200);
            let m = ReferenceMap::open(&out).unwrap();
            for level in 0..levels {
                let gsd = px / upsample as f64 * f64::from(1u32 << level);
                assert!((summary.header.levels[level].gsd_m - gsd).abs() < 1e-12);
                let sel = m.select(
                    level,
                    bx - 10.0 * gsd,
                    by - 10.0 * gsd,
                    bx + 10.0 * gsd,
                    by + 10.0 * gsd,
                );
                let best = sel
                    .features
                    .iter()
                    .max_by(|a, b| a.response.total_cmp(&b.response))
                    .unwrap_or_else(|| panic!("no feature near the blob at level {level}"));
                let err = (best.x_m - bx).hypot(best.y_m - by);
                assert!(
                    err < 0.25 * gsd,
                    "upsample {upsample} level {level}: {best:?} vs ({bx}, {by}), err {err} m"
                );
                assert_eq!(best.laplacian, 1, "dark blob");
                assert_eq!(best.z_amsl_m, 321.0);
                assert!(best.scale_m > 0.0);
                scales.push((upsample, gsd, best.scale_m));
            }
        }
        // The blob's metric scale does not depend on the grid it was detected on: the
        // interpolated 1 m level of the x2 build against the plain build's 2 m level 0 (within
        // SURF's scale sampling); a scale kept in orthophoto pixels would be off by 2.
        let at = |u: usize, gsd: f64| {
            scales
                .iter()
                .find(|s| s.0 == u && (s.1 - gsd).abs() < 1e-9)
                .unwrap()
                .2
        };
        let ratio = at(2, px / 2.0) / at(1, px);
        assert!((ratio - 1.0).abs() < 0.2, "{ratio}: {scales:?}");
        let mut spec = BuildSpec::new(vec![tif], HeightSource::ConstantAmsl(0.0));
        spec.upsample = 3;
        let e = build_map(&spec, &dir.path().join("x.vnm"), &mut |_| {}).unwrap_err();
        assert!(e.to_string().contains("upsample"), "{e}");
    }

    /// Keys' weights sum to one and interpolate; the upsampled window reproduces a linear ramp
    /// (cubic convolution is exact to second order) in the interior, passes coarser levels through
    /// and loses exactly the outputs whose taps touch a hole.
    #[test]
    fn upsampled_source_interpolates_and_passes_levels() {
        for i in 0..=10 {
            let w = keys_weights(i as f32 / 10.0);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6, "{w:?}");
        }
        assert_eq!(keys_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
        let gt = GeoTransform::north_up(0.0, 0.0, 1.0, 1.0).unwrap();
        let (w, h) = (12usize, 10usize);
        let ramp = |x: usize, y: usize| (3 * x + 7 * y + 5) as u8;
        let data: Vec<u8> = (0..h)
            .flat_map(|y| (0..w).map(move |x| ramp(x, y)))
            .collect();
        let r = Raster::new(w, h, 1, RasterData::U8(data.clone()), gt, UTM, None).unwrap();
        let mut up = Upsampled {
            inner: Box::new(r.clone()),
            shift: 1,
        };
        assert_eq!(up.dims(), (2 * w, 2 * h));
        let (x0, y0, ww, wh) = (4usize, 5usize, 14usize, 11usize);
        let (g, v) = up.level_window(0, x0, y0, ww, wh).unwrap();
        for yy in 0..wh {
            for xx in 0..ww {
                let (x, y) = (x0 + xx, y0 + yy);
                assert!(v[yy * ww + xx]);
                let u = (x as f64 + 0.5) / 2.0 - 0.5;
                let t = (y as f64 + 0.5) / 2.0 - 0.5;
                // Interior: all four taps inside the raster.
                if u >= 1.0 && u <= w as f64 - 3.0 && t >= 1.0 && t <= h as f64 - 3.0 {
                    let want = 3.0 * u + 7.0 * t + 5.0;
                    assert!(
                        (f64::from(g[yy * ww + xx]) - want).abs() < 1e-3,
                        "({x}, {y}): {} vs {want}",
                        g[yy * ww + xx]
                    );
                }
            }
        }
        // Level 1 of the upsampled source is level 0 of the raster.
        assert_eq!(
            up.level_window(1, 2, 3, 5, 4).unwrap(),
            level_window(&r, 0, 2, 3, 5, 4)
        );
        // A hole at source (6, 4) invalidates the outputs whose taps reach it: columns 9..=16
        // (u in [4, 8)) of rows 5..=12, and nothing else.
        let mut d = data;
        d[4 * w + 6] = 0;
        let r = Raster::new(w, h, 1, RasterData::U8(d), gt, UTM, Some(0.0)).unwrap();
        let mut up = Upsampled {
            inner: Box::new(r),
            shift: 1,
        };
        let (_, v) = up.level_window(0, 0, 0, 2 * w, 2 * h).unwrap();
        for y in 0..2 * h {
            for x in 0..2 * w {
                let near = |p: usize, c: f64| {
                    let u = (p as f64 + 0.5) / 2.0 - 0.5;
                    (u.floor() - 1.0..=u.floor() + 2.0).contains(&c)
                };
                let hit = near(x, 6.0) && near(y, 4.0);
                assert_eq!(v[y * 2 * w + x], !hit, "({x}, {y})");
            }
        }
    }

    #[test]
    fn margin_covers_the_largest_filter_and_is_step_aligned() {
        let p = SurfParams::default();
        let m = tile_margin_px(&p);
        assert_eq!(m % 8, 0);
        assert!(m >= 195 / 2 + 3 * 8);
        assert!(m as f32 >= descriptor_radius_px(1.2 * 195.0 / 9.0, false));
    }
}
