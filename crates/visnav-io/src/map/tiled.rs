//! A tiled map: the orthophotos cut along a fixed grid in their CRS, one `.vnm` per grid square,
//! and `index.json` listing them with their bounds, feature counts, sizes and checksums, the
//! build's parameters and its sources.
//!
//! The grid is anchored at the CRS origin (square `(col, row)` covers x in `[col T, (col + 1) T)`,
//! y in `(row T, (row + 1) T]` for side `T`), so the maps of neighbouring areas built with the
//! same side share it. Every square is built from its own area ([`BuildSpec::area`] with
//! [`BuildSpec::area_local`]: its tile cores cut at the square, read with the detector's margin
//! around it), so a square costs its own area whatever the map's size, and squares are
//! independent jobs: one machine builds them in turn ([`build_tiled`]), or a plan
//! ([`TilePlan`], `plan.json`) is written once and any number of machines build its squares by
//! index ([`TilePlan::build_square`], `visnav map build-tile PLAN K`), each leaving a result file
//! beside its tile; [`TilePlan::gather`] writes the index from them. Both ways run the same code
//! and write the same bytes: a tile records build time 0 and the index no time at all.
//!
//! Resuming: a square whose result file names the plan's settings (their digest) and whose tile
//! opens (its CRC verified) with the checksum the result recorded, or that recorded no feature
//! and has no tile, is kept; a killed build run again builds only what is missing or damaged,
//! and other settings build everything again.
//!
//! The level count, unless stated, follows the square (halving while its short side stays at or
//! above 256 px, as a single file's follows its orthophotos): a square must hold a level's
//! features without reading far outside itself, and the coarse levels of a large map (tens of
//! metres a pixel) serve altitudes far above the ones a fine map is built for.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::build::{BuildSpec, HeightSource, build_map, extent_of};
use super::format::ReferenceMap;
use super::{BoundsDef, MapError};
use visnav_core::geo::Crs;
use visnav_core::geo::raster::Bounds;

/// The index's file name in a tiled map's folder.
pub const INDEX_FILE: &str = "index.json";
/// The plan's file name in a tiled map's folder.
pub const PLAN_FILE: &str = "plan.json";
/// The tiles' folder in a tiled map's folder.
pub const TILES_DIR: &str = "tiles";
/// Version of the layout of `index.json`, `plan.json` and the square results.
pub const TILED_FORMAT_VERSION: u32 = 2;
/// Smallest tile side, metres: a tile narrower than a few hundred metres holds only a few SURF
/// tile cores at 0.3-1 m and its level pyramid would stop at one level.
pub const MIN_TILE_M: f64 = 200.0;
/// Largest tile side, metres.
pub const MAX_TILE_M: f64 = 1.0e6;
/// Most grid squares one plan holds (a continent at 2 km squares is about a million).
pub const MAX_SQUARES: usize = 4_000_000;

/// One tile of a tiled map.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileEntry {
    /// Grid column: the tile's x range starts at `col * tile_m`.
    pub col: i64,
    /// Grid row: the tile's y range starts (exclusive) at `row * tile_m`.
    pub row: i64,
    /// The tile's `.vnm`, relative to the map's folder.
    pub file: String,
    /// The tile map's bounds (its grid square moved out to its coarsest level's pixel grid and
    /// clipped to the orthophotos), metres.
    #[serde(with = "BoundsDef")]
    pub bounds: Bounds,
    /// Features in the tile.
    pub features: u64,
    /// Size of the tile's file, bytes.
    pub file_bytes: u64,
    /// The CRC-32 its file stores (the `.vnm` checksum).
    pub crc32: u32,
    /// The heights under the tile, for a map built on a DEM (absent on a constant height).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heights: Option<TileHeights>,
}

/// A tile's heights: the DEM's samples under its bounds and
/// [`crate::geo::dem::DEM_WINDOW_MARGIN_CELLS`] around
/// them, on the DEM's own grid, as a float GeoTIFF beside the tile (`x{col}_y{row}.dem.tif`), so
/// a tiled map carries its terrain tile by tile and the daemon pages it with the features.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileHeights {
    /// The GeoTIFF, relative to the map's folder.
    pub file: String,
    /// Its size, bytes.
    pub file_bytes: u64,
    /// The CRC-32 of its bytes.
    pub crc32: u32,
    /// Samples across.
    pub width: u64,
    /// Samples down.
    pub height: u64,
    /// The lowest height in it, metres.
    pub min_m: f64,
    /// The highest, metres.
    pub max_m: f64,
}

