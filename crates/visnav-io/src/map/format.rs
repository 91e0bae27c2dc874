//! The `.vnm` reference-map file: writing (streamed, bounded memory) and reading (memory mapped).
//!
//! Byte layout (all integers and floats little-endian; full description in `docs/map-format.md`):
//!
//! ```text
//! 0   8  magic  "VNMAP\r\n\x1a"
//! 8   4  u32    format version (FORMAT_VERSION)
//! 12  4  u32    flags (0)
//! 16  8  u64    header_len: bytes of the JSON header at offset 64
//! 24  8  u64    data_offset: start of the level sections = 64 + header_len rounded up to 8
//! 32  8  u64    file_len: total file size
//! 40  16        reserved (0)
//! 56  4  u32    CRC-32 (IEEE, crc32fast) of bytes [0, 56) followed by [60, file_len)
//! 60  4         reserved (0)
//! 64     JSON   MapHeader (serde_json), then zero padding to data_offset
//! data_offset + LevelInfo offsets, per level:
//!   cells_offset:       (n_cells + 1) u64, cumulative feature counts (row-major cells, row 0 north)
//!   records_offset:     n_features records of RECORD_BYTES (see `encode_record`)
//!   descriptors_offset: n_features x descriptor_bytes(kind) (SURF: kind.len() i8, quantised;
//!   binary: the 32-bit words, little endian, desc_scale 1)
//!   image.offset:       width_px x height_px u8 (grey, 0 = no data; format 2, optional)
//! ```
//!
//! Feature record (40 bytes): `x_m f64 @0, y_m f64 @8, z_amsl_m f64 @16, scale_m f32 @24,
//! response f32 @28, desc_scale f32 @32, laplacian i8 @36, level u8 @37, source u8 @38 (ortho
//! index), reserved u8 @39`. Descriptor value `d_i = q_i * desc_scale` (re-normalised to unit length
//! on reading).
//!
//! Reading never trusts the file: every field is decoded with `from_le_bytes` from a bounds-checked
//! slice (no casts of the mapped bytes, so alignment does not matter), the checksum is verified
//! before the header is parsed, and every table is checked against the file size.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use memmap2::Mmap;

use super::{IndexGrid, LevelImageInfo, MapError, MapFeature, MapHeader, MapSelection};
use visnav_core::vision::{DescriptorKind, Family, FeatureSpec};

/// File magic (PNG-style: a CR-LF and a ^Z catch text-mode transfers).
pub const MAGIC: [u8; 8] = *b"VNMAP\r\n\x1a";
/// The format version this code writes (2: level images added).
pub const FORMAT_VERSION: u32 = 2;
/// The oldest format version this code reads (version 1: no level images).
pub const MIN_READ_VERSION: u32 = 1;
/// Size of the fixed preamble.
pub const PREAMBLE_BYTES: usize = 64;
/// Size of one feature record.
pub const RECORD_BYTES: usize = 40;
/// Offset of the CRC field.
const CRC_AT: usize = 56;
/// Largest number of index cells per level accepted when opening (guards allocation).
const MAX_CELLS: u64 = 1 << 32;

fn align8(n: u64) -> u64 {
    n.div_ceil(8) * 8
}

/// Bytes one descriptor of `kind` takes in the file: one quantised `i8` per float, four per
/// binary word.
pub fn descriptor_bytes(kind: DescriptorKind) -> usize {
    match kind.family() {
        Family::Float => kind.len(),
        Family::Binary => 4 * kind.len(),
    }
}

/// A binary descriptor's words (kept as float bits in the rows) as little-endian bytes; its
/// `desc_scale` is 1.
fn binary_bytes(words: &[f32], out: &mut [i8]) -> f32 {
    for (w, b) in words.iter().zip(out.chunks_exact_mut(4)) {
        for (q, v) in b.iter_mut().zip(w.to_bits().to_le_bytes()) {
            *q = i8::from_le_bytes([v]);
        }
    }
    1.0
}

/// Quantises a descriptor to `i8` with one scale: `scale = max|d| / 127`, `q = round(d / scale)`.
pub fn quantise(desc: &[f32], out: &mut [i8]) -> f32 {
    let m = desc
        .iter()
        .filter(|v| v.is_finite())
        .fold(0f32, |a, v| a.max(v.abs()));
    if m <= 0.0 {
        out.iter_mut().for_each(|q| *q = 0);
        return 0.0;
    }
    let scale = m / 127.0;
    for (q, &d) in out.iter_mut().zip(desc) {
        let v = if d.is_finite() { d / scale } else { 0.0 };
        *q = v.round().clamp(-127.0, 127.0) as i8; // ok: clamped to the i8 range
    }
    scale
}

/// Dequantises into `out` (`q.len()` values) and re-normalises to unit length.
pub fn dequantise(q: &[i8], scale: f32, out: &mut [f32]) {
    let mut n2 = 0f32;
    for (o, &v) in out.iter_mut().zip(q) {
        *o = f32::from(v) * scale;
        n2 += *o * *o;
    }
    if n2 > 0.0 && n2.is_finite() {
        let inv = 1.0 / n2.sqrt();
        out.iter_mut().for_each(|o| *o *= inv);
    }
}

/// Encodes one feature record (layout in the module doc).
pub fn encode_record(f: &MapFeature, desc_scale: f32, source: u8) -> [u8; RECORD_BYTES] {
    let mut b = [0u8; RECORD_BYTES];
    b[0..8].copy_from_slice(&f.x_m.to_le_bytes());
    b[8..16].copy_from_slice(&f.y_m.to_le_bytes());
    b[16..24].copy_from_slice(&f.z_amsl_m.to_le_bytes());
    b[24..28].copy_from_slice(&f.scale_m.to_le_bytes());
    b[28..32].copy_from_slice(&f.response.to_le_bytes());
    b[32..36].copy_from_slice(&desc_scale.to_le_bytes());
    b[36] = f.laplacian.to_le_bytes()[0];
    b[37] = f.level;
    b[38] = source;
    b
}

#[inline]
fn rd8(b: &[u8], at: usize) -> [u8; 8] {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    a
}
#[inline]
fn rd4(b: &[u8], at: usize) -> [u8; 4] {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    a
}

/// Decodes a record: the feature and its descriptor scale. `b` must hold `RECORD_BYTES`.
pub fn decode_record(b: &[u8]) -> (MapFeature, f32) {
    (
        MapFeature {
            x_m: f64::from_le_bytes(rd8(b, 0)),
            y_m: f64::from_le_bytes(rd8(b, 8)),
            z_amsl_m: f64::from_le_bytes(rd8(b, 16)),
            scale_m: f32::from_le_bytes(rd4(b, 24)),
            response: f32::from_le_bytes(rd4(b, 28)),
            laplacian: i8::from_le_bytes([b[36]]),
            level: b[37],
        },
        f32::from_le_bytes(rd4(b, 32)),
    )
}

/// Checksum of a whole file image (everything but the CRC field).
fn crc_of(bytes: &[u8]) -> u32 {
    let mut h = crc32fast::Hasher::new();
    h.update(&bytes[..CRC_AT]);
    h.update(&bytes[CRC_AT + 4..]);
    h.finalize()
}

