//! Windowed GeoTIFF reading (`geo::window`) against the whole-image decode (`load_geotiff`):
//! synthetic files of every sample type and layout the reader supports (stripped / tiled, chunky /
//! planar, uncompressed / deflate / LZW, horizontal predictor), random and edge windows, windows
//! outside the image, truncated and corrupted files, the real files in ../shared/data, and
//! `map::build::level_window_from_reader` against `level_window` on the whole image.
//!
//! `write_large_tiled_geotiff` (ignored) writes the large tiled GeoTIFF used for the memory
//! measurement in docs/map-format.md.
#![allow(clippy::unwrap_used, clippy::expect_used)] // a test: a failed expect is a failed test

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use tiff::encoder::TiffEncoder;
use tiff::encoder::compression::{CompressionAlgorithm, Deflate, DeflateLevel, Lzw};
use tiff::tags::Tag;
use visnav_core::geo::raster::{Raster, RasterData};
use visnav_io::geo::geotiff::{GeoTiffError, load_geotiff};
use visnav_io::geo::window::{GeoTiffWindowReader, open_geotiff_window};
use visnav_io::map::build::{level_window, level_window_from_reader};

/// A sample type the test writer can store.
trait Sample: Copy {
    const BITS: u16;
    /// SampleFormat: 1 unsigned, 2 signed, 3 float.
    const FORMAT: u16;
    fn from_seed(v: u64) -> Self;
    fn push_le(self, out: &mut Vec<u8>);
    /// `self - prev` for the horizontal predictor (integers only).
    fn diff(self, prev: Self) -> Self;
}

macro_rules! int_sample {
    ($t:ty, $format:expr) => {
        impl Sample for $t {
            const BITS: u16 = 8 * std::mem::size_of::<$t>() as u16;
            const FORMAT: u16 = $format;
            fn from_seed(v: u64) -> Self {
                v as $t
            }
            fn push_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn diff(self, prev: Self) -> Self {
                self.wrapping_sub(prev)
            }
        }
    };
}
int_sample!(u8, 1);
int_sample!(u16, 1);
int_sample!(i16, 2);
int_sample!(u32, 1);
int_sample!(i32, 2);

macro_rules! float_sample {
    ($t:ty) => {
        impl Sample for $t {
            const BITS: u16 = 8 * std::mem::size_of::<$t>() as u16;
            const FORMAT: u16 = 3;
            fn from_seed(v: u64) -> Self {
                (v % 100_000) as $t * 0.25 - 1000.0
            }
            fn push_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn diff(self, _prev: Self) -> Self {
                unreachable!("no horizontal predictor for floats in these tests")
            }
        }
    };
}
float_sample!(f32);
float_sample!(f64);

#[derive(Clone, Copy, Debug, PartialEq)]
enum Comp {
    None,
    Deflate,
    Lzw,
}

#[derive(Clone, Copy, Debug)]
struct Layout {
    /// Tile size, or `None` for strips of `rows_per_strip` rows.
    tile: Option<(usize, usize)>,
    rows_per_strip: usize,
    planar: bool,
    comp: Comp,
    /// Horizontal differencing predictor (2).
    predictor: bool,
}

/// Small deterministic generator (64-bit LCG, high bits).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 16
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// GeoTIFF tags: UTM 10N, 2 m pixels, optional GDAL_NODATA.
pub(crate) fn geo_tags<W: std::io::Write + std::io::Seek>(
    d: &mut tiff::encoder::DirectoryEncoder<'_, W, tiff::encoder::TiffKindStandard>,
    nodata: Option<&str>,
) {
    geo_tags_at(d, nodata, 2.0, (494_000.0, 4_878_000.0));
}

/// GeoTIFF tags: UTM 10N, `pixel_m` pixels, the top-left corner at `origin` (x, y metres),
/// optional GDAL_NODATA.
fn geo_tags_at<W: std::io::Write + std::io::Seek>(
    d: &mut tiff::encoder::DirectoryEncoder<'_, W, tiff::encoder::TiffKindStandard>,
    nodata: Option<&str>,
    pixel_m: f64,
    origin: (f64, f64),
) {
    d.write_tag(Tag::ModelPixelScaleTag, &[pixel_m, pixel_m, 0.0][..])
        .unwrap();
    d.write_tag(
        Tag::ModelTiepointTag,
        &[0.0f64, 0.0, 0.0, origin.0, origin.1, 0.0][..],
    )
    .unwrap();
    let keys: [u16; 16] = [1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32610];
    d.write_tag(Tag::GeoKeyDirectoryTag, &keys[..]).unwrap();
    if let Some(n) = nodata {
        d.write_tag(Tag::GdalNodata, n).unwrap();
    }
}

