//! Bad input refused with a clear error, never accepted: corrupt JPEG
//! frames, map files edited with their CRC recomputed, implausible terrain heights, blank
//! orthophotos, geographic (degree) orthophotos; and sparse GeoTIFFs read as GDAL reads them.

// Test helpers (the file writer) may unwrap, as the tests themselves may.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::too_many_arguments)]

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use tiff::encoder::TiffEncoder;
use tiff::encoder::compression::{CompressionAlgorithm, Deflate, DeflateLevel};
use tiff::tags::Tag;
use visnav_core::geo::raster::RasterData;
use visnav_core::vision::GrayImage;
use visnav_io::geo::dem::load_dem;
use visnav_io::geo::geotiff::load_geotiff;
use visnav_io::image_file::GrayImageFile;
use visnav_io::map::{BuildSpec, HeightSource, MapError, ReferenceMap, build_map};

/// The georeferencing of a test file.
#[derive(Clone, Copy)]
enum Geo {
    /// UTM 10N (EPSG:32610), 2 m pixels.
    Utm,
    /// EPSG:4326, pixel steps of 0.00006 x 0.00004 degrees (about 4.5 m at 45 deg).
    Wgs84,
}

/// Writes a tiled (32 x 32 px), deflate-compressed one-band GeoTIFF of `w x h` samples
/// `pixel(x, y)`; the tiles listed in `empty` are stored with 0 bytes (a sparse file, as GDAL
/// writes with SPARSE_OK=TRUE).
fn write_tiff<T: Copy>(
    path: &Path,
    (w, h): (usize, usize),
    geo: Geo,
    empty: &[usize],
    nodata: Option<&str>,
    pixel: impl Fn(usize, usize) -> T,
    le: impl Fn(T, &mut Vec<u8>),
    (bits, format): (u16, u16),
) {
    const TILE: usize = 32;
    let file = BufWriter::new(File::create(path).unwrap());
    let mut enc = TiffEncoder::new(file).unwrap();
    let mut d = enc.image_directory().unwrap();
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    for ty in 0..h.div_ceil(TILE) {
        for tx in 0..w.div_ceil(TILE) {
            let k = offsets.len();
            let mut raw = Vec::new();
            for y in ty * TILE..(ty + 1) * TILE {
                for x in tx * TILE..(tx + 1) * TILE {
                    let v = pixel(x.min(w - 1), y.min(h - 1));
                    le(v, &mut raw);
                }
            }
            let mut bytes = Vec::new();
            if !empty.contains(&k) {
                Deflate::with_level(DeflateLevel::Fast)
                    .write_to(&mut bytes, &raw)
                    .unwrap();
            }
            let at = if bytes.is_empty() {
                0
            } else {
                u32::try_from(d.write_data(&bytes[..]).unwrap()).unwrap()
            };
            offsets.push(at);
            counts.push(bytes.len() as u32);
        }
    }
    d.write_tag(Tag::ImageWidth, w as u32).unwrap();
    d.write_tag(Tag::ImageLength, h as u32).unwrap();
    d.write_tag(Tag::BitsPerSample, bits).unwrap();
    d.write_tag(Tag::Compression, 8u16).unwrap();
    d.write_tag(Tag::PhotometricInterpretation, 1u16).unwrap();
    d.write_tag(Tag::SamplesPerPixel, 1u16).unwrap();
    d.write_tag(Tag::PlanarConfiguration, 1u16).unwrap();
    d.write_tag(Tag::SampleFormat, format).unwrap();
    d.write_tag(Tag::TileWidth, TILE as u32).unwrap();
    d.write_tag(Tag::TileLength, TILE as u32).unwrap();
    d.write_tag(Tag::TileOffsets, &offsets[..]).unwrap();
    d.write_tag(Tag::TileByteCounts, &counts[..]).unwrap();
    match geo {
        Geo::Utm => crate::geotiff_window::geo_tags(&mut d, None),
        Geo::Wgs84 => {
            d.write_tag(Tag::ModelPixelScaleTag, &[0.00006f64, 0.00004, 0.0][..])
                .unwrap();
            d.write_tag(
                Tag::ModelTiepointTag,
                &[0.0f64, 0.0, 0.0, -123.07, 44.06, 0.0][..],
            )
            .unwrap();
            let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326];
            d.write_tag(Tag::GeoKeyDirectoryTag, &keys[..]).unwrap();
        }
    }
    if let Some(n) = nodata {
        d.write_tag(Tag::GdalNodata, n).unwrap();
    }
    d.finish().unwrap();
}

