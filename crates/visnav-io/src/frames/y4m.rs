//! YUV4MPEG2 files (the module doc of [`super`] lists the colour spaces read) and their
//! writing.

use super::*;

/// Plane layout of a y4m colour space.
#[derive(Debug, Clone, Copy)]
struct Layout {
    /// Bytes per sample (1 or 2).
    bytes: usize,
    /// Maximum sample value (255, 1023, 4095, 65535).
    max: f64,
    /// Bytes after the luma plane in one frame, as a function of W, H.
    chroma: fn(usize, usize) -> usize,
}

fn chroma_420(w: usize, h: usize) -> usize {
    2 * w.div_ceil(2) * h.div_ceil(2)
}
fn chroma_422(w: usize, h: usize) -> usize {
    2 * w.div_ceil(2) * h
}
fn chroma_444(w: usize, h: usize) -> usize {
    2 * w * h
}
fn chroma_444a(w: usize, h: usize) -> usize {
    3 * w * h
}
fn chroma_none(_: usize, _: usize) -> usize {
    0
}

fn layout(c: &str) -> Option<Layout> {
    let l8 = |chroma| Layout {
        bytes: 1,
        max: 255.0,
        chroma,
    };
    let l16 = |bits: u32, chroma| Layout {
        bytes: 2,
        max: f64::from((1u32 << bits) - 1),
        chroma,
    };
    Some(match c {
        "420jpeg" | "420paldv" | "420mpeg2" | "420" => l8(chroma_420),
        "422" => l8(chroma_422),
        "444" => l8(chroma_444),
        "444alpha" => l8(chroma_444a),
        "mono" => l8(chroma_none),
        "mono16" => l16(16, chroma_none),
        _ => {
            let (base, bits) = c.split_once('p')?;
            let bits: u32 = bits.parse().ok().filter(|b| [10, 12, 16].contains(b))?;
            let chroma: fn(usize, usize) -> usize = match base {
                "420" => chroma_420,
                "422" => chroma_422,
                "444" => chroma_444,
                _ => return None,
            };
            l16(bits, chroma)
        }
    })
}

/// A YUV4MPEG2 stream (see the module docs): a file ([`Y4mSource::open`]) or any reader
/// ([`Y4mSource::from_reader`], e.g. a capture process's stdout).
pub struct Y4mSource {
    path: PathBuf,
    r: Box<dyn BufRead + Send>,
    width: usize,
    height: usize,
    fps: f64,
    colour: String,
    lay: Layout,
    next: u64,
    buf: Vec<u8>,
}

/// Largest frame accepted from a y4m stream, pixels (8192 x 8192): a corrupt header cannot
/// make the reader allocate gigabytes.
pub const MAX_Y4M_PIXELS: usize = 1 << 26;

/// Read one '\n'-terminated line of at most `max` bytes; None at a clean EOF.
pub(super) fn read_line_limited(
    r: &mut impl BufRead,
    max: usize,
) -> std::io::Result<Option<Vec<u8>>> {
    let mut out = Vec::new();
    let n = r.take(max as u64 + 1).read_until(b'\n', &mut out)?;
    if n == 0 {
        return Ok(None);
    }
    Ok(Some(out))
}

impl Y4mSource {
    /// Open a file and parse the stream header.
    pub fn open(path: &Path) -> Result<Self, FrameError> {
        let f = File::open(path).map_err(|source| FrameError::Io {
            path: path.to_path_buf(),
            cause: source,
        })?;
        Self::from_reader(Box::new(BufReader::new(f)), path)
    }

    /// Parse the stream header from `r`; `path` names the stream in errors (a file name, or a
    /// description of a process). Blocks until the header line arrived.
    pub fn from_reader(mut r: Box<dyn BufRead + Send>, path: &Path) -> Result<Self, FrameError> {
        let herr = |reason: String| FrameError::Y4mHeader {
            path: path.to_path_buf(),
            reason,
        };
        let line = read_line_limited(&mut r, 1024)
            .map_err(|source| FrameError::Io {
                path: path.to_path_buf(),
                cause: source,
            })?
            .ok_or_else(|| herr("the file is empty".into()))?;
        if line.last() != Some(&b'\n') {
            return Err(herr(
                "header line is not terminated within 1024 bytes".into(),
            ));
        }
        if line.contains(&0) {
            return Err(herr("header contains NUL bytes (binary data)".into()));
        }
        let text = std::str::from_utf8(&line[..line.len() - 1])
            .map_err(|_| herr("header is not ASCII".into()))?;
        let mut tok = text.split(' ').filter(|t| !t.is_empty());
        if tok.next() != Some("YUV4MPEG2") {
            return Err(herr("missing the \"YUV4MPEG2\" signature".into()));
        }
        let (mut w, mut h, mut fps, mut colour) = (None, None, None, "420".to_string());
        for t in tok {
            // Split after the first character (a byte split could cut a UTF-8 character).
            let mut chars = t.chars();
            let k = chars.next().unwrap_or(' ');
            let v = chars.as_str();
            match k {
                'W' => w = v.parse::<usize>().ok(),
                'H' => h = v.parse::<usize>().ok(),
                'F' => {
                    fps = v.split_once(':').and_then(|(n, d)| {
                        let n: f64 = n.parse().ok()?;
                        let d: f64 = d.parse().ok()?;
                        (n > 0.0 && d > 0.0).then_some(n / d)
                    });
                    if fps.is_none() {
                        return Err(herr(format!(
                            "frame rate \"F{v}\" is not N:D with N, D > 0"
                        )));
                    }
                }
                'C' => colour = v.to_string(),
                _ => {} // I (interlacing), A (aspect), X (comments): irrelevant for luma
            }
        }
        let width = w.filter(|v| (1..=16384).contains(v));
        let height = h.filter(|v| (1..=16384).contains(v));
        let (Some(width), Some(height)) = (width, height) else {
            return Err(herr("W and H must be present and within 1..=16384".into()));
        };
        if width * height > MAX_Y4M_PIXELS {
            return Err(herr(format!(
                "{width}x{height} exceeds the {MAX_Y4M_PIXELS} pixels accepted per frame"
            )));
        }
        let lay = layout(&colour)
            .ok_or_else(|| herr(format!("colour space \"C{colour}\" is not supported")))?;
        Ok(Self {
            path: path.to_path_buf(),
            r,
            width,
            height,
            fps: fps.unwrap_or(25.0),
            colour,
            lay,
            next: 0,
            buf: Vec::new(),
        })
    }