// ------------------------------------------------------------------------------------------------
// Writing

/// Streams features into a temporary spill file (in production order) while counting them per
/// index cell; [`SpillWriter::finish`] then lays out the final file cell by cell. Level images
/// ([`SpillWriter::with_images`]) arrive as blocks in a second spill file and are placed the same
/// way. Memory: the per-cell counters only.
pub struct SpillWriter {
    spill_path: PathBuf,
    spill: BufWriter<File>,
    kind: DescriptorKind,
    grids: Vec<IndexGrid>,
    counts: Vec<Vec<u64>>,
    qbuf: Vec<i8>,
    images: Option<ImageSpill>,
}

/// The level images' spill: their geometry and the blocks written so far.
struct ImageSpill {
    path: PathBuf,
    file: BufWriter<File>,
    levels: Vec<LevelImageInfo>,
}

/// Bytes of an image block's spill header: level u32, x0 u64, y0 u64, w u32, h u32.
const BLOCK_HEADER_BYTES: usize = 28;

impl SpillWriter {
    /// Creates the spill file `spill_path` for levels with the given index grids.
    pub fn new(
        spill_path: &Path,
        kind: DescriptorKind,
        grids: Vec<IndexGrid>,
    ) -> Result<Self, MapError> {
        let f = File::create(spill_path).map_err(|source| MapError::Io {
            path: spill_path.to_path_buf(),
            what: "cannot create the temporary feature file",
            cause: source,
        })?;
        let counts = grids.iter().map(|g| vec![0u64; g.n_cells()]).collect();
        Ok(Self {
            spill_path: spill_path.to_path_buf(),
            spill: BufWriter::with_capacity(1 << 20, f),
            kind,
            grids,
            counts,
            qbuf: vec![0; descriptor_bytes(kind)],
            images: None,
        })
    }

    /// Adds a grey image to every level (`levels[l]`: size and origin; offsets are filled in by
    /// [`Self::finish`]). Blocks come through [`Self::push_image_block`].
    pub fn with_images(mut self, levels: Vec<LevelImageInfo>) -> Result<Self, MapError> {
        let path = self.spill_path.with_extension("img.spill");
        let f = File::create(&path).map_err(|source| MapError::Io {
            path: path.clone(),
            what: "cannot create the temporary image file",
            cause: source,
        })?;
        self.images = Some(ImageSpill {
            path,
            file: BufWriter::with_capacity(1 << 20, f),
            levels,
        });
        Ok(self)
    }

    /// A `w x h` block of level `level`'s image with its top-left pixel at `(x0, y0)` (may lie
    /// partly outside the image: clipped). Zero bytes are no data and never overwrite: where
    /// blocks overlap, the last non-zero value written wins. Ignored without images.
    pub fn push_image_block(
        &mut self,
        level: usize,
        x0: i64,
        y0: i64,
        w: usize,
        h: usize,
        px: &[u8],
    ) -> Result<(), MapError> {
        let Some(img) = self.images.as_mut() else {
            return Ok(());
        };
        let Some(info) = img.levels.get(level) else {
            return Ok(());
        };
        let (iw, ih) = (info.width_px as i64, info.height_px as i64);
        let (cx0, cy0) = (x0.max(0), y0.max(0));
        let (cx1, cy1) = ((x0 + w as i64).min(iw), (y0 + h as i64).min(ih));
        if cx1 <= cx0 || cy1 <= cy0 || px.len() != w * h {
            return Ok(());
        }
        let (cw, ch) = ((cx1 - cx0) as usize, (cy1 - cy0) as usize);
        let mut buf = Vec::with_capacity(BLOCK_HEADER_BYTES + cw * ch);
        buf.extend_from_slice(&(level as u32).to_le_bytes());
        buf.extend_from_slice(&(cx0 as u64).to_le_bytes());
        buf.extend_from_slice(&(cy0 as u64).to_le_bytes());
        buf.extend_from_slice(&(cw as u32).to_le_bytes());
        buf.extend_from_slice(&(ch as u32).to_le_bytes());
        for y in cy0..cy1 {
            let row = (y - y0) as usize * w;
            let a = row + (cx0 - x0) as usize;
            buf.extend_from_slice(&px[a..a + cw]);
        }
        img.file.write_all(&buf).map_err(|source| MapError::Io {
            path: img.path.clone(),
            what: "cannot write the temporary image file",
            cause: source,
        })
    }

    /// Number of features pushed to `level` so far.
    pub fn count(&self, level: usize) -> u64 {
        self.counts.get(level).map_or(0, |c| c.iter().sum())
    }

    /// Appends a feature with its (f32, `kind.len()` values) descriptor.
    pub fn push(
        &mut self,
        level: usize,
        f: &MapFeature,
        desc: &[f32],
        source: u8,
    ) -> Result<(), MapError> {
        let scale = match self.kind.family() {
            Family::Float => quantise(&desc[..self.kind.len()], &mut self.qbuf),
            Family::Binary => binary_bytes(&desc[..self.kind.len()], &mut self.qbuf),
        };
        let rec = encode_record(f, scale, source);
        let qb: Vec<u8> = self.qbuf.iter().map(|q| q.to_le_bytes()[0]).collect();
        self.push_record(level, &rec, &qb)
    }

    /// Appends a feature as a map file stores it: its record and its descriptor's bytes (copied
    /// from another map, so a feature moves between maps bit for bit). `level` must be one the
    /// writer was made with.
    pub fn push_record(
        &mut self,
        level: usize,
        record: &[u8; RECORD_BYTES],
        descriptor: &[u8],
    ) -> Result<(), MapError> {
        let (Some(grid), true) = (
            self.grids.get(level).copied(),
            descriptor.len() == descriptor_bytes(self.kind),
        ) else {
            return Err(MapError::Param {
                name: "level",
                reason: format!("feature of level {level} does not fit the map being written"),
            });
        };
        let (x_m, y_m) = (
            f64::from_le_bytes(rd8(record, 0)),
            f64::from_le_bytes(rd8(record, 8)),
        );
        let cell = grid.cell_of(x_m, y_m);
        self.counts[level][cell] += 1;
        let io = |source| MapError::Io {
            path: self.spill_path.clone(),
            what: "cannot write the temporary feature file",
            cause: source,
        };
        self.spill
            .write_all(&(level as u32).to_le_bytes())
            .map_err(io)?;
        self.spill
            .write_all(&(cell as u64).to_le_bytes())
            .map_err(io)?;
        self.spill.write_all(record).map_err(io)?;
        self.spill.write_all(descriptor).map_err(io)?;
        Ok(())
    }

