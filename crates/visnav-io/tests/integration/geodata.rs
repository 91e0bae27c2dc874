//! Every bundled and shared GeoTIFF loads with the CRS, geotransform, nodata, sample type and
//! pixel values that GDAL reports; the real DEMs give sane heights and ray intersections.
//!
//! Reference values come from GDAL 3.10.3 through rasterio 1.4.4 (pip wheel, read in a throwaway
//! venv outside the repository): `transform`, `bounds`, `crs`, `nodata`, `dtypes`, pixel values
//! `read()[:, row, col]` at fixed and seeded-random positions, and per-band means of
//! `read(b, masked=True)` (nodata excluded). The test does not depend on Python.
//! Files under ../shared/data are skipped with a printed reason when that folder is absent; the
//! copies in sitl/maps are always checked.
#![allow(clippy::unwrap_used, clippy::expect_used)] // a test: a failed expect is a failed test

use std::io::Cursor;
use std::path::{Path, PathBuf};

use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::{Raster, SampleType};
use visnav_io::geo::geotiff::{GeoTiffError, load_geotiff, read_geotiff};

/// `+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0 +datum=WGS84` (NGI 3324C, user-defined).
const TM_LO25: Crs = Crs::TransverseMercator {
    lat0_deg: 0.0,
    lon0_deg: 25.0,
    k0: 1.0,
    false_easting_m: 0.0,
    false_northing_m: 0.0,
};

enum Root {
    Repo,
    Shared,
}

struct Ref {
    root: Root,
    rel: &'static str,
    width: usize,
    height: usize,
    bands: usize,
    dtype: SampleType,
    crs: Crs,
    /// GDAL geotransform order [x0, px_w, rot, y0, rot, px_h] (pixel corner convention).
    transform: [f64; 6],
    /// [left, bottom, right, top].
    bounds: [f64; 4],
    nodata: Option<f64>,
    /// (col, row, values of all bands).
    samples: &'static [(usize, usize, &'static [f64])],
    /// Per-band mean over non-nodata samples.
    band_means: &'static [f64],
}

fn repo_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn shared_dir() -> Option<PathBuf> {
    let d = repo_dir().join("../shared/data");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!(
            "SKIP: {} is absent; shared-data checks skipped",
            d.display()
        );
        None
    }
}

fn path_of(r: &Ref) -> Option<PathBuf> {
    match r.root {
        Root::Repo => Some(repo_dir().join(r.rel)),
        Root::Shared => shared_dir().map(|d| d.join(r.rel)),
    }
}

// Generated from GDAL 3.10.3 / rasterio 1.4.4 output (see the file doc).
const REFS: &[Ref] = &[
    Ref {
        root: Root::Shared,
        rel: "naip_nd/m_4709963_se_14_1_20090818.tif",
        width: 934,
        height: 724,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209247.0, 0.0, -5.0],
        bounds: [485900.0, 5205627.0, 490570.0, 5209247.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[148.0, 147.0, 147.0, 170.0]),
            (933, 723, &[161.0, 160.0, 154.0, 185.0]),
            (311, 362, &[154.0, 146.0, 118.0, 183.0]),
            (453, 180, &[104.0, 139.0, 113.0, 220.0]),
            (233, 233, &[141.0, 139.0, 115.0, 181.0]),
            (672, 282, &[100.0, 130.0, 95.0, 204.0]),
            (592, 346, &[104.0, 134.0, 115.0, 222.0]),
            (871, 73, &[102.0, 119.0, 101.0, 155.0]),
        ],
        band_means: &[
            118.1287414080708,
            131.32745749878737,
            113.82301069480758,
            168.5356927372319,
        ],
    },
    Ref {
        root: Root::Shared,
        rel: "naip_nd/m_4709963_se_14_1_20100629.tif",
        width: 934,
        height: 723,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209245.0, 0.0, -5.0],
        bounds: [485900.0, 5205630.0, 490570.0, 5209245.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[90.0, 113.0, 94.0, 153.0]),
            (933, 722, &[75.0, 102.0, 81.0, 168.0]),
            (311, 361, &[177.0, 175.0, 156.0, 156.0]),
            (453, 180, &[160.0, 159.0, 146.0, 141.0]),
            (233, 233, &[169.0, 171.0, 155.0, 145.0]),
            (672, 281, &[47.0, 55.0, 60.0, 73.0]),
            (592, 345, &[93.0, 117.0, 100.0, 155.0]),
            (871, 72, &[122.0, 154.0, 101.0, 154.0]),
        ],
        band_means: &[
            103.59995972053157,
            116.78412722388572,
            104.06732298506402,
            132.68407568985995,
        ],
    },
    Ref {
        root: Root::Shared,
        rel: "naip_nd/m_4709963_se_14_1_20120731.tif",
        width: 934,
        height: 723,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209245.0, 0.0, -5.0],
        bounds: [485900.0, 5205630.0, 490570.0, 5209245.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[167.0, 163.0, 139.0, 162.0]),
            (933, 722, &[122.0, 124.0, 90.0, 166.0]),
            (311, 361, &[73.0, 104.0, 91.0, 219.0]),
            (453, 180, &[70.0, 94.0, 79.0, 210.0]),
            (233, 233, &[73.0, 105.0, 84.0, 210.0]),
            (672, 281, &[56.0, 57.0, 56.0, 35.0]),
            (592, 345, &[67.0, 87.0, 77.0, 205.0]),
            (871, 72, &[62.0, 68.0, 62.0, 57.0]),
        ],
        band_means: &[
            101.47043309313739,
            115.27689320905932,
            90.13016784099088,
            158.95760141688953,
        ],
    },
    Ref {
        root: Root::Shared,
        rel: "naip_nd/m_4709963_se_14_1_20140720.tif",
        width: 934,
        height: 723,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209245.0, 0.0, -5.0],
        bounds: [485900.0, 5205630.0, 490570.0, 5209245.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[93.0, 115.0, 74.0, 128.0]),
            (933, 722, &[97.0, 129.0, 78.0, 141.0]),
            (311, 361, &[56.0, 88.0, 66.0, 175.0]),
            (453, 180, &[113.0, 135.0, 93.0, 134.0]),
            (233, 233, &[113.0, 130.0, 94.0, 110.0]),
            (672, 281, &[49.0, 64.0, 58.0, 3.0]),
            (592, 345, &[61.0, 100.0, 70.0, 159.0]),
            (871, 72, &[55.0, 67.0, 60.0, 3.0]),
        ],
        band_means: &[
            91.68843979256074,
            112.33328150313498,
            81.13881459893793,
            99.16627530876131,
        ],
    },
    Ref {
        root: Root::Shared,
        rel: "ngi_3324c/sentinel2_b432_byte.tif",
        width: 797,
        height: 1361,
        bands: 3,
        dtype: SampleType::U8,
        crs: TM_LO25,
        transform: [-60370.0, 10.0, 0.0, -3722700.0, 0.0, -10.0],
        bounds: [-60370.0, -3736310.0, -52400.0, -3722700.0],
        nodata: None,
        samples: &[
            (0, 0, &[16.0, 35.0, 51.0]),
            (796, 1360, &[30.0, 42.0, 56.0]),
            (265, 680, &[19.0, 43.0, 53.0]),
            (353, 1196, &[29.0, 45.0, 55.0]),
            (453, 517, &[33.0, 53.0, 61.0]),
            (723, 1130, &[30.0, 45.0, 58.0]),
            (202, 408, &[47.0, 64.0, 67.0]),
            (469, 721, &[20.0, 39.0, 52.0]),
        ],
        band_means: &[35.90384220031584, 48.869955942425534, 59.6217962841921],
    },
    Ref {
        root: Root::Shared,
        rel: "ngi_3324c/ngi_ortho_5m_tile1.tif",
        width: 805,
        height: 1421,
        bands: 3,
        dtype: SampleType::U8,
        crs: TM_LO25,
        transform: [-57129.44916219164, 5.0, 0.0, -3723906.806172144, 0.0, -5.0],
        bounds: [
            -57129.44916219164,
            -3731011.806172144,
            -53104.44916219164,
            -3723906.806172144,
        ],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[0.0, 0.0, 0.0]),
            (804, 1420, &[0.0, 0.0, 0.0]),
            (268, 710, &[224.0, 216.0, 193.0]),
            (128, 1247, &[199.0, 202.0, 186.0]),
            (460, 1220, &[105.0, 116.0, 128.0]),
            (303, 601, &[108.0, 116.0, 112.0]),
            (259, 402, &[87.0, 88.0, 93.0]),
            (552, 928, &[165.0, 165.0, 151.0]),
        ],
        band_means: &[128.28895222072543, 131.28254210420855, 127.41760292194974],
    },
    Ref {
        root: Root::Shared,
        rel: "ngi_3324c/ngi_ortho_5m_tile2.tif",
        width: 806,
        height: 1421,
        bands: 3,
        dtype: SampleType::U8,
        crs: TM_LO25,
        transform: [-59703.57298348243, 5.0, 0.0, -3723837.8048744886, 0.0, -5.0],
        bounds: [
            -59703.57298348243,
            -3730942.8048744886,
            -55673.57298348243,
            -3723837.8048744886,
        ],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[0.0, 0.0, 0.0]),
            (805, 1420, &[0.0, 0.0, 0.0]),
            (268, 710, &[96.0, 106.0, 109.0]),
            (129, 1247, &[207.0, 207.0, 193.0]),
            (461, 1220, &[192.0, 189.0, 176.0]),
            (303, 601, &[140.0, 146.0, 128.0]),
            (260, 402, &[210.0, 197.0, 165.0]),
            (553, 928, &[154.0, 156.0, 147.0]),
        ],
        band_means: &[130.52842997708396, 134.21491452251942, 127.84687472805348],
    },
    Ref {
        root: Root::Shared,
        rel: "ngi_3324c/dem.tif",
        width: 327,
        height: 508,
        bands: 1,
        dtype: SampleType::F32,
        crs: TM_LO25,
        transform: [-60454.0, 24.0, 0.0, -3723500.0, 0.0, -24.0],
        bounds: [-60454.0, -3735692.0, -52606.0, -3723500.0],
        nodata: Some(f64::NAN),
        samples: &[
            (0, 0, &[241.06443786621094]),
            (326, 507, &[739.9219970703125]),
            (109, 254, &[418.7683410644531]),
            (276, 376, &[528.9498291015625]),
            (52, 54, &[411.9197082519531]),
            (182, 232, &[380.2402648925781]),
            (120, 386, &[267.9787902832031]),
            (70, 18, &[488.8811950683594]),
        ],
        band_means: &[410.9741329388861],
    },
    Ref {
        root: Root::Shared,
        rel: "autzen/autzen_ortho_0p3m_utm10n.tif",
        width: 3434,
        height: 4553,
        bands: 3,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 10,
            north: true,
        },
        transform: [493961.78110887384, 0.3, 0.0, 4878793.635709699, 0.0, -0.3],
        bounds: [
            493961.78110887384,
            4877427.735709699,
            494991.98110887385,
            4878793.635709699,
        ],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[0.0, 0.0, 0.0]),
            (3433, 4552, &[0.0, 0.0, 0.0]),
            (1144, 2276, &[87.0, 85.0, 72.0]),
            (1160, 469, &[154.0, 141.0, 133.0]),
            (1574, 3757, &[60.0, 76.0, 66.0]),
            (3210, 4261, &[187.0, 168.0, 137.0]),
            (3251, 1117, &[62.0, 79.0, 89.0]),
            (332, 104, &[148.0, 133.0, 126.0]),
        ],
        band_means: &[124.87292944965816, 128.4594656383527, 113.3335169543479],
    },
    Ref {
        root: Root::Shared,
        rel: "autzen/autzen_dsm_1m_utm10n.tif",
        width: 1031,
        height: 1366,
        bands: 1,
        dtype: SampleType::F32,
        crs: Crs::Utm {
            zone: 10,
            north: true,
        },
        transform: [493961.78110887384, 1.0, 0.0, 4878793.644988446, 0.0, -1.0],
        bounds: [
            493961.78110887384,
            4877427.644988446,
            494992.78110887384,
            4878793.644988446,
        ],
        nodata: Some(-9999.0),
        samples: &[
            (0, 0, &[-9999.0]),
            (1030, 1365, &[-9999.0]),
            (343, 683, &[125.60083770751953]),
            (931, 749, &[128.69244384765625]),
            (69, 673, &[133.09303283691406]),
            (693, 782, &[128.94674682617188]),
            (487, 107, &[129.0438690185547]),
            (698, 483, &[130.7491912841797]),
        ],
        band_means: &[132.5495611911436],
    },
    Ref {
        root: Root::Repo,
        rel: "sitl/maps/naip_nd_2009.tif",
        width: 934,
        height: 724,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209247.0, 0.0, -5.0],
        bounds: [485900.0, 5205627.0, 490570.0, 5209247.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[148.0, 147.0, 147.0, 170.0]),
            (933, 723, &[161.0, 160.0, 154.0, 185.0]),
            (311, 362, &[154.0, 146.0, 118.0, 183.0]),
            (459, 624, &[99.0, 121.0, 98.0, 206.0]),
            (218, 401, &[106.0, 138.0, 115.0, 219.0]),
            (63, 283, &[118.0, 136.0, 112.0, 31.0]),
            (665, 259, &[75.0, 90.0, 74.0, 118.0]),
            (759, 551, &[150.0, 139.0, 122.0, 157.0]),
        ],
        band_means: &[
            118.1287414080708,
            131.32745749878737,
            113.82301069480758,
            168.5356927372319,
        ],
    },
    Ref {
        root: Root::Repo,
        rel: "sitl/maps/naip_nd_2014.tif",
        width: 934,
        height: 723,
        bands: 4,
        dtype: SampleType::U8,
        crs: Crs::Utm {
            zone: 14,
            north: true,
        },
        transform: [485900.0, 5.0, 0.0, 5209245.0, 0.0, -5.0],
        bounds: [485900.0, 5205630.0, 490570.0, 5209245.0],
        nodata: Some(0.0),
        samples: &[
            (0, 0, &[93.0, 115.0, 74.0, 128.0]),
            (933, 722, &[97.0, 129.0, 78.0, 141.0]),
            (311, 361, &[56.0, 88.0, 66.0, 175.0]),
            (459, 623, &[60.0, 83.0, 68.0, 133.0]),
            (218, 400, &[110.0, 130.0, 91.0, 135.0]),
            (63, 283, &[82.0, 107.0, 78.0, 14.0]),
            (665, 259, &[50.0, 63.0, 59.0, 4.0]),
            (759, 551, &[61.0, 91.0, 69.0, 150.0]),
        ],
        band_means: &[
            91.68843979256074,
            112.33328150313498,
            81.13881459893793,
            99.16627530876131,
        ],
    },
];

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() <= tol
}

