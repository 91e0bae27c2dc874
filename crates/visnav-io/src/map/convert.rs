//! Converting a single-file map (`.vnm`) into a tiled map: its features, level images and
//! heights cut along the tiled grid (`super::tiled`), bit for bit, without the orthophotos.
//!
//! Each grid square `(col, row)` (x in `[col T, (col + 1) T)`, y in `(row T, (row + 1) T]`)
//! gets the features whose position lies in it, each feature's record and descriptor copied as
//! stored (so the tiled map's selections equal the file's, descriptor for descriptor), and every
//! level's image over the square's bounds moved out to the coarsest level's pixel grid through
//! the file's image corner (the same snapping a tiled build does, so neighbouring tiles share
//! one pixel grid and overlap by at most a coarse pixel of identical bytes). Heights come with
//! the features; for a map built on a DEM, each tile also gets the DEM's samples under it
//! (`tiled::TileHeights`) when the DEM its header names is at hand (else `[map] dem` gives the
//! terrain in flight). Squares
//! with neither a feature nor a pixel get no file and are listed as empty; one with pixels only
//! (a sliver at the map's edge) keeps them. Memory: one square's features and
//! images at a time.

use std::path::Path;

use super::format::{RECORD_BYTES, ReferenceMap, SpillWriter};
use super::tiled::{
    INDEX_FILE, MAX_SQUARES, MAX_TILE_M, MIN_TILE_M, TILED_FORMAT_VERSION, TILES_DIR, TileEntry,
    TiledIndex, heights_file_of, make_tiles_dir, stored_crc, write_json, write_tile_heights,
};
use super::{HeightInfo, IndexGrid, LevelImageInfo, LevelInfo, MapError, MapHeader};
use visnav_core::geo::raster::Bounds;

/// What [`convert_to_tiled`] did.
#[derive(Clone, Debug)]
pub struct ConvertSummary {
    /// The index as written.
    pub index: TiledIndex,
    /// Features copied (all of the file's).
    pub features: u64,
    /// The DEM the tiles' heights were cut from; `None` for a constant height, or when the DEM
    /// the file names is not at hand (the tiles then carry no heights).
    pub heights_from: Option<std::path::PathBuf>,
}

/// Converts the map file `src` into a tiled map of squares of `tile_m` metres in the folder
/// `dir` (created; one that already holds a tiled map is refused). `command` is recorded as the
/// map's provenance. Every feature of the file lands in exactly one tile.
pub fn convert_to_tiled(
    src: &Path,
    tile_m: f64,
    dir: &Path,
    command: Option<String>,
) -> Result<ConvertSummary, MapError> {
    if !(tile_m.is_finite() && (MIN_TILE_M..=MAX_TILE_M).contains(&tile_m)) {
        return Err(MapError::Param {
            name: "tile_m",
            reason: format!("{tile_m} must be {MIN_TILE_M} to {MAX_TILE_M} m"),
        });
    }
    let map = ReferenceMap::open(src)?;
    let h = map.header().clone();
    let squares = squares_of(&h.bounds, tile_m)?;
    if dir.join(INDEX_FILE).exists() {
        return Err(MapError::Input {
            path: dir.to_path_buf(),
            reason: "already holds a tiled map (index.json): remove it or name another folder"
                .into(),
        });
    }
    make_tiles_dir(dir)?;
    let mut index = TiledIndex {
        version: TILED_FORMAT_VERSION,
        crs: h.crs,
        tile_m,
        gsd_m: h.levels.first().map_or(0.0, |l| l.gsd_m),
        levels: h.levels.len(),
        bounds: h.bounds,
        build_digest: format!(
            "{:08x}",
            crc32fast::hash(format!("convert {:08x} tile_m={tile_m}", map.stored_crc()).as_bytes())
        ),
        sources: sources_of(src, &h),
        command,
        tiles: Vec::new(),
        empty: Vec::new(),
        built_by: format!("visnav {}", env!("CARGO_PKG_VERSION")),
    };
    let heights_from = match &h.height {
        HeightInfo::Dem { file, .. } => super::reference::find_dem(src, file),
        HeightInfo::Constant { .. } => None,
    };
    let mut copied = 0u64;
    for [col, row] in squares {
        let file = format!("{TILES_DIR}/x{col}_y{row}.vnm");
        match cut_square(&map, (col, row), tile_m, &dir.join(&file))? {
            Some((header, file_bytes)) => {
                let features = header.n_features();
                copied += features;
                let heights = match &heights_from {
                    // In the map's CRS, as the map reads its DEM when it opens.
                    Some(dem) => {
                        let name = heights_file_of(&file);
                        write_tile_heights(
                            dem,
                            Some(h.crs),
                            &header.bounds,
                            &dir.join(&name),
                            name,
                        )?
                    }
                    None => None,
                };
                index.tiles.push(TileEntry {
                    col,
                    row,
                    crc32: stored_crc(&dir.join(&file))?,
                    file,
                    bounds: header.bounds,
                    features,
                    file_bytes,
                    heights,
                });
            }
            None => index.empty.push([col, row]),
        }
    }
    if copied != h.n_features() {
        return Err(MapError::Format {
            path: src.to_path_buf(),
            reason: format!(
                "{} of its {} features lie outside its own bounds: not converted",
                h.n_features() - copied.min(h.n_features()),
                h.n_features()
            ),
        });
    }
    write_json(&dir.join(INDEX_FILE), &index)?;
    Ok(ConvertSummary {
        index,
        features: copied,
        heights_from,
    })
}