impl TileHeights {
    /// Memory the decoded heights take, bytes (f32 samples).
    pub fn memory_bytes(&self) -> u64 {
        self.width.saturating_mul(self.height).saturating_mul(4)
    }
}

/// `index.json`: what a tiled map holds and how it was built.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TiledIndex {
    /// [`TILED_FORMAT_VERSION`].
    pub version: u32,
    /// The CRS of every tile.
    pub crs: Crs,
    /// Tile side, metres.
    pub tile_m: f64,
    /// Ground pixel of level 0, metres.
    pub gsd_m: f64,
    /// Pyramid levels of every tile.
    pub levels: usize,
    /// The orthophotos' union, metres.
    #[serde(with = "BoundsDef")]
    pub bounds: Bounds,
    /// The build's parameters (orthophotos, heights, detector, tiling), as a checksum: a tile
    /// built with others is built again.
    pub build_digest: String,
    /// The orthophotos and the DEM, as the plan named them (absolute paths).
    pub sources: Vec<String>,
    /// The command that planned the build, when it was given.
    pub command: Option<String>,
    /// The tiles with features, by row (north first) then column.
    pub tiles: Vec<TileEntry>,
    /// Grid squares over the orthophotos without features (no file).
    pub empty: Vec<[i64; 2]>,
    /// The program that built it.
    pub built_by: String,
}

/// `plan.json`: the jobs of a tiled build, one per grid square, and everything they share.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TilePlan {
    /// [`TILED_FORMAT_VERSION`].
    pub version: u32,
    /// The build every square runs (its paths absolute, `levels` stated, `area_local` on, build
    /// time 0); each square adds its own area.
    pub spec: BuildSpec,
    /// Tile side, metres.
    pub tile_m: f64,
    /// The orthophotos' CRS.
    pub crs: Crs,
    /// Ground pixel of level 0, metres.
    pub gsd_m: f64,
    /// Pyramid levels of every tile.
    pub levels: usize,
    /// The orthophotos' union, metres.
    #[serde(with = "BoundsDef")]
    pub bounds: Bounds,
    /// A checksum of `spec` and `tile_m` ([`TiledIndex::build_digest`]).
    pub build_digest: String,
    /// The command that planned the build (provenance), when given.
    pub command: Option<String>,
    /// The grid squares `[col, row]` over the orthophotos, by row (north first) then column:
    /// job `k` builds `squares[k]`.
    pub squares: Vec<[i64; 2]>,
}

/// `tiles/x{col}_y{row}.json`: what building one square gave.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SquareResult {
    /// The plan's [`TilePlan::build_digest`].
    pub build_digest: String,
    /// Grid column.
    pub col: i64,
    /// Grid row.
    pub row: i64,
    /// The tile, or `None` when the square holds no feature (no file).
    pub tile: Option<TileEntry>,
}

/// What [`TilePlan::build_square`] did.
#[derive(Clone, Debug)]
pub struct SquareOutcome {
    /// The square's result.
    pub result: SquareResult,
    /// Whether it was kept from an earlier build.
    pub reused: bool,
}

/// What [`build_tiled`] did.
#[derive(Clone, Debug)]
pub struct TiledSummary {
    /// The index as written.
    pub index: TiledIndex,
    /// Grid squares built now (with or without features).
    pub built: usize,
    /// Grid squares kept from an earlier build (same parameters; a tile's checksum verified, an
    /// empty square still without a file).
    pub reused: usize,
}

/// Progress of a tiled build, after every grid square.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TiledProgress {
    /// Grid squares done.
    pub done: usize,
    /// Grid squares in all.
    pub total: usize,
    /// Whether this one was kept from an earlier build.
    pub reused: bool,
}