fn write_u8(
    path: &Path,
    size: (usize, usize),
    geo: Geo,
    empty: &[usize],
    f: impl Fn(usize, usize) -> u8,
) {
    write_tiff(path, size, geo, empty, None, f, |v, o| o.push(v), (8, 1));
}

fn write_f32(path: &Path, size: (usize, usize), f: impl Fn(usize, usize) -> f32) {
    write_tiff(
        path,
        size,
        Geo::Utm,
        &[],
        None,
        f,
        |v: f32, o| o.extend_from_slice(&v.to_le_bytes()),
        (32, 3),
    );
}

/// A textured scene: dark and bright blobs of several sizes on a grey ground.
fn scene(x: usize, y: usize) -> u8 {
    let mut v = 128.0f64;
    for k in 0..60u64 {
        let h = k.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let (cx, cy) = ((h >> 8) % 256, (h >> 24) % 256);
        let r = 2.0 + ((h >> 40) % 6) as f64;
        let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
        let d2 = (x as f64 - cx as f64).powi(2) + (y as f64 - cy as f64).powi(2);
        v += sign * 90.0 * (-d2 / (2.0 * r * r)).exp();
    }
    v.clamp(0.0, 255.0) as u8
}

fn build(dir: &Path, ortho: &Path, height: HeightSource) -> Result<PathBuf, MapError> {
    let out = dir.join("m.vnm");
    let spec = BuildSpec::new(vec![ortho.to_path_buf()], height);
    build_map(&spec, &out, &mut |_| {}).map(|_| out)
}

// ------------------------------------------------------------------------------------------------
// Item 11: JPEG frames

/// A colour JPEG of a textured scene, and the first byte of its entropy-coded data.
fn textured_jpeg() -> (Vec<u8>, usize) {
    // Waves and noise: texture everywhere, as a camera frame of the ground has.
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    let img = image::RgbImage::from_fn(320, 240, |x, y| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        let v = 128.0 + 60.0 * (x as f32 * 0.11).sin() * (y as f32 * 0.07).cos() + (s % 40) as f32;
        let v = v.clamp(0.0, 255.0) as u8;
        image::Rgb([v, v.wrapping_add(20), v / 2])
    });
    let mut jpg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 90)
        .encode_image(&img)
        .unwrap();
    let sos = jpg.windows(2).position(|w| w == [0xFF, 0xDA]).unwrap();
    let start = sos + 2 + usize::from(u16::from_be_bytes([jpg[sos + 2], jpg[sos + 3]]));
    (jpg, start)
}

/// A flipped bit in a JPEG's entropy-coded data usually desynchronises the Huffman decoding from
/// there on: the `image` crate decodes such a frame leniently (the rest of the picture garbage or
/// filled in) and the fix engine then solved on a partly wrong picture. Every such frame must be
/// refused at decoding, naming the file. Damage is counted on horizontal gradients (what SURF
/// sees): a flipped magnitude bit changes one coefficient (one block) or, in a DC difference, the
/// brightness of the blocks after it by a constant, which no decoder can detect and which moves
/// gradients only along one block edge; a desynchronised stream breaks them everywhere after it.
#[test]
fn bit_flipped_jpeg_frames_are_refused() {
    /// Pixels whose horizontal gradient moved by more than 40 grey levels.
    fn gradient_damage(a: &GrayImage, b: &GrayImage) -> usize {
        let (a, b) = (a.data(), b.data());
        (1..a.len())
            .filter(|&i| ((a[i] - a[i - 1]) - (b[i] - b[i - 1])).abs() > 40.0)
            .count()
    }
    /// More than 16 blocks' worth: beyond what a magnitude flip does.
    const DAMAGED_PX: usize = 16 * 64;
    let dir = tempfile::tempdir().unwrap();
    let (jpg, start) = textured_jpeg();
    let clean_path = dir.path().join("clean.jpg");
    std::fs::write(&clean_path, &jpg).unwrap();
    let clean = GrayImage::load(&clean_path).unwrap();
    let (mut damaging, mut refused) = (0, 0);
    for byte in (start + 8..jpg.len() - 64).step_by(37) {
        let mut b = jpg.clone();
        b[byte] ^= 0x10;
        let Ok(lenient) = image::load_from_memory_with_format(&b, image::ImageFormat::Jpeg) else {
            continue;
        };
        let lenient = GrayImage::from_dynamic(&lenient).unwrap();
        if gradient_damage(&lenient, &clean) <= DAMAGED_PX {
            continue;
        }
        damaging += 1;
        let path = dir.path().join("flipped.jpg");
        std::fs::write(&path, &b).unwrap();
        if let Err(e) = GrayImage::load(&path) {
            let m = e.to_string();
            assert!(m.contains("flipped.jpg") && m.contains("JPEG"), "{m}");
            refused += 1;
        }
    }
    assert!(
        damaging >= 10,
        "only {damaging} damaging flips: the test needs more"
    );
    assert_eq!(
        refused, damaging,
        "{refused} of {damaging} damaged frames refused"
    );
}

