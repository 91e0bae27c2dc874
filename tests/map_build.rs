//! End-to-end: `map::build_map` on real orthophotos, `ReferenceMap::open` / `select`, and the
//! `visnav map` CLI. Prints build/open/select timings and the descriptor-quantisation effect on
//! nearest neighbours (numbers for the report, no timed assertions).

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use visnav::geo::geotiff::load_geotiff;
use visnav::map::build::level_window;
use visnav::map::format::{dequantise, quantise};
use visnav::map::{BuildSpec, HeightSource, MapFeature, ReferenceMap, build_map};
use visnav::vision::{GrayImage, Surf};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn shared(rel: &str) -> Option<PathBuf> {
    let p = repo().join("../shared/data").join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("skipping: {} is absent", p.display());
        None
    }
}

fn naip2009() -> PathBuf {
    repo().join("sitl/maps/naip_nd_2009.tif")
}

/// All features of a map, every level, sorted by (level, x, y).
fn sorted_features(m: &ReferenceMap) -> Vec<MapFeature> {
    let mut v: Vec<MapFeature> = (0..m.header().levels.len())
        .flat_map(|l| m.all_features(l))
        .collect();
    v.sort_by(|a, b| {
        a.level
            .cmp(&b.level)
            .then(a.x_m.total_cmp(&b.x_m))
            .then(a.y_m.total_cmp(&b.y_m))
    });
    v
}

fn check_select_against_brute_force(m: &ReferenceMap, rect: [f64; 4]) -> usize {
    let mut total = 0;
    for level in 0..m.header().levels.len() {
        let sel = m.select(level, rect[0], rect[1], rect[2], rect[3]);
        let kind = m.header().surf.descriptor;
        assert_eq!(sel.descriptors.len(), sel.len() * kind.stride());
        let key = |f: &MapFeature| (f.x_m.to_bits(), f.y_m.to_bits(), f.response.to_bits());
        let mut got: Vec<_> = sel.features.iter().map(key).collect();
        let mut want: Vec<_> = m
            .all_features(level)
            .iter()
            .filter(|f| {
                f.x_m >= rect[0] && f.x_m <= rect[2] && f.y_m >= rect[1] && f.y_m <= rect[3]
            })
            .map(key)
            .collect();
        got.sort_unstable();
        want.sort_unstable();
        assert_eq!(got, want, "level {level}, rect {rect:?}");
        assert!(sel.features.iter().all(|f| usize::from(f.level) == level));
        for i in 0..sel.len() {
            let d = sel.descriptor(i);
            let n: f32 = d.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((n - 1.0).abs() < 1e-3, "descriptor norm {n}");
            assert!(
                sel.descriptors[i * kind.stride() + kind.len()..(i + 1) * kind.stride()]
                    .iter()
                    .all(|v| *v == 0.0)
            );
        }
        total += sel.len();
    }
    total
}

