//! Image files to and from [`GrayImage`] (the `image` crate decodes and encodes): the file side
//! of visnav-core's pure grayscale image.
//!
//! Colour is converted with the ITU-R BT.601 luma weights (0.299 R + 0.587 G + 0.114 B), as
//! OpenCV's `cvtColor(..., COLOR_RGB2GRAY)` does; 16-bit grey is scaled by 255/65535 to the 8-bit
//! intensity scale SURF's Hessian threshold is defined on.

use std::path::Path;

use visnav_core::vision::{GrayImage, VisionError};

/// Why a JPEG was refused. The `image` crate decodes JPEG leniently (zune-jpeg with its strict
/// mode off): corrupt entropy-coded data is logged and the rest of the image filled in, so a frame
/// with a flipped bit decodes to a picture that is partly wrong. Frames are decoded here in strict
/// mode instead, and every such error refuses the frame.
#[derive(Debug, thiserror::Error)]
pub enum JpegError {
    /// The JPEG stream is corrupt.
    #[error("corrupt JPEG: {0}")]
    Corrupt(String),
    /// The JPEG has no pixels.
    #[error("JPEG has no pixels")]
    Empty,
    /// The JPEG decoded to another size than its header states.
    #[error("JPEG of {width} x {height} px decoded to {got} bytes, expected {want}")]
    Size {
        /// Width the header states, pixels.
        width: usize,
        /// Height the header states, pixels.
        height: usize,
        /// Bytes decoded.
        got: usize,
        /// Bytes the size needs.
        want: usize,
    },
}

/// Walks the entropy-coded data of a baseline (sequential Huffman) JPEG block by block, without
/// transforming anything, and checks that it holds exactly the blocks its header announces: every
/// Huffman code valid, no coefficient beyond the 64 of its block, the restart markers in sequence,
/// and no data left after the last block nor a marker before it. A flipped bit in a Huffman code
/// desynchronises the decoding, which then ends at another place (zune-jpeg, even strict, decodes
/// such a stream to the end and fills in the rest). A flipped magnitude bit changes one
/// coefficient and stays undetectable by any decoder (and local). Progressive and arithmetic
/// JPEGs are not walked (the strict decoder's checks only).
fn check_entropy_data(b: &[u8]) -> Result<(), JpegError> {
    let mut w = JpegWalk::default();
    let mut i = 2; // after SOI
    loop {
        // Next marker (fill bytes 0xFF allowed).
        if b.get(i) != Some(&0xFF) {
            return Err(corrupt(format!("expected a marker at byte {i}")));
        }
        while b.get(i) == Some(&0xFF) {
            i += 1;
        }
        let Some(&m) = b.get(i) else {
            return Err(corrupt("no end-of-image marker".into()));
        };
        i += 1;
        match m {
            0xD9 => return Ok(()), // EOI
            0xD0..=0xD7 | 0x01 => continue,
            _ => {}
        }
        let len = u16_at(b, i)?;
        let seg = b
            .get(i + 2..i + len)
            .ok_or_else(|| corrupt("truncated marker segment".into()))?;
        i += len;
        match m {
            0xC0 | 0xC1 => w.frame_header(seg)?,
            // Progressive, lossless, arithmetic: not walked.
            0xC2 | 0xC3 | 0xC5..=0xC7 | 0xC9..=0xCB | 0xCD..=0xCF => return Ok(()),
            0xC4 => w.huffman_tables(seg)?,
            0xDD => w.restart = u16_at(b, i - len + 2)?,
            0xDA => match w.scan(b, seg, i)? {
                Some(end) => i = end,
                None => return Ok(()),
            },
            _ => {}
        }
    }
}

fn corrupt(m: String) -> JpegError {
    JpegError::Corrupt(m)
}

/// The big-endian 16-bit number at `b[i..i + 2]`.
fn u16_at(b: &[u8], i: usize) -> Result<usize, JpegError> {
    match b.get(i..i + 2) {
        Some(v) => Ok(usize::from(u16::from_be_bytes([v[0], v[1]]))),
        None => Err(corrupt("truncated marker segment".into())),
    }
}

