//! The fuzz corpus on stable: every committed input under `fuzz/corpus/<target>/` goes
//! through the same target bodies libFuzzer runs (`fuzz/src/lib.rs`), so an input that once
//! crashed a target, added to the corpus with its fix, stays tested by `cargo test` without
//! nightly or libFuzzer. `scripts/fuzz.sh` runs the fuzzers themselves.
//!
//! `write_seed_corpus` (ignored) regenerates the seeds (`seed-*` files) from the repository's own
//! example configurations, test tlog and bundled public-domain NAIP orthophoto, and from small
//! generated files: `cargo test --test integration -- --ignored fuzz_corpus::write_seed_corpus`.

use std::path::{Path, PathBuf};

#[allow(dead_code)]
#[path = "../fuzz/src/lib.rs"]
mod harness;

fn corpus_dir(target: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fuzz/corpus")
        .join(target)
}

/// Every corpus file of every target returns without a panic.
#[test]
fn corpus_replays_without_panics() {
    let mut failures = Vec::new();
    for (name, target) in harness::TARGETS {
        let mut files: Vec<PathBuf> = std::fs::read_dir(corpus_dir(name))
            .unwrap_or_else(|e| panic!("fuzz/corpus/{name}: {e}"))
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        assert!(!files.is_empty(), "fuzz/corpus/{name} has no inputs");
        for f in &files {
            let data = std::fs::read(f).unwrap();
            if std::panic::catch_unwind(|| target(&data)).is_err() {
                failures.push(format!("{name}: {}", f.display()));
            }
        }
        eprintln!("fuzz corpus {name}: {} inputs", files.len());
    }
    harness::remove_scratch();
    assert!(
        failures.is_empty(),
        "inputs that panic (the messages are above):\n{}",
        failures.join("\n")
    );
}

// ------------------------------------------------------------------------------------------------
// The seeds

fn write(target: &str, name: &str, bytes: &[u8]) {
    let dir = corpus_dir(target);
    std::fs::create_dir_all(&dir).unwrap();
    assert!(
        bytes.len() <= 24 << 10,
        "{target}/{name}: {} bytes",
        bytes.len()
    );
    std::fs::write(dir.join(format!("seed-{name}")), bytes).unwrap();
}

/// Regenerates the committed seeds (run by hand; the fuzzers' own finds are kept beside them).
#[test]
#[ignore]
fn write_seed_corpus() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let tmp = tempfile::tempdir().unwrap();
    config_seeds(root);
    mavlink_seeds(root);
    let ortho = geotiff_seeds(root, tmp.path());
    map_seeds(&ortho, tmp.path());
    frame_seeds();
}

fn config_seeds(root: &Path) {
    for f in [
        "config/demo.toml",
        "config/companion.toml",
        "config/ardupilot-sitl.toml",
        "config/px4-sitl.toml",
        "sitl/ardupilot/visnav.toml",
        "sitl/px4/visnav.toml",
        "sitl/px4/visnav-jmavsim.toml",
    ] {
        let name = f.replace('/', "_");
        write("config", &name, &std::fs::read(root.join(f)).unwrap());
    }
    // A y4m frame source and every daemon key the examples leave at their defaults.
    let extra = "[link]\nconnection = \"tcp:127.0.0.1:5760\"\n\n[camera]\nwidth_px = 320\n\
                 height_px = 240\nhfov_deg = 70.0\n\n[map]\northo = [\"../sitl/maps/naip_nd_2010.tif\"]\n\
                 ground_height_amsl_m = 300.0\nupsample = 2\n\n[frames]\nsource = \"y4m\"\n\
                 path = \"../tests/data/none.y4m\"\nrealtime = false\n\n[daemon]\ngps = \"gps2\"\n\
                 imu_bias_restore = \"scaled_imu\"\nmetrics_listen = \"127.0.0.1:9187\"\n";
    write("config", "y4m-frames.toml", extra.as_bytes());
}