    /// Image size, pixels.
    pub fn size(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Frame rate of the header (25 when absent), Hz.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// The header's colour space (`C` parameter; `420` when absent).
    pub fn colour(&self) -> &str {
        &self.colour
    }

    fn ferr(&self, reason: String) -> FrameError {
        FrameError::Y4mFrame {
            path: self.path.clone(),
            frame: self.next,
            reason,
        }
    }
}

impl FrameSource for Y4mSource {
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        let io = |e: std::io::Error, s: &Self| s.ferr(e.to_string());
        let Some(line) = read_line_limited(&mut self.r, 1024).map_err(|e| io(e, self))? else {
            return Ok(None);
        };
        if !line.starts_with(b"FRAME") || line.last() != Some(&b'\n') {
            return Err(
                self.ferr("missing the \"FRAME\" marker (corrupt or truncated file)".into())
            );
        }
        let n_luma = self.width * self.height * self.lay.bytes;
        let n_total = n_luma + (self.lay.chroma)(self.width, self.height) * self.lay.bytes;
        self.buf.resize(n_total, 0);
        let mut got = 0;
        while got < n_total {
            match self.r.read(&mut self.buf[got..]) {
                Ok(0) => {
                    return Err(self.ferr(format!(
                        "truncated: {got} of {n_total} bytes ({}x{} C{})",
                        self.width, self.height, self.colour
                    )));
                }
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(io(e, self)),
            }
        }
        let luma = &self.buf[..n_luma];
        let data: Vec<f32> = if self.lay.bytes == 1 {
            luma.iter().map(|&v| f32::from(v)).collect()
        } else {
            let k = 255.0 / self.lay.max;
            luma.chunks_exact(2)
                .map(|b| (f64::from(u16::from_le_bytes([b[0], b[1]])) * k).min(255.0) as f32)
                .collect()
        };
        let image =
            GrayImage::new(self.width, self.height, data).map_err(|e| self.ferr(e.to_string()))?;
        let seq = self.next;
        self.next += 1;
        Ok(Some(Frame {
            image,
            t_capture: CaptureTime::Companion(Instant::now()),
            t_rel_s: seq as f64 / self.fps,
            seq,
        }))
    }

    fn describe(&self) -> String {
        format!(
            "y4m {} ({}x{} C{}, {:.3} fps)",
            self.path.display(),
            self.width,
            self.height,
            self.colour,
            self.fps
        )
    }

    fn rate_hz(&self) -> Option<f64> {
        Some(self.fps)
    }
}

/// Write frames as a YUV4MPEG2 file (`C420jpeg`, neutral chroma): for tests and recordings.
pub fn write_y4m(
    path: &Path,
    frames: &[GrayImage],
    fps_num: u32,
    fps_den: u32,
) -> std::io::Result<()> {
    use std::io::Write;
    let mut w = std::io::BufWriter::new(File::create(path)?);
    let (wd, ht) = frames
        .first()
        .map(|f| (f.width(), f.height()))
        .unwrap_or((1, 1));
    writeln!(
        w,
        "YUV4MPEG2 W{wd} H{ht} F{fps_num}:{fps_den} Ip A1:1 C420jpeg"
    )?;
    for f in frames {
        if (f.width(), f.height()) != (wd, ht) {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "all frames must have the same size",
            ));
        }
        w.write_all(b"FRAME\n")?;
        let luma: Vec<u8> = f
            .data()
            .iter()
            .map(|v| {
                if v.is_finite() {
                    v.round().clamp(0.0, 255.0) as u8
                } else {
                    0
                }
            })
            .collect();
        w.write_all(&luma)?;
        w.write_all(&vec![128u8; chroma_420(wd, ht)])?;
    }
    w.flush()
}