// ------------------------------------------------------------------------------------------------
// Item 11: map files edited with their CRC recomputed

/// Recomputes the CRC of a map file image (IEEE CRC-32 of [0, 56) and [60, end), at 56).
fn fix_crc(b: &mut [u8]) {
    let mut h = crc32fast::Hasher::new();
    h.update(&b[..56]);
    h.update(&b[60..]);
    let crc = h.finalize();
    b[56..60].copy_from_slice(&crc.to_le_bytes());
}

/// A map file whose bits are flipped and CRC recomputed passes the checksum: its content must
/// be checked too. Each edit below moves a feature out of its index cell or off the map, puts its
/// height outside the map's heights, breaks its descriptor (no longer a unit vector, or a value
/// the quantiser never writes), its scale, response, Laplacian sign, level or orthophoto index.
#[test]
fn map_files_with_flipped_bits_and_recomputed_crc_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = dir.path().join("o.tif");
    write_u8(&ortho, (256, 256), Geo::Utm, &[], scene);
    let map = build(dir.path(), &ortho, HeightSource::ConstantAmsl(120.0)).unwrap();
    let m = ReferenceMap::open(&map).unwrap();
    let level = &m.header().levels[0];
    assert!(level.n_features >= 10, "{} features", level.n_features);
    let good = std::fs::read(&map).unwrap();
    let data = u64::from_le_bytes(good[24..32].try_into().unwrap()) as usize;
    let rec = data + level.records_offset as usize;
    let desc = data + level.descriptors_offset as usize;
    // (what, byte offset, xor mask)
    let edits: Vec<(&str, usize, u8)> = vec![
        ("x exponent", rec + 7, 0x01),
        ("x by 2^43 ulp (kilometres)", rec + 5, 0x80),
        ("y sign", rec + 8 + 7, 0x80),
        ("z", rec + 16 + 5, 0x20),
        ("z exponent", rec + 16 + 7, 0x10),
        ("scale exponent", rec + 24 + 3, 0x20),
        ("response sign", rec + 28 + 3, 0x80),
        ("descriptor scale", rec + 32 + 3, 0x08),
        ("laplacian", rec + 36, 0x02),
        ("level", rec + 37, 0x01),
        ("ortho index", rec + 38, 0x01),
        ("reserved", rec + 39, 0x01),
        ("descriptor value", desc + 3, 0x40),
        ("descriptor to -128", desc + 5, 0x00),
    ];
    for (what, at, mask) in edits {
        let mut b = good.clone();
        if mask == 0 {
            b[at] = 0x80;
        } else {
            b[at] ^= mask;
        }
        fix_crc(&mut b);
        let path = dir.path().join("edited.vnm");
        std::fs::write(&path, &b).unwrap();
        match ReferenceMap::open(&path) {
            Ok(_) => panic!("{what}: the edited map was accepted"),
            Err(e) => {
                let msg = e.to_string();
                assert!(
                    msg.contains("edited.vnm") && msg.contains("feature"),
                    "{what}: {msg}"
                );
            }
        }
    }
    // The untouched file still opens.
    ReferenceMap::open(&map).unwrap();
}

// ------------------------------------------------------------------------------------------------
// Item 13: map build inputs

/// `--ground-height 1e300` (and other heights no terrain has) is refused, naming the parameter.
#[test]
fn implausible_ground_heights_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = dir.path().join("o.tif");
    write_u8(&ortho, (256, 256), Geo::Utm, &[], scene);
    for h in [1e300, -1e4, 2e4] {
        let e = build(dir.path(), &ortho, HeightSource::ConstantAmsl(h)).unwrap_err();
        let m = e.to_string();
        assert!(m.contains("ground_height"), "{h}: {m}");
    }
    build(dir.path(), &ortho, HeightSource::ConstantAmsl(-400.0)).unwrap();
}