fn mavlink_seeds(root: &Path) {
    use mavlink::dialects::ardupilotmega as ap;
    use mavlink::{MavHeader, MavlinkVersion, Message};
    let header = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: 0,
    };
    let mut msgs: Vec<ap::MavMessage> = Vec::new();
    for k in 0..6u32 {
        let t_ms = 10_000 + 20 * k;
        let t_us = u64::from(t_ms) * 1000;
        msgs.push(ap::MavMessage::HEARTBEAT(ap::HEARTBEAT_DATA {
            mavtype: ap::MavType::MAV_TYPE_QUADROTOR,
            autopilot: if k < 3 {
                ap::MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA
            } else {
                ap::MavAutopilot::MAV_AUTOPILOT_PX4
            },
            ..Default::default()
        }));
        msgs.push(ap::MavMessage::HIGHRES_IMU(ap::HIGHRES_IMU_DATA {
            time_usec: t_us,
            zacc: -9.81,
            xgyro: 0.01,
            ..Default::default()
        }));
        msgs.push(ap::MavMessage::SCALED_IMU(ap::SCALED_IMU_DATA {
            time_boot_ms: t_ms,
            zacc: -1000,
            xgyro: 10,
            ..Default::default()
        }));
        msgs.push(ap::MavMessage::RAW_IMU(ap::RAW_IMU_DATA {
            time_usec: t_us,
            zacc: -1000,
            ..Default::default()
        }));
        msgs.push(ap::MavMessage::ATTITUDE(ap::ATTITUDE_DATA {
            time_boot_ms: t_ms,
            roll: 0.01,
            pitch: -0.02,
            yaw: 1.0,
            ..Default::default()
        }));
        let gps = ap::GPS_RAW_INT_DATA {
            time_usec: t_us,
            fix_type: ap::GpsFixType::GPS_FIX_TYPE_3D_FIX,
            lat: 472_000_000,
            lon: -970_000_000,
            alt: 300_000,
            vel: 500,
            cog: 9000,
            h_acc: 1500,
            v_acc: 3000,
            vel_acc: 300,
            ..Default::default()
        };
        msgs.push(ap::MavMessage::GPS_RAW_INT(gps.clone()));
        msgs.push(ap::MavMessage::GPS2_RAW(ap::GPS2_RAW_DATA {
            time_usec: t_us,
            fix_type: ap::GpsFixType::GPS_FIX_TYPE_RTK_FIXED,
            lat: gps.lat,
            lon: gps.lon,
            alt: gps.alt,
            vel: u16::MAX,
            cog: u16::MAX,
            ..Default::default()
        }));
        msgs.push(ap::MavMessage::SCALED_PRESSURE(ap::SCALED_PRESSURE_DATA {
            time_boot_ms: t_ms,
            press_abs: 978.0,
            ..Default::default()
        }));
    }
    msgs.push(ap::MavMessage::TIMESYNC(ap::TIMESYNC_DATA {
        tc1: 0,
        ts1: 12345,
        ..Default::default()
    }));
    // Mode 0: a byte stream (V2, V1, and V2 signed with the harness's key under mode 4).
    for (name, mode, version, signed) in [
        ("stream-v2", 0u8, MavlinkVersion::V2, false),
        ("stream-v1-gps2-restore", 24, MavlinkVersion::V1, false),
        ("stream-v2-signed", 4 + 24, MavlinkVersion::V2, true),
    ] {
        let signing =
            mavlink::SigningData::from_config(mavlink::SigningConfig::new([7; 32], 1, true, true));
        let mut out = vec![mode];
        for (i, m) in msgs.iter().enumerate() {
            let h = MavHeader {
                sequence: i as u8,
                ..header
            };
            if signed {
                mavlink::write_versioned_msg_signed(&mut out, version, h, m, Some(&signing))
                    .unwrap();
            } else {
                mavlink::write_versioned_msg(&mut out, version, h, m).unwrap();
            }
        }
        write("mavlink", name, &out);
    }
    // Mode 1: payload records.
    let mut out = vec![1u8];
    let mut buf = [0u8; 255];
    for m in &msgs {
        let n = m.ser(MavlinkVersion::V2, &mut buf);
        let id = u16::try_from(m.message_id()).unwrap();
        out.extend_from_slice(&id.to_le_bytes());
        out.push(n as u8);
        out.extend_from_slice(&buf[..n]);
    }
    write("mavlink", "payloads", &out);
    // Mode 2: tlogs: the generated messages, and the start of the repository's SITL tlog.
    let mut out = vec![2u8];
    for (i, m) in msgs.iter().enumerate() {
        out.extend_from_slice(&(1_700_000_000_000_000u64 + 2500 * i as u64).to_be_bytes());
        mavlink::write_versioned_msg(&mut out, MavlinkVersion::V2, header, m).unwrap();
    }
    write("mavlink", "tlog-generated", &out);
    let tlog = std::fs::read(root.join("tests/data/arducopter_sitl_climb.tlog")).unwrap();
    for (name, skip) in [("tlog-sitl-start", 0usize), ("tlog-sitl-later", 2000)] {
        let records = visnav_link::tlog::read_tlog(&tlog);
        let mut out = vec![2u8];
        for (t, p) in records.iter().skip(skip) {
            if out.len() + 8 + p.len() > 12 << 10 {
                break;
            }
            out.extend_from_slice(&t.to_be_bytes());
            out.extend_from_slice(p);
        }
        write("mavlink", name, &out);
    }
}