    /// Writes the final file `out` (via `out.partial` and a rename). `header.levels` must list the
    /// levels in order with `gsd_m`; counts, grids and offsets are filled in here. Returns the
    /// header as written and the file size. The spill file is removed.
    pub fn finish(
        mut self,
        mut header: MapHeader,
        out: &Path,
    ) -> Result<(MapHeader, u64), MapError> {
        self.spill
            .flush()
            .map_err(|e| self.spill_io("cannot write the temporary feature file", e))?;
        let (starts, data_bytes) = self.lay_out(&mut header)?;
        header.version = FORMAT_VERSION;
        let json = serde_json::to_vec(&header).map_err(|e| MapError::Format {
            path: out.to_path_buf(),
            reason: format!("cannot encode the header: {e}"),
        })?;
        let data_offset = align8(PREAMBLE_BYTES as u64 + json.len() as u64);
        let file_len = data_offset + data_bytes;

        let partial = out.with_extension("vnm.partial");
        let out_io = |what, source| MapError::Io {
            path: partial.clone(),
            what,
            cause: source,
        };
        let file = File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&partial)
            .map_err(|e| out_io("cannot create the map file", e))?;
        file.set_len(file_len)
            .map_err(|e| out_io("cannot size the map file", e))?;
        let mut pre = [0u8; PREAMBLE_BYTES];
        pre[0..8].copy_from_slice(&MAGIC);
        pre[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        pre[16..24].copy_from_slice(&(json.len() as u64).to_le_bytes());
        pre[24..32].copy_from_slice(&data_offset.to_le_bytes());
        pre[32..40].copy_from_slice(&file_len.to_le_bytes());
        let wr = |buf: &[u8], at: u64| {
            file.write_all_at(buf, at)
                .map_err(|e| out_io("cannot write the map file", e))
        };
        wr(&pre, 0)?;
        wr(&json, PREAMBLE_BYTES as u64)?;
        for (l, table) in starts.iter().enumerate() {
            let bytes: Vec<u8> = table.iter().flat_map(|v| v.to_le_bytes()).collect();
            wr(&bytes, data_offset + header.levels[l].cells_offset)?;
        }
        let placed = Placed {
            file: &file,
            path: &partial,
            header: &header,
            data_offset,
        };
        self.place_features(&placed, starts)?;
        let _ = std::fs::remove_file(&self.spill_path);
        if let Some(img) = self.images.take() {
            place_image_blocks(img, &header, data_offset, &file, &partial)?;
        }
        let crc = file_crc(&file).map_err(|e| out_io("cannot read back the map file", e))?;
        wr(&crc.to_le_bytes(), CRC_AT as u64)?;
        file.sync_all()
            .map_err(|e| out_io("cannot flush the map file", e))?;
        drop(file);
        std::fs::rename(&partial, out).map_err(|source| MapError::Io {
            path: out.to_path_buf(),
            what: "cannot move the finished map into place",
            cause: source,
        })?;
        Ok((header, file_len))
    }

    fn spill_io(&self, what: &'static str, cause: std::io::Error) -> MapError {
        MapError::Io {
            path: self.spill_path.clone(),
            what,
            cause,
        }
    }

    /// Lays the levels out after the header: per level its cell table, records, descriptors and
    /// image, each 8-byte aligned. Fills `header`'s offsets and counts; returns each level's cell
    /// table (the first feature of every cell, and the end) and the data's length in bytes.
    fn lay_out(&self, header: &mut MapHeader) -> Result<(Vec<Vec<u64>>, u64), MapError> {
        let len = descriptor_bytes(self.kind) as u64;
        let mut off = 0u64;
        let mut starts: Vec<Vec<u64>> = Vec::new();
        for (l, grid) in self.grids.iter().enumerate() {
            let counts = &self.counts[l];
            let mut table = Vec::with_capacity(counts.len() + 1);
            let mut acc = 0u64;
            table.push(0);
            for &c in counts {
                acc += c;
                table.push(acc);
            }
            let cells_offset = off;
            off = align8(off + 8 * table.len() as u64);
            let records_offset = off;
            off = align8(off + RECORD_BYTES as u64 * acc);
            let descriptors_offset = off;
            off = align8(off + len * acc);
            let info = header.levels.get_mut(l).ok_or(MapError::Param {
                name: "levels",
                reason: "header lists fewer levels than the index".into(),
            })?;
            info.n_features = acc;
            info.grid = *grid;
            info.cells_offset = cells_offset;
            info.records_offset = records_offset;
            info.descriptors_offset = descriptors_offset;
            info.image = match self.images.as_ref().and_then(|i| i.levels.get(l)) {
                Some(li) => {
                    let at = off;
                    off = align8(off + li.width_px * li.height_px);
                    Some(LevelImageInfo { offset: at, ..*li })
                }
                None => None,
            };
            starts.push(table);
        }
        Ok((starts, off))
    }

    /// Places the spilled features cell by cell, in the order they were spilled within a cell.
    fn place_features(&self, to: &Placed, mut cursor: Vec<Vec<u64>>) -> Result<(), MapError> {
        let len = descriptor_bytes(self.kind) as u64;
        let spill = File::open(&self.spill_path)
            .map_err(|e| self.spill_io("cannot reopen the temporary feature file", e))?;
        let mut rd = BufReader::with_capacity(1 << 20, spill);
        let item = 4 + 8 + RECORD_BYTES + len as usize;
        let mut buf = vec![0u8; item];
        let mut rec_run = Run::default();
        let mut desc_run = Run::default();
        loop {
            match rd.read_exact(&mut buf) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
                Err(e) => return Err(self.spill_io("cannot read the temporary feature file", e)),
            }
            let level = u32::from_le_bytes(rd4(&buf, 0)) as usize;
            let cell = u64::from_le_bytes(rd8(&buf, 4)) as usize;
            let info = &to.header.levels[level];
            let idx = cursor[level][cell];
            cursor[level][cell] += 1;
            let rec_at = to.data_offset + info.records_offset + idx * RECORD_BYTES as u64;
            let desc_at = to.data_offset + info.descriptors_offset + idx * len;
            rec_run.put(to.file, rec_at, &buf[12..12 + RECORD_BYTES], to.path)?;
            desc_run.put(to.file, desc_at, &buf[12 + RECORD_BYTES..], to.path)?;
        }
        rec_run.flush(to.file, to.path)?;
        desc_run.flush(to.file, to.path)
    }
}

/// The map file being written and where its data start.
struct Placed<'a> {
    file: &'a File,
    path: &'a Path,
    header: &'a MapHeader,
    data_offset: u64,
}

/// The CRC-32 of the whole file with its CRC field skipped, streamed once.
fn file_crc(file: &File) -> std::io::Result<u32> {
    let mut h = crc32fast::Hasher::new();
    let mut f2 = file;
    f2.seek(SeekFrom::Start(0))?;
    let mut chunk = vec![0u8; 1 << 20];
    let mut pos = 0u64;
    loop {
        let n = f2.read(&mut chunk)?;
        if n == 0 {
            break;
        }
        // Hash the slice, skipping the CRC field when it falls inside this chunk.
        let (a, b) = (pos, pos + n as u64);
        let (c0, c1) = (CRC_AT as u64, CRC_AT as u64 + 4);
        if b <= c0 || a >= c1 {
            h.update(&chunk[..n]);
        } else {
            let s0 = (c0.saturating_sub(a)) as usize;
            let s1 = ((c1 - a) as usize).min(n);
            h.update(&chunk[..s0]);
            h.update(&chunk[s1..n]);
        }
        pos = b;
    }
    Ok(h.finalize())
}