/// Writes a GeoTIFF with any layout the reader supports; the `w x h x bands` samples are
/// given as `pixel(x, y, band)` (so the large-file writer needs no image buffer).
fn write_geotiff<T: Sample>(
    path: &Path,
    w: usize,
    h: usize,
    bands: usize,
    layout: Layout,
    nodata: Option<&str>,
    pixel: impl Fn(usize, usize, usize) -> T,
) {
    let at = (2.0, (494_000.0, 4_878_000.0));
    write_geotiff_at(path, w, h, bands, layout, nodata, at, pixel);
}

/// [`write_geotiff`] with its pixel size and top-left corner `(pixel_m, (x, y))`.
#[allow(clippy::too_many_arguments)]
fn write_geotiff_at<T: Sample>(
    path: &Path,
    w: usize,
    h: usize,
    bands: usize,
    layout: Layout,
    nodata: Option<&str>,
    (pixel_m, origin): (f64, (f64, f64)),
    pixel: impl Fn(usize, usize, usize) -> T,
) {
    let file = BufWriter::new(File::create(path).unwrap());
    let mut enc = TiffEncoder::new(file).unwrap();
    let mut d = enc.image_directory().unwrap();
    let (cw, ch) = layout.tile.unwrap_or((w, layout.rows_per_strip.min(h)));
    let (across, down) = (w.div_ceil(cw), h.div_ceil(ch));
    let planes = if layout.planar { bands } else { 1 };
    let spc = if layout.planar { 1 } else { bands };
    let (mut offsets, mut counts) = (Vec::new(), Vec::new());
    let mut raw = Vec::new();
    for plane in 0..planes {
        for ty in 0..down {
            for tx in 0..across {
                let (x0, y0) = (tx * cw, ty * ch);
                // Tiles are always full size (zero padded); strips end at the image.
                let (dw, dh) = if layout.tile.is_some() {
                    (cw, ch)
                } else {
                    (w, ch.min(h - y0))
                };
                let mut samples: Vec<T> = Vec::with_capacity(dw * dh * spc);
                for y in y0..y0 + dh {
                    for x in x0..x0 + dw {
                        for s in 0..spc {
                            let band = if layout.planar { plane } else { s };
                            samples.push(if x < w && y < h {
                                pixel(x, y, band)
                            } else {
                                T::from_seed(0)
                            });
                        }
                    }
                }
                if layout.predictor {
                    for row in samples.chunks_exact_mut(dw * spc) {
                        for i in (spc..row.len()).rev() {
                            row[i] = row[i].diff(row[i - spc]);
                        }
                    }
                }
                raw.clear();
                for s in &samples {
                    s.push_le(&mut raw);
                }
                let mut bytes = Vec::new();
                match layout.comp {
                    Comp::None => bytes.extend_from_slice(&raw),
                    Comp::Deflate => {
                        Deflate::with_level(DeflateLevel::Fast)
                            .write_to(&mut bytes, &raw)
                            .unwrap();
                    }
                    Comp::Lzw => {
                        Lzw.write_to(&mut bytes, &raw).unwrap();
                    }
                }
                offsets.push(u32::try_from(d.write_data(&bytes[..]).unwrap()).unwrap());
                counts.push(bytes.len() as u32);
            }
        }
    }
    d.write_tag(Tag::ImageWidth, w as u32).unwrap();
    d.write_tag(Tag::ImageLength, h as u32).unwrap();
    d.write_tag(Tag::BitsPerSample, &vec![T::BITS; bands][..])
        .unwrap();
    let comp: u16 = match layout.comp {
        Comp::None => 1,
        Comp::Deflate => 8,
        Comp::Lzw => 5,
    };
    d.write_tag(Tag::Compression, comp).unwrap();
    d.write_tag(
        Tag::PhotometricInterpretation,
        if bands >= 3 { 2u16 } else { 1 },
    )
    .unwrap();
    // 4 bands: RGB without ExtraSamples, as the NAIP files (the tiff crate would drop an
    // ExtraSamples = unspecified band).
    d.write_tag(Tag::SamplesPerPixel, bands as u16).unwrap();
    d.write_tag(
        Tag::PlanarConfiguration,
        if layout.planar { 2u16 } else { 1 },
    )
    .unwrap();
    d.write_tag(Tag::SampleFormat, &vec![T::FORMAT; bands][..])
        .unwrap();
    if layout.predictor {
        d.write_tag(Tag::Predictor, 2u16).unwrap();
    }
    if layout.tile.is_some() {
        d.write_tag(Tag::TileWidth, cw as u32).unwrap();
        d.write_tag(Tag::TileLength, ch as u32).unwrap();
        d.write_tag(Tag::TileOffsets, &offsets[..]).unwrap();
        d.write_tag(Tag::TileByteCounts, &counts[..]).unwrap();
    } else {
        d.write_tag(Tag::RowsPerStrip, ch as u32).unwrap();
        d.write_tag(Tag::StripOffsets, &offsets[..]).unwrap();
        d.write_tag(Tag::StripByteCounts, &counts[..]).unwrap();
    }
    geo_tags_at(&mut d, nodata, pixel_m, origin);
    d.finish().unwrap();
}

