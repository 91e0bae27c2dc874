//! A tiled map: the orthophotos cut along a fixed grid in their CRS, one `.vnm` per grid square
//! (each built with [`BuildSpec::area`], so the tiles together hold the whole build's features,
//! each once), and `index.json` listing them with their bounds, feature counts, sizes and
//! checksums and the build's parameters.
//!
//! The grid is anchored at the CRS origin (tile `(col, row)` covers x in
//! `[col T, (col + 1) T)`, y in `(row T, (row + 1) T]` for tile side `T`), so the maps of
//! neighbouring areas built with the same side share it. Every tile has the whole build's level
//! count. The build is resumable: the index is rewritten after every tile, and a tile the index
//! lists, built with the same parameters, whose file opens (its CRC verified) with the checksum
//! the index recorded, is kept rather than built again; a killed build restarted finishes without
//! rebuilding its finished tiles. Squares without features are counted, not written.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::build::{BuildSpec, build_map, extent_of};
use super::format::ReferenceMap;
use super::{BoundsDef, MapError};
use visnav_core::geo::Crs;
use visnav_core::geo::raster::Bounds;

/// The index's file name in a tiled map's folder.
pub const INDEX_FILE: &str = "index.json";
/// The tiles' folder in a tiled map's folder.
pub const TILES_DIR: &str = "tiles";
/// Version of `index.json`'s layout.
pub const TILED_FORMAT_VERSION: u32 = 1;
/// Smallest tile side, metres: a tile narrower than a few hundred metres holds only a few SURF
/// tile cores at 0.3-1 m and its level pyramid would stop at one level.
pub const MIN_TILE_M: f64 = 200.0;
/// Largest tile side, metres.
pub const MAX_TILE_M: f64 = 1.0e6;

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
    /// Pyramid levels of every tile.
    pub levels: usize,
    /// The orthophotos' union, metres.
    #[serde(with = "BoundsDef")]
    pub bounds: Bounds,
    /// The build's parameters (orthophotos, heights, detector, tiling), as a checksum: a tile
    /// built with others is built again.
    pub build_digest: String,
    /// The tiles with features, by row then column.
    pub tiles: Vec<TileEntry>,
    /// Grid squares over the orthophotos without features (no file).
    pub empty: Vec<[i64; 2]>,
    /// The program that built it.
    pub built_by: String,
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

/// Builds the tiled map of `spec` (its `area` ignored) into the folder `dir`, tiles of
/// `tile_m` metres (module doc).
pub fn build_tiled(
    spec: &BuildSpec,
    tile_m: f64,
    dir: &Path,
    progress: &mut dyn FnMut(TiledProgress),
) -> Result<TiledSummary, MapError> {
    if !(tile_m.is_finite() && (MIN_TILE_M..=MAX_TILE_M).contains(&tile_m)) {
        return Err(MapError::Param {
            name: "tile_m",
            reason: format!("{tile_m} must be {MIN_TILE_M} to {MAX_TILE_M} m"),
        });
    }
    let (union, crs, levels) = extent_of(spec)?;
    let spec = BuildSpec {
        area: None,
        levels: Some(levels),
        ..spec.clone()
    };
    let digest = build_digest(&spec, tile_m);
    let tiles_dir = dir.join(TILES_DIR);
    std::fs::create_dir_all(&tiles_dir).map_err(|source| MapError::Io {
        path: tiles_dir.clone(),
        what: "cannot create the tiles' folder",
        cause: source,
    })?;
    let (earlier, earlier_empty) = read_index(&dir.join(INDEX_FILE))
        .filter(|i| i.build_digest == digest)
        .map(|i| (i.tiles, i.empty))
        .unwrap_or_default();
    let squares = grid_squares(&union, tile_m);
    let mut index = TiledIndex {
        version: TILED_FORMAT_VERSION,
        crs,
        tile_m,
        levels,
        bounds: union,
        build_digest: digest,
        tiles: Vec::new(),
        empty: Vec::new(),
        built_by: format!("visnav {}", env!("CARGO_PKG_VERSION")),
    };
    let (mut built, mut reused) = (0, 0);
    for (k, &(col, row)) in squares.iter().enumerate() {
        let file = format!("{TILES_DIR}/x{col}_y{row}.vnm");
        let path = dir.join(&file);
        let kept = earlier
            .iter()
            .find(|t| t.col == col && t.row == row && t.file == file)
            .filter(|t| still_valid(&path, t));
        let was_empty = earlier_empty.contains(&[col, row]) && !path.exists();
        let entry = match kept {
            Some(t) => Some(t.clone()),
            None if was_empty => None,
            None => {
                built += 1;
                build_tile(&spec, (col, row), tile_m, &path, file)?
            }
        };
        let from_earlier = kept.is_some() || was_empty;
        reused += usize::from(from_earlier);
        match entry {
            Some(t) => index.tiles.push(t),
            None => index.empty.push([col, row]),
        }
        write_index(&dir.join(INDEX_FILE), &index)?;
        progress(TiledProgress {
            done: k + 1,
            total: squares.len(),
            reused: from_earlier,
        });
    }
    Ok(TiledSummary {
        index,
        built,
        reused,
    })
}