impl Drop for SpillWriter {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.spill_path);
        if let Some(img) = &self.images {
            let _ = std::fs::remove_file(&img.path);
        }
    }
}

/// Writes the spilled image blocks into their places (runs of non-zero bytes only, so no data
/// never overwrites data) and removes the spill.
fn place_image_blocks(
    mut img: ImageSpill,
    header: &MapHeader,
    data_offset: u64,
    file: &File,
    partial: &Path,
) -> Result<(), MapError> {
    let io = |what, source| MapError::Io {
        path: img.path.clone(),
        what,
        cause: source,
    };
    img.file
        .flush()
        .map_err(|e| io("cannot write the temporary image file", e))?;
    let spill =
        File::open(&img.path).map_err(|e| io("cannot reopen the temporary image file", e))?;
    let mut rd = BufReader::with_capacity(1 << 20, spill);
    let mut head = [0u8; BLOCK_HEADER_BYTES];
    let mut row = Vec::new();
    loop {
        match rd.read_exact(&mut head) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
            Err(e) => return Err(io("cannot read the temporary image file", e)),
        }
        let level = u32::from_le_bytes(rd4(&head, 0)) as usize;
        let x0 = u64::from_le_bytes(rd8(&head, 4));
        let y0 = u64::from_le_bytes(rd8(&head, 12));
        let w = u32::from_le_bytes(rd4(&head, 20)) as usize;
        let h = u32::from_le_bytes(rd4(&head, 24)) as usize;
        let Some(info) = header.levels.get(level).and_then(|l| l.image) else {
            return Err(MapError::Param {
                name: "levels",
                reason: "an image block names a level without an image".into(),
            });
        };
        row.resize(w, 0);
        for y in 0..h as u64 {
            rd.read_exact(&mut row)
                .map_err(|e| io("cannot read the temporary image file", e))?;
            let base = data_offset + info.offset + (y0 + y) * info.width_px + x0;
            let mut x = 0;
            while x < w {
                if row[x] == 0 {
                    x += 1;
                    continue;
                }
                let start = x;
                while x < w && row[x] != 0 {
                    x += 1;
                }
                file.write_all_at(&row[start..x], base + start as u64)
                    .map_err(|source| MapError::Io {
                        path: partial.to_path_buf(),
                        what: "cannot write the map file",
                        cause: source,
                    })?;
            }
        }
    }
    drop(rd);
    let _ = std::fs::remove_file(&img.path);
    Ok(())
}

/// Coalesces writes to consecutive offsets into one `write_all_at` (features of a cell arrive in
/// runs, e.g. a whole tile at once).
#[derive(Default)]
struct Run {
    at: u64,
    buf: Vec<u8>,
}

impl Run {
    fn put(&mut self, f: &File, at: u64, bytes: &[u8], path: &Path) -> Result<(), MapError> {
        if self.buf.is_empty() || at != self.at + self.buf.len() as u64 || self.buf.len() > 1 << 20
        {
            self.flush(f, path)?;
            self.at = at;
        }
        self.buf.extend_from_slice(bytes);
        Ok(())
    }
    fn flush(&mut self, f: &File, path: &Path) -> Result<(), MapError> {
        if !self.buf.is_empty() {
            f.write_all_at(&self.buf, self.at)
                .map_err(|source| MapError::Io {
                    path: path.to_path_buf(),
                    what: "cannot write the map file",
                    cause: source,
                })?;
            self.buf.clear();
        }
        Ok(())
    }
}

// ------------------------------------------------------------------------------------------------
// Reading

/// An opened, memory-mapped reference map.
#[derive(Debug)]
pub struct ReferenceMap {
    path: PathBuf,
    mmap: Mmap,
    header: MapHeader,
    data_offset: usize,
}

impl ReferenceMap {
    /// Opens and validates a map file: magic, version, sizes, checksum, header, tables. Errors
    /// name the file and what is wrong; a malformed file never panics.
    pub fn open(path: &Path) -> Result<Self, MapError> {
        let file = crate::files::require_regular(path, "a reference map")
            .and_then(|()| File::open(path))
            .map_err(|source| MapError::Io {
                path: path.to_path_buf(),
                what: "cannot open the map file",
                cause: source,
            })?;
        // SAFETY: the map is read-only for us; the file must not be truncated or rewritten by
        // another process while it is mapped (maps are written to a temporary name and renamed
        // into place, so a rebuild replaces the directory entry, not these pages).
        let mmap = unsafe { Mmap::map(&file) }.map_err(|source| MapError::Io {
            path: path.to_path_buf(),
            what: "cannot memory-map the map file",
            cause: source,
        })?;
        let (header, data_offset) = validate(&mmap, path)?;
        Ok(Self {
            path: path.to_path_buf(),
            mmap,
            header,
            data_offset,
        })
    }

    /// The file this map was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The header.
    pub fn header(&self) -> &MapHeader {
        &self.header
    }

    /// The CRC-32 the file stores (verified when it was opened).
    pub fn stored_crc(&self) -> u32 {
        let b = &self.mmap[CRC_AT..CRC_AT + 4];
        u32::from_le_bytes([b[0], b[1], b[2], b[3]])
    }

    /// The file's size, bytes.
    pub fn file_len(&self) -> u64 {
        self.mmap.len() as u64
    }

    /// Features of `level` whose `(x_m, y_m)` lies inside the closed rectangle, via the spatial
    /// index (only cells overlapping the rectangle are read). An unknown level or an empty/NaN
    /// rectangle gives an empty selection. Features are in file order (cell by cell, row 0 =
    /// north first).
    pub fn select(
        &self,
        level: usize,
        min_x_m: f64,
        min_y_m: f64,
        max_x_m: f64,
        max_y_m: f64,
    ) -> MapSelection {
        let kind = self.header.descriptor_kind();
        let mut sel = MapSelection {
            features: Vec::new(),
            descriptors: Vec::new(),
            kind,
        };
        let stride = kind.stride();
        let binary = kind.family() == Family::Binary;
        let mut q = vec![0i8; descriptor_bytes(kind)];
        self.for_each_record(level, [min_x_m, min_y_m, max_x_m, max_y_m], |rb, db| {
            let (f, scale) = decode_record(rb);
            sel.features.push(f);
            for (k, v) in db.iter().enumerate() {
                q[k] = i8::from_le_bytes([*v]);
            }
            let at = sel.descriptors.len();
            sel.descriptors.resize(at + stride, 0.0);
            let row = &mut sel.descriptors[at..at + kind.len()];
            if binary {
                for (w, b) in row.iter_mut().zip(db.chunks_exact(4)) {
                    *w = f32::from_bits(u32::from_le_bytes(rd4(b, 0)));
                }
            } else {
                dequantise(&q, scale, row);
            }
        });
        sel
    }