#[test]
fn naip_constant_height_map() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("naip.vnm");
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.max_features_per_tile = 1_000_000; // no cap: tiling independence must hold exactly
    let t0 = Instant::now();
    let summary = build_map(&spec, &out, &mut |_| {}).unwrap();
    let build_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let m = ReferenceMap::open(&out).unwrap();
    let open_s = t1.elapsed().as_secs_f64();
    let h = m.header();
    let r = load_geotiff(&naip2009(), None).unwrap();
    assert_eq!(h.crs, r.crs());
    assert_eq!(h.bounds, r.bounds());
    // 934 x 724 px: the short side halves to 362 (>= 256), then 181: 2 levels.
    assert_eq!(h.levels.len(), 2);
    assert!((h.levels[0].gsd_m - 5.0).abs() < 1e-3 && (h.levels[1].gsd_m - 10.0).abs() < 2e-3);
    assert!(
        h.levels.iter().all(|l| l.n_features > 100),
        "{:?}",
        h.levels
    );
    assert_eq!(h.n_features(), summary.header.n_features());
    // Each level's grey image is its level window, rounded into 1..=255 (0 = no data), on a
    // grid whose origin is the bounds' north-west corner.
    for (l, info) in h.levels.iter().enumerate() {
        let (img, data) = m.level_image(l).expect("format 2 maps carry level images");
        assert_eq!(
            (img.origin_x_m, img.origin_y_m),
            (h.bounds.min_x_m, h.bounds.max_y_m)
        );
        let (w, hh) = (r.width() >> l, r.height() >> l);
        assert!(img.width_px as usize >= w && img.height_px as usize >= hh);
        assert!((img.width_px as f64 - (r.width() as f64) / f64::from(1u32 << l)).abs() < 1.0);
        let (grey, valid) = level_window(&r, l, 0, 0, w, hh);
        let iw = img.width_px as usize;
        for y in 0..hh {
            for x in 0..w {
                let want = if valid[y * w + x] {
                    grey[y * w + x].round().clamp(1.0, 255.0) as u8
                } else {
                    0
                };
                assert_eq!(data[y * iw + x], want, "level {l} pixel ({x}, {y})");
            }
        }
        assert!(info.image.is_some());
    }
    let all = sorted_features(&m);
    assert!(all.iter().all(|f| f.z_amsl_m == 580.0
        && h.bounds.contains(f.x_m, f.y_m)
        && f.scale_m > 0.0
        && (f.laplacian == 1 || f.laplacian == -1)));
    eprintln!(
        "naip_nd_2009 (934x724 px): {} features ({:?}), {} bytes, build {:.2} s, open {:.2} ms",
        h.n_features(),
        h.levels.iter().map(|l| l.n_features).collect::<Vec<_>>(),
        summary.file_bytes,
        build_s,
        open_s * 1e3
    );

    // select == brute force, for a few rectangles (2 km x 2 km timed).
    let (cx, cy) = (
        0.5 * (h.bounds.min_x_m + h.bounds.max_x_m),
        0.5 * (h.bounds.min_y_m + h.bounds.max_y_m),
    );
    let t2 = Instant::now();
    let sel = m.select(0, cx - 1000.0, cy - 1000.0, cx + 1000.0, cy + 1000.0);
    let sel_s = t2.elapsed().as_secs_f64();
    eprintln!(
        "select 2 km x 2 km at level 0: {} features in {:.3} ms",
        sel.len(),
        sel_s * 1e3
    );
    assert!(!sel.is_empty());
    for rect in [
        [cx - 1000.0, cy - 1000.0, cx + 1000.0, cy + 1000.0],
        [cx - 333.3, cy - 77.7, cx + 12.5, cy + 1500.0],
        [
            h.bounds.min_x_m - 10.0,
            h.bounds.min_y_m - 10.0,
            h.bounds.max_x_m + 10.0,
            h.bounds.max_y_m + 10.0,
        ],
    ] {
        assert!(check_select_against_brute_force(&m, rect) > 0);
    }

    // Tiling independence: small tiles (many tile borders through the image) give the same set.
    let out2 = dir.path().join("naip_small_tiles.vnm");
    let mut spec2 = spec.clone();
    spec2.tile_px = 200;
    let s2 = build_map(&spec2, &out2, &mut |_| {}).unwrap();
    assert!(s2.tiles > summary.tiles);
    let m2 = ReferenceMap::open(&out2).unwrap();
    assert!(m2.header().levels[0].grid.n_cells() > 1);
    let all2 = sorted_features(&m2);
    assert_eq!(all.len(), all2.len(), "feature count depends on the tiling");
    for (a, b) in all.iter().zip(&all2) {
        assert_eq!(a.level, b.level);
        assert!(
            (a.x_m - b.x_m).abs() < 1e-3 && (a.y_m - b.y_m).abs() < 1e-3,
            "{a:?} vs {b:?}"
        );
        assert!((a.response - b.response).abs() <= 1e-3 * a.response.abs());
        assert_eq!(a.laplacian, b.laplacian);
        assert!((a.scale_m - b.scale_m).abs() < 1e-3);
    }
    // Descriptors agree too (compare a selection from both).
    let r1 = [cx - 500.0, cy - 500.0, cx + 500.0, cy + 500.0];
    for level in 0..2 {
        let s_a = m.select(level, r1[0], r1[1], r1[2], r1[3]);
        let s_b = m2.select(level, r1[0], r1[1], r1[2], r1[3]);
        assert_eq!(s_a.len(), s_b.len());
        for i in 0..s_a.len() {
            let j = (0..s_b.len())
                .find(|&j| {
                    (s_b.features[j].x_m - s_a.features[i].x_m).abs() < 1e-3
                        && (s_b.features[j].y_m - s_a.features[i].y_m).abs() < 1e-3
                        && s_b.features[j].response == s_a.features[i].response
                })
                .expect("same feature in both maps");
            let d: f32 = s_a
                .descriptor(i)
                .iter()
                .zip(s_b.descriptor(j))
                .map(|(x, y)| (x - y).abs())
                .sum();
            assert!(d < 1e-3, "descriptor differs by {d}");
        }
    }

    // A binding per-tile cap limits each tile.
    let out3 = dir.path().join("naip_capped.vnm");
    let mut spec3 = spec.clone();
    spec3.max_features_per_tile = 50;
    spec3.tile_px = 256;
    let s3 = build_map(&spec3, &out3, &mut |_| {}).unwrap();
    assert!(s3.header.n_features() <= 50 * s3.tiles);
    assert!(s3.header.n_features() < h.n_features());
}