/// Builds the tiled map of `spec` (its `area` ignored) into the folder `dir`, squares of
/// `tile_m` metres, one after the other (each square's build uses every core): writes the plan,
/// builds or keeps every square, then writes the index (module doc). `command` is recorded as
/// the build's provenance.
pub fn build_tiled(
    spec: &BuildSpec,
    tile_m: f64,
    dir: &Path,
    command: Option<String>,
    progress: &mut dyn FnMut(TiledProgress),
) -> Result<TiledSummary, MapError> {
    let plan = TilePlan::new(spec, tile_m, command)?;
    plan.write(dir)?;
    let (mut built, mut reused) = (0, 0);
    for k in 0..plan.squares.len() {
        let o = plan.build_square(dir, k)?;
        if o.reused {
            reused += 1;
        } else {
            built += 1;
        }
        progress(TiledProgress {
            done: k + 1,
            total: plan.squares.len(),
            reused: o.reused,
        });
    }
    Ok(TiledSummary {
        index: plan.gather(dir)?,
        built,
        reused,
    })
}

impl TiledIndex {
    /// The index of the tiled map in the folder `dir` (or the index file itself).
    pub fn read(dir: &Path) -> Result<Self, MapError> {
        let path = if dir.is_dir() {
            dir.join(INDEX_FILE)
        } else {
            dir.to_path_buf()
        };
        let index: Self = read_json(&path)?;
        if index.version != TILED_FORMAT_VERSION {
            return Err(MapError::Format {
                path,
                reason: format!(
                    "index version {} (this visnav reads {TILED_FORMAT_VERSION}): build it again",
                    index.version
                ),
            });
        }
        Ok(index)
    }

    /// Sum of the tiles' file sizes, bytes.
    pub fn total_bytes(&self) -> u64 {
        self.tiles.iter().map(|t| t.file_bytes).sum()
    }

    /// Sum of the tiles' features.
    pub fn total_features(&self) -> u64 {
        self.tiles.iter().map(|t| t.features).sum()
    }

    /// Ground the tiles cover (the sum of their bounds), km².
    pub fn tiles_area_km2(&self) -> f64 {
        self.tiles
            .iter()
            .map(|t| (t.bounds.max_x_m - t.bounds.min_x_m) * (t.bounds.max_y_m - t.bounds.min_y_m))
            .sum::<f64>()
            / 1e6
    }
}

impl TilePlan {
    /// The plan of `spec` (its `area` ignored) in squares of `tile_m` metres: the paths made
    /// absolute, the level count fixed (module doc), the squares over the orthophotos listed.
    pub fn new(spec: &BuildSpec, tile_m: f64, command: Option<String>) -> Result<Self, MapError> {
        if !(tile_m.is_finite() && (MIN_TILE_M..=MAX_TILE_M).contains(&tile_m)) {
            return Err(MapError::Param {
                name: "tile_m",
                reason: format!("{tile_m} must be {MIN_TILE_M} to {MAX_TILE_M} m"),
            });
        }
        let (bounds, crs, gsd_m, levels) = extent_of(spec, Some(tile_m))?;
        let spec = BuildSpec {
            orthos: spec
                .orthos
                .iter()
                .map(|p| absolute(p))
                .collect::<Result<_, _>>()?,
            height: match &spec.height {
                HeightSource::Dem(p) => HeightSource::Dem(absolute(p)?),
                h => h.clone(),
            },
            area: None,
            area_local: true,
            levels: Some(levels),
            built_unix_s: Some(0),
            ..spec.clone()
        };
        let squares = grid_squares(&bounds, tile_m)?;
        Ok(Self {
            version: TILED_FORMAT_VERSION,
            build_digest: build_digest(&spec, tile_m),
            spec,
            tile_m,
            crs,
            gsd_m,
            levels,
            bounds,
            command,
            squares,
        })
    }

    /// Writes the plan to `dir/plan.json` and makes the tiles' folder.
    pub fn write(&self, dir: &Path) -> Result<(), MapError> {
        make_tiles_dir(dir)?;
        write_json(&dir.join(PLAN_FILE), self)
    }

    /// The plan at `path` (`plan.json`).
    pub fn read(path: &Path) -> Result<Self, MapError> {
        let plan: Self = read_json(path)?;
        if plan.version != TILED_FORMAT_VERSION {
            return Err(MapError::Format {
                path: path.to_path_buf(),
                reason: format!(
                    "plan version {} (this visnav reads {TILED_FORMAT_VERSION}): plan again",
                    plan.version
                ),
            });
        }
        if plan.squares.len() > MAX_SQUARES
            || build_digest(&plan.spec, plan.tile_m) != plan.build_digest
        {
            return Err(MapError::Format {
                path: path.to_path_buf(),
                reason: "the plan's settings do not match its digest (edited?): plan again".into(),
            });
        }
        Ok(plan)
    }