    /// Calls `f` with the stored record and descriptor bytes of every feature of `level` whose
    /// `(x_m, y_m)` lies inside the closed rectangle `[min_x, min_y, max_x, max_y]`, in file
    /// order, reading only the index cells that overlap it (an unknown level or an empty / NaN
    /// rectangle: none).
    pub fn for_each_record(
        &self,
        level: usize,
        [min_x_m, min_y_m, max_x_m, max_y_m]: [f64; 4],
        mut f: impl FnMut(&[u8; RECORD_BYTES], &[u8]),
    ) {
        let Some(info) = self.header.levels.get(level) else {
            return;
        };
        if !(min_x_m <= max_x_m && min_y_m <= max_y_m) {
            return;
        }
        let g = &info.grid;
        let (c0, c1) = (g.col_of(min_x_m), g.col_of(max_x_m));
        let (r0, r1) = (g.row_of(max_y_m), g.row_of(min_y_m));
        let base = self.data_offset;
        let cells = &self.mmap[base + info.cells_offset as usize..];
        let recs = &self.mmap[base + info.records_offset as usize..];
        let descs = &self.mmap[base + info.descriptors_offset as usize..];
        let len = descriptor_bytes(self.header.descriptor_kind());
        for r in r0..=r1 {
            for c in c0..=c1 {
                let cell = r * g.cols as usize + c;
                let start = u64::from_le_bytes(rd8(cells, 8 * cell)) as usize;
                let end = u64::from_le_bytes(rd8(cells, 8 * cell + 8)) as usize;
                for i in start..end {
                    let mut rb = [0u8; RECORD_BYTES];
                    rb.copy_from_slice(&recs[i * RECORD_BYTES..(i + 1) * RECORD_BYTES]);
                    let x = f64::from_le_bytes(rd8(&rb, 0));
                    let y = f64::from_le_bytes(rd8(&rb, 8));
                    if x >= min_x_m && x <= max_x_m && y >= min_y_m && y <= max_y_m {
                        f(&rb, &descs[i * len..(i + 1) * len]);
                    }
                }
            }
        }
    }

    /// The grey image of `level` (format 2) with its geometry; `None` for a version-1 map.
    pub fn level_image(&self, level: usize) -> Option<(LevelImageInfo, &[u8])> {
        let info = self.header.levels.get(level)?.image?;
        let at = self.data_offset + info.offset as usize;
        let len = (info.width_px * info.height_px) as usize; // ok: checked against the file
        Some((info, &self.mmap[at..at + len]))
    }

    /// Every feature of `level` (brute force, for tests and tools).
    pub fn all_features(&self, level: usize) -> Vec<MapFeature> {
        let Some(info) = self.header.levels.get(level) else {
            return Vec::new();
        };
        let base = self.data_offset + info.records_offset as usize;
        (0..info.n_features as usize)
            .map(|i| {
                decode_record(&self.mmap[base + i * RECORD_BYTES..base + (i + 1) * RECORD_BYTES]).0
            })
            .collect()
    }
}

/// Checks the whole file image of `path`; returns the parsed header and the data offset, or
/// [`MapError::Format`] with the reason.
fn validate(b: &[u8], path: &Path) -> Result<(MapHeader, usize), MapError> {
    let bad = |reason: String| MapError::Format {
        path: path.to_path_buf(),
        reason,
    };
    if b.len() < PREAMBLE_BYTES {
        return Err(bad(format!(
            "truncated: {} bytes, the preamble alone has {PREAMBLE_BYTES}",
            b.len()
        )));
    }
    if b[0..8] != MAGIC {
        return Err(bad(format!(
            "wrong magic {} (expected {}): not a .vnm map",
            visnav_core::text::quote(&String::from_utf8_lossy(&b[0..8])),
            visnav_core::text::quote(&String::from_utf8_lossy(&MAGIC))
        )));
    }
    let version = u32::from_le_bytes(rd4(b, 8));
    if !(MIN_READ_VERSION..=FORMAT_VERSION).contains(&version) {
        return Err(bad(format!(
            "format version {version}, this visnav reads versions {MIN_READ_VERSION} to {FORMAT_VERSION} (rebuild the map with `visnav map build`)"
        )));
    }
    let header_len = u64::from_le_bytes(rd8(b, 16));
    let data_offset = u64::from_le_bytes(rd8(b, 24));
    let file_len = u64::from_le_bytes(rd8(b, 32));
    if file_len != b.len() as u64 {
        return Err(bad(format!(
            "the preamble records {file_len} bytes but the file has {} (truncated or appended to)",
            b.len()
        )));
    }
    // Saturating: a header_len near u64::MAX overflowed here (found by fuzzing); it
    // fails the header_len check below.
    let expect_data = (PREAMBLE_BYTES as u64).saturating_add(header_len);
    if header_len > file_len || data_offset != align8(expect_data) || data_offset > file_len {
        return Err(bad(format!(
            "inconsistent preamble: header_len {header_len}, data_offset {data_offset}, file_len {file_len}"
        )));
    }
    let stored = u32::from_le_bytes(rd4(b, CRC_AT));
    let actual = crc_of(b);
    if stored != actual {
        return Err(bad(format!(
            "checksum mismatch (stored {stored:08x}, computed {actual:08x}): the file is corrupted"
        )));
    }
    let hdr_bytes = &b[PREAMBLE_BYTES..PREAMBLE_BYTES + header_len as usize];
    let header: MapHeader =
        serde_json::from_slice(hdr_bytes).map_err(|e| bad(format!("header JSON: {e}")))?;
    if header.version != version {
        return Err(bad(format!(
            "header version {} differs from the preamble's {version}",
            header.version
        )));
    }
    header
        .feature_spec()
        .validate()
        .map_err(|e| bad(format!("header feature parameters: {e}")))?;
    let data = &b[data_offset as usize..];
    for l in 0..header.levels.len() {
        check_level(&header, l, data).map_err(|e| bad(e.0))?;
    }
    Ok((header, data_offset as usize))
}