fn check(r: &Ref, raster: &Raster) {
    let name = r.rel;
    assert_eq!(
        (raster.width(), raster.height(), raster.bands()),
        (r.width, r.height, r.bands),
        "{name}: dimensions"
    );
    assert_eq!(raster.source_type(), r.dtype, "{name}: sample type");
    assert_eq!(raster.crs(), r.crs, "{name}: CRS");
    let gt = raster.transform().coeffs();
    for k in 0..6 {
        assert!(
            close(gt[k], r.transform[k], 1e-9 * (1.0 + r.transform[k].abs())),
            "{name}: transform {gt:?} vs GDAL {:?}",
            r.transform
        );
    }
    let b = raster.bounds();
    let got = [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m];
    for k in 0..4 {
        assert!(
            close(got[k], r.bounds[k], 1e-6),
            "{name}: bounds {got:?} vs GDAL {:?}",
            r.bounds
        );
    }
    match (raster.nodata(), r.nodata) {
        (None, None) => {}
        // GDAL reports nodata NaN; we store NaN nodata as None (NaN is always missing).
        (None, Some(n)) if n.is_nan() => {}
        (Some(a), Some(n)) => assert_eq!(a, n, "{name}: nodata"),
        (a, n) => panic!("{name}: nodata {a:?} vs GDAL {n:?}"),
    }
    for &(col, row, vals) in r.samples {
        for (band, &v) in vals.iter().enumerate() {
            let got = raster.sample(col, row, band).unwrap();
            assert!(
                close(got, v, 0.0),
                "{name}: pixel ({col},{row}) band {band}: {got} vs GDAL {v}"
            );
        }
    }
    for (band, &mean) in r.band_means.iter().enumerate() {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for row in 0..raster.height() {
            for col in 0..raster.width() {
                if let Some(v) = raster.value(col, row, band) {
                    sum += v;
                    n += 1;
                }
            }
        }
        let m = sum / n as f64;
        assert!(
            (m - mean).abs() <= 1e-9 * mean.abs().max(1.0),
            "{name}: band {band} mean {m} vs GDAL {mean}"
        );
    }
}

#[test]
fn every_geotiff_matches_gdal() {
    let mut checked = 0;
    for r in REFS {
        let Some(path) = path_of(r) else { continue };
        let raster =
            load_geotiff(&path, None).unwrap_or_else(|e| panic!("{}: failed to load: {e}", r.rel));
        check(r, &raster);
        eprintln!(
            "{}: {}x{}x{} {:?} {:?} ok",
            r.rel,
            raster.width(),
            raster.height(),
            raster.bands(),
            raster.source_type(),
            raster.crs()
        );
        checked += 1;
    }
    assert!(
        checked >= 2,
        "at least the bundled sitl/maps files must be checked"
    );
}

#[test]
fn readme_dimensions() {
    // sitl/maps/README.md and naip_nd/README.md: 934 x 724 px, 4 bands, 5 m/px. GDAL reports
    // 934 x 723 for 2010/2012/2014, so the README's "724" is the 2009 file only.
    let naip09 = load_geotiff(&repo_dir().join("sitl/maps/naip_nd_2009.tif"), None).unwrap();
    assert_eq!(
        (naip09.width(), naip09.height(), naip09.bands()),
        (934, 724, 4)
    );
    assert_eq!(naip09.transform().pixel_size(), (5.0, 5.0));
    let Some(shared) = shared_dir() else { return };
    // autzen/README.md: ortho 3434 x 4553 px at 0.3 m; DSM 1 m; bounds x 493962-494992,
    // y 4877428-4878794.
    let ortho = load_geotiff(&shared.join("autzen/autzen_ortho_0p3m_utm10n.tif"), None).unwrap();
    assert_eq!(
        (ortho.width(), ortho.height(), ortho.bands()),
        (3434, 4553, 3)
    );
    let dsm = load_geotiff(&shared.join("autzen/autzen_dsm_1m_utm10n.tif"), None).unwrap();
    for b in [ortho.bounds(), dsm.bounds()] {
        assert!((b.min_x_m - 493962.0).abs() < 1.0 && (b.max_x_m - 494992.0).abs() < 1.0);
        assert!((b.min_y_m - 4877428.0).abs() < 1.0 && (b.max_y_m - 4878794.0).abs() < 1.0);
    }
    assert_eq!(dsm.transform().pixel_size(), (1.0, 1.0));
    // ngi_3324c/README.md: 5 m orthos, 10 m Sentinel-2, 24 m DEM.
    for (f, px) in [
        ("ngi_3324c/ngi_ortho_5m_tile1.tif", 5.0),
        ("ngi_3324c/ngi_ortho_5m_tile2.tif", 5.0),
        ("ngi_3324c/sentinel2_b432_byte.tif", 10.0),
        ("ngi_3324c/dem.tif", 24.0),
    ] {
        let r = load_geotiff(&shared.join(f), None).unwrap();
        assert_eq!(r.transform().pixel_size(), (px, px), "{f}");
        assert_eq!(r.crs(), TM_LO25, "{f}");
    }
}

#[test]
fn crs_override_for_the_real_files() {
    // Understood keys + a matching override: fine; + a contradicting one: refused.
    let p = repo_dir().join("sitl/maps/naip_nd_2014.tif");
    let utm14 = Crs::Utm {
        zone: 14,
        north: true,
    };
    assert_eq!(load_geotiff(&p, Some(utm14)).unwrap().crs(), utm14);
    assert!(matches!(
        load_geotiff(&p, Some(TM_LO25)),
        Err(GeoTiffError::CrsConflict { .. })
    ));
}

#[test]
fn truncated_real_file_is_an_error() {
    let src = repo_dir().join("sitl/maps/naip_nd_2009.tif");
    let bytes = std::fs::read(&src).unwrap();
    let dir = tempfile::tempdir().unwrap();
    for frac in [0.001, 0.01, 0.1, 0.5, 0.9, 0.999] {
        let cut = (bytes.len() as f64 * frac) as usize;
        let p = dir.path().join(format!("naip_cut_{cut}.tif"));
        std::fs::write(&p, &bytes[..cut]).unwrap();
        let e = load_geotiff(&p, None).expect_err("a truncated file must not load");
        assert!(
            e.to_string().contains(&format!("naip_cut_{cut}.tif")),
            "{e}"
        );
    }
    // Non-TIFF: a PNG from the repository's bench data is not available here, so use text.
    let p = dir.path().join("readme.tif");
    std::fs::copy(repo_dir().join("sitl/maps/README.md"), &p).unwrap();
    assert!(matches!(
        load_geotiff(&p, None),
        Err(GeoTiffError::Decode { .. })
    ));
}