    /// The files of square `k`: its tile and its result, relative to the map's folder.
    fn files_of(&self, k: usize) -> (String, String) {
        let [col, row] = self.squares[k];
        (
            format!("{TILES_DIR}/x{col}_y{row}.vnm"),
            format!("{TILES_DIR}/x{col}_y{row}.json"),
        )
    }

    /// Builds square `k` into the folder `dir` (the plan's), or keeps it when an earlier build
    /// left it valid (module doc); writes its result file.
    pub fn build_square(&self, dir: &Path, k: usize) -> Result<SquareOutcome, MapError> {
        let Some(&[col, row]) = self.squares.get(k) else {
            return Err(MapError::Param {
                name: "square",
                reason: format!(
                    "{k} is not a square of the plan (0 to {})",
                    self.squares.len().saturating_sub(1)
                ),
            });
        };
        let (file, result_file) = self.files_of(k);
        let (path, result_path) = (dir.join(&file), dir.join(&result_file));
        if let Some(r) = read_json::<SquareResult>(&result_path)
            .ok()
            .filter(|r| self.still_valid(r, col, row, &path))
        {
            return Ok(SquareOutcome {
                result: r,
                reused: true,
            });
        }
        // A result that no longer holds goes first: a build killed now leaves no stale claim.
        let _ = std::fs::remove_file(&result_path);
        let tile = self.build_tile((col, row), &path, file)?;
        let result = SquareResult {
            build_digest: self.build_digest.clone(),
            col,
            row,
            tile,
        };
        write_json(&result_path, &result)?;
        Ok(SquareOutcome {
            result,
            reused: false,
        })
    }

    /// Whether the result `r` of square `(col, row)` was made by this plan and its tile (at
    /// `path`) is intact: the file opens with the checksum recorded, or there is none for an
    /// empty square.
    fn still_valid(&self, r: &SquareResult, col: i64, row: i64, path: &Path) -> bool {
        if r.build_digest != self.build_digest || (r.col, r.row) != (col, row) {
            return false;
        }
        let on_dem = matches!(self.spec.height, HeightSource::Dem(_));
        match &r.tile {
            Some(t) => {
                ReferenceMap::open(path).is_ok_and(|m| m.stored_crc() == t.crc32)
                    && match (&t.heights, on_dem) {
                        (Some(h), true) => {
                            heights_intact(h, &path.with_file_name(file_name_of(&h.file)))
                        }
                        // A constant height, or a DEM without a height under the tile.
                        (None, _) => true,
                        (Some(_), false) => false,
                    }
            }
            None => !path.exists(),
        }
    }

