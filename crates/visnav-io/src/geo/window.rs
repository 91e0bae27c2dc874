//! Windowed GeoTIFF reading: decode only the strips/tiles under a pixel window.
//!
//! [`GeoTiffWindowReader`] opens a GeoTIFF, parses its tags, GeoKeys, CRS, geotransform and nodata
//! exactly as [`super::geotiff::load_geotiff`] does (the same code: `geotiff_info::read_info`), and then
//! [`GeoTiffWindowReader::read_window`] returns the [`Raster`] of pixels
//! `col0 .. col0 + width` x `row0 .. row0 + height`, decoding only the chunks (strips or tiles,
//! every plane of a planar file) that intersect the window. `load_geotiff` is the special case of
//! the whole image: both go through [`GeoTiffWindowReader::read_window`], so a window is
//! sample-for-sample the same as the corresponding part of the whole-image decode.
//!
//! Supported: what `load_geotiff` supports (stripped or tiled, chunky or planar, 8/16/32/64-bit
//! integer and 32/64-bit float samples, any compression the `tiff` crate decodes, predictors as
//! the crate applies them, YCbCr converted to RGB with the JFIF equations).
//!
//! Conventions:
//! * pixel `(col, row)` of the window is pixel `(col0 + col, row0 + row)` of the image; the
//!   returned raster's geotransform is the image's with the origin moved to the window's top-left
//!   corner ([`GeoTransform::window`]), so map coordinates are unchanged;
//! * a window must be non-empty and lie wholly inside the image: anything else is an error
//!   ([`GeoTiffError::Window`]) naming the file, the window and the image size; windows are never
//!   clipped or padded silently; a window is at most [`MAX_DECODED_BYTES`] decoded;
//! * samples are stored as `load_geotiff` stores them (u8, u16, else f32), with the file's sample
//!   type recorded; every chunk of a file must have the same sample type.
//!
//! Memory: the window itself, plus one decoded chunk, plus a bounded LRU cache of decoded chunks
//! ([`DEFAULT_CACHE_BYTES`], settable with [`GeoTiffWindowReader::set_cache_bytes`]; 0 disables
//! it) so that overlapping windows (tile margins) do not decode the same chunk again. A chunk is
//! decoded whole by the `tiff` crate, so a file stored as one huge strip still costs that strip:
//! memory is bounded by the chunk size, which GDAL-made tiled files keep small (256 x 256).
//!
//! Malformed files never panic: decoder errors are returned naming the file, and a panic inside
//! the `tiff` crate is caught (as in `load_geotiff`) and reported as [`GeoTiffError::Decode`];
//! after such a panic the reader refuses further reads (its decoder state is unknown).

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tiff::decoder::{Decoder, DecodingResult};

use super::geotiff_info::{
    GeoTiffError, GeoTiffInfo, MAX_DECODED_BYTES, YCBCR_ONLY_RGB8, guarded, new_decoder, read_info,
    ycbcr_to_rgb_in_place,
};
use visnav_core::geo::Crs;
use visnav_core::geo::raster::{GeoTransform, Raster, RasterData, SampleType};

/// Default bound of the decoded-chunk cache, bytes.
pub const DEFAULT_CACHE_BYTES: usize = 64 << 20;
/// Largest empty (sparse, byte count 0) chunk filled with nodata, bytes: 256 MiB, the tiff
/// crate's default decoding buffer limit (a real chunk's data is bounded by that too).
pub const MAX_EMPTY_CHUNK_BYTES: usize = 256 << 20;

/// Opens `path` for windowed reading. `crs_override` as for `load_geotiff`.
pub fn open_geotiff_window(
    path: &Path,
    crs_override: Option<Crs>,
) -> Result<GeoTiffWindowReader<BufReader<File>>, GeoTiffError> {
    let file =
        crate::files::open_regular(path, "a GeoTIFF").map_err(|source| GeoTiffError::Io {
            path: path.to_path_buf(),
            cause: source,
        })?;
    GeoTiffWindowReader::new(BufReader::new(file), path, crs_override)
}