/// Samples of the `w x h` window at `(c0, r0)` of a whole raster.
fn sub(r: &Raster, c0: usize, r0: usize, w: usize, h: usize) -> RasterData {
    fn rows<T: Copy>(
        v: &[T],
        width: usize,
        b: usize,
        (c0, r0, w, h): (usize, usize, usize, usize),
    ) -> Vec<T> {
        (r0..r0 + h)
            .flat_map(|y| {
                let s = (y * width + c0) * b;
                v[s..s + w * b].to_vec()
            })
            .collect()
    }
    let (width, b, win) = (r.width(), r.bands(), (c0, r0, w, h));
    match r.data() {
        RasterData::U8(v) => RasterData::U8(rows(v, width, b, win)),
        RasterData::U16(v) => RasterData::U16(rows(v, width, b, win)),
        RasterData::F32(v) => RasterData::F32(rows(v, width, b, win)),
    }
}

/// `read_window` == the same part of the whole image: samples (bit for bit), size, bands, CRS,
/// nodata, sample type, and the window's geotransform.
fn check_window<R: std::io::Read + std::io::Seek + Send>(
    rd: &mut GeoTiffWindowReader<R>,
    whole: &Raster,
    (c0, r0, w, h): (usize, usize, usize, usize),
    what: &str,
) {
    let win = rd
        .read_window(c0, r0, w, h)
        .unwrap_or_else(|e| panic!("{what}: window {c0},{r0} {w}x{h}: {e}"));
    assert_eq!((win.width(), win.height()), (w, h), "{what}");
    assert_eq!(win.bands(), whole.bands(), "{what}");
    assert_eq!(win.crs(), whole.crs(), "{what}");
    assert_eq!(win.nodata(), whole.nodata(), "{what}");
    assert_eq!(win.source_type(), whole.source_type(), "{what}");
    let want = sub(whole, c0, r0, w, h);
    // Bit-level equality (NaN-safe) through the debug representation of equal-length data.
    let same = match (win.data(), &want) {
        (RasterData::U8(a), RasterData::U8(b)) => a == b,
        (RasterData::U16(a), RasterData::U16(b)) => a == b,
        (RasterData::F32(a), RasterData::F32(b)) => {
            a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()) && a.len() == b.len()
        }
        _ => false,
    };
    assert!(same, "{what}: window {c0},{r0} {w}x{h} differs");
    let (gc, wc) = (whole.transform().coeffs(), win.transform().coeffs());
    assert_eq!(
        (wc[0], wc[3]),
        whole.transform().pixel_to_map(c0 as f64, r0 as f64),
        "{what}"
    );
    assert_eq!((wc[1], wc[2], wc[4], wc[5]), (gc[1], gc[2], gc[4], gc[5]));
    let (x, y) = win.transform().pixel_to_map(0.5, 0.5);
    let (col, row) = win.transform().map_to_pixel(x, y);
    assert!(
        (col - 0.5).abs() < 1e-6 && (row - 0.5).abs() < 1e-6,
        "{what}"
    );
}