/// Fraction of query nearest neighbours (2014 NAIP features against 2009 map features) that are
/// unchanged when the map descriptors are i8-quantised.
#[test]
fn descriptor_quantisation_keeps_nearest_neighbours() {
    let Some(q_path) = shared("naip_nd/m_4709963_se_14_1_20140720.tif") else {
        return;
    };
    let grey = |p: &Path| {
        let r = load_geotiff(p, None).unwrap();
        let (g, _) = level_window(&r, 0, 0, 0, r.width(), r.height());
        GrayImage::new(r.width(), r.height(), g).unwrap()
    };
    let surf = Surf::new(BuildSpec::new(vec![], HeightSource::ConstantAmsl(0.0)).surf).unwrap();
    let map = surf.detect_and_describe(&grey(&naip2009()));
    let qry = surf.detect_and_describe(&grey(&q_path));
    let kind = map.kind();
    let len = kind.len();
    let mut deq = vec![0f32; map.len() * len];
    let mut q = vec![0i8; len];
    for i in 0..map.len() {
        let s = quantise(map.descriptor(i), &mut q);
        dequantise(&q, s, &mut deq[i * len..(i + 1) * len]);
    }
    // Nearest and second-nearest squared distances of `d` in a flat table of rows of `stride`.
    let nn = |d: &[f32], db: &[f32], stride: usize| -> (usize, f32, f32) {
        let (mut b1, mut b2, mut bi) = (f32::INFINITY, f32::INFINITY, 0);
        for j in 0..map.len() {
            let row = &db[j * stride..j * stride + len];
            let e: f32 = d.iter().zip(row).map(|(a, b)| (a - b) * (a - b)).sum();
            if e < b1 {
                b2 = b1;
                b1 = e;
                bi = j;
            } else if e < b2 {
                b2 = e;
            }
        }
        (bi, b1, b2)
    };
    let n_q = qry.len().min(1500);
    let (mut same, mut same_ratio, mut n_ratio) = (0usize, 0usize, 0usize);
    for i in 0..n_q {
        let d = qry.descriptor(i);
        let (a, a1, a2) = nn(d, map.descriptors_padded(), kind.stride());
        let (b, _, _) = nn(d, &deq, len);
        same += usize::from(a == b);
        // Among the matches a ratio test (0.8) would keep.
        if a1.sqrt() < 0.8 * a2.sqrt() {
            n_ratio += 1;
            same_ratio += usize::from(a == b);
        }
    }
    let f_all = same as f64 / n_q as f64;
    let f_ratio = same_ratio as f64 / n_ratio.max(1) as f64;
    eprintln!(
        "i8 descriptors: nearest neighbour unchanged for {:.2} % of {n_q} queries, {:.2} % of the {n_ratio} passing the 0.8 ratio test ({} map features)",
        100.0 * f_all,
        100.0 * f_ratio,
        map.len()
    );
    assert!(f_all > 0.9, "{f_all}");
    assert!(f_ratio > 0.97, "{f_ratio}");
}

#[test]
fn ngi_ortho_with_dem_heights() {
    let (Some(ortho), Some(dem_path)) = (
        shared("ngi_3324c/ngi_ortho_5m_tile1.tif"),
        shared("ngi_3324c/dem.tif"),
    ) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ngi.vnm");
    let spec = BuildSpec::new(vec![ortho.clone()], HeightSource::Dem(dem_path.clone()));
    let t0 = Instant::now();
    let s = build_map(&spec, &out, &mut |_| {}).unwrap();
    eprintln!(
        "ngi tile1 + DEM: {} features, {} bytes, {:.2} s, dropped {} at nodata, {} without height",
        s.header.n_features(),
        s.file_bytes,
        t0.elapsed().as_secs_f64(),
        s.dropped_nodata,
        s.dropped_no_height
    );
    let m = ReferenceMap::open(&out).unwrap();
    let dem = visnav::geo::dem::load_dem(&dem_path, None).unwrap();
    let (lo, hi) = dem.height_range_m();
    assert!(matches!(
        m.header().crs,
        visnav::geo::Crs::TransverseMercator { .. }
    ));
    let all = sorted_features(&m);
    assert!(all.len() > 100);
    for f in &all {
        let z = dem
            .height_at(f.x_m, f.y_m)
            .expect("features have DEM heights");
        assert!((f.z_amsl_m - z).abs() < 1e-9, "{f:?} vs {z}");
        assert!(f.z_amsl_m >= lo - 1e-6 && f.z_amsl_m <= hi + 1e-6);
    }
    let b = m.header().bounds;
    let (cx, cy) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
    assert!(
        check_select_against_brute_force(&m, [cx - 1000.0, cy - 1000.0, cx + 1000.0, cy + 1000.0])
            > 0
    );

    // Two orthos of one CRS share the index.
    let Some(ortho2) = shared("ngi_3324c/ngi_ortho_5m_tile2.tif") else {
        return;
    };
    let out2 = dir.path().join("ngi2.vnm");
    let spec2 = BuildSpec::new(vec![ortho, ortho2], HeightSource::Dem(dem_path));
    let s2 = build_map(&spec2, &out2, &mut |_| {}).unwrap();
    let m2 = ReferenceMap::open(&out2).unwrap();
    assert_eq!(m2.header().orthos.len(), 2);
    assert!(s2.header.n_features() > s.header.n_features());
    let b2 = m2.header().bounds;
    assert!(
        b2.min_x_m <= b.min_x_m
            && b2.max_x_m >= b.max_x_m
            && b2.min_y_m <= b.min_y_m
            && b2.max_y_m >= b.max_y_m
    );
    assert!(
        check_select_against_brute_force(&m2, [b2.min_x_m, b2.min_y_m, b2.max_x_m, b2.max_y_m]) > 0
    );
}