/// A GeoTIFF opened for reading pixel windows (see the module doc).
pub struct GeoTiffWindowReader<R: Read + Seek + Send> {
    dec: Decoder<R>,
    /// More decoders on their own handles of the file: `read_window` decodes the chunks it
    /// misses in parallel, one group per decoder ([`GeoTiffWindowReader::set_decode_threads`]).
    helpers: Vec<Decoder<R>>,
    path: PathBuf,
    info: GeoTiffInfo,
    cache: ChunkCache,
    /// Sample type of the chunks decoded so far (all must agree).
    sample_type: Option<SampleType>,
    /// A decoder panic was caught: the decoder state is unknown, refuse further reads.
    poisoned: bool,
    chunks_decoded: u64,
    /// Chunks stored with 0 bytes (TileByteCounts / StripByteCounts = 0): a sparse file's empty
    /// tiles, which GDAL reads as the nodata value (0 without one). Read the same way here.
    empty_chunks: std::collections::HashSet<u32>,
}

impl<R: Read + Seek + Send> std::fmt::Debug for GeoTiffWindowReader<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GeoTiffWindowReader")
            .field("path", &self.path)
            .field("info", &self.info)
            .field("cached_bytes", &self.cache.bytes)
            .field("chunks_decoded", &self.chunks_decoded)
            .finish_non_exhaustive()
    }
}

impl<R: Read + Seek + Send> GeoTiffWindowReader<R> {
    /// Parses the header of the first image of `reader`; `path` is used in error messages only.
    pub fn new(reader: R, path: &Path, crs_override: Option<Crs>) -> Result<Self, GeoTiffError> {
        guarded(path, || Self::new_unguarded(reader, path, crs_override))
    }

    /// [`Self::new`] without the panic guard (the caller holds one).
    pub(crate) fn new_unguarded(
        reader: R,
        path: &Path,
        crs_override: Option<Crs>,
    ) -> Result<Self, GeoTiffError> {
        let mut dec = new_decoder(reader, path)?;
        let info = read_info(&mut dec, path, crs_override)?;
        let (counts_tag, counts_name) = if info.tiled {
            (tiff::tags::Tag::TileByteCounts, "TileByteCounts")
        } else {
            (tiff::tags::Tag::StripByteCounts, "StripByteCounts")
        };
        let empty_chunks = dec
            .find_tag_unsigned_vec::<u64>(counts_tag)
            .map_err(|e| GeoTiffError::Decode {
                path: path.to_path_buf(),
                reason: format!("{counts_name}: {e}"),
            })?
            .unwrap_or_default()
            .iter()
            .enumerate()
            .filter(|&(_, &n)| n == 0)
            .filter_map(|(i, _)| u32::try_from(i).ok())
            .collect();
        Ok(Self {
            dec,
            helpers: Vec::new(),
            path: path.to_path_buf(),
            info,
            cache: ChunkCache::new(DEFAULT_CACHE_BYTES),
            sample_type: None,
            poisoned: false,
            chunks_decoded: 0,
            empty_chunks,
        })
    }

    /// Size, layout and georeferencing of the image.
    pub fn info(&self) -> &GeoTiffInfo {
        &self.info
    }

    /// The file name used in errors.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bounds the decoded-chunk cache to `bytes` (evicting least recently used chunks now);
    /// 0 disables caching.
    pub fn set_cache_bytes(&mut self, bytes: usize) {
        self.cache.capacity = bytes;
        self.cache.evict_to(bytes);
    }

    /// Bytes currently held by the chunk cache.
    pub fn cached_bytes(&self) -> usize {
        self.cache.bytes
    }

    /// Number of chunk decodes so far (a chunk evicted and needed again counts twice).
    pub fn chunks_decoded(&self) -> u64 {
        self.chunks_decoded
    }

    /// Pixels `col0 .. col0 + width` x `row0 .. row0 + height` (inside the image, non-empty) as a
    /// raster with the window's own geotransform. See the module doc.
    pub fn read_window(
        &mut self,
        col0: usize,
        row0: usize,
        width: usize,
        height: usize,
    ) -> Result<Raster, GeoTiffError> {
        if self.poisoned {
            return Err(GeoTiffError::Decode {
                path: self.path.clone(),
                reason: "an earlier read of this file made the TIFF decoder panic; reopen it"
                    .into(),
            });
        }
        let path = self.path.clone();
        let r = guarded(&path, || {
            self.read_window_unguarded(col0, row0, width, height)
        });
        if let Err(GeoTiffError::Decode { reason, .. }) = &r
            && reason.contains("panicked")
        {
            self.poisoned = true;
        }
        r
    }

