//! A tiled map in flight (`map::paged::PagedMap`): the fix engine's reference answers from the
//! tiles in memory without waiting, counts and queues what it misses, loads in the background,
//! and keeps to its memory budget; what it lends is the single-file map's.

use std::path::{Path, PathBuf};
use std::time::Duration;

use visnav::fix::MapReference;
use visnav::fix::reference::{RefSelection, Reference};
use visnav::map::paged::PagedMap;
use visnav::map::tiled::build_tiled;
use visnav::map::{BuildSpec, HeightSource, build_map};

fn naip2009() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps/naip_nd_2009.tif")
}

/// NAIP 2009 as one file and as 12 squares of 2 km, the same levels and cores.
fn both(dir: &Path) -> (MapReference, PathBuf) {
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.tile_px = 256;
    spec.levels = Some(2);
    let one = dir.join("one.vnm");
    build_map(&spec, &one, &mut |_| {}).unwrap();
    let tiled = dir.join("tiled");
    build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    (MapReference::open(&one, None).unwrap(), tiled)
}

/// Features as comparable rows (position, height, scale, sign, descriptor), sorted.
fn rows(s: &RefSelection) -> Vec<(i64, i64, i64, i64, i8, Vec<i32>)> {
    let stride = s.kind.stride();
    let mut v: Vec<_> = s
        .features
        .iter()
        .enumerate()
        .map(|(i, f)| {
            (
                (f.x_m * 1e3).round() as i64,
                (f.y_m * 1e3).round() as i64,
                (f.z_amsl_m * 1e3).round() as i64,
                (f64::from(f.scale_m) * 1e3).round() as i64,
                f.laplacian,
                s.descriptors[i * stride..(i + 1) * stride]
                    .iter()
                    .map(|d| (d * 1e5).round() as i32)
                    .collect(),
            )
        })
        .collect();
    v.sort();
    v
}

/// Before its tiles are loaded a select answers at once with what is held (nothing), counts the
/// misses and queues them; once loaded, selects and level windows across tile seams are the
/// single file's.
#[test]
fn a_paged_map_lends_the_single_files_features_and_pixels_once_loaded() {
    let dir = tempfile::tempdir().unwrap();
    let (one, tiled) = both(dir.path());
    let paged = PagedMap::open(&tiled, 256, None).unwrap();
    assert_eq!(paged.index().tiles.len(), 12);
    assert_eq!(paged.crs(), one.crs());
    assert_eq!(paged.level_gsd_m(), one.level_gsd_m());
    assert_eq!(paged.feature_spec(), one.feature_spec());
    // A rectangle over four squares' corner (x 488 000, y 5 208 000).
    let rect = [487_300.0, 5_207_200.0, 488_900.0, 5_208_700.0];
    let first = paged.select(0, rect);
    assert!(first.features.is_empty());
    let s = paged.stats();
    assert!(s.misses >= 4 && s.loads == 0, "{s:?}");
    assert!(paged.wait_loaded(Duration::from_secs(30)));
    for level in 0..2 {
        let a = rows(&paged.select(level, rect));
        let b = rows(&one.select(level, rect));
        assert!(!b.is_empty());
        assert!(
            a == b,
            "level {level}: {} against {} features",
            a.len(),
            b.len()
        );
        // The level window: every pixel the single file has there, at the same place.
        let w = paged.level_window(level, rect).unwrap();
        let (w, whole) = (w.image(), one.level_image(level).unwrap());
        let mut compared = 0;
        for y in 0..w.height {
            for x in 0..w.width {
                let p = whole.to_px(
                    w.to_map([x as f64, y as f64])[0],
                    w.to_map([x as f64, y as f64])[1],
                );
                let (wx, wy) = (p[0].round() as usize, p[1].round() as usize);
                assert!((p[0] - wx as f64).abs() < 1e-6 && (p[1] - wy as f64).abs() < 1e-6);
                assert_eq!(
                    w.data[y * w.width + x],
                    whole.data[wy * whole.width + wx],
                    "level {level} ({x}, {y})"
                );
                compared += 1;
            }
        }
        assert!(compared > 10_000, "{compared}");
    }
    let s = paged.stats();
    assert_eq!((s.load_errors, s.evictions), (0, 0));
    assert!(s.resident_tiles >= 4 && s.queued == 0, "{s:?}");
}