/// What [`check_entropy_data`] has read of the headers so far.
#[derive(Default)]
struct JpegWalk {
    /// (DC, AC) Huffman tables by id.
    dc: [Option<Huffman>; 4],
    ac: [Option<Huffman>; 4],
    /// Components: (id, h, v).
    comps: Vec<(u8, usize, usize)>,
    width: usize,
    height: usize,
    /// MCUs per restart interval (0: none).
    restart: usize,
}

impl JpegWalk {
    /// A baseline or extended sequential frame header (SOF0, SOF1).
    fn frame_header(&mut self, seg: &[u8]) -> Result<(), JpegError> {
        if seg.len() < 6 {
            return Err(corrupt("short frame header".into()));
        }
        self.height = usize::from(u16::from_be_bytes([seg[1], seg[2]]));
        self.width = usize::from(u16::from_be_bytes([seg[3], seg[4]]));
        self.comps = seg[6..]
            .chunks_exact(3)
            .take(usize::from(seg[5]))
            .map(|c| (c[0], usize::from(c[1] >> 4), usize::from(c[1] & 15)))
            .collect();
        if self.comps.is_empty() || self.comps.iter().any(|&(_, h, v)| h == 0 || v == 0) {
            return Err(corrupt("invalid components in the frame header".into()));
        }
        Ok(())
    }

    /// A DHT segment: one or more Huffman tables.
    fn huffman_tables(&mut self, seg: &[u8]) -> Result<(), JpegError> {
        let mut k = 0;
        while k < seg.len() {
            let class_id = seg[k];
            let counts = seg
                .get(k + 1..k + 17)
                .ok_or_else(|| corrupt("short Huffman table".into()))?;
            let n: usize = counts.iter().map(|&c| usize::from(c)).sum();
            let values = seg
                .get(k + 17..k + 17 + n)
                .ok_or_else(|| corrupt("short Huffman table".into()))?;
            let t = Huffman::new(counts, values);
            let id = usize::from(class_id & 3);
            if class_id >> 4 == 0 {
                self.dc[id] = Some(t);
            } else {
                self.ac[id] = Some(t);
            }
            k += 17 + n;
        }
        Ok(())
    }

    /// A scan whose header `seg` ends at byte `start` of `b`: walks its blocks and returns where
    /// the scan ends, or `None` when it is not walked (no tables: MJPG's default tables).
    fn scan(&self, b: &[u8], seg: &[u8], start: usize) -> Result<Option<usize>, JpegError> {
        if self.width == 0 || self.height == 0 {
            return Err(corrupt("scan before the frame header".into()));
        }
        let n = usize::from(*seg.first().unwrap_or(&0));
        let mut scan = Vec::new();
        for c in seg.get(1..1 + 2 * n).unwrap_or(&[]).chunks_exact(2) {
            let &(_, h, v) = self
                .comps
                .iter()
                .find(|x| x.0 == c[0])
                .ok_or_else(|| corrupt(format!("scan names unknown component {}", c[0])))?;
            // Table selectors are 0-3 (T.81 B.2.3); a larger one is a corrupt header.
            let (Some(d), Some(a)) = (
                self.dc
                    .get(usize::from(c[1] >> 4))
                    .ok_or_else(|| corrupt(format!("DC table {} out of range", c[1] >> 4)))?,
                &self.ac[usize::from(c[1] & 3)],
            ) else {
                return Ok(None);
            };
            scan.push((h, v, d, a));
        }
        if scan.is_empty() {
            return Err(corrupt("scan without components".into()));
        }
        let (mcus, per) = self.mcus(&scan);
        let mut r = BitReader {
            b,
            pos: start,
            acc: 0,
            n: 0,
        };
        for mcu in 0..mcus {
            if self.restart > 0 && mcu > 0 && mcu % self.restart == 0 {
                r.n = 0; // padding of the interval's last byte
                let want = 0xD0 + ((mcu / self.restart - 1) % 8) as u8;
                if b.get(r.pos) != Some(&0xFF) || b.get(r.pos + 1) != Some(&want) {
                    return Err(corrupt(format!(
                        "restart marker {} missing before MCU {mcu}",
                        want - 0xD0
                    )));
                }
                r.pos += 2;
            }
            for (c, &nb) in scan.iter().zip(&per) {
                for _ in 0..nb {
                    r.block(c.2, c.3)
                        .map_err(|m| corrupt(format!("MCU {mcu}: {m}")))?;
                }
            }
        }
        // The scan must end here: at most the padding bits of this byte remain.
        if !(b.get(r.pos) == Some(&0xFF) && b.get(r.pos + 1).is_some_and(|&m| m != 0)) {
            let rest = b
                .get(r.pos..)
                .unwrap_or(&[])
                .windows(2)
                .position(|w| w[0] == 0xFF && w[1] != 0);
            return Err(corrupt(format!(
                "{} bytes of entropy-coded data after the last block",
                rest.unwrap_or(b.len().saturating_sub(r.pos))
            )));
        }
        Ok(Some(r.pos))
    }