    /// [`Self::read_window`] without the panic guard (the caller holds one).
    pub(crate) fn read_window_unguarded(
        &mut self,
        col0: usize,
        row0: usize,
        width: usize,
        height: usize,
    ) -> Result<Raster, GeoTiffError> {
        let info = self.info.clone();
        let inside = width > 0
            && height > 0
            && col0.checked_add(width).is_some_and(|c| c <= info.width)
            && row0.checked_add(height).is_some_and(|r| r <= info.height);
        if !inside {
            return Err(GeoTiffError::Window {
                path: self.path.clone(),
                reason: format!(
                    "window of {width} x {height} px at column {col0}, row {row0} is empty or not \
                     inside the {} x {} px image",
                    info.width, info.height
                ),
            });
        }
        let path = self.path.clone();
        let decode_err = |reason: String| GeoTiffError::Decode {
            path: path.clone(),
            reason,
        };
        // Stored as u8, u16 or f32.
        let stored_bytes = match info.bits_per_sample {
            0..=8 => 1,
            9..=16 => 2,
            _ => 4,
        };
        let samples = width
            .checked_mul(height)
            .and_then(|n| n.checked_mul(info.bands))
            .filter(|n| n.saturating_mul(stored_bytes) <= MAX_DECODED_BYTES)
            .ok_or_else(|| GeoTiffError::Window {
                path: self.path.clone(),
                reason: format!(
                    "window of {width} x {height} px x {} bands exceeds the {MAX_DECODED_BYTES} \
                     byte limit",
                    info.bands
                ),
            })?;
        let (cw, ch) = (info.chunk_width, info.chunk_height);
        let across = info.width.div_ceil(cw);
        let down = info.height.div_ceil(ch);
        let per_plane = across * down;
        let planes = if info.planar { info.bands } else { 1 };
        let spc = if info.planar { 1 } else { info.bands }; // samples per pixel inside one chunk
        if per_plane
            .checked_mul(planes)
            .is_none_or(|n| n > u32::MAX as usize)
        {
            return Err(decode_err("too many chunks".into()));
        }
        let chunk_ids = || {
            (0..planes).flat_map(move |plane| {
                (row0 / ch..=(row0 + height - 1) / ch).flat_map(move |ty| {
                    (col0 / cw..=(col0 + width - 1) / cw)
                        .map(move |tx| (plane * per_plane + ty * across + tx) as u32) // ok: < n_chunks <= u32::MAX
                })
            })
        };
        let mut prefetched = if self.helpers.is_empty() {
            HashMap::new()
        } else {
            let missing: Vec<u32> = chunk_ids().filter(|&i| !self.cache.has(i)).collect();
            self.decode_parallel(&missing)?
        };
        let mut out: Option<Acc> = None;
        for plane in 0..planes {
            for ty in row0 / ch..=(row0 + height - 1) / ch {
                for tx in col0 / cw..=(col0 + width - 1) / cw {
                    let idx = plane * per_plane + ty * across + tx;
                    let (x0, y0) = (tx * cw, ty * ch);
                    let (dw, dh) = (cw.min(info.width - x0), ch.min(info.height - y0));
                    let chunk = match prefetched.remove(&(idx as u32)) {
                        Some(c) => c,
                        None => self.chunk(idx as u32)?, // ok: idx < n_chunks <= u32::MAX
                    };
                    let (ix0, iy0) = (x0.max(col0), y0.max(row0));
                    let (ix1, iy1) = ((x0 + dw).min(col0 + width), (y0 + dh).min(row0 + height));
                    let geom = ChunkGeom {
                        out_width: width,
                        bands: self.info.bands,
                        spc,
                        plane,
                        dw,
                        dh,
                        ch,
                        src_x: ix0 - x0,
                        src_y: iy0 - y0,
                        dst_x: ix0 - col0,
                        dst_y: iy0 - row0,
                        nx: ix1 - ix0,
                        ny: iy1 - iy0,
                    };
                    let acc = out.get_or_insert_with(|| Acc::for_chunk(&chunk, samples));
                    acc.place(&chunk, &geom)
                        .map_err(|e| decode_err(format!("chunk {idx} at ({x0}, {y0}): {e}")))?;
                }
            }
        }
        let (data, source_type) = self.samples_of(out)?;
        let transform: GeoTransform = self.info.transform.window(col0, row0);
        Ok(Raster::new(
            width,
            height,
            self.info.bands,
            data,
            transform,
            self.info.crs,
            self.info.nodata,
        )
        .map_err(|e| decode_err(e.to_string()))?
        .with_source_type(source_type))
    }