/// The grid squares `[col, row]` a feature inside `b` can lie in (x to column by floor, y to
/// row by ceiling minus one: the squares' half-open sides), north row first.
fn squares_of(b: &Bounds, tile_m: f64) -> Result<Vec<[i64; 2]>, MapError> {
    let col = |x: f64| (x / tile_m).floor() as i64; // ok: finite bounds of an opened map
    let row = |y: f64| (y / tile_m).ceil() as i64 - 1;
    let (c0, c1, r0, r1) = (
        col(b.min_x_m),
        col(b.max_x_m),
        row(b.min_y_m),
        row(b.max_y_m),
    );
    let n = c1
        .saturating_sub(c0)
        .saturating_add(1)
        .saturating_mul(r1.saturating_sub(r0).saturating_add(1));
    if !(0..=MAX_SQUARES as i64).contains(&n) {
        return Err(MapError::Param {
            name: "tile_m",
            reason: format!("{tile_m} m cuts the map into {n} squares, over {MAX_SQUARES}"),
        });
    }
    Ok((r0..=r1)
        .rev()
        .flat_map(|r| (c0..=c1).map(move |c| [c, r]))
        .collect())
}

/// The file's orthophotos and DEM as its header names them, after the file itself.
fn sources_of(src: &Path, h: &MapHeader) -> Vec<String> {
    let mut s = vec![
        std::fs::canonicalize(src)
            .unwrap_or_else(|_| src.to_path_buf())
            .display()
            .to_string(),
    ];
    s.extend(h.orthos.iter().map(|o| o.file.clone()));
    if let HeightInfo::Dem { file, .. } = &h.height {
        s.push(file.clone());
    }
    s
}

/// Writes square `(col, row)` of `map` to `out`: its features and its level images over its
/// snapped bounds. `None` (and no file) when the square holds neither a feature nor a pixel.
fn cut_square(
    map: &ReferenceMap,
    (col, row): (i64, i64),
    tile_m: f64,
    out: &Path,
) -> Result<Option<(MapHeader, u64)>, MapError> {
    let h = map.header();
    let square = [
        col as f64 * tile_m,
        row as f64 * tile_m,
        (col + 1) as f64 * tile_m,
        (row + 1) as f64 * tile_m,
    ];
    let in_square = |rec: &[u8; RECORD_BYTES]| {
        let x = f64::from_le_bytes(rec[0..8].try_into().unwrap_or([0; 8]));
        let y = f64::from_le_bytes(rec[8..16].try_into().unwrap_or([0; 8]));
        x < square[2] && y > square[1]
    };
    let mut n = 0u64;
    for l in 0..h.levels.len() {
        map.for_each_record(l, square, |rec, _| n += u64::from(in_square(rec)));
    }
    let bounds = snapped_bounds(h, square);
    let images = image_windows(map, &bounds)?;
    // A square with pixels but no feature keeps its pixels (area matching works there).
    if n == 0 && images.iter().all(|(_, px)| px.iter().all(|&v| v == 0)) {
        let _ = std::fs::remove_file(out);
        return Ok(None);
    }
    let grids: Vec<IndexGrid> = h
        .levels
        .iter()
        .map(|l| {
            let cell_m = l.grid.cell_m;
            let span = |a: f64, b: f64| ((b - a) / cell_m).ceil().clamp(1.0, f64::from(u32::MAX));
            IndexGrid {
                origin_x_m: bounds.min_x_m,
                origin_y_m: bounds.max_y_m,
                cell_m,
                cols: span(bounds.min_x_m, bounds.max_x_m) as u32, // ok: clamped
                rows: span(bounds.min_y_m, bounds.max_y_m) as u32, // ok: clamped
            }
        })
        .collect();
    let mut writer = SpillWriter::new(
        &out.with_extension("vnm.spill"),
        h.descriptor_kind(),
        grids.clone(),
    )?;
    if !images.is_empty() {
        writer = writer.with_images(images.iter().map(|(info, _)| *info).collect())?;
        for (l, (info, px)) in images.iter().enumerate() {
            writer.push_image_block(
                l,
                0,
                0,
                info.width_px as usize,
                info.height_px as usize,
                px,
            )?;
        }
    }
    let mut failed = None;
    for l in 0..h.levels.len() {
        map.for_each_record(l, square, |rec, desc| {
            if failed.is_none() && in_square(rec) {
                failed = writer.push_record(l, rec, desc).err();
            }
        });
    }
    if let Some(e) = failed {
        return Err(e);
    }
    let header = MapHeader {
        bounds,
        levels: h
            .levels
            .iter()
            .zip(&grids)
            .map(|(l, g)| LevelInfo {
                gsd_m: l.gsd_m,
                n_features: 0,
                grid: *g,
                cells_offset: 0,
                records_offset: 0,
                descriptors_offset: 0,
                image: None,
            })
            .collect(),
        ..h.clone()
    };
    writer.finish(header, out).map(Some)
}