#[test]
fn mismatched_inputs_are_refused_with_the_file_name() {
    let Some(dem) = shared("ngi_3324c/dem.tif") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // NAIP (UTM 14N) with the NGI DEM (transverse Mercator 25E): refused, naming the DEM.
    let spec = BuildSpec::new(vec![naip2009()], HeightSource::Dem(dem.clone()));
    let e = build_map(&spec, &dir.path().join("x.vnm"), &mut |_| {}).unwrap_err();
    assert!(
        e.to_string().contains("dem.tif") && e.to_string().contains("CRS"),
        "{e}"
    );
    // Orthos in two CRSs: refused, naming the second.
    let Some(ngi) = shared("ngi_3324c/ngi_ortho_5m_tile1.tif") else {
        return;
    };
    let spec = BuildSpec::new(vec![naip2009(), ngi], HeightSource::ConstantAmsl(0.0));
    let e = build_map(&spec, &dir.path().join("y.vnm"), &mut |_| {}).unwrap_err();
    assert!(e.to_string().contains("ngi_ortho_5m_tile1.tif"), "{e}");
    assert!(!dir.path().join("y.vnm").exists());
}

#[test]
fn cli_build_and_info() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cli.vnm");
    let bin = env!("CARGO_BIN_EXE_visnav");
    let o = Command::new(bin)
        .args(["map", "build", "--ortho"])
        .arg(naip2009())
        .args(["--ground-height", "580", "--levels", "1", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("features in 1 level"));
    let o = Command::new(bin)
        .args(["map", "info"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("level 0") && text.contains("UTM zone 14N"),
        "{text}"
    );
    // User-facing text, not Rust debug formatting.
    assert!(
        !text.contains("Utm {") && !text.contains("Surf64"),
        "{text}"
    );
    let o = Command::new(bin)
        .args(["map", "info", "--json"])
        .arg(&out)
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["levels"].as_array().unwrap().len(), 1);
    // Neither or both height sources: a usage error.
    let o = Command::new(bin)
        .args(["map", "build", "--ortho"])
        .arg(naip2009())
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    // A corrupt file: error naming it.
    std::fs::write(dir.path().join("bad.vnm"), b"VNMAP\r\n\x1a garbage").unwrap();
    let o = Command::new(bin)
        .args(["map", "info"])
        .arg(dir.path().join("bad.vnm"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("bad.vnm"));
    for sub in ["build", "info"] {
        let o = Command::new(bin)
            .args(["map", sub, "--help"])
            .output()
            .unwrap();
        assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("Usage:"));
    }
}

/// The map file without what differs between two builds of the same input: the CRC (bytes
/// 56..60) and the digits of the header's build time.
fn without_build_time(path: &Path) -> Vec<u8> {
    let mut b = std::fs::read(path).unwrap();
    b[56..60].fill(0);
    let key = b"\"built_unix_s\":";
    let at = b
        .windows(key.len())
        .position(|w| w == key)
        .expect("header has built_unix_s")
        + key.len();
    for v in b[at..].iter_mut().take_while(|v| v.is_ascii_digit()) {
        *v = b'0';
    }
    b
}