/// Level `l`'s index grid, section bounds (within the `data` bytes), cell table and features
/// (header bounds-checked by the caller).
fn check_level(header: &MapHeader, l: usize, data: &[u8]) -> Result<(), BadFeature> {
    let info = &header.levels[l]; // ok: l < header.levels.len()
    let data_len = data.len() as u64;
    let len = descriptor_bytes(header.descriptor_kind()) as u64;
    let g = &info.grid;
    if !(g.cell_m.is_finite()
        && g.cell_m > 0.0
        && g.origin_x_m.is_finite()
        && g.origin_y_m.is_finite())
        || g.cols == 0
        || g.rows == 0
        || g.cols as u64 * g.rows as u64 > MAX_CELLS
    {
        return Err(BadFeature(format!(
            "level {l}: invalid index grid (origin {}, {} m, cell {} m, {} x {} cells)",
            g.origin_x_m, g.origin_y_m, g.cell_m, g.cols, g.rows
        )));
    }
    if !(info.gsd_m.is_finite() && info.gsd_m > 0.0) {
        return Err(BadFeature(format!(
            "level {l}: invalid gsd_m {}",
            info.gsd_m
        )));
    }
    let n = info.n_features;
    let n_cells = g.n_cells() as u64;
    let sections = [
        (
            "cell table",
            info.cells_offset,
            (n_cells + 1).checked_mul(8),
        ),
        (
            "records",
            info.records_offset,
            n.checked_mul(RECORD_BYTES as u64),
        ),
        ("descriptors", info.descriptors_offset, n.checked_mul(len)),
    ];
    let image = info.image.map(|im| {
        (
            im.offset,
            im.width_px.checked_mul(im.height_px),
            im.width_px > 0
                && im.height_px > 0
                && im.origin_x_m.is_finite()
                && im.origin_y_m.is_finite(),
        )
    });
    if image.is_some_and(|(_, _, ok)| !ok) {
        return Err(BadFeature(format!(
            "level {l}: invalid image geometry (size, origin not positive and finite)"
        )));
    }
    let sections = sections
        .into_iter()
        .chain(image.map(|(at, size, _)| ("image", at, size)));
    for (name, at, size) in sections {
        let end = size.and_then(|s| at.checked_add(s));
        if end.is_none_or(|e| e > data_len) {
            let size = size.map_or_else(|| "an overflowing size".to_string(), |s| s.to_string());
            return Err(BadFeature(format!(
                "level {l}: {name} at {at} (+{size} bytes) exceed the {data_len} data bytes (truncated?)"
            )));
        }
    }
    let cells = &data[info.cells_offset as usize..];
    let mut prev = 0u64;
    for k in 0..=n_cells as usize {
        let v = u64::from_le_bytes(rd8(cells, 8 * k));
        if (k == 0 && v != 0) || v < prev || v > n {
            return Err(BadFeature(format!(
                "level {l}: cell table entry {k} = {v} is not a cumulative count (previous {prev}, {n} features)"
            )));
        }
        prev = v;
    }
    if prev != n {
        return Err(BadFeature(format!(
            "level {l}: cell table ends at {prev}, header says {n} features"
        )));
    }
    check_features(header, l, data)
}

/// Slack on a feature's height against the header's height range, metres: the build stores the
/// DEM's bilinear interpolation of samples inside that range (or the constant itself), so any
/// height outside it by more than rounding is not what the build wrote.
const HEIGHT_SLACK_M: f64 = 1e-6;
/// How far outside the orthophotos' bounds a keypoint centre may lie, in level pixels: SURF keeps
/// keypoints whose filters fit inside the image, so their centres lie inside it; one pixel covers
/// the sub-pixel interpolation of the extremum.
const BOUNDS_SLACK_PX: f64 = 1.0;
/// Smallest SURF scale a keypoint can have, level pixels: the first filter (9 px) has scale
/// 1.2 px, and the interpolation of the extremum moves it by less than half a filter step.
const MIN_SCALE_PX: f64 = 0.5;
/// Slack on a descriptor's length after dequantisation, beyond the quantisation bound: the
/// descriptors are unit vectors stored with a rounding error of at most `desc_scale / 2` per
/// value, so `| |q| desc_scale - 1 | <= sqrt(len) desc_scale / 2`; this covers the f32 sums.
const DESCRIPTOR_NORM_SLACK: f64 = 1e-3;

/// What is wrong with a feature (the caller names the file).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct BadFeature(String);

/// Checks what a feature of level `l` can be, record by record: the checksum only proves the
/// file is the one that was written, not that what was written is a map (a file edited and its
/// CRC recomputed passes it). Each feature must lie in its index cell and inside the
/// orthophotos' bounds, have a height in the header's range, a SURF scale and response its level
/// and parameters allow, a Laplacian sign of -1 or +1, its own level, a listed orthophoto, a zero
/// reserved byte, and a descriptor that dequantises to unit length (quantised values in
/// `-127..=127`, the largest magnitude 127). Sections are already bounds-checked.
fn check_features(header: &MapHeader, l: usize, data: &[u8]) -> Result<(), BadFeature> {
    let info = &header.levels[l]; // ok: l enumerates header.levels
    let g = &info.grid;
    let len = descriptor_bytes(header.descriptor_kind());
    let expect = expected_features(header);
    let (h_lo, h_hi) = match header.height {
        super::HeightInfo::Dem { min_m, max_m, .. } => (min_m, max_m),
        super::HeightInfo::Constant { amsl_m } => (amsl_m, amsl_m),
    };
    if !(h_lo.is_finite() && h_hi.is_finite() && h_lo <= h_hi) {
        return Err(BadFeature(format!(
            "invalid height range {h_lo} to {h_hi} m in the header"
        )));
    }
    let b = &header.bounds;
    let slack = BOUNDS_SLACK_PX * info.gsd_m;
    let (max_scale_px, threshold) = (expect.max_scale_px, expect.min_response);
    let cells = &data[info.cells_offset as usize..];
    let recs = &data[info.records_offset as usize..];
    let descs = &data[info.descriptors_offset as usize..];
    for cell in 0..g.n_cells() {
        let start = u64::from_le_bytes(rd8(cells, 8 * cell)) as usize; // ok: checked <= n
        let end = u64::from_le_bytes(rd8(cells, 8 * cell + 8)) as usize;
        for i in start..end {
            let rb = &recs[i * RECORD_BYTES..(i + 1) * RECORD_BYTES];
            let (f, desc_scale) = decode_record(rb);
            let at = |what: String| BadFeature(format!("level {l} feature {i}: {what}"));
            if !(f.x_m >= b.min_x_m - slack
                && f.x_m <= b.max_x_m + slack
                && f.y_m >= b.min_y_m - slack
                && f.y_m <= b.max_y_m + slack)
            {
                return Err(at(format!(
                    "position ({}, {}) m is outside the map's bounds",
                    f.x_m, f.y_m
                )));
            }
            if g.cell_of(f.x_m, f.y_m) != cell {
                return Err(at(format!(
                    "position ({}, {}) m is not in its index cell {cell}",
                    f.x_m, f.y_m
                )));
            }
            if !(f.z_amsl_m >= h_lo - HEIGHT_SLACK_M && f.z_amsl_m <= h_hi + HEIGHT_SLACK_M) {
                return Err(at(format!(
                    "height {} m is outside the map's heights {h_lo} to {h_hi} m",
                    f.z_amsl_m
                )));
            }
            let scale_px = f64::from(f.scale_m) / info.gsd_m;
            if !(scale_px >= MIN_SCALE_PX && scale_px <= max_scale_px) {
                return Err(at(format!(
                    "feature scale {} m ({scale_px:.3} level px) is outside {MIN_SCALE_PX} to {max_scale_px:.0} px",
                    f.scale_m
                )));
            }
            if !(f64::from(f.response) >= threshold && f.response.is_finite()) {
                return Err(at(format!(
                    "feature response {} is below the detector's threshold {threshold} or not finite",
                    f.response
                )));
            }
            if !expect.laplacians.contains(&f.laplacian) {
                return Err(at(format!(
                    "Laplacian sign {} does not belong to {} features",
                    f.laplacian,
                    header.feature_spec()
                )));
            }
            if usize::from(f.level) != l {
                return Err(at(format!("records level {}", f.level)));
            }
            if usize::from(rb[38]) >= header.orthos.len() {
                return Err(at(format!(
                    "orthophoto index {} of {} orthophotos",
                    rb[38],
                    header.orthos.len()
                )));
            }
            if rb[39] != 0 {
                return Err(at(format!("reserved byte is {}, not 0", rb[39])));
            }
            if expect.binary {
                // Any bit pattern is a binary descriptor; its scale is fixed.
                if desc_scale != 1.0 {
                    return Err(at(format!(
                        "binary descriptor with scale {desc_scale} (binary descriptors have 1)"
                    )));
                }
                continue;
            }
            let q = &descs[i * len..(i + 1) * len];
            let (mut max_q, mut n2) = (0u8, 0f64);
            for &v in q {
                let v = i8::from_le_bytes([v]);
                if v == i8::MIN {
                    return Err(at(
                        "descriptor value -128 (quantised values are -127..=127)".into(),
                    ));
                }
                max_q = max_q.max(v.unsigned_abs());
                n2 += f64::from(v) * f64::from(v);
            }
            let s = f64::from(desc_scale);
            let norm = n2.sqrt() * s;
            let tol = (len as f64).sqrt() * s / 2.0 + DESCRIPTOR_NORM_SLACK;
            if !(s.is_finite() && s > 0.0 && max_q == 127 && (norm - 1.0).abs() <= tol) {
                return Err(at(format!(
                    "descriptor is not a quantised unit vector (scale {desc_scale}, largest value {max_q}, length {norm:.4})"
                )));
            }
        }
    }
    Ok(())
}