/// The grid squares `(col, row)` that overlap `union`, by row (north first) then column.
fn grid_squares(union: &Bounds, tile_m: f64) -> Vec<(i64, i64)> {
    let c0 = (union.min_x_m / tile_m).floor() as i64; // ok: bounds of a real raster
    let c1 = (union.max_x_m / tile_m).ceil() as i64;
    let r0 = (union.min_y_m / tile_m).floor() as i64;
    let r1 = (union.max_y_m / tile_m).ceil() as i64;
    (r0..r1)
        .rev()
        .flat_map(|r| (c0..c1).map(move |c| (c, r)))
        .collect()
}

/// Builds grid square `(col, row)` into `path`; `None` when it holds no feature.
fn build_tile(
    spec: &BuildSpec,
    (col, row): (i64, i64),
    tile_m: f64,
    path: &Path,
    file: String,
) -> Result<Option<TileEntry>, MapError> {
    let area = Bounds {
        min_x_m: col as f64 * tile_m,
        max_x_m: (col + 1) as f64 * tile_m,
        min_y_m: row as f64 * tile_m,
        max_y_m: (row + 1) as f64 * tile_m,
    };
    let part = BuildSpec {
        area: Some(area),
        ..spec.clone()
    };
    match build_map(&part, path, &mut |_| {}) {
        Ok(s) => Ok(Some(TileEntry {
            col,
            row,
            file,
            bounds: s.header.bounds,
            features: s.header.n_features(),
            file_bytes: s.file_bytes,
            crc32: stored_crc(path)?,
        })),
        Err(MapError::NoFeatures { .. } | MapError::Param { name: "area", .. }) => {
            // No file stands for an empty square (one left by an earlier build would be stale).
            let _ = std::fs::remove_file(path);
            Ok(None)
        }
        Err(e) => Err(e),
    }
}

/// Whether the tile file at `path` opens (its checksum verified) with the checksum `t` records.
fn still_valid(path: &Path, t: &TileEntry) -> bool {
    ReferenceMap::open(path).is_ok() && stored_crc(path).is_ok_and(|c| c == t.crc32)
}

/// The CRC-32 a `.vnm` stores (bytes 56-59 of its preamble).
fn stored_crc(path: &Path) -> Result<u32, MapError> {
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
    let text = format!("{spec:?} tile_m={tile_m}"); // debug form: hashed, never shown
    format!("{:08x}", crc32fast::hash(text.as_bytes()))
}

/// The index at `path`, when there is one that reads.
fn read_index(path: &Path) -> Option<TiledIndex> {
    let text = crate::files::read_text(path, crate::files::TILED_INDEX).ok()?;
    serde_json::from_str(&text).ok()
}

/// Writes the index to a temporary name and moves it into place.
fn write_index(path: &Path, index: &TiledIndex) -> Result<(), MapError> {
    let tmp: PathBuf = path.with_extension("json.partial");
    let io = |what, source| MapError::Io {
        path: path.to_path_buf(),
        what,
        cause: source,
    };
    let text = serde_json::to_string_pretty(index).map_err(|e| MapError::Format {
        path: path.to_path_buf(),
        reason: format!("cannot encode the index: {e}"),
    })?;
    std::fs::write(&tmp, text).map_err(|e| io("cannot write the index", e))?;
    std::fs::rename(&tmp, path).map_err(|e| io("cannot move the index into place", e))
}