    /// The scan's MCUs and the blocks of each of its components per MCU (a one-component scan
    /// is not interleaved: one block per MCU).
    fn mcus(&self, scan: &[(usize, usize, &Huffman, &Huffman)]) -> (usize, Vec<usize>) {
        let hmax = self.comps.iter().map(|c| c.1).max().unwrap_or(1);
        let vmax = self.comps.iter().map(|c| c.2).max().unwrap_or(1);
        if scan.len() == 1 {
            let (h, v, _, _) = scan[0];
            let bw = (self.width * h).div_ceil(hmax).div_ceil(8);
            let bh = (self.height * v).div_ceil(vmax).div_ceil(8);
            (bw * bh, vec![1])
        } else {
            let mw = self.width.div_ceil(8 * hmax);
            let mh = self.height.div_ceil(8 * vmax);
            (mw * mh, scan.iter().map(|s| s.0 * s.1).collect())
        }
    }
}

/// A Huffman table in the decoding form of ITU T.81 F.2.2.3.
struct Huffman {
    max_code: [i32; 17],
    first_code: [i32; 17],
    first_index: [usize; 17],
    values: Vec<u8>,
}

impl Huffman {
    fn new(counts: &[u8], values: &[u8]) -> Self {
        let mut t = Huffman {
            max_code: [-1; 17],
            first_code: [0; 17],
            first_index: [0; 17],
            values: values.to_vec(),
        };
        let (mut code, mut k) = (0i32, 0usize);
        for l in 1..=16 {
            let n = usize::from(counts[l - 1]);
            t.first_index[l] = k;
            t.first_code[l] = code;
            if n > 0 {
                code += n as i32; // ok: at most 256 values
                t.max_code[l] = code - 1;
                k += n;
            }
            code <<= 1;
        }
        t
    }
}

/// What is wrong in the entropy-coded data (the caller adds where).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
struct StreamError(String);

/// Bits of the entropy-coded data (byte stuffing removed; a marker ends them).
struct BitReader<'a> {
    b: &'a [u8],
    pos: usize,
    acc: u32,
    n: u32,
}