/// Reading tile windows (bounded memory, the default for orthophotos over
/// `WHOLE_DECODE_MAX_BYTES`) builds the same map, byte for byte, as decoding the orthophoto
/// whole, for several tilings and level counts (windows straddling
/// strips/tiles, level windows averaged from several level-0 bands).
#[test]
fn windowed_build_is_byte_identical_to_the_whole_image_build() {
    let dir = tempfile::tempdir().unwrap();
    let mut cases: Vec<(String, BuildSpec)> = Vec::new();
    for (tile_px, levels, upsample) in [(1024, None, 1), (128, Some(3), 1), (128, Some(3), 2)] {
        let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
        spec.tile_px = tile_px;
        spec.levels = levels;
        // Upsampled: interpolated level-0 windows with the left tile's columns reused, over the
        // odd 723 px height.
        spec.upsample = upsample;
        cases.push((format!("naip2009_t{tile_px}_x{upsample}"), spec));
    }
    if let (Some(o), Some(d)) = (
        shared("autzen/autzen_ortho_0p3m_utm10n.tif"),
        shared("autzen/autzen_dsm_1m_utm10n.tif"),
    ) {
        // 1024 px tiles over 256 px deflate tiles: windows straddle chunks at every level.
        cases.push((
            "autzen_t1024".into(),
            BuildSpec::new(vec![o], HeightSource::Dem(d)),
        ));
    }
    for (name, spec) in cases {
        let spec = BuildSpec {
            whole_decode_max_bytes: 0,
            ..spec
        };
        let a = dir.path().join(format!("{name}_windowed.vnm"));
        let t0 = Instant::now();
        let sa = build_map(&spec, &a, &mut |_| {}).unwrap();
        let ta = t0.elapsed().as_secs_f64();
        let whole = BuildSpec {
            whole_decode_max_bytes: usize::MAX,
            ..spec.clone()
        };
        let b = dir.path().join(format!("{name}_whole.vnm"));
        let t1 = Instant::now();
        let sb = build_map(&whole, &b, &mut |_| {}).unwrap();
        let tb = t1.elapsed().as_secs_f64();
        assert!(sa.header.n_features() > 100, "{name}");
        assert_eq!(sa.header.n_features(), sb.header.n_features(), "{name}");
        assert_eq!(
            (sa.tiles, sa.dropped_nodata, sa.dropped_no_height),
            (sb.tiles, sb.dropped_nodata, sb.dropped_no_height),
            "{name}"
        );
        assert!(
            without_build_time(&a) == without_build_time(&b),
            "{name}: the windowed build differs from the whole-image build"
        );
        eprintln!(
            "{name}: {} features, {} tiles, identical files; windowed {ta:.2} s, whole {tb:.2} s",
            sa.header.n_features(),
            sa.tiles
        );
    }
}

/// A build of part of the orthophotos (`BuildSpec::area`) holds the whole build's features in
/// that part: four parts meeting at an inner point, built separately, hold the whole build's
/// features, each once, and their level images hold the whole build's pixels. An area off the
/// orthophotos is refused by name.
#[test]
fn parts_of_an_area_hold_the_whole_builds_features_each_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.tile_px = 256;
    spec.levels = Some(3);
    let whole_path = dir.path().join("whole.vnm");
    let whole = build_map(&spec, &whole_path, &mut |_| {}).unwrap();
    let b = whole.header.bounds;
    // An inner point off the tile and pixel grids: the parts' edges move out to the coarsest
    // level's grid, and their features split at those edges.
    let (mx, my) = (
        b.min_x_m + 0.43 * (b.max_x_m - b.min_x_m),
        b.min_y_m + 0.61 * (b.max_y_m - b.min_y_m),
    );
    let far = 1e5;
    let quads = [
        (b.min_x_m - far, mx, my, b.max_y_m + far),
        (mx, b.max_x_m + far, my, b.max_y_m + far),
        (b.min_x_m - far, mx, b.min_y_m - far, my),
        (mx, b.max_x_m + far, b.min_y_m - far, my),
    ];
    let whole_map = ReferenceMap::open(&whole_path).unwrap();
    let mut parts: Vec<MapFeature> = Vec::new();
    let mut edges = Vec::new();
    for (i, (x0, x1, y0, y1)) in quads.into_iter().enumerate() {
        let part_spec = BuildSpec {
            area: Some(visnav::geo::raster::Bounds {
                min_x_m: x0,
                max_x_m: x1,
                min_y_m: y0,
                max_y_m: y1,
            }),
            ..spec.clone()
        };
        let p = dir.path().join(format!("part{i}.vnm"));
        let s = build_map(&part_spec, &p, &mut |_| {}).unwrap();
        assert!(
            s.header.n_features() > 50,
            "part {i}: {}",
            s.header.n_features()
        );
        edges.push(s.header.bounds);
        let m = ReferenceMap::open(&p).unwrap();
        parts.extend(sorted_features(&m));
        // Every level image pixel of the part is the whole map's pixel at the same place.
        for level in 0..3 {
            let (pi, px) = m.level_image(level).unwrap();
            let (wi, wx) = whole_map.level_image(level).unwrap();
            let gsd = whole_map.header().levels[level].gsd_m;
            let dx = ((pi.origin_x_m - wi.origin_x_m) / gsd).round() as usize;
            let dy = ((wi.origin_y_m - pi.origin_y_m) / gsd).round() as usize;
            assert_eq!(
                pi.origin_x_m,
                wi.origin_x_m + dx as f64 * gsd,
                "part {i} level {level}"
            );
            for y in 0..pi.height_px as usize {
                let a = &px[y * pi.width_px as usize..][..pi.width_px as usize];
                let w = &wx[(y + dy) * wi.width_px as usize + dx..][..pi.width_px as usize];
                assert_eq!(a, w, "part {i} level {level} row {y}");
            }
        }
    }
    // The parts' edges lie on the coarsest level's grid (4 x 5 m from the ortho's corner).
    let step = 4.0 * whole_map.header().levels[0].gsd_m;
    for e in &edges {
        for (v, o) in [(e.min_x_m, b.min_x_m), (e.max_y_m, b.max_y_m)] {
            let k = (v - o) / step;
            assert!((k - k.round()).abs() < 1e-9, "edge {v} off the grid");
        }
    }
    let sort = |v: &mut Vec<MapFeature>| {
        v.sort_by(|a, b| {
            a.level
                .cmp(&b.level)
                .then(a.x_m.total_cmp(&b.x_m))
                .then(a.y_m.total_cmp(&b.y_m))
        })
    };
    sort(&mut parts);
    let all = sorted_features(&whole_map);
    assert_eq!(parts.len(), all.len());
    assert!(
        parts == all,
        "the parts' features differ from the whole build's"
    );

    let off = BuildSpec {
        area: Some(visnav::geo::raster::Bounds {
            min_x_m: b.max_x_m + 10.0,
            max_x_m: b.max_x_m + 20.0,
            min_y_m: b.min_y_m,
            max_y_m: b.max_y_m,
        }),
        ..spec
    };
    let e = build_map(&off, &dir.path().join("off.vnm"), &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("area") && e.contains("does not overlap"), "{e}");
}