/// The budget holds: tiles of the latest request are kept over older ones, the least recently
/// used go first, and a request larger than the budget loads what fits and counts the rest.
#[test]
fn a_paged_map_keeps_to_its_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let (_, tiled) = both(dir.path());
    let probe = PagedMap::open(&tiled, 1024, None).unwrap();
    let largest = probe
        .index()
        .tiles
        .iter()
        .map(|t| t.file_bytes)
        .max()
        .unwrap();
    drop(probe);
    // Room for two of the largest tiles (the budget is whole MB).
    let mb = (2 * largest).div_ceil(1 << 20);
    let paged = PagedMap::open(&tiled, mb, None).unwrap();
    let budget = paged.budget_bytes();
    let ix = paged.index().clone();
    let centre = |k: usize| {
        let b = &ix.tiles[k].bounds;
        let (x, y) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
        [x - 1.0, y - 1.0, x + 1.0, y + 1.0]
    };
    for k in 0..ix.tiles.len() {
        paged.request(&[centre(k)], 1);
        assert!(paged.wait_loaded(Duration::from_secs(30)));
        let s = paged.stats();
        assert!(s.resident_bytes <= budget, "{s:?} over {budget}");
    }
    let s = paged.stats();
    assert_eq!(s.loads, ix.tiles.len() as u64, "{s:?}");
    assert!(
        s.evictions > 0 && s.evictions + s.resident_tiles as u64 == s.loads,
        "{s:?}"
    );
    // The last tile asked for is held: a select there needs no load.
    let before = paged.stats().misses;
    let sel = paged.select(0, centre(ix.tiles.len() - 1));
    assert_eq!(paged.stats().misses, before);
    drop(sel);
    // A request over the whole map: what fits is loaded, the rest counted.
    let b = paged.bounds_m();
    paged.request(&[b], 1);
    assert!(paged.wait_loaded(Duration::from_secs(60)));
    let s = paged.stats();
    assert!(s.over_budget > 0 && s.resident_bytes <= budget, "{s:?}");

    // Prefetch: beyond the needed rectangles, tiles load only into room the budget has or that
    // tiles outside the request free; never counted over budget, never pushing out a needed one.
    let paged = PagedMap::open(&tiled, mb, None).unwrap();
    let all: Vec<[f64; 4]> = (0..ix.tiles.len()).map(centre).collect();
    paged.request(&all, 1);
    assert!(paged.wait_loaded(Duration::from_secs(30)));
    let s = paged.stats();
    assert!(
        s.loads >= 2 && s.over_budget == 0 && s.evictions == 0,
        "{s:?}"
    );
    assert!(s.resident_bytes <= budget, "{s:?}");
    let held_before = s.resident_tiles;
    // The same request again: nothing moves (its tiles protect each other).
    paged.request(&all, 1);
    assert!(paged.wait_loaded(Duration::from_secs(30)));
    assert_eq!(paged.stats().loads, s.loads);
    // A request elsewhere frees the others for it.
    let last = ix.tiles.len() - 1;
    paged.request(&[centre(last)], 1);
    assert!(paged.wait_loaded(Duration::from_secs(30)));
    let before = paged.stats().misses;
    let _ = paged.select(0, centre(last));
    assert_eq!(paged.stats().misses, before, "{:?}", paged.stats());
    assert!(held_before >= 2);
}