/// Brute-force reference for ray casting: march in 0.25 m steps and return the first sample
/// below the surface (or `None` when a hole/edge is met first).
fn brute_first_crossing(dem: &Dem, o: [f64; 3], d: [f64; 3], max_t: f64) -> Option<f64> {
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let d = [d[0] / n, d[1] / n, d[2] / n];
    let mut t = 0.0;
    while t <= max_t {
        let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
        let h = dem.height_at(p[0], p[1])?;
        if p[2] <= h {
            return Some(t);
        }
        t += 0.25;
    }
    None
}

#[test]
fn ngi_dem_heights_and_rays() {
    let Some(shared) = shared_dir() else { return };
    let dem = visnav_io::geo::dem::load_dem(&shared.join("ngi_3324c/dem.tif"), None).unwrap();
    assert_eq!(dem.crs(), Some(TM_LO25));
    // GDAL: band 1 min 148.55587768554688, max 781.2567749023438 (README: about 150-780 m).
    let (lo, hi) = dem.height_range_m();
    assert_eq!((lo, hi), (148.55587768554688, 781.2567749023438));
    // Pixel centre (col 109, row 254) holds 418.7683410644531 (GDAL): bilinear there is exact.
    let (x, y) = (-60454.0 + 109.5 * 24.0, -3723500.0 - 254.5 * 24.0);
    let h = dem.height_at(x, y).unwrap();
    assert!((h - 418.7683410644531).abs() < 1e-9, "{h}");

    // Principal rays of the two real frames (omega-phi-kappa, R = Rx(w) Ry(p) Rz(k), camera looks
    // along -z_cam): hit the ground about 4.8 km below, close to the nadir point.
    let truth = std::fs::read_to_string(shared.join("ngi_3324c/frames_truth.csv")).unwrap();
    for line in truth.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let v: Vec<f64> = f[1..7].iter().map(|s| s.trim().parse().unwrap()).collect();
        let (o, w, p, k) = (
            [v[0], v[1], v[2]],
            v[3].to_radians(),
            v[4].to_radians(),
            v[5].to_radians(),
        );
        let rx = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::x_axis(), w);
        let ry = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::y_axis(), p);
        let rz = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), k);
        let d = (rx * ry * rz) * nalgebra::Vector3::new(0.0, 0.0, -1.0);
        let d = [d.x, d.y, d.z];
        let hit = dem
            .intersect_ray(o, d, f64::INFINITY)
            .expect("principal ray hits the DEM");
        let ground = dem.height_at(hit[0], hit[1]).unwrap();
        assert!((hit[2] - ground).abs() < 1e-3, "{hit:?} vs ground {ground}");
        let horiz = (hit[0] - o[0]).hypot(hit[1] - o[1]);
        assert!(horiz < 100.0, "near-nadir ray landed {horiz} m away");
        eprintln!(
            "{}: principal ray hits {hit:?} ({horiz:.1} m from nadir)",
            f[0]
        );
    }

    // Oblique rays over the mountains against a 0.25 m brute-force march: the exact traversal
    // must find the same first crossing (the brute force can only be late, by < 0.25 m).
    let mut hits = 0;
    for i in 0..200 {
        let a = i as f64 * 0.731;
        let o = [
            -56500.0 + 2500.0 * (a * 1.3).sin(),
            -3729600.0 + 4000.0 * (a * 0.7).cos(),
            900.0 + 300.0 * (a * 2.1).sin().abs(),
        ];
        let dip = (5.0 + 40.0 * (a * 1.7).sin().abs()).to_radians();
        let d = [dip.cos() * a.cos(), dip.cos() * a.sin(), -dip.sin()];
        let exact = dem.intersect_ray(o, d, 20_000.0);
        let brute = brute_first_crossing(&dem, o, d, 20_000.0);
        match (exact, brute) {
            (Some(p), Some(tb)) => {
                let t =
                    ((p[0] - o[0]).powi(2) + (p[1] - o[1]).powi(2) + (p[2] - o[2]).powi(2)).sqrt();
                assert!(
                    t <= tb + 1e-6 && t > tb - 0.25 - 1e-6,
                    "ray {i}: exact {t} vs brute {tb}"
                );
                hits += 1;
            }
            (None, None) => {}
            // The brute force stops at the outer half-pixel margin like the exact one; a
            // disagreement can only be a grazing contact thinner than 0.25 m of range.
            (e, b) => panic!("ray {i}: exact {e:?} vs brute {b:?}"),
        }
    }
    eprintln!("NGI DEM: {hits}/200 oblique rays hit, all equal to the brute-force march");
    assert!(hits > 150);
}

#[test]
fn autzen_dsm_nodata_and_range() {
    let Some(shared) = shared_dir() else { return };
    let path = shared.join("autzen/autzen_dsm_1m_utm10n.tif");
    let raster = load_geotiff(&path, None).unwrap();
    assert_eq!(raster.nodata(), Some(-9999.0));
    // Corner pixels are nodata (-9999 per GDAL), so bilinear next to them is None.
    assert_eq!(raster.sample(0, 0, 0), Some(-9999.0));
    let (x0, y0) = raster.pixel_centre_to_map(0, 0);
    assert_eq!(raster.bilinear(x0, y0, 0), None);
    let dem = Dem::from_raster(&raster).unwrap();
    // GDAL (masked): min 123.85013580322266, max 181.239501953125; README: about 124-185 m.
    assert_eq!(dem.height_range_m(), (123.85013580322266, 181.239501953125));
    // A vertical ray at the centre hits the surface; one into the nodata corner does not.
    let b = raster.bounds();
    let (cx, cy) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
    let hit = dem
        .intersect_ray([cx, cy, 400.0], [0.0, 0.0, -1.0], 1000.0)
        .unwrap();
    assert!((hit[2] - dem.height_at(cx, cy).unwrap()).abs() < 1e-5);
    assert_eq!(
        dem.intersect_ray([x0, y0, 400.0], [0.0, 0.0, -1.0], 1000.0),
        None
    );
}

#[test]
fn naip_flat_dem() {
    // NAIP has no DEM: a constant 580 m ground behind the same interface.
    let map = load_geotiff(&repo_dir().join("sitl/maps/naip_nd_2009.tif"), None).unwrap();
    let dem = Dem::flat(580.0).unwrap();
    let b = map.bounds();
    let (cx, cy) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
    let hit = dem
        .intersect_ray([cx, cy, 880.0], [0.0, 1.0, -1.0], 1000.0)
        .unwrap();
    assert!((hit[0] - cx).abs() < 1e-9 && (hit[1] - (cy + 300.0)).abs() < 1e-9 && hit[2] == 580.0);
    let mut px = [0.0; 4];
    assert!(map.bilinear_all_bands(hit[0], hit[1], &mut px));
    // 8-bit imagery stays u8 and can be handed out without copying.
    assert_eq!(map.data().as_u8().map(<[u8]>::len), Some(934 * 724 * 4));
}

/// Timing printout (not an assertion): `cargo test --test integration geodata:: -- --ignored --nocapture`.
/// Numbers depend on the profile (dev = opt-level 1) and on the machine's load.
#[test]
#[ignore]
fn bench_load_and_raycast() {
    use std::time::Instant;
    let Some(shared) = shared_dir() else { return };
    let t = Instant::now();
    let ortho = load_geotiff(&shared.join("autzen/autzen_ortho_0p3m_utm10n.tif"), None).unwrap();
    eprintln!(
        "load autzen ortho {}x{}x{}: {:.3} s",
        ortho.width(),
        ortho.height(),
        ortho.bands(),
        t.elapsed().as_secs_f64()
    );
    for (f, alt_m) in [
        ("ngi_3324c/dem.tif", 1500.0),
        ("autzen/autzen_dsm_1m_utm10n.tif", 400.0),
    ] {
        let dem = visnav_io::geo::dem::load_dem(&shared.join(f), None).unwrap();
        let (lo, hi) = dem.height_range_m();
        let Dem::Grid(g) = &dem else { unreachable!() };
        let (c, r) = (g.width() as f64 / 2.0, g.height() as f64 / 2.0);
        let (cx, cy) = g.transform().pixel_to_map(c, r);
        let n = 100_000;
        let t = Instant::now();
        let mut hits = 0;
        for i in 0..n {
            let a = i as f64 * 0.618_033_988 * std::f64::consts::TAU;
            let dip = (30.0 + 60.0 * ((i % 97) as f64 / 97.0)).to_radians();
            let d = [dip.cos() * a.cos(), dip.cos() * a.sin(), -dip.sin()];
            if dem
                .intersect_ray([cx, cy, hi + alt_m], d, f64::INFINITY)
                .is_some()
            {
                hits += 1;
            }
        }
        let dt = t.elapsed().as_secs_f64();
        eprintln!(
            "{f}: heights {lo:.1}-{hi:.1} m, {n} rays from {alt_m} m above max, dip 30-90 deg: \
             {hits} hits, {:.2} us/ray",
            dt / n as f64 * 1e6
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Small GeoTIFFs written by GDAL 3.10.3 (rasterio 1.4.4), 20 x 12 px, embedded as base64, covering
// layouts, sample types, compressions and CRS encodings that the real data set does not. Pixel
// (col, row) of band b holds off + scale * ((b+1) 7 col + 3 row + (col row mod 5)) in the file's
// type; the expected values below are GDAL's own read-back.

fn b64(s: &str) -> Vec<u8> {
    let val = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("bad base64 {c}"),
        }
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= val(c) << (18 - 6 * i);
        }
        let n = chunk.len() * 6 / 8;
        for i in 0..n {
            out.push((acc >> (16 - 8 * i)) as u8);
        }
    }
    out
}

fn load_fx(name: &str, data: &str, crs_override: Option<Crs>) -> Result<Raster, GeoTiffError> {
    read_geotiff(Cursor::new(b64(data)), Path::new(name), crs_override)
}