/// `visnav map build --area` builds the part of the orthophoto inside the box, and refuses a box
/// that is not four numbers, is empty, or misses the orthophoto, naming the option.
#[test]
fn map_build_cli_builds_an_area_and_refuses_bad_boxes() {
    let dir = tempfile::tempdir().unwrap();
    let bin = env!("CARGO_BIN_EXE_visnav");
    let ortho = naip2009();
    let out = dir.path().join("area.vnm");
    let run = |area: &str| {
        Command::new(bin)
            .args(["map", "build", "--ground-height", "580", "--area", area])
            .arg("--ortho")
            .arg(&ortho)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    let o = run("487000,5206000,488500,5207500");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m = ReferenceMap::open(&out).unwrap();
    let b = m.header().bounds;
    assert!(b.min_x_m <= 487000.0 && b.max_x_m >= 488500.0 && b.max_x_m - b.min_x_m < 1600.0);
    assert!(sorted_features(&m).iter().all(|f| {
        (487000.0..488500.0).contains(&f.x_m) && f.y_m > 5206000.0 && f.y_m <= 5207500.0
    }));
    for (bad, says) in [
        ("1,2,3", "four numbers"),
        ("5,2,3,4", "MIN_X < MAX_X"),
        ("0,0,10,10", "does not overlap"),
    ] {
        let o = run(bad);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && e.contains("area") && e.contains(says),
            "{bad}: {e}"
        );
    }
}