/// A damaged tile is refused by its checksum, counted and never retried; the others load.
#[test]
fn a_paged_map_refuses_a_damaged_tile_and_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let (_, tiled) = both(dir.path());
    let ix = visnav::map::tiled::TiledIndex::read(&tiled).unwrap();
    let victim = tiled.join(&ix.tiles[1].file);
    let mut bytes = std::fs::read(&victim).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x10;
    std::fs::write(&victim, bytes).unwrap();
    let paged = PagedMap::open(&tiled, 256, None).unwrap();
    paged.request(&[paged.bounds_m()], 1);
    assert!(paged.wait_loaded(Duration::from_secs(60)));
    let s = paged.stats();
    assert_eq!(
        (s.load_errors, s.loads),
        (1, ix.tiles.len() as u64 - 1),
        "{s:?}"
    );
    // Not queued again by a select over it.
    let _ = paged.select(0, paged.bounds_m());
    assert!(paged.wait_loaded(Duration::from_secs(5)));
    assert_eq!(paged.stats().load_errors, 1);
}

/// The daemon's paged fixer over a tiled NAIP map: a fix before any tile is in memory goes on at
/// once with what is held (its misses counted and queued, nothing waited for); once the tiles
/// asked for are loaded, the paged fixes are the single-file engine's, frame for frame. What
/// it asks for covers the prior's footprint first, then the ground ahead along the velocity.
#[test]
fn the_paged_fixer_asks_ahead_and_fixes_as_the_single_file_does() {
    use std::sync::Arc;
    use visnav::daemon::FrameFixer;
    use visnav::daemon::paging::{LOOKAHEAD_S, PREFETCH_S, PagedFixer};
    use visnav::fix::{FixEngine, FixParams};
    use visnav::sitl::fixeval::NaipEval;
    use visnav_core::rng::Rng;

    let dir = tempfile::tempdir().unwrap();
    let maps = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sitl/maps");
    let eval = NaipEval::new(&maps, FixParams::default()).unwrap();
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.levels = Some(2);
    let one_path = dir.path().join("one.vnm");
    build_map(&spec, &one_path, &mut |_| {}).unwrap();
    let tiled = dir.path().join("tiled");
    build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    let camera = *eval.engine().camera();
    let one = FixEngine::new(
        Arc::new(MapReference::open(&one_path, None).unwrap()),
        camera,
        FixParams::default(),
    )
    .unwrap();
    let map = Arc::new(PagedMap::open(&tiled, 64, None).unwrap());
    let paged = PagedFixer::new(
        FixEngine::new(map.clone(), camera, FixParams::default()).unwrap(),
        map.clone(),
    );
    let mut rng = Rng::new(7);
    let (b, margin) = eval.frame_area_m();
    let mut cold = true;
    let mut agreed = 0;
    for i in 0..8u64 {
        let x = b[0] + margin + (b[2] - b[0] - 2.0 * margin) * rng.uniform();
        let y = b[1] + margin + (b[3] - b[1] - 2.0 * margin) * rng.uniform();
        let case = eval.random_case(&mut rng, x, y);
        let img = eval.frame(&case, i, None).unwrap();
        let prior = eval.prior(&mut rng, &case, i).unwrap();
        // What the pager asks for: the prior's footprint first, holding the true nadir point.
        let rects = paged.wanted(&prior);
        let r = rects[0];
        assert!(
            r[0] < x && x < r[2] && r[1] < y && y < r[3],
            "{r:?} misses ({x}, {y})"
        );
        if cold {
            // Nothing in memory and nothing asked for: the engine's selects answer at once with
            // what is held, count what they miss and queue it.
            let bare = FixEngine::new(map.clone(), camera, FixParams::default()).unwrap();
            let _ = bare.fix(&img, &prior);
            let s = map.stats();
            assert!(s.misses > 0, "{s:?}");
            cold = false;
        }
        assert!(map.wait_loaded(Duration::from_secs(30)));
        // The same frame again with its tiles in memory: the single file's fix.
        let p = paged.fix(&img, &prior);
        let o = one.fix(&img, &prior);
        assert_eq!(
            p.accepted, o.accepted,
            "frame {i}: {:?} / {:?}",
            p.rejection, o.rejection
        );
        if o.accepted {
            // The same features in another order: the same fix up to float summation order.
            let d = (p.x_m - o.x_m)
                .abs()
                .max((p.y_m - o.y_m).abs())
                .max((p.z_m - o.z_m).abs());
            assert!(d < 1e-3 && p.inliers == o.inliers, "frame {i}: {d} m apart");
            agreed += 1;
        }
    }
    assert!(agreed >= 3, "{agreed} accepted fixes compared");
    // Two priors a second apart, 25 m/s east: the next asks for the ground 15 and 30 s ahead, and prefetches further.
    let fixer = PagedFixer::new(
        FixEngine::new(map.clone(), camera, FixParams::default()).unwrap(),
        map.clone(),
    );
    let case = eval.random_case(&mut rng, 487_000.0, 5_207_000.0);
    let mut prior = eval.prior(&mut rng, &case, 0).unwrap();
    prior.t_capture_us = 10_000_000;
    fixer.wanted(&prior);
    let crs = fixer.map().crs();
    let p0 = prior.position.unwrap();
    let (x0, y0) = crs.from_geodetic(p0.lat_deg, p0.lon_deg).unwrap();
    let (lat, lon) = crs.to_geodetic(x0 + 25.0, y0).unwrap();
    let mut next = prior;
    next.t_capture_us += 1_000_000;
    next.position.as_mut().unwrap().lat_deg = lat;
    next.position.as_mut().unwrap().lon_deg = lon;
    let rects = fixer.wanted(&next);
    assert_eq!(
        rects.len(),
        1 + LOOKAHEAD_S.len() + PREFETCH_S.len(),
        "{rects:?}"
    );
    for (r, s) in rects[1..].iter().zip(LOOKAHEAD_S.iter().chain(&PREFETCH_S)) {
        let cx = 0.5 * (r[0] + r[2]) - 0.5 * (rects[0][0] + rects[0][2]);
        let cy = 0.5 * (r[1] + r[3]) - 0.5 * (rects[0][1] + rects[0][3]);
        assert!(
            (cx - 25.0 * s).abs() < 0.5 && cy.abs() < 0.5,
            "{s} s ahead: ({cx}, {cy})"
        );
    }
    // Without a position (relocalisation): around the last position, wider with time lost.
    let mut lost = next;
    lost.position = None;
    lost.t_capture_us += 10_000_000;
    let r = fixer.wanted(&lost)[0];
    assert!(r[2] - r[0] > 2.0 * 600.0 && r[2] - r[0] < 1e5, "{r:?}");
}