/// Random windows plus the edge cases: the whole image, one pixel at each corner, the last row
/// and column, windows crossing chunk borders.
fn windows(w: usize, h: usize, n: usize, seed: u64) -> Vec<(usize, usize, usize, usize)> {
    let mut rng = Lcg(seed);
    let mut v = vec![
        (0, 0, w, h),
        (0, 0, 1, 1),
        (w - 1, h - 1, 1, 1),
        (w - 1, 0, 1, h),
        (0, h - 1, w, 1),
        (w / 3, h / 3, w - w / 3, h - h / 3),
    ];
    for _ in 0..n {
        let c0 = rng.below(w);
        let r0 = rng.below(h);
        let ww = 1 + rng.below(w - c0);
        let hh = 1 + rng.below(h - r0);
        v.push((c0, r0, ww, hh));
    }
    v
}

fn check_file(path: &Path, n_random: usize, what: &str) {
    let whole = load_geotiff(path, None).unwrap_or_else(|e| panic!("{what}: {e}"));
    let mut rd = open_geotiff_window(path, None).unwrap();
    let info = rd.info().clone();
    assert_eq!((info.width, info.height), (whole.width(), whole.height()));
    assert_eq!(info.bands, whole.bands());
    assert_eq!(&info.transform, whole.transform());
    assert_eq!(info.bounds(), whole.bounds());
    for (i, win) in windows(info.width, info.height, n_random, 7 + n_random as u64)
        .into_iter()
        .enumerate()
    {
        // Alternate cached and uncached reads, and 1 to 3 decoding threads.
        rd.set_cache_bytes(if i % 3 == 2 { 0 } else { 1 << 20 });
        rd.set_decode_threads(1 + i % 4 / 2 * 2).unwrap();
        check_window(&mut rd, &whole, win, what);
    }
}

fn layouts() -> Vec<Layout> {
    let l = |tile, rows_per_strip, planar, comp, predictor| Layout {
        tile,
        rows_per_strip,
        planar,
        comp,
        predictor,
    };
    vec![
        l(None, 7, false, Comp::Deflate, false),
        l(None, 1, false, Comp::None, false),
        l(None, 1000, false, Comp::Lzw, false),
        l(None, 5, true, Comp::Lzw, false),
        l(Some((16, 16)), 0, false, Comp::None, false),
        l(Some((32, 16)), 0, true, Comp::Deflate, false),
        // LZW only in strips: tiles written by the tiff crate's LZW encoder sometimes fail its
        // own decoder ("no lzw end code found"), whole image or window alike.
        l(Some((16, 32)), 0, false, Comp::None, false),
    ]
}

fn check_type<T: Sample>(name: &str, predictor_ok: bool) {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (75, 53);
    let mut all = layouts();
    if predictor_ok {
        all.push(Layout {
            tile: Some((16, 16)),
            rows_per_strip: 0,
            planar: false,
            comp: Comp::Deflate,
            predictor: true,
        });
        all.push(Layout {
            tile: None,
            rows_per_strip: 4,
            planar: false,
            comp: Comp::Lzw,
            predictor: true,
        });
    }
    for (li, layout) in all.into_iter().enumerate() {
        for bands in [1usize, 3, 4] {
            if bands == 1 && layout.planar {
                continue;
            }
            let p = dir.path().join(format!("{name}_{li}_{bands}.tif"));
            let seed = (li * 10 + bands) as u64;
            write_geotiff::<T>(&p, w, h, bands, layout, Some("0"), |x, y, b| {
                let mut g = Lcg(seed ^ ((y * w + x) * 8 + b) as u64);
                T::from_seed(g.next())
            });
            check_file(&p, 25, &format!("{name} {layout:?} {bands} bands"));
        }
    }
}

#[test]
fn windows_match_the_whole_image_for_every_sample_type_and_layout() {
    check_type::<u8>("u8", true);
    check_type::<u16>("u16", true);
    check_type::<i16>("i16", true);
    check_type::<u32>("u32", false);
    check_type::<i32>("i32", false);
    check_type::<f32>("f32", false);
    check_type::<f64>("f64", false);
}