/// GDAL's read-back at (col, row) = (0,0), (19,11), (13,7), (5,5), (3,2).
fn check_fx(name: &str, r: &Raster, expect: [&[f64]; 5], tol: f64) {
    let pos = [(0, 0), (19, 11), (13, 7), (5, 5), (3, 2)];
    for ((col, row), vals) in pos.into_iter().zip(expect) {
        assert_eq!(vals.len(), r.bands(), "{name}");
        for (b, &v) in vals.iter().enumerate() {
            let got = r.sample(col, row, b).unwrap();
            assert!(
                (got.is_nan() && v.is_nan()) || (got - v).abs() <= tol,
                "{name}: ({col},{row}) band {b}: {got} vs GDAL {v}"
            );
        }
    }
}

#[test]
fn gdal_written_variants() {
    let gt = [500000.0, 2.0, 0.0, 7000000.0, 0.0, -3.0];

    // uint16, 3 bands planar, 16x16 tiles, LZW + horizontal predictor, EPSG:32735, nodata 65535.
    let r = load_fx("u16_planar", U16_PLANAR_LZW_UTM35S, None).unwrap();
    assert_eq!(
        r.crs(),
        Crs::Utm {
            zone: 35,
            north: false
        }
    );
    assert_eq!(r.transform().coeffs(), gt);
    assert_eq!(
        (r.source_type(), r.nodata()),
        (SampleType::U16, Some(65535.0))
    );
    check_fx(
        "u16_planar",
        &r,
        [
            &[0.0, 0.0, 0.0],
            &[17000.0, 30300.0, 43600.0],
            &[11300.0, 20400.0, 29500.0],
            &[5000.0, 8500.0, 12000.0],
            &[2800.0, 4900.0, 7000.0],
        ],
        0.0,
    );

    // int16 strips of 5 rows, deflate + predictor, EPSG:3857, nodata -32768, PixelIsPoint: GDAL
    // reports the corner-convention transform (-1000, 10, 0, 2000, 0, -10).
    let r = load_fx("i16_point", I16_STRIP_DEFLATE_3857_POINT, None).unwrap();
    assert_eq!(r.crs(), Crs::WebMercator);
    assert_eq!(
        r.transform().coeffs(),
        [-1000.0, 10.0, 0.0, 2000.0, 0.0, -10.0]
    );
    assert_eq!(
        (r.source_type(), r.nodata()),
        (SampleType::I16, Some(-32768.0))
    );
    check_fx(
        "i16_point",
        &r,
        [&[100.0], &[-8400.0], &[-5550.0], &[-32768.0], &[-1300.0]],
        0.0,
    );
    assert_eq!(r.value(5, 5, 0), None);

    // float64 tiles, deflate + floating-point predictor, EPSG:4326, nodata NaN.
    let r = load_fx("f64_geo", F64_TILED_PRED3_4326, None).unwrap();
    assert_eq!(r.crs(), Crs::Geographic);
    assert_eq!(r.transform().coeffs(), [25.0, 0.01, 0.0, -33.0, 0.0, -0.01]);
    assert_eq!((r.source_type(), r.nodata()), (SampleType::F64, None));
    check_fx(
        "f64_geo",
        &r,
        [&[-5.5], &[-5.33], &[-5.387], &[-5.45], &[f64::NAN]],
        1e-6, // stored as f32
    );

    // uint8 RGB, JPEG (photometric RGB) tiles, EPSG:26910. Lossy: decoders may differ by a few DN.
    let r = load_fx("jpeg_rgb", U8_RGB_JPEG_26910, None).unwrap();
    assert_eq!(
        r.crs(),
        Crs::Utm {
            zone: 10,
            north: true
        }
    );
    assert_eq!(r.transform().coeffs(), gt);
    check_fx(
        "jpeg_rgb",
        &r,
        [
            &[0.0, 0.0, 0.0],
            &[169.0, 47.0, 180.0],
            &[115.0, 206.0, 40.0],
            &[49.0, 84.0, 119.0],
            &[30.0, 51.0, 71.0],
        ],
        3.0,
    );

    // float32 with a rotated/sheared transform: GDAL writes ModelTransformationTag.
    let r = load_fx("f32_rot", F32_ROTATED_32610, None).unwrap();
    assert_eq!(
        r.crs(),
        Crs::Utm {
            zone: 10,
            north: true
        }
    );
    assert_eq!(
        r.transform().coeffs(),
        [400000.0, 0.8, 0.6, 5000000.0, 0.6, -0.8]
    );
    check_fx(
        "f32_rot",
        &r,
        [&[0.0], &[85.0], &[56.5], &[25.0], &[14.0]],
        0.0,
    );

    // int32 2 bands (deflate) and uint32 1 band (uncompressed), EPSG:32633.
    let r = load_fx("i32", I32_2BAND_32633, None).unwrap();
    assert_eq!(
        (r.source_type(), r.crs()),
        (
            SampleType::I32,
            Crs::Utm {
                zone: 33,
                north: true
            }
        )
    );
    check_fx(
        "i32",
        &r,
        [
            &[0.0, 0.0],
            &[-170000.0, -303000.0],
            &[-113000.0, -204000.0],
            &[-50000.0, -85000.0],
            &[-28000.0, -49000.0],
        ],
        0.0,
    );
    let r = load_fx("u32", U32_1BAND_32633, None).unwrap();
    assert_eq!(r.source_type(), SampleType::U32);
    check_fx(
        "u32",
        &r,
        [
            &[0.0],
            &[17000000.0],
            &[11300000.0],
            &[5000000.0],
            &[2800000.0],
        ],
        0.0,
    );

    // User-defined transverse Mercator as GDAL writes it from a PROJ string
    // (+proj=tmerc +lat_0=-30 +lon_0=31 +k=0.9996 +x_0=500000 +y_0=10000000 +datum=WGS84).
    let r = load_fx("tm", TM_CUSTOM, None).unwrap();
    assert_eq!(
        r.crs(),
        Crs::TransverseMercator {
            lat0_deg: -30.0,
            lon0_deg: 31.0,
            k0: 0.9996,
            false_easting_m: 500000.0,
            false_northing_m: 10000000.0,
        }
    );

    // Refused, naming the key: feet, the international ellipsoid, Lambert conformal conic.
    for (name, data, key) in [
        ("tm_feet", TM_FEET, "ProjLinearUnitsGeoKey (3076)"),
        ("tm_intl", TM_INTL, "GeogSemiMajorAxisGeoKey (2057)"),
        ("lcc", LCC, "ProjCoordTransGeoKey (3075)"),
    ] {
        let msg = load_fx(name, data, None).unwrap_err().to_string();
        assert!(msg.contains(name) && msg.contains(key), "{msg}");
        // With an override the file loads.
        assert_eq!(load_fx(name, data, Some(TM_LO25)).unwrap().crs(), TM_LO25);
    }
}

#[test]
fn gdal_ycbcr_jpeg() {
    // JPEG with YCbCr 2x2 chroma subsampling (GDAL's default for RGB JPEG), a smooth gradient
    // R = 60 + 4 col + 3 row, G = 200 - 3 col - 2 row, B = 90 + 2 col + 5 row. The values are
    // GDAL's read-back (itself within 4 DN of the source); chroma upsampling filters differ
    // between JPEG decoders, hence the tolerance.
    let r = load_fx("ycbcr", U8_YCBCR_JPEG_26910, None).unwrap();
    assert_eq!(
        r.crs(),
        Crs::Utm {
            zone: 10,
            north: true
        }
    );
    check_fx(
        "ycbcr",
        &r,
        [
            &[63.0, 199.0, 91.0],
            &[166.0, 122.0, 181.0],
            &[135.0, 146.0, 150.0],
            &[96.0, 174.0, 126.0],
            &[76.0, 188.0, 104.0],
        ],
        4.0,
    );
}

const U16_PLANAR_LZW_UTM35S: &str = concat!(
    "SUkqAAgAAAATAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwADAAAA8gAAAAMBAwABAAAABQAAAAYBAwABAAAAAQAAABUB",
    "AwABAAAAAwAAABwBAwABAAAAAgAAAD0BAwABAAAAAgAAAEIBAwABAAAAEAAAAEMBAwABAAAAEAAAAEQBBAAGAAAABAEAAEUB",
    "AwAGAAAA+AAAAFIBAwACAAAAAAAAAFMBAwADAAAAHAEAAA6DDAADAAAAIgEAAIKEDAAGAAAAOgEAAK+HAwAgAAAAagEAALGH",
    "AgAeAAAAqgEAAIGkAgAGAAAAyAEAAAAAAAAQABAAEACuAI4ArgCPAK4AjwDOAQAAfAIAAAoDAAC4AwAARwQAAPUEAAABAAEA",
    "AQAAAAAAAAAAQAAAAAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAA",
    "AAABAAEAAAAHAAAEAAABAAEAAQQAAAEAAQACBLGHFgAAAAEIsYcHABYABggAAAEAjiMADAAAAQDffwQMAAABACkjV0dTIDg0",
    "IC8gVVRNIHpvbmUgMzVTfFdHUyA4NHwANjU1MzUAgAAAC8AUEg0FhEHhUJhgsAIgAcQiQDh0TicViMZiEOLACQgDj6QAMhkc",
    "gAcikkflMnkroAb0AMumEwmUxl4Bmk3mswWAEJgEjtBAUdn9CoVFodJjrcAsLp0Mp8HBAHi0ZjFVq8aigBGgIlUslcrlEmsc",
    "iMAJms7m05mdrt0wRgKpFGAVzpV1oF3jq4BdRqF/p7kBlVjcPrWFwlbgWLxmNx2PyGRyWTymVy2XyMBAgDAFa8AUEggMZgAh",
    "ULhkNhwAKAtEADicTKDJh8Zh7gFyEAaQAMeRDIjUlhZwGD0ALoAcqYDHk0xGRYAU0mj4Y0xkqcGMGgoCGE5nUZFgzisUAZ0Y",
    "dDjK8GkekEeVjCpkPJg2lUslTkYNVhzcG82moCDldr0MPA3n0EKjAs8MBA5o8TTC9t93vF5vV7vEBIAAAAeALBINBYRB4VCY",
    "YLAC3ALEIkBXQA4nE4rF4jFAGWAEQANICYBJFJJCBpHJZBKpQBEIA1IBlgBJjM5nNZpMgJN51OJsBAQBwoBaHRQLQaNRqRRK",
    "ZQ4hC6hDKjB6DGohGY3GItWY3FRoCJXLZZLJTJ7LIzACZxPpzPJ/a51M0YCqXSaPQqbTLreVwC6nUsBUXIDKtHMLWI1FYFi8",
    "Zjcdj8hkclk8plctl8jAQIAgCueALBIIGEwAIVC4ZDYcAAgWW4BYnEy4lYfGYeoC0QAMTAJHkolI1JYWMC4sAIpANKmYk5NJ",
    "mAXQoBZrNQJMJjGi4XYNBQKPElO407C9FYoBUAj6JGT4YI9II8uEdTYeDDFKpZKngjatDk4Y5vNgKKK9X4YODHP4IYEZaIYy",
    "DJSImpETcLxeb1e75eYCgAAAA0BEEg0FhEHhUJhgsAKYBEQiQIUgGicTisXiMUAxYAT8BEgBAHkUkkIIkclkEqlAHQgDMAJN",
    "gHmMzmc1mkyA83nU4mawAjEBLQA9EowHoVHo9JotNojcAsLqUMqcHkcaiEZjcYi1bjcVgkrlsslkpk9mkcxnE+nM8m1tuEzR",
    "gKplKpFDp1Nut5XALqtUwFTcgMrEcwtajUVgWLxmNx2PyGRyWTymVy2XyMBAgBAQY0BEEggkMgAhULhkNhwAaCETAIicTNBh",
    "h8Zh5gQz8BAIA8eUBgjUlhbwQ5sA5gBMqbBfk0mQCJaAHms1CEwmMaDiJg0FBBIL07jSsRUVigIRhbokZHiMj0gjzELVNh7M",
    "RsqlkqfhZq0OLiPm82A40r1fhj4R0/ghsLFohiISFIiawKtwvF5vV7vl5gI=",
);