/// `[map] file` may name a tiled map's folder, with `[map] memory_mb`: the configuration loads
/// and passes its data check, and the daemon's fixer pages it; a folder without an index and a
/// budget out of range are refused by key.
#[test]
fn a_configuration_flies_a_tiled_map_folder() {
    use visnav::daemon::config::Config;
    let dir = tempfile::tempdir().unwrap();
    let (_, tiled) = both(dir.path());
    let cfg = dir.path().join("c.toml");
    let write = |file: &Path, memory_mb: u64| {
        std::fs::write(
            &cfg,
            format!(
                "[link]\nconnection = \"udpin:127.0.0.1:14999\"\n[camera]\nwidth_px = 640\n\
                 height_px = 480\nhfov_deg = 60.0\n[map]\nfile = \"{}\"\nmemory_mb = {memory_mb}\n",
                file.display()
            ),
        )
        .unwrap();
    };
    write(&tiled, 64);
    let c = Config::load(&cfg).unwrap();
    c.check_data(&cfg).unwrap();
    let fixer = visnav::daemon::fixer_from_config(&c).unwrap();
    drop(fixer);
    write(&tiled, 1);
    let e = Config::load(&cfg).unwrap_err().to_string();
    assert!(e.contains("map.memory_mb"), "{e}");
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    write(&empty, 64);
    let e = Config::load(&cfg).unwrap_err().to_string();
    assert!(e.contains("map.file") && e.contains("index.json"), "{e}");
}