#[test]
fn only_the_chunks_under_the_window_are_decoded_and_cached() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("tiled.tif");
    let layout = Layout {
        tile: Some((16, 16)),
        rows_per_strip: 0,
        planar: true,
        comp: Comp::Deflate,
        predictor: false,
    };
    write_geotiff::<u8>(&p, 100, 70, 3, layout, None, |x, y, b| {
        (x * 7 + y * 3 + b) as u8
    });
    let mut rd = open_geotiff_window(&p, None).unwrap();
    rd.set_cache_bytes(0);
    // Inside tile (1, 1): one chunk per plane.
    rd.read_window(17, 18, 10, 10).unwrap();
    assert_eq!(rd.chunks_decoded(), 3);
    // Across 2 x 2 tiles: 4 per plane; uncached, the same window costs them again.
    rd.read_window(10, 10, 20, 20).unwrap();
    assert_eq!(rd.chunks_decoded(), 3 + 12);
    rd.read_window(10, 10, 20, 20).unwrap();
    assert_eq!(rd.chunks_decoded(), 3 + 24);
    assert_eq!(rd.cached_bytes(), 0);
    // Cached: the second read decodes nothing; the cache stays within its bound and evicts the
    // least recently used chunks (one 16 x 16 u8 plane chunk is 256 bytes).
    rd.set_cache_bytes(12 * 256);
    rd.read_window(10, 10, 20, 20).unwrap();
    assert_eq!(rd.chunks_decoded(), 27 + 12);
    assert_eq!(rd.cached_bytes(), 12 * 256);
    rd.read_window(10, 10, 20, 20).unwrap();
    assert_eq!(rd.chunks_decoded(), 39);
    rd.read_window(40, 40, 5, 5).unwrap(); // 3 new chunks evict 3
    assert_eq!(rd.chunks_decoded(), 42);
    assert_eq!(rd.cached_bytes(), 12 * 256);
    rd.set_cache_bytes(256);
    assert!(rd.cached_bytes() <= 256);
    // Parallel decoding: the same chunks are decoded, once each.
    rd.set_cache_bytes(0);
    rd.set_decode_threads(3).unwrap();
    let n0 = rd.chunks_decoded();
    let par = rd.read_window(10, 10, 20, 20).unwrap();
    assert_eq!(rd.chunks_decoded(), n0 + 12);
    rd.set_decode_threads(1).unwrap();
    assert_eq!(rd.read_window(10, 10, 20, 20).unwrap(), par);
    // Whole image through the reader == load_geotiff.
    let whole = load_geotiff(&p, None).unwrap();
    assert_eq!(rd.read_window(0, 0, 100, 70).unwrap(), whole);
}

#[test]
fn windows_outside_the_image_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("small_image.tif");
    let layout = Layout {
        tile: None,
        rows_per_strip: 3,
        planar: false,
        comp: Comp::None,
        predictor: false,
    };
    write_geotiff::<u16>(&p, 10, 8, 1, layout, None, |x, y, _| (x + 10 * y) as u16);
    let mut rd = open_geotiff_window(&p, None).unwrap();
    for (c0, r0, w, h) in [
        (9, 0, 2, 1),
        (0, 7, 1, 2),
        (10, 0, 1, 1),
        (0, 0, 0, 1),
        (0, 0, 1, 0),
        (usize::MAX, 0, 2, 1),
        (0, usize::MAX, 1, 2),
        (0, 0, 11, 8),
    ] {
        let e = rd.read_window(c0, r0, w, h).unwrap_err();
        assert!(matches!(e, GeoTiffError::Window { .. }), "{e:?}");
        let msg = e.to_string();
        assert!(
            msg.contains("small_image.tif") && msg.contains("10 x 8"),
            "{msg}"
        );
    }
    // The reader is still usable afterwards.
    let r = rd.read_window(9, 7, 1, 1).unwrap();
    assert_eq!(r.sample(0, 0, 0), Some(79.0));
}