/// A tiled map of NAIP 2009 (2 km squares on the CRS grid, each built from its own square: its
/// cores cut there): its tiles hold the whole build's features, each once, when the per-core cap
/// does not bind; a second build keeps every square; a damaged tile or a lost result is found
/// and that square alone built again; other settings build everything again.
#[test]
fn a_tiled_map_holds_the_whole_build_and_resumes() {
    use visnav::map::tiled::{INDEX_FILE, build_tiled};
    let dir = tempfile::tempdir().unwrap();
    let mut spec = BuildSpec::new(vec![naip2009()], HeightSource::ConstantAmsl(580.0));
    spec.tile_px = 256;
    // The whole build's level count (a tiled map's automatic count follows its squares).
    spec.levels = Some(2);
    let whole_path = dir.path().join("whole.vnm");
    let whole = build_map(&spec, &whole_path, &mut |_| {}).unwrap();
    let tiled = dir.path().join("tiled");
    let mut seen = 0;
    let first = build_tiled(&spec, 2000.0, &tiled, None, &mut |p| {
        seen = p.done;
        assert!(p.done <= p.total);
    })
    .unwrap();
    let ix = &first.index;
    // 4.67 x 3.62 km from x 485 900, y 5 205 627: columns 242-245, rows 2602-2604.
    assert_eq!(ix.tiles.len() + ix.empty.len(), 12, "{ix:?}");
    assert_eq!((first.built, first.reused, seen), (12, 0, 12));
    assert_eq!(ix.levels, whole.header.levels.len());
    let mut parts: Vec<MapFeature> = Vec::new();
    for t in &ix.tiles {
        let m = ReferenceMap::open(&tiled.join(&t.file)).unwrap();
        assert_eq!(m.header().n_features(), t.features);
        assert_eq!(m.header().levels.len(), ix.levels);
        parts.extend(sorted_features(&m));
    }
    parts.sort_by(|a, b| {
        a.level
            .cmp(&b.level)
            .then(a.x_m.total_cmp(&b.x_m))
            .then(a.y_m.total_cmp(&b.y_m))
    });
    let all = sorted_features(&ReferenceMap::open(&whole_path).unwrap());
    assert_eq!(parts.len(), all.len());
    assert!(
        parts == all,
        "the tiles' features differ from the whole build's"
    );
    let text = std::fs::read_to_string(tiled.join(INDEX_FILE)).unwrap();
    assert!(
        text.contains("\"tile_m\": 2000.0") && text.contains("crc32"),
        "{text}"
    );

    // Again: every square kept.
    let again = build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    assert_eq!((again.built, again.reused), (0, 12));
    assert_eq!(again.index, first.index);
    // A damaged tile is built again, the others kept.
    let victim = tiled.join(&first.index.tiles[0].file);
    let mut bytes = std::fs::read(&victim).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x40;
    std::fs::write(&victim, bytes).unwrap();
    let repaired = build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    assert_eq!((repaired.built, repaired.reused), (1, 11));
    // The same tiles.
    let same =
        |t: &visnav::map::tiled::TileEntry| (t.col, t.row, t.bounds, t.features, t.file_bytes);
    let a: Vec<_> = repaired.index.tiles.iter().map(same).collect();
    let b: Vec<_> = first.index.tiles.iter().map(same).collect();
    assert_eq!(a, b);
    // Tiles record no build time: the same settings write the same bytes.
    assert_eq!(repaired.index, first.index);
    // A square whose result is lost (a build killed between its tile and its result) is built
    // again, the others kept.
    let t = &first.index.tiles[3];
    std::fs::remove_file(tiled.join(t.file.replace(".vnm", ".json"))).unwrap();
    let resumed = build_tiled(&spec, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    assert_eq!((resumed.built, resumed.reused), (1, 11));
    assert_eq!(resumed.index, first.index);
    // Without a stated level count the squares set it: 2 km at 5 m is 400 px, one level.
    let auto = BuildSpec {
        levels: None,
        ..spec.clone()
    };
    let plan = visnav::map::tiled::TilePlan::new(&auto, 2000.0, None).unwrap();
    assert_eq!(plan.levels, 1);
    assert_eq!(plan.squares.len(), 12);
    // Other settings: all built again.
    let other = BuildSpec {
        max_features_per_tile: 500,
        ..spec.clone()
    };
    let rebuilt = build_tiled(&other, 2000.0, &tiled, None, &mut |_| {}).unwrap();
    assert_eq!((rebuilt.built, rebuilt.reused), (12, 0));
    // A side outside the range is refused by name.
    let e = build_tiled(&spec, 10.0, &dir.path().join("t2"), None, &mut |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("tile_m"), "{e}");
}

/// `visnav map build --tile-m` writes a tiled map's folder and a second run keeps every square.
#[test]
fn map_build_cli_builds_a_tiled_map_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tiled");
    let run = || {
        let o = Command::new(env!("CARGO_BIN_EXE_visnav"))
            .args(["map", "build", "--ground-height", "580", "--tile-m", "2000"])
            .arg("--ortho")
            .arg(naip2009())
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).to_string()
    };
    let first = run();
    assert!(
        first.contains("12 tiles of 2000 m") && first.contains("12 squares built"),
        "{first}"
    );
    let second = run();
    assert!(second.contains("0 squares built, 12 kept"), "{second}");
    assert!(out.join("index.json").is_file() && out.join("tiles/x243_y2603.vnm").is_file());
}