    /// The window's samples as a raster's data and the type they were stored as (YCbCr
    /// converted to RGB).
    fn samples_of(&self, out: Option<Acc>) -> Result<(RasterData, SampleType), GeoTiffError> {
        Ok(match out {
            Some(Acc::U8(mut v)) => {
                if self.info.ycbcr {
                    // The tiff crate hands out YCbCr samples unconverted (JPEG included).
                    ycbcr_to_rgb_in_place(&mut v);
                }
                (RasterData::U8(v), SampleType::U8)
            }
            Some(_) if self.info.ycbcr => {
                return Err(GeoTiffError::Tag {
                    path: self.path.clone(),
                    tag: "PhotometricInterpretation (262)".into(),
                    reason: YCBCR_ONLY_RGB8.into(),
                });
            }
            Some(Acc::U16(v)) => (RasterData::U16(v), SampleType::U16),
            Some(Acc::F32(v, t)) => (RasterData::F32(v), t),
            None => {
                return Err(GeoTiffError::Decode {
                    path: self.path.clone(),
                    reason: "the image has no data chunks".into(),
                });
            }
        })
    }

    /// Chunk `idx`, from the cache or decoded (and cached).
    fn chunk(&mut self, idx: u32) -> Result<Arc<Chunk>, GeoTiffError> {
        if let Some(c) = self.cache.get(idx) {
            return Ok(c);
        }
        let decoded = if self.empty_chunks.contains(&idx) {
            empty_chunk(&mut self.dec, idx, self.info.nodata)
        } else {
            decode_one(&mut self.dec, idx)
        };
        self.accept(idx, decoded)
    }

    /// Decodes the chunks `ids` on the main decoder and the helpers at once (contiguous groups,
    /// one per decoder), caching them; returns them all.
    fn decode_parallel(&mut self, ids: &[u32]) -> Result<HashMap<u32, Arc<Chunk>>, GeoTiffError> {
        use rayon::prelude::*;
        let n = (1 + self.helpers.len()).min(ids.len()).max(1);
        let per = ids.len().div_ceil(n).max(1);
        let decs: Vec<&mut Decoder<R>> = std::iter::once(&mut self.dec)
            .chain(self.helpers.iter_mut())
            .take(n)
            .collect();
        let (empty, nodata) = (&self.empty_chunks, self.info.nodata);
        let groups: Vec<Vec<(u32, Result<Chunk, ChunkError>)>> = decs
            .into_par_iter()
            .zip(ids.par_chunks(per))
            .map(|(dec, group)| {
                group
                    .iter()
                    .map(|&i| {
                        let c = if empty.contains(&i) {
                            empty_chunk(dec, i, nodata)
                        } else {
                            decode_one(dec, i)
                        };
                        (i, c)
                    })
                    .collect()
            })
            .collect();
        let mut out = HashMap::with_capacity(ids.len());
        for (i, decoded) in groups.into_iter().flatten() {
            out.insert(i, self.accept(i, decoded)?);
        }
        Ok(out)
    }