#[test]
fn truncated_and_corrupted_files_are_errors_never_panics() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("full.tif");
    let layout = Layout {
        tile: Some((16, 16)),
        rows_per_strip: 0,
        planar: false,
        comp: Comp::Deflate,
        predictor: true,
    };
    write_geotiff::<u8>(&p, 64, 48, 3, layout, Some("0"), |x, y, b| {
        ((x * x + y * 5 + b * 40) % 251) as u8
    });
    let bytes = std::fs::read(&p).unwrap();
    let whole = load_geotiff(&p, None).unwrap();
    let mut rng = Lcg(99);
    // The pixel data comes first (the directory is written last): cutting anywhere makes the
    // header unreadable, and cutting off the directory's out-of-line values too.
    for cut in [
        0,
        8,
        100,
        bytes.len() / 2,
        bytes.len() - 200,
        bytes.len() - 1,
    ] {
        let q = dir.path().join(format!("cut{cut}.tif"));
        std::fs::write(&q, &bytes[..cut]).unwrap();
        let e = open_geotiff_window(&q, None)
            .and_then(|mut r| r.read_window(0, 0, 64, 48))
            .expect_err("a truncated file must not read");
        assert!(e.to_string().contains(&format!("cut{cut}.tif")), "{e}");
    }
    // Corrupted chunk data (header intact): every window either matches the file as written
    // (corruption elsewhere) or fails naming the file; nothing panics.
    let data_end = bytes.len() / 2;
    for k in 0..20 {
        let mut b = bytes.clone();
        let at = 8 + rng.below(data_end - 8);
        for j in 0..8 {
            if let Some(v) = b.get_mut(at + j) {
                *v ^= 0x5a ^ (k as u8);
            }
        }
        let q = dir.path().join(format!("corrupt{k}.tif"));
        std::fs::write(&q, &b).unwrap();
        let mut rd = open_geotiff_window(&q, None).unwrap();
        for (c0, r0, w, h) in windows(64, 48, 5, k) {
            match rd.read_window(c0, r0, w, h) {
                Ok(r) => assert_eq!((r.width(), r.height()), (w, h)),
                Err(e) => assert!(e.to_string().contains(&format!("corrupt{k}.tif")), "{e}"),
            }
        }
    }
    // A first chunk that is not a deflate stream at all.
    let mut rd = open_geotiff_window(&p, None).unwrap();
    check_window(&mut rd, &whole, (0, 0, 64, 48), "intact");
    let q = dir.path().join("short_data.tif");
    let mut b = bytes.clone();
    b[8..40].fill(0xff);
    std::fs::write(&q, &b).unwrap();
    let e = open_geotiff_window(&q, None)
        .unwrap()
        .read_window(0, 0, 4, 4)
        .unwrap_err();
    assert!(e.to_string().contains("short_data.tif"), "{e}");
}

fn shared(rel: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join("../shared/data")
        .join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("skipping {}: absent", p.display());
        None
    }
}

/// Every real GeoTIFF (deflate + predictor tiles, JPEG YCbCr, tiled planar, strips, f32 DEMs):
/// random windows equal the whole-image decode.
#[test]
fn real_files_windows_match_the_whole_image() {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut files: Vec<PathBuf> = vec![
        repo.join("sitl/maps/naip_nd_2009.tif"),
        repo.join("sitl/maps/naip_nd_2014.tif"),
    ];
    for rel in [
        "naip_nd/m_4709963_se_14_1_20100629.tif",
        "naip_nd/m_4709963_se_14_1_20120731.tif",
        "ngi_3324c/ngi_ortho_5m_tile1.tif",
        "ngi_3324c/ngi_ortho_5m_tile2.tif",
        "ngi_3324c/sentinel2_b432_byte.tif",
        "ngi_3324c/dem.tif",
        "autzen/autzen_ortho_0p3m_utm10n.tif",
        "autzen/autzen_dsm_1m_utm10n.tif",
    ] {
        files.extend(shared(rel));
    }
    for f in &files {
        let t0 = std::time::Instant::now();
        check_file(f, 12, &f.display().to_string());
        eprintln!(
            "{}: 18 windows checked in {:.2} s",
            f.file_name().unwrap().to_string_lossy(),
            t0.elapsed().as_secs_f64()
        );
    }
}