/// The square `[min_x, min_y, max_x, max_y]` within the map's bounds, moved out to the coarsest
/// level's pixel grid through the map's top-left corner (where its level images start) and
/// clipped to the bounds again.
fn snapped_bounds(h: &MapHeader, square: [f64; 4]) -> Bounds {
    let b = &h.bounds;
    let (ox, oy) = h
        .levels
        .first()
        .and_then(|l| l.image)
        .map_or((b.min_x_m, b.max_y_m), |i| (i.origin_x_m, i.origin_y_m));
    let step = h.levels.last().map_or(1.0, |l| l.gsd_m);
    let down = |v: f64, o: f64| o + ((v - o) / step).floor() * step;
    let up = |v: f64, o: f64| o + ((v - o) / step).ceil() * step;
    Bounds {
        min_x_m: down(square[0].max(b.min_x_m), ox).max(b.min_x_m),
        min_y_m: down(square[1].max(b.min_y_m), oy).max(b.min_y_m),
        max_x_m: up(square[2].min(b.max_x_m), ox).min(b.max_x_m),
        max_y_m: up(square[3].min(b.max_y_m), oy).min(b.max_y_m),
    }
}

/// Every level's image over `bounds` (the file's pixels, 0 where it has none), with its
/// geometry; empty when the file has no level images (format 1). A window larger than the
/// file's own image (a header whose bounds and images disagree) is refused.
fn image_windows(
    map: &ReferenceMap,
    bounds: &Bounds,
) -> Result<Vec<(LevelImageInfo, Vec<u8>)>, MapError> {
    let h = map.header();
    let mut out = Vec::with_capacity(h.levels.len());
    for (l, level) in h.levels.iter().enumerate() {
        let Some((src, px)) = map.level_image(l) else {
            return Ok(Vec::new());
        };
        let gsd = level.gsd_m;
        let info = LevelImageInfo {
            offset: 0,
            width_px: ((bounds.max_x_m - bounds.min_x_m) / gsd).ceil().max(1.0) as u64,
            height_px: ((bounds.max_y_m - bounds.min_y_m) / gsd).ceil().max(1.0) as u64,
            origin_x_m: bounds.min_x_m,
            origin_y_m: bounds.max_y_m,
        };
        // The window's corner on the file's pixel grid (a whole number of pixels: the bounds
        // are snapped to the coarsest level's grid through the same corner).
        if info.width_px > src.width_px.saturating_add(2)
            || info.height_px > src.height_px.saturating_add(2)
        {
            return Err(MapError::Format {
                path: map.path().to_path_buf(),
                reason: format!(
                    "level {l}'s image ({} x {} px) does not cover the map's bounds",
                    src.width_px, src.height_px
                ),
            });
        }
        let x0 = ((bounds.min_x_m - src.origin_x_m) / gsd).round() as i64; // ok: finite
        let y0 = ((src.origin_y_m - bounds.max_y_m) / gsd).round() as i64;
        let (w, hh) = (info.width_px as usize, info.height_px as usize);
        let (sw, sh) = (src.width_px as i64, src.height_px as i64);
        let mut win = vec![0u8; w * hh];
        for y in 0..hh as i64 {
            let sy = y0 + y;
            if !(0..sh).contains(&sy) {
                continue;
            }
            for x in 0..w as i64 {
                let sx = x0 + x;
                if (0..sw).contains(&sx) {
                    win[y as usize * w + x as usize] = px[(sy * sw + sx) as usize];
                }
            }
        }
        out.push((info, win));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn squares_cover_features_on_every_side_of_a_grid_line() {
        let b = Bounds {
            min_x_m: 1000.0,
            min_y_m: 2000.0,
            max_x_m: 3000.0,
            max_y_m: 4000.0,
        };
        let sq = squares_of(&b, 1000.0).unwrap();
        // x = 3000 lies in column 3; y = 2000 in row 1 (its side (1000, 2000]).
        assert!(sq.contains(&[3, 1]));
        assert!(sq.contains(&[1, 3]));
        assert_eq!(sq.len(), 9);
        assert_eq!(sq[0], [1, 3], "north row first");
    }

    #[test]
    fn too_many_squares_are_refused() {
        let b = Bounds {
            min_x_m: 0.0,
            min_y_m: 0.0,
            max_x_m: 1.0e7,
            max_y_m: 1.0e7,
        };
        assert!(matches!(
            squares_of(&b, 200.0),
            Err(MapError::Param { name: "tile_m", .. })
        ));
    }
}