impl BitReader<'_> {
    fn bit(&mut self) -> Result<u32, StreamError> {
        if self.n == 0 {
            let byte = *self
                .b
                .get(self.pos)
                .ok_or(StreamError("the data ends inside a block".into()))?;
            if byte == 0xFF {
                match self.b.get(self.pos + 1) {
                    Some(0x00) => self.pos += 2,
                    _ => {
                        return Err(StreamError(
                            "a marker inside a block (the data ran out)".into(),
                        ));
                    }
                }
            } else {
                self.pos += 1;
            }
            self.acc = u32::from(byte);
            self.n = 8;
        }
        self.n -= 1;
        Ok((self.acc >> self.n) & 1)
    }
    fn bits(&mut self, s: u32) -> Result<(), StreamError> {
        for _ in 0..s {
            self.bit()?;
        }
        Ok(())
    }
    fn decode(&mut self, t: &Huffman) -> Result<u8, StreamError> {
        let mut code = 0i32;
        for l in 1..=16 {
            code = (code << 1) | self.bit()? as i32; // ok: one bit
            if code <= t.max_code[l] {
                let k = t.first_index[l] + (code - t.first_code[l]) as usize; // ok: >= 0
                return t
                    .values
                    .get(k)
                    .copied()
                    .ok_or_else(|| StreamError("invalid Huffman code".into()));
            }
        }
        Err(StreamError("invalid Huffman code".into()))
    }
    /// One 8 x 8 block: DC difference, then AC run/size pairs up to 63 or end-of-block.
    fn block(&mut self, dc: &Huffman, ac: &Huffman) -> Result<(), StreamError> {
        let s = self.decode(dc)?;
        if s > 11 {
            return Err(StreamError(format!("DC magnitude category {s}")));
        }
        self.bits(u32::from(s))?;
        let mut k = 1;
        while k < 64 {
            let rs = self.decode(ac)?;
            let (run, size) = (usize::from(rs >> 4), rs & 15);
            if size == 0 {
                if run == 15 {
                    k += 16;
                    continue;
                }
                break; // end of block
            }
            k += run;
            if k > 63 || size > 10 {
                return Err(StreamError(format!(
                    "AC coefficient {k} of size {size} beyond the block"
                )));
            }
            self.bits(u32::from(size))?;
            k += 1;
        }
        if k > 64 {
            return Err(StreamError("zero run beyond the block".into()));
        }
        Ok(())
    }
}

/// Whether `bytes` start with the JPEG start-of-image marker.
pub fn is_jpeg(bytes: &[u8]) -> bool {
    bytes.starts_with(&[0xFF, 0xD8, 0xFF])
}

/// Decode a JPEG to grey, strictly: any error in the entropy-coded data, a premature end or an
/// unexpected marker is an error (the lenient decoder would fill the damage in). Grey JPEGs give
/// their luma; colour ones are converted to RGB and then to luma with the weights of
/// [`GrayImageFile::from_dynamic`], as the `image` crate's decoder does.
pub fn decode_jpeg_strict(bytes: &[u8]) -> Result<GrayImage, JpegError> {
    use zune_core::colorspace::ColorSpace;
    let corrupt = |e: zune_jpeg::errors::DecodeErrors| JpegError::Corrupt(e.to_string());
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(usize::MAX)
        .set_max_height(usize::MAX);
    let mut dec = zune_jpeg::JpegDecoder::new_with_options(
        zune_core::bytestream::ZCursor::new(bytes),
        options,
    );
    dec.decode_headers().map_err(corrupt)?;
    check_entropy_data(bytes)?;
    let grey = matches!(
        dec.input_colorspace(),
        Some(ColorSpace::Luma | ColorSpace::LumaA)
    );
    let out = if grey {
        ColorSpace::Luma
    } else {
        ColorSpace::RGB
    };
    dec.set_options(dec.options().jpeg_set_out_colorspace(out));
    let px = dec.decode().map_err(corrupt)?;
    let (width, height) = dec.dimensions().ok_or(JpegError::Empty)?;
    if width == 0 || height == 0 {
        return Err(JpegError::Empty);
    }
    let channels = if grey { 1 } else { 3 };
    let want = width * height * channels;
    if px.len() != want {
        return Err(JpegError::Size {
            width,
            height,
            got: px.len(),
            want,
        });
    }
    let data = if grey {
        px.iter().map(|&v| f32::from(v)).collect()
    } else {
        px.chunks_exact(3)
            .map(|p| 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]))
            .collect()
    };
    GrayImage::new(width, height, data).map_err(|_| JpegError::Empty)
}

/// [`GrayImage`] from and to files and decoded images. In scope, `GrayImage::load(path)` and
/// `image.save_png(path)` read as methods of the image.
pub trait GrayImageFile: Sized {
    /// Convert any decoded image (gray, RGB, RGBA; for 4-band RGBN GeoTIFFs the 4th band is
    /// ignored). `InvalidImage` when it has no pixels.
    fn from_dynamic(img: &image::DynamicImage) -> Result<Self, VisionError>;
    /// Read an image file (PNG, JPEG, TIFF incl. 4-band GeoTIFF pixels) and convert it to gray.
    fn load(path: &Path) -> Result<Self, VisionError>;
    /// Save as 8-bit PNG (values rounded and clamped to 0..=255, non-finite values as 0).
    fn save_png(&self, path: &Path) -> Result<(), VisionError>;
}