/// `level_window_from_reader` (banded, windowed) is bit-identical to `level_window` on the
/// whole decoded image, at every level, for band budgets from one block row to everything.
#[test]
fn banded_level_windows_equal_the_whole_image_ones() {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut files = vec![repo.join("sitl/maps/naip_nd_2009.tif")];
    files.extend(shared("autzen/autzen_ortho_0p3m_utm10n.tif"));
    files.extend(shared("ngi_3324c/ngi_ortho_5m_tile1.tif"));
    let mut rng = Lcg(5);
    for f in &files {
        let whole = load_geotiff(f, None).unwrap();
        let mut rd = open_geotiff_window(f, None).unwrap();
        for level in 0..5 {
            let (lw, lh) = (whole.width() >> level, whole.height() >> level);
            for _ in 0..4 {
                let x0 = rng.below(lw);
                let y0 = rng.below(lh);
                let w = 1 + rng.below((lw - x0).min(300));
                let h = 1 + rng.below((lh - y0).min(300));
                let (g, v) = level_window(&whole, level, x0, y0, w, h);
                for band_bytes in [0, 100_000, 1 << 40] {
                    let (g2, v2) =
                        level_window_from_reader(&mut rd, level, x0, y0, w, h, band_bytes).unwrap();
                    assert!(
                        g.iter().zip(&g2).all(|(a, b)| a.to_bits() == b.to_bits())
                            && g.len() == g2.len()
                            && v == v2,
                        "{}: level {level} window {x0},{y0} {w}x{h} band {band_bytes}",
                        f.display()
                    );
                }
            }
        }
    }
}

/// Writes a large tiled (256 x 256, deflate) RGB GeoTIFF made by mirror-tiling the NAIP 2009
/// excerpt (or a mosaic of them), for the memory and time measurements of `visnav map build`
/// (docs/map-format.md). Run with `VISNAV_LARGE_TIFF=/tmp/large.tif [VISNAV_LARGE_PX=20000]
/// [VISNAV_LARGE_PIXEL_M=2] [VISNAV_LARGE_FILES=1] cargo nextest run -p visnav-io --test
/// integration --run-ignored ignored-only -E 'test(/write_large_tiled_geotiff/)'`.
#[test]
#[ignore = "writes a large file; for the memory measurement"]
fn write_large_tiled_geotiff() {
    let Some(out) = std::env::var_os("VISNAV_LARGE_TIFF") else {
        eprintln!("skipping: set VISNAV_LARGE_TIFF to the output path");
        return;
    };
    let px: usize = std::env::var("VISNAV_LARGE_PX")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_000);
    let src = load_geotiff(
        &PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../..")
            .join("sitl/maps/naip_nd_2009.tif"),
        None,
    )
    .unwrap();
    let (sw, sh, sb) = (src.width(), src.height(), src.bands());
    let s = src.data().as_u8().unwrap().to_vec();
    // Mirror tiling: no seams.
    let mirror = |v: usize, n: usize| {
        let p = v % (2 * n);
        if p < n { p } else { 2 * n - 1 - p }
    };
    let layout = Layout {
        tile: Some((256, 256)),
        rows_per_strip: 0,
        planar: false,
        comp: Comp::Deflate,
        predictor: true,
    };
    // A mosaic of n x n files (`VISNAV_LARGE_FILES=n`, named `OUT_{col}_{row}.tif`) of
    // `VISNAV_LARGE_PIXEL_M` pixels (default 2 m), the pattern running on across them: a list of
    // GeoTIFFs covering one area, as a country's orthophoto comes.
    let pixel_m: f64 = std::env::var("VISNAV_LARGE_PIXEL_M")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2.0);
    let n: usize = std::env::var("VISNAV_LARGE_FILES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let out = PathBuf::from(out);
    let jobs: Vec<(usize, usize)> = (0..n).flat_map(|r| (0..n).map(move |c| (c, r))).collect();
    jobs.par_iter().for_each(|&(col, row)| {
        let path = if n == 1 {
            out.clone()
        } else {
            out.with_file_name(format!(
                "{}_{col}_{row}.tif",
                out.file_stem().unwrap().to_string_lossy()
            ))
        };
        let t0 = std::time::Instant::now();
        let origin = (
            494_000.0 + (col * px) as f64 * pixel_m,
            4_878_000.0 - (row * px) as f64 * pixel_m,
        );
        let (dx, dy) = (col * px, row * px);
        write_geotiff_at::<u8>(
            &path,
            px,
            px,
            3,
            layout,
            Some("0"),
            (pixel_m, origin),
            |x, y, b| s[(mirror(y + dy, sh) * sw + mirror(x + dx, sw)) * sb + b],
        );
        eprintln!(
            "{}: {px} x {px} RGB at {pixel_m} m, {} bytes, written in {:.1} s",
            path.display(),
            std::fs::metadata(&path).unwrap().len(),
            t0.elapsed().as_secs_f64()
        );
    });
}
