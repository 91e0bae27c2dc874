//! Every bundled and shared GeoTIFF loads with the CRS, geotransform, nodata, sample type and
//! pixel values that GDAL reports; the real DEMs give sane heights and ray intersections.
//!
//! Reference values come from GDAL 3.10.3 through rasterio 1.4.4 (pip wheel, read in a throwaway
//! venv outside the repository): `transform`, `bounds`, `crs`, `nodata`, `dtypes`, pixel values
//! `read()[:, row, col]` at fixed and seeded-random positions, and per-band means of
//! `read(b, masked=True)` (nodata excluded). The test does not depend on Python.
//! Files under ../shared/data are skipped with a printed reason when that folder is absent; the
//! copies in sitl/maps are always checked.

use std::path::PathBuf;

use visnav::geo::Crs;
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::{GeoTiffError, load_geotiff};
use visnav::geo::raster::{Raster, SampleType};

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
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
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
    let dem = Dem::load_geotiff(&shared.join("ngi_3324c/dem.tif"), None).unwrap();
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
}