    /// Builds grid square `(col, row)` into `path`; `None` when it holds no feature.
    fn build_tile(
        &self,
        (col, row): (i64, i64),
        path: &Path,
        file: String,
    ) -> Result<Option<TileEntry>, MapError> {
        let t = self.tile_m;
        let area = Bounds {
            min_x_m: col as f64 * t,
            max_x_m: (col + 1) as f64 * t,
            min_y_m: row as f64 * t,
            max_y_m: (row + 1) as f64 * t,
        };
        let part = BuildSpec {
            area: Some(area),
            ..self.spec.clone()
        };
        match build_map(&part, path, &mut |_| {}) {
            Ok(s) => {
                let heights = match &self.spec.height {
                    HeightSource::Dem(dem) => {
                        let name = heights_file_of(&file);
                        write_tile_heights(
                            dem,
                            self.spec.crs_override,
                            &s.header.bounds,
                            &path.with_file_name(file_name_of(&name)),
                            name,
                        )?
                    }
                    _ => None,
                };
                Ok(Some(TileEntry {
                    col,
                    row,
                    file,
                    bounds: s.header.bounds,
                    features: s.header.n_features(),
                    file_bytes: s.file_bytes,
                    crc32: stored_crc(path)?,
                    heights,
                }))
            }
            Err(MapError::NoFeatures { .. } | MapError::Param { name: "area", .. }) => {
                // No file stands for an empty square (one left by an earlier build would be
                // stale).
                let _ = std::fs::remove_file(path);
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }

    /// Writes `dir/index.json` from the squares' results; every square must be done (an error
    /// names the first that is not).
    pub fn gather(&self, dir: &Path) -> Result<TiledIndex, MapError> {
        let mut index = TiledIndex {
            version: TILED_FORMAT_VERSION,
            crs: self.crs,
            tile_m: self.tile_m,
            gsd_m: self.gsd_m,
            levels: self.levels,
            bounds: self.bounds,
            build_digest: self.build_digest.clone(),
            sources: self.sources(),
            command: self.command.clone(),
            tiles: Vec::new(),
            empty: Vec::new(),
            built_by: format!("visnav {}", env!("CARGO_PKG_VERSION")),
        };
        for (k, &[col, row]) in self.squares.iter().enumerate() {
            let (file, result_file) = self.files_of(k);
            let done = read_json::<SquareResult>(&dir.join(&result_file))
                .ok()
                .filter(|r| r.build_digest == self.build_digest && (r.col, r.row) == (col, row));
            match done {
                Some(SquareResult { tile: Some(t), .. }) if t.file == file => index.tiles.push(t),
                Some(SquareResult { tile: None, .. }) => index.empty.push([col, row]),
                _ => {
                    return Err(MapError::Input {
                        path: dir.join(result_file),
                        reason: format!(
                            "square {k} of {} (x{col}_y{row}) is not built with this plan's \
                             settings: run `visnav map build-tile` for it",
                            self.squares.len()
                        ),
                    });
                }
            }
        }
        write_json(&dir.join(INDEX_FILE), &index)?;
        Ok(index)
    }

    /// The orthophotos and the DEM, as named in the plan.
    fn sources(&self) -> Vec<String> {
        let mut s: Vec<String> = self
            .spec
            .orthos
            .iter()
            .map(|p| p.display().to_string())
            .collect();
        if let HeightSource::Dem(p) = &self.spec.height {
            s.push(p.display().to_string());
        }
        s
    }
}

/// `p` as an absolute path without `.`/`..` (a plan's jobs may run in another folder or on
/// another machine that mounts the same files).
fn absolute(p: &Path) -> Result<PathBuf, MapError> {
    std::fs::canonicalize(p).map_err(|source| MapError::Io {
        path: p.to_path_buf(),
        what: "cannot find the input file",
        cause: source,
    })
}

/// The grid squares `[col, row]` that overlap `union`, by row (north first) then column.
fn grid_squares(union: &Bounds, tile_m: f64) -> Result<Vec<[i64; 2]>, MapError> {
    let c0 = (union.min_x_m / tile_m).floor() as i64; // ok: bounds of a real raster
    let c1 = (union.max_x_m / tile_m).ceil() as i64;
    let r0 = (union.min_y_m / tile_m).floor() as i64;
    let r1 = (union.max_y_m / tile_m).ceil() as i64;
    let n = (c1 - c0).saturating_mul(r1 - r0);
    if n > MAX_SQUARES as i64 {
        return Err(MapError::Param {
            name: "tile_m",
            reason: format!("{tile_m} m cuts the orthophotos into {n} squares, over {MAX_SQUARES}"),
        });
    }
    Ok((r0..r1)
        .rev()
        .flat_map(|r| (c0..c1).map(move |c| [c, r]))
        .collect())
}

/// Makes the tiles' folder of the tiled map in `dir` (and `dir`).
pub(super) fn make_tiles_dir(dir: &Path) -> Result<(), MapError> {
    let tiles_dir = dir.join(TILES_DIR);
    std::fs::create_dir_all(&tiles_dir).map_err(|source| MapError::Io {
        path: tiles_dir.clone(),
        what: "cannot create the tiles' folder",
        cause: source,
    })
}

/// The heights file of the tile file `file` (`tiles/x0_y0.vnm` -> `tiles/x0_y0.dem.tif`).
pub(super) fn heights_file_of(file: &str) -> String {
    format!("{}.dem.tif", file.strip_suffix(".vnm").unwrap_or(file))
}

/// The last component of a relative file name of the index.
fn file_name_of(file: &str) -> &str {
    file.rsplit('/').next().unwrap_or(file)
}

/// Writes the DEM `dem`'s samples under `bounds` (and
/// [`crate::geo::dem::DEM_WINDOW_MARGIN_CELLS`] around) to `out` as a float GeoTIFF (via a
/// temporary name); `file` is its name in the index. `None` (and no file) where the DEM holds
/// no height there: never more than the window.
pub(super) fn write_tile_heights(
    dem: &Path,
    crs_override: Option<Crs>,
    bounds: &Bounds,
    out: &Path,
    file: String,
) -> Result<Option<TileHeights>, MapError> {
    let dem_err = |reason: String| MapError::Input {
        path: dem.to_path_buf(),
        reason,
    };
    let grid = match crate::geo::dem::load_dem_window(dem, crs_override, bounds) {
        Ok(Some(visnav_core::geo::dem::Dem::Grid(g))) => g,
        Ok(Some(visnav_core::geo::dem::Dem::Flat { .. })) => {
            return Err(dem_err("a DEM file read as a constant height".into()));
        }
        Ok(None) => {
            let _ = std::fs::remove_file(out);
            return Ok(None);
        }
        Err(e) => {
            return Err(MapError::Dem {
                path: dem.to_path_buf(),
                cause: Box::new(e),
            });
        }
    };
    let raster = grid.to_raster().map_err(|e| dem_err(e.to_string()))?;
    let partial = out.with_extension("tif.partial");
    crate::geo::geotiff_write::write_geotiff(&raster, &partial).map_err(|e| MapError::Input {
        path: out.to_path_buf(),
        reason: format!("cannot write the tile's heights: {e}"),
    })?;
    std::fs::rename(&partial, out).map_err(|source| MapError::Io {
        path: out.to_path_buf(),
        what: "cannot move the tile's heights into place",
        cause: source,
    })?;
    let bytes = std::fs::read(out).map_err(|source| MapError::Io {
        path: out.to_path_buf(),
        what: "cannot read back the tile's heights",
        cause: source,
    })?;
    let (min_m, max_m) = grid.height_range_m();
    Ok(Some(TileHeights {
        file,
        file_bytes: bytes.len() as u64,
        crc32: crc32fast::hash(&bytes),
        width: grid.width() as u64,
        height: grid.height() as u64,
        min_m,
        max_m,
    }))
}

/// Whether the heights file at `path` is the one `h` records (size and checksum).
pub fn heights_intact(h: &TileHeights, path: &Path) -> bool {
    std::fs::metadata(path).is_ok_and(|m| m.len() == h.file_bytes)
        && std::fs::read(path).is_ok_and(|b| crc32fast::hash(&b) == h.crc32)
}

/// The CRC-32 a `.vnm` stores (bytes 56-59 of its preamble).
pub(super) fn stored_crc(path: &Path) -> Result<u32, MapError> {
    use std::io::Read;
    let mut b = [0u8; 60];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut b))
        .map_err(|source| MapError::Io {
            path: path.to_path_buf(),
            what: "cannot read the tile's checksum",
            cause: source,
        })?;
    Ok(u32::from_le_bytes([b[56], b[57], b[58], b[59]]))
}