const I16_STRIP_DEFLATE_3857_POINT: &str = concat!(
    "SUkqACwCAAARAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAAEAAAAAMBAwABAAAACAAAAAYBAwABAAAAAQAAABEB",
    "BAADAAAA4AAAABUBAwABAAAAAQAAABYBAwABAAAABQAAABcBAwADAAAA2gAAABwBAwABAAAAAQAAAD0BAwABAAAAAgAAAFMB",
    "AwABAAAAAgAAAA6DDAADAAAA7AAAAIKEDAAGAAAABAEAAK+HAwAgAAAANAEAALGHAgAhAAAAdAEAAIGkAgAHAAAAlgEAAAAA",
    "AAA1AEEAGACdAQAA0gEAABMCAAAAAAAAAAAkQAAAAAAAACRAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
    "AECPwAAAAAAAQJ9AAAAAAAAAAAABAAEAAAAHAAAEAAABAAEAAQQAAAEAAQACBLGHGQAAAAEIsYcHABkABggAAAEAjiMADAAA",
    "AQARDwQMAAABACkjV0dTIDg0IC8gUHNldWRvLU1lcmNhdG9yfFdHUyA4NHwAAC0zMjc2OAB4nEthWPSPGHjuf8E/CMzCy7L4",
    "b/fPDkziZy36x/OP7T8IQ0hcLJ5/t/5e+QeB+FgAOpiNkHicK/u76B8EMnU4lcLYmPDBn4J/EJj1Hx/L64/dP7t/Fv8hGDdr",
    "y2+ef2z/QRhC4mLJ/b7198o/CMTHAgCsT4zceJzr+LXoHzHw08+CfxCY9R8fCwD5IT1pABIAAAEDAAEAAAAUAAAAAQEDAAEA",
    "AAAMAAAAAgEDAAEAAAAQAAAAAwEDAAEAAAAIAAAABgEDAAEAAAABAAAAEQEEAAMAAAAQAwAAFQEDAAEAAAABAAAAFgEDAAEA",
    "AAAFAAAAFwEDAAMAAAAKAwAAHAEDAAEAAAABAAAAPQEDAAEAAAACAAAAUwEDAAEAAAACAAAADoMMAAMAAACGAwAAgoQMAAYA",
    "AACeAwAAr4cDACAAAAAcAwAAsIcMAAEAAADOAwAAsYcCACEAAABcAwAAgaQCAAcAAAB+AwAAAAAAADUAQQAYAJ0BAADSAQAA",
    "EwIAAAEAAQAAAAcAAAQAAAEAAQABBAAAAQACAAIEsYcZAAAAAQixhwcAGQAGCAAAAQCOIwAMAAABABEPBAwAAAEAKSNXR1Mg",
    "ODQgLyBQc2V1ZG8tTWVyY2F0b3J8V0dTIDg0fAAALTMyNzY4AAAAAAAAAAAkQAAAAAAAACRAAAAAAAAAAAAAAAAAAAAAAAAA",
    "AAAAAAAAAAAAAAAAAAAAAAAAABiPwAAAAAAALJ9AAAAAAAAAAAAAAAAAAAAAAA==",
);

const F64_TILED_PRED3_4326: &str = concat!(
    "SUkqAAgAAAATAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAAQAAAAAMBAwABAAAACAAAAAYBAwABAAAAAQAAABUB",
    "AwABAAAAAQAAABwBAwABAAAAAQAAAD0BAwABAAAAAwAAAEIBAwABAAAAEAAAAEMBAwABAAAAEAAAAEQBBAACAAAA8gAAAEUB",
    "AwACAAAAhwIAAlMBAwABAAAAAwAAAA6DDAADAAAA+gAAAIKEDAAGAAAAEgEAAK+HAwAgAAAAQgEAALCHDAACAAAAggEAALGH",
    "AgAIAAAAkgEAAIGkAgAEAAAAbmFuAAAAAACaAQAAIQQAAHsUrkfheoQ/exSuR+F6hD8AAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
    "AAAAAAAAAAAAAAAAAAAAADlAAAAAAACAQMAAAAAAAAAAAAEAAQAAAAcAAAQAAAEAAgABBAAAAQABAAAIAAABAOYQAQixhwcA",
    "AAAGCAAAAQCOIwkIsIcBAAEACwiwhwEAAACIbXSWHaRyQAAAAECmVFhBV0dTIDg0fAB4nO3UT2vTYBzA8XiTXWyhfxB0wnqQ",
    "IggeU1CQzloPXgZKDh20N+e6g4oXe+jJpVChU6yvYEdpJ7QdBcWxXlbo7ByW6VKETNsKjoHYPvm3Tn/PkyzPnlzyAvSXJ988",
    "OT0EPmSNY+fuH/b9p6rBkJCmP3WYWRwfMXPh93BoLvNRr9Vqq/RenYndiMEiwc81x/l3HO8DFWas4KjQcaLdbn84oAl/gXmB",
    "83wXBwWCwcBcIBgI3oM7MLcu5kTxkSiayT1cugSzYucNnP/+Onv+t/Mn3r8rytndQ6QcKmZubzRfnvux0Rw0zbSqlcev05Vq",
    "urJQgbXQivDvTuf5SJ5/xvP5SH5TEOavRAVhGi4hKkxvej3Zi0Wv5xVcOG7fLyMDGTqOMcK52pAbskzzoBAvxG8ukcAVX06U",
    "EqXSLA7elXfCvrDPD/HDgt0EyqBMZmTH7fyvI13XNRx9iHP5rSR1JRrf/FQoFLofsjKVyX6EwdkiO1nv9Xt9De4e3vVuSclk",
    "MgVJJUnczpcYfZo22WGn7vA3Y8szH/smO1vgIssv5nb+ZxXYjVUojjo+A+jaBzQJh78wUUf9IUovh3cN1t+K2/kdRTHAHejD",
    "UQyuCeoGNFy1kq6e8MfxAC8f4Yk/2HGUHt5FT3m8RW+RxOuBuJ2/jcCdYQUk/mrI63syzTL2Fy/Y/nZAXZnQgzVbKk1QemR3",
    "DYE7gIee4Lj7a480UDfSNRzoHqiTunakuMNfObtl+YPA1q/3junpcPczUgoAknSxRLfzW4w+Vdt2+Ns/YgE+HbIAJ49/fJbA",
    "OsvP1V+T/PXMYIkNQAf07BRsfybCBKiz6BGEYZAnmvSIRET+etQf93/+6fkLdHXyfnic7dQ9SBthHMfxm9o1hV4yCC3GlioZ",
    "LF2K2qG0zRHoYFs6pMXCBRzsi4VaHOT6QgvtKcGmltY6CCqi4hIV5NRBkYiCCJ43ZIiHb8GL4AsIOe8tEvyDg79Nnt0Hbvgs",
    "91u+/Gc5jrvPnT2evj1wu+u4beDadDp9B7xRLBZvgWvMvLkLrleUiRbwSyEspMGz5+y3ObbzG3xXXVZfgR9nMqsV4IWAP2CB",
    "h1pleQ58GAqFEgz7P6xj+w/42uLO4mvw5Hjj+Efw0+p41Rh4L/ooWor/u/LPN8+w/82zCn/Bl7ZS2WbwjUgiMg1eS9Yl34Ir",
    "r1bwX8El0pHkMex/8jyvE3yg6/p3cEdZWfAyuEHTtJvgppxhrINHxZhYybD/2XXdLnCe+vsFVqi/J+CwaeY3wX0TinIPvBQW",
    "hHqG/RbHcXrA+rKqToGD1N8z8Ar1tw82ZFn+CRapv+sM+832sd0HTlF/2E+C+usG11XFqwfB5S8eRrfBlq/T95xh/0PBKvSD",
    "h7OprAYuUH858A71FwO/48v5B+C4ZEl4T87bb6T+BsAd1B/21ED93QY3UX8l4FHDyPWCS0UxNsOw/576GwL/p/7wvrVTf3jf",
    "ak3TxPu2QfevCK4RhLDJsP/GcewR8BdVVXmwm1nNSGDdH/BnwUG5VY6ANeovyV28i3f6TgBA1fEB",
);