/// `visnav map convert`: a single file cut into squares answers, once its tiles are loaded, with
/// the file's own features (every one once, bit for bit) and pixels, at every level and across
/// seams; its index names the file; an occupied folder and an impossible side are refused.
#[test]
fn a_converted_map_file_lends_its_own_features_and_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.tile_px = 256;
    spec.levels = Some(3);
    let one_path = dir.path().join("one.vnm");
    build_map(&spec, &one_path, &mut |_| {}).unwrap();
    let one = MapReference::open(&one_path, None).unwrap();
    let tiled = dir.path().join("converted");
    let convert = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_visnav"))
            .args(["map", "convert"])
            .arg(&one_path)
            .args(["--tile-m", "1500", "--out"])
            .arg(&tiled)
            .output()
            .unwrap()
    };
    let o = convert();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let file = visnav::map::ReferenceMap::open(&one_path).unwrap();
    let ix = visnav::map::tiled::TiledIndex::read(&tiled).unwrap();
    assert_eq!(ix.total_features(), file.header().n_features());
    assert!(ix.tiles.len() >= 9, "{}", ix.tiles.len());
    assert!(ix.sources[0].ends_with("one.vnm"), "{:?}", ix.sources);
    assert!(ix.command.as_deref().unwrap().contains("map convert"));

    let paged =
        PagedMap::open_with(&tiled, 256, None, visnav::map::paged::LoadMode::Inline).unwrap();
    assert_eq!(paged.level_gsd_m(), one.level_gsd_m());
    assert_eq!(paged.bounds_m(), one.bounds_m());
    let b = one.bounds_m();
    let whole = [b[0] - 10.0, b[1] - 10.0, b[2] + 10.0, b[3] + 10.0];
    // Across the seams of squares x 487 500 / 489 000, y 5 206 500 / 5 208 000.
    let seams = [487_100.0, 5_206_100.0, 489_400.0, 5_208_400.0];
    for level in 0..3 {
        for rect in [whole, seams] {
            let (a, c) = (paged.select(level, rect), one.select(level, rect));
            assert_eq!(a.features.len(), c.features.len(), "level {level}");
            assert!(rows(&a) == rows(&c), "level {level} {rect:?}");
        }
        let w = paged.level_window(level, whole).unwrap();
        let (w, src) = (w.image(), one.level_image(level).unwrap());
        assert_eq!(
            (w.width, w.height),
            (src.width, src.height),
            "level {level}"
        );
        assert_eq!(
            (w.origin_x_m, w.origin_y_m),
            (src.origin_x_m, src.origin_y_m)
        );
        let diff: Vec<usize> = (0..w.data.len())
            .filter(|&i| w.data[i] != src.data[i])
            .collect();
        assert!(
            diff.is_empty(),
            "level {level}: {} pixels differ, first at ({}, {}) of {}x{}: {} vs {}",
            diff.len(),
            diff[0] % w.width,
            diff[0] / w.width,
            w.width,
            w.height,
            w.data[diff[0]],
            src.data[diff[0]]
        );
    }
    assert_eq!(paged.stats().load_errors, 0);

    // Descriptors as stored: the fullest tile's features, byte for byte against the file.
    let t = ix.tiles.iter().max_by_key(|t| t.features).unwrap();
    let tile = visnav::map::ReferenceMap::open(&tiled.join(&t.file)).unwrap();
    let mut n = 0;
    tile.for_each_record(
        0,
        [
            t.bounds.min_x_m,
            t.bounds.min_y_m,
            t.bounds.max_x_m,
            t.bounds.max_y_m,
        ],
        |rec, desc| {
            let x = f64::from_le_bytes(rec[0..8].try_into().unwrap());
            let y = f64::from_le_bytes(rec[8..16].try_into().unwrap());
            let mut found = false;
            file.for_each_record(0, [x, y, x, y], |r2, d2| found |= r2 == rec && d2 == desc);
            assert!(found, "feature at ({x}, {y}) is not the file's bytes");
            n += 1;
        },
    );
    assert!(n > 50, "{n}");

    let again = convert();
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(
        !again.status.success() && err.contains("already holds a tiled map"),
        "{err}"
    );
    let small =
        visnav::map::convert::convert_to_tiled(&one_path, 50.0, &dir.path().join("x"), None);
    assert!(small.unwrap_err().to_string().contains("tile_m"));
}