/// A checksum of everything that decides a tile's content: the build's settings and the tile
/// side (the orthophotos by path: a moved file means a rebuild).
fn build_digest(spec: &BuildSpec, tile_m: f64) -> String {
    // "heights": tiles on a DEM carry their heights (plans from before are built again).
    let text = format!("{spec:?} tile_m={tile_m} heights"); // debug form: hashed, never shown
    format!("{:08x}", crc32fast::hash(text.as_bytes()))
}

/// The JSON file at `path`, read with the tiled map's size limit.
fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, MapError> {
    let text = crate::files::read_text(path, crate::files::TILED_INDEX).map_err(|source| {
        MapError::Io {
            path: path.to_path_buf(),
            what: "cannot read",
            cause: source,
        }
    })?;
    serde_json::from_str(&text).map_err(|e| MapError::Format {
        path: path.to_path_buf(),
        reason: format!("not a tiled map file of this version: {e}"),
    })
}

/// Writes `value` as JSON to a temporary name and moves it into place (a reader never sees half
/// a file).
pub(super) fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), MapError> {
    let tmp: PathBuf = path.with_extension("json.partial");
    let io = |what, source| MapError::Io {
        path: path.to_path_buf(),
        what,
        cause: source,
    };
    let text = serde_json::to_string_pretty(value).map_err(|e| MapError::Format {
        path: path.to_path_buf(),
        reason: format!("cannot encode: {e}"),
    })?;
    std::fs::write(&tmp, text).map_err(|e| io("cannot write", e))?;
    std::fs::rename(&tmp, path).map_err(|e| io("cannot move into place", e))
}