/// Minimal GeoTIFF writer: one image, `bands` x `bits` samples (`fmt`: SampleFormat), strips or
/// tiles, chunky, uncompressed; UTM 14N (EPSG 32614), 1 m pixels; optional GDAL_NODATA.
#[allow(clippy::too_many_arguments)]
fn geotiff_bytes(
    w: u32,
    h: u32,
    bands: u16,
    bits: u16,
    fmt: u16,
    tile: Option<u32>,
    nodata: Option<&str>,
    samples: &[u8],
) -> Vec<u8> {
    use tiff::encoder::TiffEncoder;
    use tiff::tags::Tag;
    let mut out = std::io::Cursor::new(Vec::new());
    let mut enc = TiffEncoder::new(&mut out).unwrap();
    let mut d = enc.image_directory().unwrap();
    let px = usize::from(bands) * usize::from(bits / 8);
    let (cw, ch) = tile.map_or((w, h), |t| (t, t));
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    for ty in 0..h.div_ceil(ch) {
        for tx in 0..w.div_ceil(cw) {
            let mut chunk = Vec::new();
            for y in ty * ch..(ty + 1) * ch {
                for x in tx * cw..(tx + 1) * cw {
                    if x < w && y < h {
                        let at = (y * w + x) as usize * px;
                        chunk.extend_from_slice(&samples[at..at + px]);
                    } else {
                        chunk.extend(std::iter::repeat_n(0u8, px));
                    }
                }
            }
            offsets.push(d.write_data(&chunk[..]).unwrap() as u32);
            counts.push(chunk.len() as u32);
        }
    }
    d.write_tag(Tag::ImageWidth, w).unwrap();
    d.write_tag(Tag::ImageLength, h).unwrap();
    d.write_tag(Tag::BitsPerSample, &vec![bits; usize::from(bands)][..])
        .unwrap();
    d.write_tag(Tag::SampleFormat, &vec![fmt; usize::from(bands)][..])
        .unwrap();
    d.write_tag(Tag::SamplesPerPixel, bands).unwrap();
    d.write_tag(Tag::Compression, 1u16).unwrap();
    d.write_tag(
        Tag::PhotometricInterpretation,
        if bands >= 3 { 2u16 } else { 1 },
    )
    .unwrap();
    d.write_tag(Tag::PlanarConfiguration, 1u16).unwrap();
    match tile {
        Some(t) => {
            d.write_tag(Tag::TileWidth, t).unwrap();
            d.write_tag(Tag::TileLength, t).unwrap();
            d.write_tag(Tag::TileOffsets, &offsets[..]).unwrap();
            d.write_tag(Tag::TileByteCounts, &counts[..]).unwrap();
        }
        None => {
            d.write_tag(Tag::RowsPerStrip, h).unwrap();
            d.write_tag(Tag::StripOffsets, &offsets[..]).unwrap();
            d.write_tag(Tag::StripByteCounts, &counts[..]).unwrap();
        }
    }
    d.write_tag(Tag::ModelPixelScaleTag, &[1.0f64, 1.0, 0.0][..])
        .unwrap();
    d.write_tag(
        Tag::ModelTiepointTag,
        &[0.0f64, 0.0, 0.0, 500_000.0, 5_200_000.0, 0.0][..],
    )
    .unwrap();
    let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32614];
    d.write_tag(Tag::GeoKeyDirectoryTag, &keys[..]).unwrap();
    if let Some(n) = nodata {
        d.write_tag(Tag::GdalNodata, n).unwrap();
    }
    d.finish().unwrap();
    out.into_inner()
}