const U8_RGB_JPEG_26910: &str = concat!(
    "SUkqAAgAAAARAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwADAAAA2gAAAAMBAwABAAAABwAAAAYBAwABAAAAAgAAABUB",
    "AwABAAAAAwAAABwBAwABAAAAAQAAAEIBAwABAAAAEAAAAEMBAwABAAAAEAAAAEQBBAACAAAA4AAAAEUBAwACAAAAOwE+AVMB",
    "AwADAAAA6AAAAFsBBwBJAAAA7gAAAA6DDAADAAAAOAEAAIKEDAAGAAAAUAEAAK+HAwAgAAAAgAEAALGHAgAcAAAAwAEAAAAA",
    "AAAIAAgACADcAQAAFwMAAAEAAQABAP/Y/9sAQwACAQEBAQECAQEBAgICAgIEAwICAgIFBAQDBAYFBgYGBQYGBgcJCAYHCQcG",
    "BggLCAkKCgoKCgYICwwLCgwJCgoK/9kAAAAAAAAAAEAAAAAAAAAIQAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
    "AAAAAICEHkEAAAAA8LNaQQAAAAAAAAAAAQABAAAABwAABAAAAQABAAEEAAABAAEAAgSxhxUAAAABCLGHBgAVAAYIAAABAI4j",
    "AAwAAAEAHmkEDAAAAQApI05BRDgzIC8gVVRNIHpvbmUgMTBOfE5BRDgzfAD/2P/AABEIABAAEANSEQBHEQBCEQD/xAAXAAEB",
    "AQEAAAAAAAAAAAAAAAAICQYH/8QALBAAAAQDBQgCAwAAAAAAAAAAAQQCIQUAAxIGEQgJQVEHEyQxQnFSChkiJf/aAAwDUgBH",
    "AEIAAD8Akjl+uOmyW6Td4g7TPPT/ALjpsw/pPj4g7SVdH+46bMJ6T4eIO0uDgBccMKYgUdtgM03AyA3HDAoIFH/XYDMErD7D",
    "JS9JO6mVe4pONxClBIjEL1H4hB6ZxaShk0WpwemXMVKQDYXVpINGkoWICpCTNUEiAVFgJwy/Qknyyy7A9wDBt3qZIaf8JJ8u",
    "HrsD3SGDbvU8g0f4ST5cJXYHugMG3epcPAGDksUJsiwAOx2Cbg5AYOSxKpsiwJHY7BOh13IOS/KfwwTZFsv0HHY/9uOT/9n/",
    "2P/AABEIABAAEANSEQBHEQBCEQD/xAAYAAADAQEAAAAAAAAAAAAAAAAFBgcIA//EACwQAAEDAgMGBQUAAAAAAAAAAAIBAwUE",
    "BgARUZEIB9ESFRZUCSFhJicxMmL/2gAMA1IARwBCAAA/AHGy7H+n2eiiRU/pE0TGH/X34jR28H6s3FuUti9a+4IO1ZChtWKG",
    "uJ9G4tyOoKenr6Jht9EVpoJMZAlQERs3HHXQUkd6yb92Wx/tDHdFEip7/siaDgt4HPyIbExjnwOfkQ2JigeBz8iGxMPtkQdC",
    "7brJkhZ/GXLFZnOKE5vM37du8ffkdQ0k5f8AeEnckzSxDRt0jNVXVR1TwMi4RmLSG6SChGZIKJmRLmqk92KDoXOD8cZIWfv+",
    "MtE+MF+wR+h7U5Y5dgj9D2pyxQewR+h7U5Y//9k=",
);

const F32_ROTATED_32610: &str = concat!(
    "SUkqAAgAAAAPAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAAIAAAAAMBAwABAAAABQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAAoAEAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAA2AEAABwBAwABAAAAAQAAAD0BAwABAAAAAQAAAFMB",
    "AwABAAAAAwAAANiFDAAQAAAAwgAAAK+HAwAgAAAAQgEAALGHAgAeAAAAggEAAAAAAACamZmZmZnpPzMzMzMzM+M/AAAAAAAA",
    "AAAAAAAAAGoYQTMzMzMzM+M/mpmZmZmZ6b8AAAAAAAAAAAAAAADQElNBAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
    "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAADwPwEAAQAAAAcAAAQAAAEAAQABBAAAAQABAAIEsYcWAAAAAQixhwcA",
    "FgAGCAAAAQCOIwAMAAABAGJ/BAwAAAEAKSNXR1MgODQgLyBVVE0gem9uZSAxME58V0dTIDg0fACAACBQMwECBOCDAAUEGBGC",
    "GABGQ9UQ9iQ9wQ9+Q8GEKBBqOQqPjaPkSPlKPmCPm6PnyPoWPsAfwJYQkMQ8sQ+IwJMQ9cQ9sQ98RqPhKPiKPjKPkKSx8sR8",
    "0R88R9CR9GR8gQl4QkgQ+HQJKQ9SQ9kQ92RiHhCPhiPiqPjyRx8rR8vR84R9Ay2Po6PpCaQ+twJEQ9OQ9YT6yQ8FR8KR8PUe",
    "2x8oR8tR8yVC7R9F3uXwkcQ80TiwQ9eQ90Q8AR+NwK1QISR8dR8jUuBXOBGqPoCPoaqR9JR+swIYZ6HpCHqyxQ9yaaPg6Phy",
    "1x8cbCPlSPmK6R8/bmPo2PpSPhCHlCH4GBROBWOBNSHvTER+PQK2cCrZCT9eBHaPoPMR9Jx9No+haBDgwTioeaCLIeATFOaj",
    "4XJCj4kMk6qPjolaPkOzSvI+TqrPHAiBIqgSfoEsqBMSgTFoEFDHIEtyBMigTJoElSBKigS7oEzKBEgj5NI+T6mIenaZOOg6",
    "gIeoiBMa+EHoEpSBKagTKwFCyBKmgRHo+Sr/I+UK6Ier8iIEZjSQS77GI+FjXQguDKI+OTbwuvMtI+TiPlGqTQxA5EzIEBC0",
    "wA6E2IEJy5JS7E5IERTeR6j5RI+VQhIC",
);

const I32_2BAND_32633: &str = concat!(
    "SUkqAAgAAAARAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwACAAAAIAAgAAMBAwABAAAACAAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAAgAEAABUBAwABAAAAAgAAABYBAwABAAAADAAAABcBBAABAAAASAQAABwBAwABAAAAAQAAAD0BAwABAAAAAQAAAFIB",
    "AwABAAAAAAAAAFMBAwACAAAAAgACAA6DDAADAAAA2gAAAIKEDAAGAAAA8gAAAK+HAwAgAAAAIgEAALGHAgAeAAAAYgEAAAAA",
    "AAAAAAAAAAAAQAAAAAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAA",
    "AAABAAEAAAAHAAAEAAABAAEAAQQAAAEAAQACBLGHFgAAAAEIsYcHABYABggAAAEAjiMADAAAAQB5fwQMAAABACkjV0dTIDg0",
    "IC8gVVRNIHpvbmUgMzNOfFdHUyA4NHwAeJxFVW2IVFUYHvwhE1ht9KMJEUcknBBpoq+pJIaIGERkf4QMFjYF5YSIExKuSLgh",
    "0pQUk5UMJrGIyCUshj5sDMoNWZwQcZdYnKBy/UBHQRlkkcF7znl8n/d1uAsH7tz7nvM+5/l4N3XvL7oMjP5la2IfMPge6L9u",
    "z8XHgNJ2oHEz6Lu5XwOaRSD/UdBv42sCevcB0w8Hrcn+51H4O6B2xGvt5FaP+sGAkee97qks8Oi+E9A67XRv6muH3BMBoxud",
    "njGxwmFs4NHvxyjNQ1d6FmgdBzq/AJldQH2/9H3FcLF3YzPQvShnrBW8kfRaBURbAqbvB0aeMlw8kzXVGY/mSfm236N8OKDw",
    "hkdmj/RdZrjSVx2yGwIGJxzmXhC8exwmFgd01jhUnNxhxOkdm7MxGj3oqk5Jn++k9yHDQt7I0dhWwbtAsL0JZM8FtFbLt2ZA",
    "/VFoD2Ln3SevBER9bzVTHoOfAvIfe0w35HfJeGsv8UhvFLznHarrhPufHYorZe8HDpm0/H7OeCstchid9eicidH9F7rIW+1A",
    "gi+/U/o+LhxtEg7viGavyR1OG2+pTxJ8Y7ek7yOi+/8B3Z7XmsFx462xPcE3+V5AaaHovl74PefQelnOiIy37LsJvvQF4Xg+",
    "xvgZueNUjOwMdOWOiH8+Bdqfi9Zl05XeIm/EUC2J/ifEU0uAyg7xzELh91XTlZ4hbzybNcUfPNpfCeZNwsWHAblnTFf6jrw1",
    "zzoMnpV9Bx1SiwLG1zs05mXPctOVvqMGuT9i1XWoLbEN8VW2AeVl9hxdN12pGd+x5xAfv/UeFF+eFd3+MV3rh7x6oLs5wdd/",
    "S7gOTvd0TpmumS+c7q1uSPDxjPSNGHO/iwbHYs0EF7VlLqgrc8Gc0lvExd6DvOWi/ZDlgpwyF8wpPUNcPJM1zAU9wFxQV+aC",
    "OWUuiKt21KG+1HJRSlkuyD1z0fnTcsE7pr6JdY5wUVtmgX4jFvJGjuaeFrynbI5wRjAr9Dj9xh7EzrvnjgreY95q9nr1QHOt",
    "+S3zgFfespccassF72GbI9EOp5nKvejUb5Ez3lozMdoHBO+XseaBi7zRa0N8zC69xTzQU8wDva5eXJfg43yjZ5gH+o41lV3G",
    "22B1go8Z57xjHug75qG/xXirr0zwcWYWf4vR2yd33BvrnONiZguj0JwyA9SV3iJvxMA5xxnG+dZ5KWhO6W3qSs+QN57Nmmib",
    "12yXV3nNaeOO6UrfkTfOY865wttOZ2VvsdPMZ6+ZrvQdNWjsjlXXobbENsTXKUBnGp9HWqYrNeM79hzi4zfOKuZ14lvTlbml",
    "B4pPJvjKK4Trk5bX/GemK3PLvdNLE3w8o/aj/N/YLRrsjDUTXNSWuaCuzAVzSm8RF3tXbgfNBecIc0FOmQvmlJ4hLp7JGuaC",
    "HmAuqCtzwZwyF8TVfd+hf9lrLjhHmAtyz1xwpjMXvGO1EuMuJKaPiA==",
);