    /// Counts, type-checks and caches a freshly decoded chunk.
    fn accept(
        &mut self,
        idx: u32,
        decoded: Result<Chunk, ChunkError>,
    ) -> Result<Arc<Chunk>, GeoTiffError> {
        let decode_err = |reason: String| GeoTiffError::Decode {
            path: self.path.clone(),
            reason,
        };
        self.chunks_decoded += 1;
        let chunk = decoded.map_err(|e| decode_err(format!("chunk {idx}: {e}")))?;
        match self.sample_type {
            None => self.sample_type = Some(chunk.sample_type),
            Some(t) if t == chunk.sample_type => {}
            Some(t) => {
                return Err(decode_err(format!(
                    "chunk {idx} holds {} samples, the chunks read before {t}",
                    chunk.sample_type
                )));
            }
        }
        let chunk = Arc::new(chunk);
        self.cache.insert(idx, Arc::clone(&chunk));
        Ok(chunk)
    }
}

/// Why one chunk could not be read or placed (the caller names the file and the chunk).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum ChunkError {
    /// The tiff crate's decoder failed (its message).
    #[error("{0}")]
    Read(String),
    #[error("64-bit integer samples are not supported")]
    Int64Samples,
    #[error("sample type differs from the first chunk of the window")]
    MixedSampleTypes,
    #[error("holds {len} samples, expected {expected}")]
    Length { len: usize, expected: usize },
    #[error("destination outside the window")]
    DestinationOutside,
    #[error("copy of {nx} x {ny} px at ({x}, {y}) exceeds the {dw} x {dh} px chunk")]
    Outside {
        nx: usize,
        ny: usize,
        x: usize,
        y: usize,
        dw: usize,
        dh: usize,
    },
}

/// Reads and converts chunk `idx`.
fn decode_one<R: Read + Seek>(dec: &mut Decoder<R>, idx: u32) -> Result<Chunk, ChunkError> {
    let raw = dec
        .read_chunk(idx)
        .map_err(|e| ChunkError::Read(e.to_string()))?;
    Chunk::from_decoded(raw)
}

/// Chunk `idx` stored with 0 bytes (sparse file): as GDAL reads it, every sample the nodata
/// value when the file declares one the sample type can hold, else 0.
fn empty_chunk<R: Read + Seek>(
    dec: &mut Decoder<R>,
    idx: u32,
    nodata: Option<f64>,
) -> Result<Chunk, ChunkError> {
    use tiff::decoder::DecodingSampleType as T;
    let layout = dec
        .image_chunk_buffer_layout(idx)
        .map_err(|e| ChunkError::Read(e.to_string()))?;
    // A sparse chunk has no data to bound it: its size comes from the header alone, which a
    // corrupt file can make tens of gigabytes (found by fuzzing). No real tile or strip is
    // near this.
    if layout.len > MAX_EMPTY_CHUNK_BYTES {
        return Err(ChunkError::Read(format!(
            "an empty chunk of {} bytes (more than {MAX_EMPTY_CHUNK_BYTES}): corrupt tile size",
            layout.len
        )));
    }
    let fill = nodata.filter(|v| v.is_finite()).unwrap_or(0.0);
    // Integer samples: the nodata value if it is one of the type's values, else 0.
    macro_rules! ints {
        ($t:ty, $variant:ident) => {{
            let n = layout.len / std::mem::size_of::<$t>();
            let v = if fill.fract() == 0.0 && fill >= <$t>::MIN as f64 && fill <= <$t>::MAX as f64 {
                fill as $t // ok: integral and in range
            } else {
                0
            };
            DecodingResult::$variant(vec![v; n])
        }};
    }
    let d = match layout.sample_type {
        Some(T::U8) => ints!(u8, U8),
        Some(T::U16) => ints!(u16, U16),
        Some(T::U32) => ints!(u32, U32),
        Some(T::I8) => ints!(i8, I8),
        Some(T::I16) => ints!(i16, I16),
        Some(T::I32) => ints!(i32, I32),
        Some(T::F32) => DecodingResult::F32(vec![fill as f32; layout.len / 4]),
        Some(T::F64) => DecodingResult::F64(vec![fill; layout.len / 8]),
        Some(T::U64 | T::I64) => return Err(ChunkError::Int64Samples),
        _ => {
            return Err(ChunkError::Read(
                "an empty (0-byte) chunk of a sample type visnav does not read".into(),
            ));
        }
    };
    Chunk::from_decoded(d)
}