impl GrayImageFile for GrayImage {
    fn from_dynamic(img: &image::DynamicImage) -> Result<Self, VisionError> {
        use image::DynamicImage as D;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let data = match img {
            D::ImageLuma8(g) => g.as_raw().iter().map(|&v| f32::from(v)).collect(),
            D::ImageLuma16(g) => g.as_raw().iter().map(|&v| f32::from(v) / 257.0).collect(),
            other => other
                .to_rgb8()
                .as_raw()
                .chunks_exact(3)
                .map(|p| {
                    0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])
                })
                .collect(),
        };
        GrayImage::new(w, h, data)
    }

    fn load(path: &Path) -> Result<Self, VisionError> {
        let read_error = |reason: String| VisionError::ImageRead {
            path: path.to_path_buf(),
            reason,
        };
        let bytes = crate::files::read_bytes(path, crate::files::IMAGE)
            .map_err(|e| read_error(e.to_string()))?;
        if is_jpeg(&bytes) {
            return decode_jpeg_strict(&bytes).map_err(|e| read_error(e.to_string()));
        }
        let img = image::load_from_memory(&bytes).map_err(|e| read_error(e.to_string()))?;
        if img.width() == 0 || img.height() == 0 {
            return Err(read_error("image has no pixels".into()));
        }
        Self::from_dynamic(&img).map_err(|e| read_error(e.to_string()))
    }

    fn save_png(&self, path: &Path) -> Result<(), VisionError> {
        let buf: Vec<u8> = self
            .data()
            .iter()
            .map(|&v| {
                if v.is_finite() {
                    v.round().clamp(0.0, 255.0) as u8
                } else {
                    0
                }
            })
            .collect();
        image::save_buffer(
            path,
            &buf,
            self.width() as u32,
            self.height() as u32,
            image::ExtendedColorType::L8,
        )
        .map_err(|e| VisionError::ImageWrite {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Grey, 16-bit grey and colour decode to the 8-bit luma scale; a PNG round trip keeps the
    /// rounded values; a missing file names its path.
    #[test]
    fn files_decode_to_luma_and_round_trip() {
        let g8 = image::DynamicImage::ImageLuma8(
            image::GrayImage::from_raw(2, 1, vec![10, 200]).unwrap(),
        );
        let g = GrayImage::from_dynamic(&g8).unwrap();
        assert_eq!(g.data(), &[10.0, 200.0]);
        let g16 = image::DynamicImage::ImageLuma16(
            image::ImageBuffer::from_raw(1, 1, vec![65535u16]).unwrap(),
        );
        assert!((GrayImage::from_dynamic(&g16).unwrap().data()[0] - 255.0).abs() < 1e-3);
        let rgb = image::DynamicImage::ImageRgb8(
            image::RgbImage::from_raw(1, 1, vec![100, 50, 20]).unwrap(),
        );
        let want = 0.299 * 100.0 + 0.587 * 50.0 + 0.114 * 20.0;
        assert!((GrayImage::from_dynamic(&rgb).unwrap().data()[0] - want).abs() < 1e-3);

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.png");
        let img = GrayImage::new(3, 2, vec![0.4, 1.6, 254.7, 300.0, -5.0, f32::NAN]).unwrap();
        img.save_png(&path).unwrap();
        let back = GrayImage::load(&path).unwrap();
        assert_eq!(back.data(), &[0.0, 2.0, 255.0, 255.0, 0.0, 0.0]);
        let missing = dir.path().join("none.png");
        let e = GrayImage::load(&missing).unwrap_err().to_string();
        assert!(e.contains("none.png"), "{e}");
    }

    #[test]
    fn an_endless_device_is_refused_not_read() {
        let e = GrayImage::load(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("/dev/zero") && e.contains("not a regular file"),
            "{e}"
        );
    }
}