const U32_1BAND_32633: &str = concat!(
    "SUkqAAgAAAAPAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAAIAAAAAMBAwABAAAAAQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAAaAEAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAAwAMAABwBAwABAAAAAQAAAFMBAwABAAAAAQAAAA6D",
    "DAADAAAAwgAAAIKEDAAGAAAA2gAAAK+HAwAgAAAACgEAALGHAgAeAAAASgEAAAAAAAAAAAAAAAAAQAAAAAAAAAhAAAAAAAAA",
    "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAAHAAAEAAABAAEAAQQAAAEA",
    "AQACBLGHFgAAAAEIsYcHABYABggAAAEAjiMADAAAAQB5fwQMAAABACkjV0dTIDg0IC8gVVRNIHpvbmUgMzNOfFdHUyA4NHwA",
    "AAAAAGCuCgDAXBUAIAsgAIC5KgDgZzUAQBZAAKDESgAAc1UAYCFgAMDPagAgfnUAgCyAAODaigBAiZUAoDegAADmqgBglLUA",
    "wELAACDxygDgkwQA4MgQAOD9HADgMikA4Gc1AMD7OQDAMEYAwGVSAMCaXgDAz2oAoGNvAKCYewCgzYcAoAKUAKA3oACAy6QA",
    "gACxAIA1vQCAaskAgJ/VAMAnCQBg4xYAAJ8kAIC5KgAgdTgAoI8+AEBLTADgBloAYCFgAADdbQCA93MAILOBAMBujwBAiZUA",
    "4ESjAGBfqQAAG7cAoNbEACDxygDArNgAoLsNAOD9HAAAnyQAQOEzAGCCOwCAI0MAwGVSAOAGWgAgSWkAQOpwAGCLeACgzYcA",
    "wG6PAACxngAgUqYAQPOtAIA1vQCg1sQA4BjUAAC62wCATxIAYBgjACBALADgZzUAoI8+AGC3RwBAgFgAAKhhAMDPagCA93MA",
    "QB99ACDojQDgD5cAoDegAGBfqQAgh7IAAFDDAMB3zACAn9UAQMfeAGDjFgDAkSEAIEAsAIDuNgDgnEEAQEtMAKD5VgAAqGEA",
    "YFZsAMAEdwAgs4EAgGGMAOAPlwBAvqEAoGysAAAbtwBgycEAwHfMACAm1wCA1OEAQHcbAECsJwBA4TMAQBZAAEBLTAAg31AA",
    "IBRdACBJaQAgfnUAILOBAABHhgAAfJIAALGeAADmqgAAG7cA4K67AODjxwDgGNQA4E3gAOCC7AAgCyAAwMYtAGCCOwDgnEEA",
    "gFhPAABzVQCgLmMAQOpwAMAEdwBgwIQA4NqKAICWmAAgUqYAoGysAEAougDAQsAAYP7NAAC62wCA1OEAIJDvAACfJABA4TMA",
    "YII7AKDESgDAZVIA4AZaACBJaQBA6nAAgCyAAKDNhwDAbo8AALGeACBSpgBglLUAgDW9AKDWxADgGNQAALrbAED86gBgnfIA",
    "4DIpAMD7OQCAI0MAQEtMAABzVQDAml4AoGNvAGCLeAAgs4EA4NqKAKAClACAy6QAQPOtAAAbtwDAQsAAgGrJAGAz2gAgW+MA",
    "4ILsAKCq9QDAxi0AIHU4AIAjQwDg0U0AQIBYAKAuYwAA3W0AYIt4AMA5gwAg6I0AgJaYAOBEowBA860AoKG4AABQwwBg/s0A",
    "wKzYACBb4wCACe4A4Lf4AKBaMgCgjz4AoMRKAKD5VgCgLmMAgMJnAID3cwCALIAAgGGMAICWmABgKp0AYF+pAGCUtQBgycEA",
    "YP7NAECS0gBAx94AQPzqAEAx9wBAZgMB",
);

const TM_CUSTOM: &str = concat!(
    "SUkqAAgAAAAQAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAACAAAAAMBAwABAAAAAQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAAJgIAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAA8AAAABwBAwABAAAAAQAAAFMBAwABAAAAAQAAAA6D",
    "DAADAAAAzgAAAIKEDAAGAAAA5gAAAK+HAwBQAAAAFgEAALCHDAAIAAAAtgEAALGHAgAwAAAA9gEAAAAAAAAAAAAAAAAAQAAA",
    "AAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAATAAAE",
    "AAABAAEAAQQAAAEAAQACBLGHCAAAAAAIAAABAP9/AQixhycACAACCAAAAQC2GAYIAAABAI4jCQiwhwEABgALCLCHAQAFAA0I",
    "sIcBAAcAAAwAAAEA/38CDAAAAQD/fwMMAAABAAEABAwAAAEAKSMIDLCHAQABAAkMsIcBAAAACgywhwEAAwALDLCHAQAEABQM",
    "sIcBAAIAAAAAAAAAPsAAAAAAAAA/QHicoiO5/O8/AAAAAICEHkEAAAAA0BJjQYhtdJYdpHJAAAAAQKZUWEEAAAAAAAAAAHVu",
    "a25vd258R0NTIE5hbWUgPSB1bmtub3dufFByaW1lbSA9IEdyZWVud2ljaHx8AAAHDhUcIyoxOD9GTVRbYmlwd36FAwsTGyMm",
    "LjY+RklRWWFpbHR8hIwGDxgcJSkyOz9ITFVeYmtveIGFjgkTGCInLDY7RUpPWV5obXJ8gYuQDBcdIykvOkBGTFJdY2lvdYCG",
    "jJIPFh0kKzI5QEdOVVxjanF4f4aNlBIaIioyNT1FTVVYYGhweHuDi5ObFR4nKzQ4QUpOV1tkbXF6foeQlJ0YIicxNjtFSlRZ",
    "Xmhtd3yBi5CanxsmLDI4PklPVVthbHJ4foSPlZuhHiUsMzpBSE9WXWRrcnmAh46VnKMhKTE5QURMVFxkZ293f4eKkpqiqg==",
);

const TM_FEET: &str = concat!(
    "SUkqAAgAAAAQAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAACAAAAAMBAwABAAAAAQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAAJgIAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAA8AAAABwBAwABAAAAAQAAAFMBAwABAAAAAQAAAA6D",
    "DAADAAAAzgAAAIKEDAAGAAAA5gAAAK+HAwBQAAAAFgEAALCHDAAIAAAAtgEAALGHAgAwAAAA9gEAAAAAAAAAAAAAAAAAQAAA",
    "AAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAATAAAE",
    "AAABAAEAAQQAAAEAAQACBLGHCAAAAAAIAAABAP9/AQixhycACAACCAAAAQC2GAYIAAABAI4jCQiwhwEABgALCLCHAQAFAA0I",
    "sIcBAAcAAAwAAAEA/38CDAAAAQD/fwMMAAABAAEABAwAAAEAKiMIDLCHAQABAAkMsIcBAAAACgywhwEAAwALDLCHAQAEABQM",
    "sIcBAAIAAAAAAAAAAAAAAAAAAAA5QAAAAAAAAPA/AAAAAAAAAAAAAAAAAAAAAIhtdJYdpHJAAAAAQKZUWEEAAAAAAAAAAHVu",
    "a25vd258R0NTIE5hbWUgPSB1bmtub3dufFByaW1lbSA9IEdyZWVud2ljaHx8AAAHDhUcIyoxOD9GTVRbYmlwd36FAwsTGyMm",
    "LjY+RklRWWFpbHR8hIwGDxgcJSkyOz9ITFVeYmtveIGFjgkTGCInLDY7RUpPWV5obXJ8gYuQDBcdIykvOkBGTFJdY2lvdYCG",
    "jJIPFh0kKzI5QEdOVVxjanF4f4aNlBIaIioyNT1FTVVYYGhweHuDi5ObFR4nKzQ4QUpOV1tkbXF6foeQlJ0YIicxNjtFSlRZ",
    "Xmhtd3yBi5CanxsmLDI4PklPVVthbHJ4foSPlZuhHiUsMzpBSE9WXWRrcnmAh46VnKMhKTE5QURMVFxkZ293f4eKkpqiqg==",
);

const TM_INTL: &str = concat!(
    "SUkqAAgAAAAQAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAACAAAAAMBAwABAAAAAQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAArQIAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAA8AAAABwBAwABAAAAAQAAAFMBAwABAAAAAQAAAA6D",
    "DAADAAAAzgAAAIKEDAAGAAAA5gAAAK+HAwBUAAAAFgEAALCHDAAIAAAAvgEAALGHAgCvAAAA/gEAAAAAAAAAAAAAAAAAQAAA",
    "AAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAAUAAAE",
    "AAABAAEAAQQAAAEAAQACBLGHCAAAAAAIAAABAP9/AQixh6YACAACCAAAAQD/fwYIAAABAI4jCAgAAAEA/38JCLCHAQAFAAsI",
    "sIcBAAYADQiwhwEABwAADAAAAQD/fwIMAAABAP9/AwwAAAEAAQAEDAAAAQApIwgMsIcBAAEACQywhwEAAAAKDLCHAQADAAsM",
    "sIcBAAQAFAywhwEAAgAAAAAAAAAAAAAAAAAAADlAAAAAAAAA8D8AAAAAAAAAAAAAAAAAAAAAAAAAAOVUWEEAAAAAAJByQAAA",
    "AAAAAAAAdW5rbm93bnxHQ1MgTmFtZSA9IHVua25vd258RGF0dW0gPSBVbmtub3duIGJhc2VkIG9uIEludGVybmF0aW9uYWwg",
    "MTkyNCAoSGF5Zm9yZCAxOTA5LCAxOTEwKSBlbGxpcHNvaWR8RWxsaXBzb2lkID0gSW50ZXJuYXRpb25hbCAxOTI0IChIYXlm",
    "b3JkIDE5MDksIDE5MTApfFByaW1lbSA9IEdyZWVud2ljaHx8AAAHDhUcIyoxOD9GTVRbYmlwd36FAwsTGyMmLjY+RklRWWFp",
    "bHR8hIwGDxgcJSkyOz9ITFVeYmtveIGFjgkTGCInLDY7RUpPWV5obXJ8gYuQDBcdIykvOkBGTFJdY2lvdYCGjJIPFh0kKzI5",
    "QEdOVVxjanF4f4aNlBIaIioyNT1FTVVYYGhweHuDi5ObFR4nKzQ4QUpOV1tkbXF6foeQlJ0YIicxNjtFSlRZXmhtd3yBi5Ca",
    "nxsmLDI4PklPVVthbHJ4foSPlZuhHiUsMzpBSE9WXWRrcnmAh46VnKMhKTE5QURMVFxkZ293f4eKkpqiqg==",
);