impl GeoTiffWindowReader<BufReader<File>> {
    /// Decode up to `n` chunks at once (on rayon's pool) in `read_window`, each thread on its own
    /// handle of the file. `n <= 1`: one decoder (the default). The chunks a window misses are
    /// then all decoded before they are placed (held at once: about the window's size).
    pub fn set_decode_threads(&mut self, n: usize) -> Result<(), GeoTiffError> {
        let n = n.max(1);
        self.helpers.truncate(n - 1);
        while self.helpers.len() + 1 < n {
            let path = self.path.clone();
            let file = File::open(&path).map_err(|source| GeoTiffError::Io {
                path: path.clone(),
                cause: source,
            })?;
            let dec = guarded(&path, || new_decoder(BufReader::new(file), &path))?;
            self.helpers.push(dec);
        }
        Ok(())
    }
}

/// One decoded chunk in the storage type of the output (u8, u16, else f32).
#[derive(Debug)]
struct Chunk {
    data: ChunkData,
    sample_type: SampleType,
}

#[derive(Debug)]
enum ChunkData {
    U8(Vec<u8>),
    U16(Vec<u16>),
    F32(Vec<f32>),
}

impl Chunk {
    fn from_decoded(d: DecodingResult) -> Result<Self, ChunkError> {
        let f32s = |v: Vec<f32>, t| Chunk {
            data: ChunkData::F32(v),
            sample_type: t,
        };
        Ok(match d {
            DecodingResult::U8(v) => Chunk {
                data: ChunkData::U8(v),
                sample_type: SampleType::U8,
            },
            DecodingResult::U16(v) => Chunk {
                data: ChunkData::U16(v),
                sample_type: SampleType::U16,
            },
            DecodingResult::I8(v) => f32s(v.into_iter().map(f32::from).collect(), SampleType::I16),
            DecodingResult::I16(v) => f32s(v.into_iter().map(f32::from).collect(), SampleType::I16),
            DecodingResult::U32(v) => {
                f32s(v.into_iter().map(|s| s as f32).collect(), SampleType::U32)
            }
            DecodingResult::I32(v) => {
                f32s(v.into_iter().map(|s| s as f32).collect(), SampleType::I32)
            }
            DecodingResult::F64(v) => {
                f32s(v.into_iter().map(|s| s as f32).collect(), SampleType::F64)
            }
            DecodingResult::F32(v) => f32s(v, SampleType::F32),
            DecodingResult::F16(v) => f32s(v.into_iter().map(f32::from).collect(), SampleType::F32),
            DecodingResult::U64(_) | DecodingResult::I64(_) => {
                return Err(ChunkError::Int64Samples);
            }
        })
    }

    fn bytes(&self) -> usize {
        match &self.data {
            ChunkData::U8(v) => v.len(),
            ChunkData::U16(v) => 2 * v.len(),
            ChunkData::F32(v) => 4 * v.len(),
        }
    }
}

/// Output accumulator: the storage type is fixed by the first chunk.
enum Acc {
    U8(Vec<u8>),
    U16(Vec<u16>),
    F32(Vec<f32>, SampleType),
}

impl Acc {
    fn for_chunk(c: &Chunk, samples: usize) -> Self {
        match c.data {
            ChunkData::U8(_) => Acc::U8(vec![0; samples]),
            ChunkData::U16(_) => Acc::U16(vec![0; samples]),
            ChunkData::F32(_) => Acc::F32(vec![0.0; samples], c.sample_type),
        }
    }

    fn place(&mut self, c: &Chunk, g: &ChunkGeom) -> Result<(), ChunkError> {
        match (self, &c.data) {
            (Acc::U8(out), ChunkData::U8(v)) => place(out, v, g),
            (Acc::U16(out), ChunkData::U16(v)) => place(out, v, g),
            (Acc::F32(out, _), ChunkData::F32(v)) => place(out, v, g),
            _ => Err(ChunkError::MixedSampleTypes),
        }
    }
}