/// A DEM full of 3e38 (float32's largest value, an undeclared nodata value) is not terrain: the
/// load and the build refuse it, naming the file.
#[test]
fn dems_of_implausible_heights_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = dir.path().join("o.tif");
    write_u8(&ortho, (256, 256), Geo::Utm, &[], scene);
    let dem = dir.path().join("dem.tif");
    write_f32(&dem, (256, 256), |_, _| 3e38);
    let Err(e) = load_dem(&dem, None).map(|_| ()) else {
        panic!("a DEM of 3e38 m was loaded")
    };
    let e = e.to_string();
    assert!(e.contains("dem.tif") && e.contains("nodata"), "{e}");
    let e = build(dir.path(), &ortho, HeightSource::Dem(dem.clone()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("dem.tif") && e.contains("nodata"), "{e}");
    // One undeclared nodata corner among real heights: refused too.
    write_f32(
        &dem,
        (256, 256),
        |x, y| if x + y == 0 { -3.4e38 } else { 150.0 },
    );
    assert!(load_dem(&dem, None).map(|_| ()).is_err());
    write_f32(&dem, (256, 256), |x, _| 100.0 + x as f32);
    build(dir.path(), &ortho, HeightSource::Dem(dem)).unwrap();
}

/// An all-black (or uniform) orthophoto gives no feature: an error, and no map file.
#[test]
fn orthophotos_without_features_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (name, v) in [("black.tif", 0u8), ("grey.tif", 128)] {
        let ortho = dir.path().join(name);
        write_u8(&ortho, (256, 256), Geo::Utm, &[], |_, _| v);
        let e = build(dir.path(), &ortho, HeightSource::ConstantAmsl(100.0)).unwrap_err();
        let m = e.to_string();
        assert!(m.contains(name) && m.contains("no features"), "{m}");
        assert!(!dir.path().join("m.vnm").exists());
    }
}

/// An orthophoto in EPSG:4326 (pixel steps in degrees) gets a message that says so and what to
/// do, not "pixels are not square (0.00006 x 0.00004 m)".
#[test]
fn geographic_orthophotos_get_a_reprojection_message() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = dir.path().join("wgs84.tif");
    write_u8(&ortho, (256, 256), Geo::Wgs84, &[], scene);
    let e = build(dir.path(), &ortho, HeightSource::ConstantAmsl(100.0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("wgs84.tif")
            && e.contains("geographic")
            && e.contains("gdalwarp -t_srs EPSG:32610"),
        "{e}"
    );
    assert!(!e.contains("not square"), "{e}");
}

/// A sparse GeoTIFF (tiles stored with 0 bytes, valid for GDAL, which reads them as nodata or 0)
/// loads, the empty tiles as 0, and builds a map.
#[test]
fn sparse_geotiff_tiles_read_as_zero() {
    let dir = tempfile::tempdir().unwrap();
    let ortho = dir.path().join("sparse.tif");
    // 8 x 8 tiles of 32 px; tiles 0 and 9 empty.
    write_u8(&ortho, (256, 256), Geo::Utm, &[0, 9], scene);
    let r = load_geotiff(&ortho, None).unwrap();
    let RasterData::U8(v) = r.data() else {
        panic!("u8 expected")
    };
    let at = |x: usize, y: usize| v[y * 256 + x];
    assert_eq!(at(0, 0), 0);
    assert_eq!(at(31, 31), 0);
    assert_eq!(at(40, 40), 0); // tile 9 = (1, 1)
    assert_eq!(at(100, 100), scene(100, 100));
    assert_eq!(at(32, 0), scene(32, 0));
    let map = build(dir.path(), &ortho, HeightSource::ConstantAmsl(100.0)).unwrap();
    assert!(ReferenceMap::open(&map).unwrap().header().levels[0].n_features > 0);
    // The windowed reader (large orthophotos) reads the same.
    let mut w = visnav_io::geo::window::open_geotiff_window(&ortho, None).unwrap();
    let win = w.read_window(0, 0, 64, 64).unwrap();
    let RasterData::U8(wv) = win.data() else {
        panic!("u8 expected")
    };
    assert_eq!(wv[0], 0);
    assert_eq!(wv[40 * 64 + 40], 0);
    assert_eq!(wv[33], scene(33, 0));
}