/// A grey excerpt of the bundled NAIP orthophoto (public domain): `n` x `n` pixels of luma.
fn naip_grey(root: &Path, n: usize) -> Vec<u8> {
    use visnav::geo::window::open_geotiff_window;
    let mut r = open_geotiff_window(&root.join("sitl/maps/naip_nd_2009.tif"), None).unwrap();
    let (w, h) = (r.info().width, r.info().height);
    let win = r.read_window(w / 2, h / 2, n, n).unwrap();
    (0..n * n)
        .map(|i| {
            let (x, y) = (i % n, i / n);
            let v: f64 = (0..3.min(win.bands()))
                .map(|b| win.sample(x, y, b).unwrap_or(0.0) * [0.299, 0.587, 0.114][b])
                .sum();
            v.round().clamp(1.0, 255.0) as u8
        })
        .collect()
}

/// Writes the GeoTIFF seeds; returns the path of a small textured orthophoto for the map seeds.
fn geotiff_seeds(root: &Path, tmp: &Path) -> PathBuf {
    let grey = naip_grey(root, 48);
    write(
        "geotiff",
        "naip-grey-48-strip",
        &geotiff_bytes(48, 48, 1, 8, 1, None, Some("0"), &grey),
    );
    let rgb: Vec<u8> = grey[..16 * 16]
        .iter()
        .flat_map(|&v| [v, v / 2, 255 - v])
        .collect();
    write(
        "geotiff",
        "rgb-16-tiled",
        &geotiff_bytes(16, 16, 3, 8, 1, Some(16), None, &rgb),
    );
    let dem: Vec<u8> = (0..8 * 8)
        .flat_map(|i| (300.0f32 + i as f32 * 0.5).to_le_bytes())
        .collect();
    write(
        "geotiff",
        "dem-f32-8",
        &geotiff_bytes(8, 8, 1, 32, 3, None, Some("-9999"), &dem),
    );
    let u16s: Vec<u8> = (0..20 * 12)
        .flat_map(|i| (i as u16 * 200).to_le_bytes())
        .collect();
    write(
        "geotiff",
        "u16-20x12-tiled",
        &geotiff_bytes(20, 12, 1, 16, 1, Some(16), None, &u16s),
    );
    let ortho = tmp.join("ortho.tif");
    let big = naip_grey(root, 48);
    std::fs::write(
        &ortho,
        geotiff_bytes(48, 48, 1, 8, 1, None, Some("0"), &big),
    )
    .unwrap();
    std::fs::write(
        tmp.join("dem.tif"),
        geotiff_bytes(8, 8, 1, 32, 3, None, Some("-9999"), &dem),
    )
    .unwrap();
    ortho
}

fn map_seeds(ortho: &Path, tmp: &Path) {
    use visnav::map::{BuildSpec, HeightSource, build_map};
    for (name, height) in [
        ("naip-constant-height", HeightSource::ConstantAmsl(300.0)),
        ("naip-dem", HeightSource::Dem(tmp.join("dem.tif"))),
    ] {
        let mut spec = BuildSpec::new(vec![ortho.to_path_buf()], height);
        spec.levels = Some(2);
        spec.tile_px = 64;
        spec.max_features_per_tile = 12;
        spec.surf.hessian_threshold = 50.0;
        let out = tmp.join(format!("{name}.vnm"));
        match build_map(&spec, &out, &mut |_| {}) {
            Ok(_) => write("map_file", name, &std::fs::read(&out).unwrap()),
            Err(e) => panic!("map seed {name}: {e}"),
        }
    }
}