/// A DEM of relief under the NAIP tile (30 m cells, a slope and ridges, 580 +- 60 m), written as
/// a float GeoTIFF in the orthophoto's CRS.
fn relief_dem(dir: &Path) -> PathBuf {
    use visnav::geo::raster::{GeoTransform, Raster, RasterData};
    let crs = visnav::geo::geotiff::load_geotiff(&naip2009(), None)
        .unwrap()
        .crs();
    let (x0, y0, cell, n) = (485_000.0, 5_210_500.0, 30.0, 220usize);
    let data = (0..n)
        .flat_map(|r| (0..n).map(move |c| (c, r)))
        .map(|(c, r)| {
            let (x, y) = (c as f64 * cell, r as f64 * cell);
            (560.0 + 0.006 * x + 25.0 * (y / 700.0).sin() + 15.0 * (x / 450.0).cos()) as f32
        })
        .collect();
    let t = GeoTransform::new([x0, cell, 0.0, y0, 0.0, -cell]).unwrap();
    let raster = Raster::new(n, n, 1, RasterData::F32(data), t, crs, None).unwrap();
    let p = dir.join("relief.tif");
    visnav::geo::geotiff_write::write_geotiff(&raster, &p).unwrap();
    p
}

/// A tiled map built on a DEM carries the DEM's heights tile by tile: opened without the DEM, it
/// lends (once the tiles under a request are in memory) the DEM's own heights and ray hits
/// across seams, nothing where no tile is in memory, and features with the single file's
/// heights; a tile whose heights file is damaged is refused, and a build run again rebuilds the
/// square whose heights went missing. A converted file carries them the same way.
#[test]
fn a_tiled_map_on_a_dem_pages_its_heights_with_its_tiles() {
    let dir = tempfile::tempdir().unwrap();
    let dem_path = relief_dem(dir.path());
    let whole = visnav::geo::dem::load_dem(&dem_path, None).unwrap();
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::Dem(dem_path.clone()));
    spec.tile_px = 256;
    spec.levels = Some(2);
    let one_path = dir.path().join("one.vnm");
    build_map(&spec, &one_path, &mut |_| {}).unwrap();
    let one = MapReference::open(&one_path, None).unwrap();
    let tiled = dir.path().join("tiled");
    build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    let ix = visnav::map::tiled::TiledIndex::read(&tiled).unwrap();
    assert!(ix.tiles.iter().all(|t| t.heights.is_some()), "{ix:?}");

    let paged =
        PagedMap::open_with(&tiled, 256, None, visnav::map::paged::LoadMode::Inline).unwrap();
    // Nothing in memory: no height anywhere, the map's height range.
    assert_eq!(paged.height_amsl_m(488_000.0, 5_207_000.0), None);
    let (lo, hi) = paged.dem().height_range_m();
    assert!(lo >= 500.0 && hi <= 660.0 && hi > lo, "{lo} {hi}");
    // Four squares' corner (x 488 000, y 5 208 000).
    let rect = [487_300.0, 5_207_200.0, 488_900.0, 5_208_700.0];
    paged.request(&[rect], 1);
    let mut compared = 0;
    for i in 0..40 {
        for j in 0..40 {
            let (x, y) = (487_310.0 + 39.7 * i as f64, 5_207_210.0 + 37.1 * j as f64);
            assert_eq!(
                paged.height_amsl_m(x, y),
                whole.height_at(x, y),
                "({x}, {y})"
            );
            compared += 1;
        }
    }
    assert_eq!(compared, 1600);
    let dem = paged.dem();
    for (x, y) in [
        (487_500.0, 5_207_500.0),
        (488_010.0, 5_207_990.0),
        (488_700.0, 5_208_500.0),
    ] {
        let ray = ([x - 300.0, y + 200.0, 2_000.0], [0.2, -0.13, -1.0]);
        let a = dem.intersect_ray(ray.0, ray.1, 1e4).unwrap();
        let b = whole.intersect_ray(ray.0, ray.1, 1e4).unwrap();
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-6), "{a:?} {b:?}");
    }
    // Far from the request: no height (not a guess).
    assert_eq!(paged.height_amsl_m(490_500.0, 5_205_100.0), None);
    for level in 0..2 {
        assert!(rows(&paged.select(level, rect)) == rows(&one.select(level, rect)));
    }
    drop(dem);
    drop(paged);

    // A damaged heights file: its tile is refused, the others load.
    let victim = ix.tiles.iter().max_by_key(|t| t.features).unwrap();
    let h = victim.heights.as_ref().unwrap();
    let hp = tiled.join(&h.file);
    let mut bytes = std::fs::read(&hp).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x5a;
    std::fs::write(&hp, &bytes).unwrap();
    let paged =
        PagedMap::open_with(&tiled, 256, None, visnav::map::paged::LoadMode::Inline).unwrap();
    let b = victim.bounds;
    paged.request(&[[b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m]], 1);
    assert_eq!(paged.stats().load_errors, 1);
    drop(paged);
    // A valid GeoTIFF of another size under the index's own checksum (a hostile or mixed-up
    // file): refused as not the grid the index records, never joined.
    {
        use visnav::geo::raster::{GeoTransform, Raster, RasterData};
        let t = GeoTransform::new([1.0e20, 30.0, 0.0, -1.0e20, 0.0, -30.0]).unwrap();
        let crs = ix.crs;
        let r = Raster::new(3, 3, 1, RasterData::F32(vec![600.0; 9]), t, crs, None).unwrap();
        visnav::geo::geotiff_write::write_geotiff(&r, &hp).unwrap();
        let bytes = std::fs::read(&hp).unwrap();
        let mut forged = ix.clone();
        for t in forged.tiles.iter_mut().filter(|t| t.file == victim.file) {
            let h = t.heights.as_mut().unwrap();
            (h.file_bytes, h.crc32) = (bytes.len() as u64, crc32fast::hash(&bytes));
        }
        let index_path = tiled.join("index.json");
        let original = std::fs::read(&index_path).unwrap();
        std::fs::write(&index_path, serde_json::to_vec(&forged).unwrap()).unwrap();
        let paged =
            PagedMap::open_with(&tiled, 256, None, visnav::map::paged::LoadMode::Inline).unwrap();
        paged.request(&[[b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m]], 1);
        assert_eq!(paged.stats().load_errors, 1);
        let c = [0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m)];
        assert!(
            paged.height_amsl_m(c[0], c[1]).is_none(),
            "no height from a refused tile"
        );
        std::fs::write(&index_path, original).unwrap();
    }
    // Gone: a build run again rebuilds that square alone.
    std::fs::remove_file(&hp).unwrap();
    let again = build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    assert_eq!(
        (again.built, again.reused),
        (1, ix.tiles.len() + ix.empty.len() - 1)
    );
    assert!(visnav::map::tiled::heights_intact(h, &hp));

    // Converted from the single file: the same heights come with the tiles.
    let conv = dir.path().join("converted");
    let s = visnav::map::convert::convert_to_tiled(&one_path, 1500.0, &conv, None).unwrap();
    assert_eq!(s.heights_from.as_deref(), Some(dem_path.as_path()));
    let paged =
        PagedMap::open_with(&conv, 256, None, visnav::map::paged::LoadMode::Inline).unwrap();
    paged.request(&[rect], 1);
    for (x, y) in [
        (487_400.0, 5_207_300.0),
        (488_050.0, 5_208_020.0),
        (488_800.0, 5_208_600.0),
    ] {
        assert_eq!(
            paged.height_amsl_m(x, y),
            whole.height_at(x, y),
            "({x}, {y})"
        );
    }
}