/// What a feature of a map's detector may hold ([`check_features`]).
struct ExpectedFeatures {
    /// Largest keypoint scale, level pixels (twice the detector's largest: the interpolation).
    max_scale_px: f64,
    /// Smallest response.
    min_response: f64,
    /// The Laplacian signs a keypoint may carry.
    laplacians: &'static [i8],
    /// Binary descriptors (any bits, scale 1) rather than quantised unit vectors.
    binary: bool,
}

fn expected_features(header: &MapHeader) -> ExpectedFeatures {
    match header.feature_spec() {
        FeatureSpec::Surf(s) => {
            // The largest SURF filter: 3 (2^octaves (layers + 2) + 1) px, scale 1.2 / 9 of it;
            // twice that covers the interpolation of the extremum between filters.
            let max_filter =
                3.0 * ((1u64 << s.n_octaves.min(30)) as f64 * (s.n_octave_layers + 2) as f64 + 1.0);
            ExpectedFeatures {
                max_scale_px: 2.0 * 1.2 * max_filter / 9.0,
                min_response: f64::from(s.hessian_threshold),
                laplacians: &[-1, 1],
                binary: false,
            }
        }
        FeatureSpec::Orb(o) => ExpectedFeatures {
            max_scale_px: 2.0 * o.largest_scale_px(),
            min_response: 0.0,
            laplacians: &[0],
            binary: true,
        },
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::map::{HeightInfo, LevelInfo};
    use visnav_core::geo::Crs;
    use visnav_core::geo::raster::Bounds;
    use visnav_core::vision::SurfParams;

    pub(crate) fn tiny_header(levels: usize) -> MapHeader {
        MapHeader {
            version: FORMAT_VERSION,
            crs: Crs::Utm {
                zone: 14,
                north: true,
            },
            surf: SurfParams {
                upright: true,
                ..SurfParams::default()
            },
            orb: None,
            levels: (0..levels)
                .map(|l| LevelInfo {
                    gsd_m: 5.0 * f64::from(1u32 << l),
                    n_features: 0,
                    grid: IndexGrid {
                        origin_x_m: 0.0,
                        origin_y_m: 0.0,
                        cell_m: 1.0,
                        cols: 1,
                        rows: 1,
                    },
                    cells_offset: 0,
                    records_offset: 0,
                    descriptors_offset: 0,
                    image: None,
                })
                .collect(),
            bounds: Bounds {
                min_x_m: 1000.0,
                min_y_m: 2000.0,
                max_x_m: 1100.0,
                max_y_m: 2100.0,
            },
            height: HeightInfo::Constant { amsl_m: 580.0 },
            height_sigma_m: 10.0,
            height_slope_sigma: Some(0.01),
            height_point_sigma_m: Some(10.0),
            vertical_datum: "constant".into(),
            orthos: vec![],
            tile_px: 64,
            max_features_per_tile: 100,
            built_unix_s: 0,
            built_by: "test".into(),
        }
    }

    /// Writes a map with pseudo-random features in [1000, 1100] x [2000, 2100] on 2 levels.
    fn tiny_map(dir: &Path, n: usize) -> (PathBuf, Vec<(MapFeature, Vec<f32>)>) {
        let grid = IndexGrid {
            origin_x_m: 1000.0,
            origin_y_m: 2100.0,
            cell_m: 30.0,
            cols: 4,
            rows: 4,
        };
        let kind = DescriptorKind::Surf64;
        let mut w = SpillWriter::new(&dir.join("t.spill"), kind, vec![grid, grid]).unwrap();
        let mut rng = 12345u64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut all = Vec::new();
        for i in 0..n {
            let level = (i % 2) as u8;
            let f = MapFeature {
                x_m: 1000.0 + 100.0 * next(),
                y_m: 2000.0 + 100.0 * next(),
                z_amsl_m: 500.0 + next(),
                scale_m: 2.0 * 5.0 * f32::from(1u8 << level),
                response: 100.0 + 900.0 * next() as f32,
                laplacian: if i % 3 == 0 { -1 } else { 1 },
                level,
            };
            let mut d: Vec<f32> = (0..64).map(|_| next() as f32 - 0.5).collect();
            let n2: f32 = d.iter().map(|v| v * v).sum::<f32>().sqrt();
            d.iter_mut().for_each(|v| *v /= n2);
            w.push(usize::from(level), &f, &d, 0).unwrap();
            all.push((f, d));
        }
        let path = dir.join("t.vnm");
        let mut header = tiny_header(2);
        header.height = HeightInfo::Dem {
            file: "dem.tif".into(),
            min_m: 500.0,
            max_m: 501.0,
        };
        header.orthos = vec![crate::map::OrthoInfo {
            file: "o.tif".into(),
            width_px: 20,
            height_px: 20,
            bands: 1,
            pixel_size_m: 5.0,
        }];
        w.finish(header, &path).unwrap();
        (path, all)
    }

    #[test]
    fn round_trip_and_select_matches_brute_force() {
        let dir = tempfile::tempdir().unwrap();
        let (path, all) = tiny_map(dir.path(), 500);
        let m = ReferenceMap::open(&path).unwrap();
        assert_eq!(m.header().n_features(), 500);
        assert_eq!(m.header().levels[0].n_features, 250);
        for level in 0..2 {
            for rect in [
                (1010.0, 2020.0, 1050.0, 2070.0),
                (900.0, 1900.0, 1200.0, 2200.0),
                (1031.0, 2031.0, 1032.0, 2099.0),
            ] {
                let sel = m.select(level, rect.0, rect.1, rect.2, rect.3);
                let mut expect: Vec<&(MapFeature, Vec<f32>)> = all
                    .iter()
                    .filter(|(f, _)| {
                        usize::from(f.level) == level
                            && f.x_m >= rect.0
                            && f.x_m <= rect.2
                            && f.y_m >= rect.1
                            && f.y_m <= rect.3
                    })
                    .collect();
                assert_eq!(sel.len(), expect.len(), "{rect:?}");
                assert_eq!(sel.descriptors.len(), sel.len() * 64);
                expect.sort_by(|a, b| a.0.x_m.total_cmp(&b.0.x_m));
                let mut got: Vec<usize> = (0..sel.len()).collect();
                got.sort_by(|&a, &b| sel.features[a].x_m.total_cmp(&sel.features[b].x_m));
                for (e, &g) in expect.iter().zip(&got) {
                    assert_eq!(e.0, sel.features[g]);
                    let d = sel.descriptor(g);
                    let err: f32 = d.iter().zip(&e.1).map(|(a, b)| (a - b).abs()).sum();
                    assert!(err < 64.0 * 0.01, "descriptor error {err}");
                }
            }
        }
        assert!(m.select(5, 0.0, 0.0, 1e9, 1e9).is_empty());
        assert!(m.select(0, f64::NAN, 0.0, 1e9, 1e9).is_empty());
        assert!(m.select(0, 1100.0, 0.0, 1000.0, 1e9).is_empty());
    }

    #[test]
    fn quantisation_round_trip() {
        let d: Vec<f32> = (0..64).map(|i| ((i as f32) * 0.37).sin()).collect();
        let n: f32 = d.iter().map(|v| v * v).sum::<f32>().sqrt();
        let d: Vec<f32> = d.iter().map(|v| v / n).collect();
        let mut q = vec![0i8; 64];
        let s = quantise(&d, &mut q);
        let mut back = vec![0f32; 64];
        dequantise(&q, s, &mut back);
        for (a, b) in d.iter().zip(&back) {
            assert!((a - b).abs() <= s, "{a} vs {b}");
        }
        let z = quantise(&[0.0; 64], &mut q);
        assert_eq!(z, 0.0);
        dequantise(&q, z, &mut back);
        assert!(back.iter().all(|v| *v == 0.0));
    }

    /// A version-1 file (no level images) still opens: its levels have no image.
    #[test]
    fn version_1_maps_are_read_without_images() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = tiny_map(dir.path(), 40);
        let mut b = std::fs::read(&path).unwrap();
        assert_eq!(u32::from_le_bytes(rd4(&b, 8)), FORMAT_VERSION);
        // Rewrite the version in the preamble and the JSON header (same length), re-checksum.
        b[8..12].copy_from_slice(&1u32.to_le_bytes());
        let hl = u64::from_le_bytes(rd8(&b, 16)) as usize;
        let json = String::from_utf8(b[64..64 + hl].to_vec()).unwrap();
        let v1 = json.replacen(&format!("\"version\":{FORMAT_VERSION}"), "\"version\":1", 1);
        assert_eq!(v1.len(), json.len());
        assert!(!v1.contains("\"image\""));
        b[64..64 + hl].copy_from_slice(v1.as_bytes());
        let crc = crc_of(&b);
        b[CRC_AT..CRC_AT + 4].copy_from_slice(&crc.to_le_bytes());
        let p1 = dir.path().join("v1.vnm");
        std::fs::write(&p1, &b).unwrap();
        let m = ReferenceMap::open(&p1).unwrap();
        assert_eq!(m.header().version, 1);
        assert!(m.level_image(0).is_none());
        assert_eq!(m.all_features(0).len(), 20);
    }

    /// Image blocks land at their places, clipped, and no-data bytes never overwrite data.
    #[test]
    fn image_blocks_are_placed_and_clipped() {
        let dir = tempfile::tempdir().unwrap();
        let grid = IndexGrid {
            origin_x_m: 1000.0,
            origin_y_m: 2100.0,
            cell_m: 50.0,
            cols: 2,
            rows: 2,
        };
        let img = |w, h| LevelImageInfo {
            offset: 0,
            width_px: w,
            height_px: h,
            origin_x_m: 1000.0,
            origin_y_m: 2100.0,
        };
        let mut w = SpillWriter::new(
            &dir.path().join("i.spill"),
            DescriptorKind::Surf64,
            vec![grid, grid],
        )
        .unwrap()
        .with_images(vec![img(5, 4), img(3, 2)])
        .unwrap();
        // Level 0: a 3x2 block at (-1, 1): its first column is clipped away.
        w.push_image_block(0, -1, 1, 3, 2, &[9, 1, 2, 9, 3, 4])
            .unwrap();
        // A later block with a hole (0) over (0, 1) keeps the earlier value there.
        w.push_image_block(0, 0, 1, 2, 1, &[0, 7]).unwrap();
        // Level 1: beyond the image entirely: ignored.
        w.push_image_block(1, 5, 5, 1, 1, &[8]).unwrap();
        let path = dir.path().join("i.vnm");
        w.finish(tiny_header(2), &path).unwrap();
        let m = ReferenceMap::open(&path).unwrap();
        let (info, data) = m.level_image(0).unwrap();
        assert_eq!((info.width_px, info.height_px), (5, 4));
        #[rustfmt::skip]
        let want = [
            0, 0, 0, 0, 0,
            1, 7, 0, 0, 0,
            3, 4, 0, 0, 0,
            0, 0, 0, 0, 0,
        ];
        assert_eq!(data, &want);
        assert!(m.level_image(1).unwrap().1.iter().all(|v| *v == 0));
        assert!(!dir.path().join("i.img.spill").exists());
    }

    /// Truncations and byte flips anywhere give a `Format` error naming the file, never a panic
    /// and never a silently accepted file.
    #[test]
    fn corrupted_files_are_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = tiny_map(dir.path(), 60);
        let good = std::fs::read(&path).unwrap();
        let bad = dir.path().join("bad.vnm");
        let check = |bytes: &[u8], what: &str| {
            std::fs::write(&bad, bytes).unwrap();
            match ReferenceMap::open(&bad) {
                Err(MapError::Format { path, reason }) => {
                    assert_eq!(path, bad, "{what}");
                    assert!(!reason.is_empty());
                    reason
                }
                other => panic!("{what}: expected a format error, got {other:?}"),
            }
        };
        for cut in [0, 7, 63, 64, 100, good.len() / 2, good.len() - 1] {
            check(&good[..cut], &format!("truncated at {cut}"));
        }
        let step = (good.len() / 97).max(1);
        for at in (0..good.len()).step_by(step) {
            let mut b = good.clone();
            b[at] ^= 0x5a;
            check(&b, &format!("flipped byte {at}"));
        }
        let mut b = good.clone();
        b[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        let r = check(&b, "version");
        assert!(
            r.contains(&format!("version {}", FORMAT_VERSION + 1)),
            "{r}"
        );
        let mut b = good.clone();
        b[0] = b'X';
        assert!(check(&b, "magic").contains("magic"));
        let mut b = good.clone();
        b.extend_from_slice(&[0; 8]);
        check(&b, "appended");
        // A missing file: an Io error naming it.
        match ReferenceMap::open(&dir.path().join("absent.vnm")) {
            Err(e @ MapError::Io { .. }) => assert!(e.to_string().contains("absent.vnm")),
            other => panic!("{other:?}"),
        }
    }
}
