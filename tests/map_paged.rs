//! A tiled map in flight (`map::paged::PagedMap`): the fix engine's reference answers from the
//! tiles in memory without waiting, counts and queues what it misses, loads in the background,
//! and keeps to its memory budget; what it lends is the single-file map's.

use std::path::{Path, PathBuf};
use std::time::Duration;

use visnav::fix::reference::{RefSelection, Reference};
use visnav::fix::MapReference;
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
        assert!(a == b, "level {level}: {} against {} features", a.len(), b.len());
        // The level window: every pixel the single file has there, at the same place.
        let w = paged.level_window(level, rect).unwrap();
        let (w, whole) = (w.image(), one.level_image(level).unwrap());
        let mut compared = 0;
        for y in 0..w.height {
            for x in 0..w.width {
                let p = whole.to_px(w.to_map([x as f64, y as f64])[0], w.to_map([x as f64, y as f64])[1]);
                let (wx, wy) = (p[0].round() as usize, p[1].round() as usize);
                assert!((p[0] - wx as f64).abs() < 1e-6 && (p[1] - wy as f64).abs() < 1e-6);
                assert_eq!(w.data[y * w.width + x], whole.data[wy * whole.width + wx], "level {level} ({x}, {y})");
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
    let largest = probe.index().tiles.iter().map(|t| t.file_bytes).max().unwrap();
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
        paged.request(&[centre(k)]);
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
    paged.request(&[b]);
    assert!(paged.wait_loaded(Duration::from_secs(60)));
    let s = paged.stats();
    assert!(s.over_budget > 0 && s.resident_bytes <= budget, "{s:?}");
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
    paged.request(&[paged.bounds_m()]);
    assert!(paged.wait_loaded(Duration::from_secs(60)));
    let s = paged.stats();
    assert_eq!((s.load_errors, s.loads), (1, ix.tiles.len() as u64 - 1), "{s:?}");
    // Not queued again by a select over it.
    let _ = paged.select(0, paged.bounds_m());
    assert!(paged.wait_loaded(Duration::from_secs(5)));
    assert_eq!(paged.stats().load_errors, 1);
}