/// Where (part of) one decoded chunk goes in the window.
#[derive(Debug, Clone, Copy)]
struct ChunkGeom {
    /// Window width, pixels.
    out_width: usize,
    bands: usize,
    /// Samples per pixel in the chunk (1 for planar, `bands` for chunky).
    spc: usize,
    /// Band of a planar chunk.
    plane: usize,
    /// Chunk data size inside the image (clipped at the right and bottom edges), pixels.
    dw: usize,
    dh: usize,
    /// Nominal chunk height (tile height or rows per strip).
    ch: usize,
    /// First chunk pixel copied.
    src_x: usize,
    src_y: usize,
    /// Where it goes in the window.
    dst_x: usize,
    dst_y: usize,
    /// Pixels copied per row, rows copied.
    nx: usize,
    ny: usize,
}

/// Copies the `nx x ny` pixels at `(src_x, src_y)` of a chunk (`dw x dh` pixels of `spc` samples,
/// rows packed) to `(dst_x, dst_y)` of the band-interleaved window. A chunk of any other length
/// (e.g. packed sub-byte samples) is an error.
fn place<T: Copy>(out: &mut [T], chunk: &[T], g: &ChunkGeom) -> Result<(), ChunkError> {
    let row_len = g.dw * g.spc;
    // tiff 0.11.3 reports full-height chunks for the bottom tiles of planes >= 1 of planar files
    // (its chunk_data_dimensions ignores the plane); rows are still packed at `dw`, so the first
    // `dh` rows are the data. Any other length is an error.
    if chunk.len() != row_len * g.dh && chunk.len() != row_len * g.ch {
        return Err(ChunkError::Length {
            len: chunk.len(),
            expected: row_len * g.dh,
        });
    }
    if g.src_x + g.nx > g.dw || g.src_y + g.ny > g.dh {
        return Err(ChunkError::Outside {
            nx: g.nx,
            ny: g.ny,
            x: g.src_x,
            y: g.src_y,
            dw: g.dw,
            dh: g.dh,
        });
    }
    let n = g.nx * g.spc;
    for r in 0..g.ny {
        let s0 = (g.src_y + r) * row_len + g.src_x * g.spc;
        let src = &chunk[s0..s0 + n];
        let base = ((g.dst_y + r) * g.out_width + g.dst_x) * g.bands;
        let dst = out
            .get_mut(base..base + g.nx * g.bands)
            .ok_or(ChunkError::DestinationOutside)?;
        if g.spc == g.bands {
            dst.copy_from_slice(src);
        } else {
            for (c, &s) in src.iter().enumerate() {
                dst[c * g.bands + g.plane] = s;
            }
        }
    }
    Ok(())
}

/// Least-recently-used cache of decoded chunks, bounded in bytes.
struct ChunkCache {
    capacity: usize,
    bytes: usize,
    tick: u64,
    /// Chunk index -> (last use, chunk).
    map: HashMap<u32, (u64, Arc<Chunk>)>,
    /// Last use -> chunk index (oldest first).
    order: BTreeMap<u64, u32>,
}

impl ChunkCache {
    fn new(capacity: usize) -> Self {
        Self {
            capacity,
            bytes: 0,
            tick: 0,
            map: HashMap::new(),
            order: BTreeMap::new(),
        }
    }

    fn has(&self, idx: u32) -> bool {
        self.map.contains_key(&idx)
    }

    fn get(&mut self, idx: u32) -> Option<Arc<Chunk>> {
        self.tick += 1;
        let tick = self.tick;
        let (used, c) = self.map.get_mut(&idx)?;
        self.order.remove(used);
        *used = tick;
        self.order.insert(tick, idx);
        Some(Arc::clone(c))
    }

    fn insert(&mut self, idx: u32, c: Arc<Chunk>) {
        let b = c.bytes();
        if b > self.capacity {
            return;
        }
        self.evict_to(self.capacity - b);
        self.tick += 1;
        if let Some((old, prev)) = self.map.insert(idx, (self.tick, c)) {
            self.order.remove(&old);
            self.bytes -= prev.bytes();
        }
        self.order.insert(self.tick, idx);
        self.bytes += b;
    }

    fn evict_to(&mut self, bytes: usize) {
        while self.bytes > bytes {
            let Some((_, idx)) = self.order.pop_first() else {
                break;
            };
            if let Some((_, c)) = self.map.remove(&idx) {
                self.bytes -= c.bytes();
            }
        }
    }
}