fn frame_seeds() {
    // Mode 0: y4m streams.
    let y4m = |header: &str, frame_bytes: usize, frames: usize| {
        let mut v = vec![0u8];
        v.extend_from_slice(header.as_bytes());
        for f in 0..frames {
            v.extend_from_slice(b"FRAME\n");
            v.extend((0..frame_bytes).map(|i| (i * 7 + f * 13) as u8));
        }
        v
    };
    write(
        "frame",
        "y4m-420jpeg",
        &y4m(
            "YUV4MPEG2 W8 H6 F25:1 Ip A1:1 C420jpeg\n",
            8 * 6 + 2 * 4 * 3,
            2,
        ),
    );
    write(
        "frame",
        "y4m-mono",
        &y4m("YUV4MPEG2 W5 H3 F30000:1001 Cmono\n", 15, 3),
    );
    write(
        "frame",
        "y4m-444p16",
        &y4m(
            "YUV4MPEG2 W4 H4 F10:1 C444p16 XYSCSS=444P16\n",
            4 * 4 * 2 * 3,
            1,
        ),
    );
    // Mode 1: image files (sub 0 .png, 1 .jpg, 2 .tif).
    let encode = |img: image::DynamicImage, fmt: image::ImageFormat| {
        let mut c = std::io::Cursor::new(Vec::new());
        img.write_to(&mut c, fmt).unwrap();
        c.into_inner()
    };
    let g = image::GrayImage::from_fn(16, 12, |x, y| image::Luma([(x * 13 + y * 7) as u8]));
    let rgb = image::RgbImage::from_fn(8, 8, |x, y| {
        image::Rgb([(x * 30) as u8, (y * 30) as u8, 99])
    });
    let g16 = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(6, 4, |x, y| {
        image::Luma([(x * 9000 + y * 700) as u16])
    });
    let with_mode = |mode: u8, bytes: Vec<u8>| [vec![mode], bytes].concat();
    let png = image::ImageFormat::Png;
    write(
        "frame",
        "png-grey",
        &with_mode(1, encode(g.clone().into(), png)),
    );
    write(
        "frame",
        "png-rgb",
        &with_mode(1, encode(rgb.clone().into(), png)),
    );
    write(
        "frame",
        "png-grey16",
        &with_mode(1, encode(g16.into(), png)),
    );
    let jpg = encode(g.clone().into(), image::ImageFormat::Jpeg);
    write("frame", "jpeg-grey", &with_mode(5, jpg.clone()));
    write(
        "frame",
        "jpeg-rgb",
        &with_mode(5, encode(rgb.into(), image::ImageFormat::Jpeg)),
    );
    write(
        "frame",
        "tiff-grey",
        &with_mode(9, encode(g.into(), image::ImageFormat::Tiff)),
    );
    // Mode 2: V4L2 buffers [w-1, h-1, stride/2, data] (sub 0 GREY, 1 YUYV, 2 MJPG).
    let grey: Vec<u8> = (0..8 * 6).map(|i| i as u8 * 5).collect();
    write(
        "frame",
        "v4l2-grey",
        &[vec![2, 7, 5, 0], grey.clone()].concat(),
    );
    write(
        "frame",
        "v4l2-grey-stride",
        &[vec![2, 5, 5, 4], grey].concat(),
    );
    let yuyv: Vec<u8> = (0..2 * 8 * 4).map(|i| (i * 3) as u8).collect();
    write("frame", "v4l2-yuyv", &[vec![6, 7, 3, 0], yuyv].concat());
    write("frame", "v4l2-mjpg", &[vec![10, 15, 11, 0], jpg].concat());
    // Mode 3: frames.csv.
    write(
        "frame",
        "csv-boot",
        b"\x03# frames\nfile,t_boot_us\n000001.png,81234567\n000002.png,81334567\n",
    );
    write(
        "frame",
        "csv-seconds",
        b"\x03file, t_s\na.jpg, 0.5\nb.jpg, 0.75\n\n",
    );
}