const LCC: &str = concat!(
    "SUkqAAgAAAAQAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwABAAAACAAAAAMBAwABAAAAAQAAAAYBAwABAAAAAQAAABEB",
    "BAABAAAANgIAABUBAwABAAAAAQAAABYBAwABAAAADAAAABcBBAABAAAA8AAAABwBAwABAAAAAQAAAFMBAwABAAAAAQAAAA6D",
    "DAADAAAAzgAAAIKEDAAGAAAA5gAAAK+HAwBUAAAAFgEAALCHDAAJAAAAvgEAALGHAgAwAAAABgIAAAAAAAAAAAAAAAAAQAAA",
    "AAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAgIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAAUAAAE",
    "AAABAAEAAQQAAAEAAQACBLGHCAAAAAAIAAABAP9/AQixhycACAACCAAAAQC2GAYIAAABAI4jCQiwhwEABwALCLCHAQAGAA0I",
    "sIcBAAgAAAwAAAEA/38CDAAAAQD/fwMMAAABAAgABAwAAAEAKSMGDLCHAQACAAcMsIcBAAMADAywhwEAAQANDLCHAQAAAA4M",
    "sIcBAAQADwywhwEABQAAAAAAAIBDQAAAAAAAAFjAAAAAAACAQEAAAAAAAIBGQAAAAAAAAAAAAAAAAAAAAACIbXSWHaRyQAAA",
    "AECmVFhBAAAAAAAAAAB1bmtub3dufEdDUyBOYW1lID0gdW5rbm93bnxQcmltZW0gPSBHcmVlbndpY2h8fAAABw4VHCMqMTg/",
    "Rk1UW2JpcHd+hQMLExsjJi42PkZJUVlhaWx0fISMBg8YHCUpMjs/SExVXmJrb3iBhY4JExgiJyw2O0VKT1leaG1yfIGLkAwX",
    "HSMpLzpARkxSXWNpb3WAhoySDxYdJCsyOUBHTlVcY2pxeH+GjZQSGiIqMjU9RU1VWGBocHh7g4uTmxUeJys0OEFKTldbZG1x",
    "en6HkJSdGCInMTY7RUpUWV5obXd8gYuQmp8bJiwyOD5JT1VbYWxyeH6Ej5WboR4lLDM6QUhPVl1ka3J5gIeOlZyjISkxOUFE",
    "TFRcZGdvd3+HipKaoqo=",
);

const U8_YCBCR_JPEG_26910: &str = concat!(
    "SUkqAAgAAAATAAABAwABAAAAFAAAAAEBAwABAAAADAAAAAIBAwADAAAA8gAAAAMBAwABAAAABwAAAAYBAwABAAAABgAAABUB",
    "AwABAAAAAwAAABwBAwABAAAAAQAAAEIBAwABAAAAEAAAAEMBAwABAAAAEAAAAEQBBAACAAAA+AAAAEUBAwACAAAAoACkAFMB",
    "AwADAAAAAAEAAFsBBwCOAAAANgEAABICAwACAAAAAgACABQCBQAGAAAABgEAAA6DDAADAAAAxAEAAIKEDAAGAAAA3AEAAK+H",
    "AwAgAAAADAIAALGHAgAcAAAATAIAAAAAAAAIAAgACABoAgAACAMAAAEAAQABAAAAAAABAAAA/wAAAAEAAACAAAAAAQAAAP8A",
    "AAABAAAAgAAAAAEAAAD/AAAAAQAAAP/Y/9sAQwACAQEBAQECAQEBAgICAgIEAwICAgIFBAQDBAYFBgYGBQYGBgcJCAYHCQcG",
    "BggLCAkKCgoKCgYICwwLCgwJCgoK/9sAQwECAgICAgIFAwMFCgcGBwoKCgoKCgoKCgoKCgoKCgoKCgoKCgoKCgoKCgoKCgoK",
    "CgoKCgoKCgoKCgoKCgoKCgoK/9kAAAAAAAAAQAAAAAAAAAhAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
    "gIQeQQAAAADws1pBAAAAAAAAAAABAAEAAAAHAAAEAAABAAEAAQQAAAEAAQACBLGHFQAAAAEIsYcGABUABggAAAEAjiMADAAA",
    "AQAeaQQMAAABACkjTkFEODMgLyBVVE0gem9uZSAxME58TkFEODN8AP/Y/8AAEQgAEAAQAwEiAAIRAQMRAf/EABYAAQEBAAAA",
    "AAAAAAAAAAAAAAQFB//EABgQAAMBAQAAAAAAAAAAAAAAAAMBAFEC/8QAFQEBAQAAAAAAAAAAAAAAAAAABAf/xAAaEQACAgMA",
    "AAAAAAAAAAAAAAAAAwUGISIx/9oADAMBAAIRAxEAPwDRjCeRDCdTMlkQ3KhQ9XRjhHaNBK0P/9n/2P/AABEIABAAEAMBIgAC",
    "EQEDEQH/xAAWAAEBAQAAAAAAAAAAAAAAAAABBAb/xAAbEAACAQUAAAAAAAAAAAAAAAAAAQIDERMiYf/EABQBAQAAAAAAAAAA",
    "AAAAAAAAAAb/xAAdEQABAgcAAAAAAAAAAAAAAAADAAIBBQYSEzFx/9oADAMBAAIRAxEAPwDZTo7BhXCiaswFzKXBbDSThkQs",
    "LeL/2Q==",
);

#[test]
fn corrupted_files_never_panic() {
    // Deterministic byte corruption of the GDAL fixtures and a bundled map header: every load
    // returns (Ok or Err) without a panic escaping; a panic inside the tiff crate would be caught
    // and surface as a Decode error saying so (none occur for these inputs). TIFF has no checksums,
    // so some corrupted files load with wrong pixel values: that is inherent to the format.
    let mut files: Vec<(&str, Vec<u8>)> = vec![
        ("u16_planar", b64(U16_PLANAR_LZW_UTM35S)),
        ("i16_point", b64(I16_STRIP_DEFLATE_3857_POINT)),
        ("f64_geo", b64(F64_TILED_PRED3_4326)),
        ("jpeg_rgb", b64(U8_RGB_JPEG_26910)),
        ("ycbcr", b64(U8_YCBCR_JPEG_26910)),
        ("tm", b64(TM_CUSTOM)),
    ];
    files.push((
        "naip_2014",
        std::fs::read(repo_dir().join("sitl/maps/naip_nd_2014.tif")).unwrap(),
    ));
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    let (mut ok, mut err, mut crate_panics) = (0, 0, 0);
    let mut total = 0;
    for (name, bytes) in &files {
        let rounds = if bytes.len() > 100_000 { 60 } else { 300 };
        for _ in 0..rounds {
            total += 1;
            let mut b = bytes.clone();
            // Corrupt 1-4 bytes, mostly in the first 2 KiB (header, IFD, tag values).
            for _ in 0..1 + next() % 4 {
                let span = if next() % 4 == 0 {
                    b.len()
                } else {
                    b.len().min(2048)
                };
                let i = (next() % span as u64) as usize;
                b[i] = next() as u8;
            }
            match read_geotiff(Cursor::new(b), Path::new(name), None) {
                Ok(_) => ok += 1,
                Err(e) => {
                    if e.to_string().contains("panicked") {
                        crate_panics += 1;
                    }
                    err += 1;
                }
            }
        }
    }
    eprintln!("corrupted loads: {ok} ok, {err} errors ({crate_panics} caught tiff-crate panics)");
    assert_eq!(ok + err, total);
    assert_eq!(
        crate_panics, 0,
        "the tiff crate panicked on a corrupted file (caught)"
    );
}

/// The part of a DEM under an area holds the same heights there as the whole DEM, bit for bit,
/// and is decoded from a window only; an area off the DEM, or one that holds all of it, loads the
/// whole DEM.
#[test]
fn a_dem_loaded_for_an_area_has_the_whole_dems_heights_there() {
    use visnav_core::geo::raster::Bounds;
    use visnav_io::geo::dem::{load_dem, load_dem_covering};
    let Some(shared) = shared_dir() else { return };
    for f in ["ngi_3324c/dem.tif", "autzen/autzen_dsm_1m_utm10n.tif"] {
        let path = shared.join(f);
        let whole = load_dem(&path, None).unwrap();
        let r = visnav_io::geo::window::open_geotiff_window(&path, None).unwrap();
        let b = r.info().bounds();
        let (w, h) = (b.max_x_m - b.min_x_m, b.max_y_m - b.min_y_m);
        // An off-centre area a fifth of the DEM's side.
        let area = Bounds {
            min_x_m: b.min_x_m + 0.3 * w,
            max_x_m: b.min_x_m + 0.5 * w,
            min_y_m: b.min_y_m + 0.55 * h,
            max_y_m: b.min_y_m + 0.75 * h,
        };
        let part = load_dem_covering(&path, None, &area).unwrap();
        let (cell_whole, cell_part) = (whole.cell_m().unwrap(), part.cell_m().unwrap());
        assert_eq!(cell_whole, cell_part, "{f}");
        let (lo, hi) = part.height_range_m();
        let (wlo, whi) = whole.height_range_m();
        assert!(
            lo >= wlo && hi <= whi && (lo, hi) != (wlo, whi),
            "{f}: {lo}..{hi}"
        );
        let mut compared = 0;
        for i in 0..=40 {
            for j in 0..=40 {
                let x = area.min_x_m + (area.max_x_m - area.min_x_m) * f64::from(i) / 40.0;
                let y = area.min_y_m + (area.max_y_m - area.min_y_m) * f64::from(j) / 40.0;
                let (a, b) = (whole.height_at(x, y), part.height_at(x, y));
                assert_eq!(
                    a.map(f64::to_bits),
                    b.map(f64::to_bits),
                    "{f}: height at {x} {y}"
                );
                compared += usize::from(a.is_some());
            }
        }
        assert!(compared > 1500, "{f}: {compared} heights compared");
        // Beyond the area's margin the part has no heights.
        let far = (
            area.max_x_m + 10.0 * cell_whole,
            area.max_y_m + 10.0 * cell_whole,
        );
        assert!(whole.height_at(far.0, far.1).is_some(), "{f}");
        assert!(part.height_at(far.0, far.1).is_none(), "{f}");
        // Off the DEM, or all of it: the whole DEM.
        let off = Bounds {
            min_x_m: b.max_x_m + 1000.0,
            max_x_m: b.max_x_m + 2000.0,
            min_y_m: b.min_y_m,
            max_y_m: b.max_y_m,
        };
        let all = Bounds {
            min_x_m: b.min_x_m - 100.0,
            max_x_m: b.max_x_m + 100.0,
            min_y_m: b.min_y_m - 100.0,
            max_y_m: b.max_y_m + 100.0,
        };
        for a in [off, all] {
            let d = load_dem_covering(&path, None, &a).unwrap();
            assert_eq!(d.height_range_m(), whole.height_range_m(), "{f}");
        }
    }
}