/// `visnav map plan`, `map build-tile` for every square and `map gather` write the same index
/// and tiles, byte for byte, as `map build --tile-m` on one machine; the jobs refuse what is not
/// theirs by name; `map info` reads the tiled map.
#[test]
fn planned_squares_built_one_by_one_match_the_one_machine_build() {
    let dir = tempfile::tempdir().unwrap();
    let (planned, whole) = (dir.path().join("planned"), dir.path().join("one"));
    fn visnav<S: AsRef<OsStr>>(args: impl IntoIterator<Item = S>) -> std::process::Output {
        Command::new(env!("CARGO_BIN_EXE_visnav"))
            .args(args)
            .output()
            .unwrap()
    }
    let build_args = |cmd: &str, out: &Path| -> Vec<std::ffi::OsString> {
        let mut v: Vec<std::ffi::OsString> = ["map", cmd, "--ground-height", "580", "--tile-m"]
            .iter()
            .map(Into::into)
            .collect();
        v.extend(["2000".into(), "--ortho".into(), naip2009().into()]);
        v.extend(["--out".into(), out.into()]);
        v
    };
    let ok = |o: std::process::Output| {
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).to_string()
    };
    let said = ok(visnav(build_args("plan", &planned)));
    assert!(said.contains("12 squares of 2000 m"), "{said}");
    let plan = planned.join("plan.json");
    // Gathering before the squares are built names the first missing one.
    let o = visnav([OsStr::new("map"), OsStr::new("gather"), planned.as_os_str()]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("square 0 of 12"), "{e}");
    let o = visnav([
        OsStr::new("map"),
        OsStr::new("build-tile"),
        plan.as_os_str(),
        OsStr::new("12"),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("0 to 11"), "{e}");
    // The squares in reverse order, as machines finishing at random would.
    for k in (0..12).rev() {
        let k = k.to_string();
        let said = ok(visnav([
            OsStr::new("map"),
            OsStr::new("build-tile"),
            plan.as_os_str(),
            OsStr::new(&k),
        ]));
        assert!(said.contains("built"), "{said}");
    }
    ok(visnav([
        OsStr::new("map"),
        OsStr::new("gather"),
        plan.as_os_str(),
    ]));
    ok(visnav(build_args("build", &whole)));
    let index = |d: &Path| std::fs::read(d.join("index.json")).unwrap();
    assert!(index(&planned) == index(&whole), "the indexes differ");
    let ix = visnav::map::tiled::TiledIndex::read(&whole).unwrap();
    assert!(
        ix.command.as_deref().is_some_and(|c| c
            .starts_with("visnav map build --ground-height 580")
            && !c.contains("--out")),
        "{:?}",
        ix.command
    );
    for t in &ix.tiles {
        let a = std::fs::read(planned.join(&t.file)).unwrap();
        assert!(
            a == std::fs::read(whole.join(&t.file)).unwrap(),
            "{}",
            t.file
        );
    }
    // A plan whose settings were edited is refused.
    let text = std::fs::read_to_string(&plan).unwrap();
    std::fs::write(
        &plan,
        text.replace(
            "\"max_features_per_tile\": 4000",
            "\"max_features_per_tile\": 9",
        ),
    )
    .unwrap();
    let o = visnav([
        OsStr::new("map"),
        OsStr::new("build-tile"),
        plan.as_os_str(),
        OsStr::new("0"),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("digest"), "{e}");
    // `map info` of the folder: the area, tiles, bytes per km², resolution, sources, command.
    let info = ok(visnav([
        OsStr::new("map"),
        OsStr::new("info"),
        whole.as_os_str(),
    ]));
    for says in [
        "tiled map",
        "12 tiles of 2000 m",
        "kB per km²",
        "level 0 5 m per pixel",
        "naip_nd_2009.tif",
        "build command: visnav map build",
    ] {
        assert!(info.contains(says), "{says}: {info}");
    }
}

/// `scripts/map_build_dask.py` builds a plan's squares on a Dask LocalCluster of two workers;
/// the index is byte-identical to the one-machine build's. Needs the venv with Dask
/// (`scripts/interop/setup_venv.sh dask`); skips when it cannot be made, except under CI.
#[test]
fn the_dask_driver_builds_the_same_map_on_a_local_cluster() {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true" || v == "1");
    let venv = Command::new("bash")
        .arg(repo().join("scripts/interop/setup_venv.sh"))
        .arg("dask")
        .output()
        .unwrap();
    if !venv.status.success() {
        assert!(
            !ci,
            "CI: the Dask venv could not be set up: {}",
            String::from_utf8_lossy(&venv.stderr)
        );
        eprintln!("SKIP: the Dask venv could not be set up ({})", venv.status);
        return;
    }
    let python = repo().join(String::from_utf8_lossy(&venv.stdout).trim());
    let dir = tempfile::tempdir().unwrap();
    let (planned, whole) = (dir.path().join("dask"), dir.path().join("one"));
    let map = |cmd: &str, out: &Path| {
        let o = Command::new(env!("CARGO_BIN_EXE_visnav"))
            .args([
                "map",
                cmd,
                "--ground-height",
                "580",
                "--tile-m",
                "1000",
                "--ortho",
            ])
            .arg(naip2009())
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    map("plan", &planned);
    let o = Command::new(&python)
        .arg(repo().join("scripts/map_build_dask.py"))
        .arg(planned.join("plan.json"))
        .args(["--workers", "2", "--visnav", env!("CARGO_BIN_EXE_visnav")])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{said}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        said.contains("on 2 workers") && said.contains("squares per minute per core"),
        "{said}"
    );
    eprintln!("{said}");
    map("build", &whole);
    let index = |d: &Path| std::fs::read(d.join("index.json")).unwrap();
    assert!(
        index(&planned) == index(&whole),
        "the Dask build's index differs from one machine's"
    );
}
