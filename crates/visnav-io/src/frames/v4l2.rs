//! Direct V4L2 capture (the `v4l2` cargo feature): the kernel ABI written out, the luma of the
//! pixel formats asked for, memory-mapped streaming.

use super::*;

/// Pixel format asked from a V4L2 device (`pixel_format`; only the luma is used).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
pub enum PixelFormat {
    /// 8-bit gray (`GREY`).
    #[serde(rename = "GREY")]
    Grey,
    /// Packed 4:2:2 `Y0 U Y1 V` (`YUYV`), what most USB (UVC) cameras give uncompressed.
    #[default]
    #[serde(rename = "YUYV")]
    Yuyv,
    /// Motion JPEG (`MJPG`), decoded with the `image` crate.
    #[serde(rename = "MJPG")]
    Mjpg,
}

impl PixelFormat {
    /// The format's V4L2 four-character code, as the configuration names it.
    pub fn fourcc_name(self) -> &'static str {
        match self {
            PixelFormat::Grey => "GREY",
            PixelFormat::Yuyv => "YUYV",
            PixelFormat::Mjpg => "MJPG",
        }
    }
}

/// The V4L2 kernel ABI used by the `v4l2` feature (linux/videodev2.h, 64-bit Linux), written out
/// by hand: the `v4l` crate generates it with bindgen, which needs libclang at build time. The
/// sizes and ioctl numbers are checked against the kernel's values in the tests.
pub mod v4l2_abi {
    #![allow(dead_code)]
    // used by the `v4l2` feature only
    // Each item is the kernel's (linux/videodev2.h) under its own name without the `V4L2_`
    // prefix, field for field: the header documents them.
    #![allow(missing_docs)]

    /// `v4l2_fourcc(a, b, c, d)`.
    pub const fn fourcc(c: &[u8; 4]) -> u32 {
        (c[0] as u32) | ((c[1] as u32) << 8) | ((c[2] as u32) << 16) | ((c[3] as u32) << 24)
    }
    pub const PIX_FMT_GREY: u32 = fourcc(b"GREY");
    pub const PIX_FMT_YUYV: u32 = fourcc(b"YUYV");
    pub const PIX_FMT_MJPEG: u32 = fourcc(b"MJPG");
    pub const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
    pub const MEMORY_MMAP: u32 = 1;
    pub const FIELD_ANY: u32 = 0;
    pub const CAP_VIDEO_CAPTURE: u32 = 0x0000_0001;
    pub const CAP_STREAMING: u32 = 0x0400_0000;
    pub const CAP_DEVICE_CAPS: u32 = 0x8000_0000;
    pub const BUF_FLAG_ERROR: u32 = 0x0000_0040;
    pub const BUF_FLAG_TIMESTAMP_MASK: u32 = 0x0000_e000;
    pub const BUF_FLAG_TIMESTAMP_MONOTONIC: u32 = 0x0000_2000;

    /// `_IOC(dir, 'V', nr, size)` (asm-generic: dir bits 30..32, size 16..30, type 8..16).
    const fn ioc(dir: u64, nr: u64, size: usize) -> u64 {
        (dir << 30) | ((size as u64) << 16) | ((b'V' as u64) << 8) | nr
    }
    const R: u64 = 2;
    const W: u64 = 1;
    pub const VIDIOC_QUERYCAP: u64 = ioc(R, 0, size_of::<Capability>());
    pub const VIDIOC_S_FMT: u64 = ioc(R | W, 5, size_of::<Format>());
    pub const VIDIOC_REQBUFS: u64 = ioc(R | W, 8, size_of::<RequestBuffers>());
    pub const VIDIOC_QUERYBUF: u64 = ioc(R | W, 9, size_of::<Buffer>());
    pub const VIDIOC_QBUF: u64 = ioc(R | W, 15, size_of::<Buffer>());
    pub const VIDIOC_DQBUF: u64 = ioc(R | W, 17, size_of::<Buffer>());
    pub const VIDIOC_STREAMON: u64 = ioc(W, 18, size_of::<i32>());
    pub const VIDIOC_STREAMOFF: u64 = ioc(W, 19, size_of::<i32>());

    /// `struct v4l2_capability`.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default)]
    pub struct Capability {
        pub driver: [u8; 16],
        pub card: [u8; 32],
        pub bus_info: [u8; 32],
        pub version: u32,
        pub capabilities: u32,
        pub device_caps: u32,
        pub reserved: [u32; 3],
    }

    /// `struct v4l2_pix_format`.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default)]
    pub struct PixFormat {
        pub width: u32,
        pub height: u32,
        pub pixelformat: u32,
        pub field: u32,
        pub bytesperline: u32,
        pub sizeimage: u32,
        pub colorspace: u32,
        pub priv_: u32,
        pub flags: u32,
        pub ycbcr_enc: u32,
        pub quantization: u32,
        pub xfer_func: u32,
    }

    /// `struct v4l2_format` with the `pix` member of its 200-byte union (8-byte aligned on
    /// 64-bit: hence the padding after `type_`).
    #[repr(C)]
    #[derive(Debug, Clone, Copy)]
    pub struct Format {
        pub type_: u32,
        pub pad: u32,
        pub pix: PixFormat,
        pub rest: [u8; 200 - 48],
    }

    impl Default for Format {
        fn default() -> Self {
            Self {
                type_: 0,
                pad: 0,
                pix: PixFormat::default(),
                rest: [0; 152],
            }
        }
    }

    /// `struct v4l2_requestbuffers`.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default)]
    pub struct RequestBuffers {
        pub count: u32,
        pub type_: u32,
        pub memory: u32,
        pub capabilities: u32,
        pub flags: u8,
        pub reserved: [u8; 3],
    }

    /// `struct v4l2_timecode`.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default)]
    pub struct Timecode {
        pub type_: u32,
        pub flags: u32,
        pub frames: u8,
        pub seconds: u8,
        pub minutes: u8,
        pub hours: u8,
        pub userbits: [u8; 4],
    }

    /// `struct v4l2_buffer` (single-planar; `m` is the union of offset / userptr / fd).
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Default)]
    pub struct Buffer {
        pub index: u32,
        pub type_: u32,
        pub bytesused: u32,
        pub flags: u32,
        pub field: u32,
        /// `struct timeval` (tv_sec, tv_usec) of the 64-bit ABI.
        pub timestamp: [i64; 2],
        pub timecode: Timecode,
        pub sequence: u32,
        pub memory: u32,
        /// `m.offset` in the low 32 bits (little endian) for MMAP buffers.
        pub m: u64,
        pub length: u32,
        pub reserved2: u32,
        pub request_fd: i32,
    }
}

/// Why a V4L2 buffer is not a frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BadFrame {
    /// An MJPG frame that does not decode.
    #[error("MJPG frame of {bytes} bytes: {reason}")]
    Jpeg {
        /// The frame's size, bytes.
        bytes: usize,
        /// The decoder's reason.
        reason: String,
    },
    /// An MJPG frame of another size than the format set.
    #[error("MJPG frame is {got_width}x{got_height}, the format is {width}x{height}")]
    JpegSize {
        /// The frame's width, pixels.
        got_width: usize,
        /// The frame's height, pixels.
        got_height: usize,
        /// The format's width, pixels.
        width: usize,
        /// The format's height, pixels.
        height: usize,
    },
    /// A row stride shorter than a row.
    #[error("bytes per line {stride} < {row_bytes} for {width} pixels")]
    Stride {
        /// Bytes per line the driver states.
        stride: usize,
        /// Bytes one row needs.
        row_bytes: usize,
        /// Width, pixels.
        width: usize,
    },
    /// A buffer shorter than the frame.
    #[error("{len} bytes, {need} needed for {width}x{height} {format}")]
    Short {
        /// Bytes in the buffer.
        len: usize,
        /// Bytes the frame needs.
        need: usize,
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// The pixel format.
        format: &'static str,
    },
    /// The driver flagged the buffer as corrupt.
    #[error("the driver flagged the buffer as corrupt")]
    Corrupt,
    /// The driver returned a buffer index it was not given.
    #[error("buffer index {0} out of range")]
    BufferIndex(usize),
    /// The frame could not be made into an image.
    #[error("{0}")]
    Image(String),
}

/// The luma plane of a frame as delivered by a V4L2 device: `GREY` and `YUYV` with a row stride
/// of `bytes_per_line` (`0`: packed), `MJPG` decoded. Errors say what does not fit.
pub fn v4l2_luma(
    fmt: PixelFormat,
    data: &[u8],
    width: usize,
    height: usize,
    bytes_per_line: usize,
) -> Result<GrayImage, BadFrame> {
    let row_bytes = match fmt {
        PixelFormat::Grey => width,
        PixelFormat::Yuyv => 2 * width,
        PixelFormat::Mjpg => {
            let jpeg = |reason: String| BadFrame::Jpeg {
                bytes: data.len(),
                reason,
            };
            // Strict: a frame with corrupt entropy data is refused, not filled in.
            let g = crate::image_file::decode_jpeg_strict(data).map_err(|e| jpeg(e.to_string()))?;
            if (g.width(), g.height()) != (width, height) {
                return Err(BadFrame::JpegSize {
                    got_width: g.width(),
                    got_height: g.height(),
                    width,
                    height,
                });
            }
            return Ok(g);
        }
    };
    let stride = if bytes_per_line == 0 {
        row_bytes
    } else {
        bytes_per_line
    };
    if stride < row_bytes {
        return Err(BadFrame::Stride {
            stride,
            row_bytes,
            width,
        });
    }
    let need = stride * height.saturating_sub(1) + row_bytes;
    if height == 0 || width == 0 || data.len() < need {
        return Err(BadFrame::Short {
            len: data.len(),
            need,
            width,
            height,
            format: fmt.fourcc_name(),
        });
    }
    let step = if fmt == PixelFormat::Yuyv { 2 } else { 1 };
    let mut out = Vec::with_capacity(width * height);
    for row in data.chunks(stride).take(height) {
        out.extend(row[..row_bytes].iter().step_by(step).map(|&v| f32::from(v)));
    }
    GrayImage::new(width, height, out).map_err(|e| BadFrame::Image(e.to_string()))
}

#[cfg(feature = "v4l2")]
pub use v4l2_capture::V4l2Source;

#[cfg(feature = "v4l2")]
mod v4l2_capture {
    use super::v4l2_abi::*;
    use super::*;
    use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};

    /// Direct V4L2 capture (`source = "v4l2"`, cargo feature `v4l2`): memory-mapped streaming
    /// I/O with 4 buffers. The frame's capture time is the driver's buffer timestamp when it is
    /// on CLOCK_MONOTONIC (the clock of `std::time::Instant` on Linux), else its arrival, minus
    /// `latency_s`.
    pub struct V4l2Source {
        device: PathBuf,
        fd: OwnedFd,
        buffers: Vec<(*mut libc::c_void, usize)>,
        fmt: PixelFormat,
        width: usize,
        height: usize,
        bytes_per_line: usize,
        timeout: Duration,
        latency: Duration,
        seq: u64,
        streaming: bool,
    }

    // The mapped buffers belong to this source only (moved to the reader thread, never shared).
    unsafe impl Send for V4l2Source {}

    fn ioctl<T>(fd: i32, req: u64, arg: &mut T) -> std::io::Result<()> {
        loop {
            // SAFETY: `arg` is the #[repr(C)] struct the request number encodes (size checked
            // in the tests); the kernel writes at most size_of::<T>() bytes.
            let r = unsafe { libc::ioctl(fd, req as _, arg as *mut T) };
            if r != -1 {
                return Ok(());
            }
            let e = std::io::Error::last_os_error();
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
    }

    impl V4l2Source {
        /// Open `device`, set `width` x `height` in `fmt`, map the buffers and start streaming.
        pub fn open(
            device: &Path,
            width: usize,
            height: usize,
            fmt: PixelFormat,
            timeout_s: f64,
            latency_s: f64,
        ) -> Result<Self, FrameError> {
            let err = |what: &str, e: std::io::Error| FrameError::Io {
                path: device.to_path_buf(),
                cause: std::io::Error::new(e.kind(), format!("{what}: {e}")),
            };
            let cpath =
                std::ffi::CString::new(device.as_os_str().as_encoded_bytes()).map_err(|_| {
                    FrameError::Config(format!("{}: NUL in the path", device.display()))
                })?;
            // SAFETY: a valid C string; the returned descriptor is owned below.
            let raw = unsafe {
                libc::open(
                    cpath.as_ptr(),
                    libc::O_RDWR | libc::O_NONBLOCK | libc::O_CLOEXEC,
                )
            };
            if raw < 0 {
                return Err(err("open", std::io::Error::last_os_error()));
            }
            // SAFETY: `raw` is a fresh descriptor nobody else owns.
            let fd = unsafe { OwnedFd::from_raw_fd(raw) };
            let mut me = Self {
                device: device.to_path_buf(),
                fd,
                buffers: Vec::new(),
                fmt,
                width,
                height,
                bytes_per_line: 0,
                timeout: Duration::from_secs_f64(timeout_s.clamp(0.1, 600.0)),
                latency: Duration::from_secs_f64(latency_s.clamp(0.0, 10.0)),
                seq: 0,
                streaming: false,
            };
            let fd = me.fd.as_raw_fd();
            let mut cap = Capability::default();
            ioctl(fd, VIDIOC_QUERYCAP, &mut cap)
                .map_err(|e| err("not a V4L2 device (VIDIOC_QUERYCAP)", e))?;
            let caps = if cap.capabilities & CAP_DEVICE_CAPS != 0 {
                cap.device_caps
            } else {
                cap.capabilities
            };
            let card = String::from_utf8_lossy(&cap.card)
                .trim_end_matches('\0')
                .to_string();
            if caps & CAP_VIDEO_CAPTURE == 0 || caps & CAP_STREAMING == 0 {
                return Err(FrameError::Config(format!(
                    "{} ({card}) is not a video capture device with streaming I/O",
                    device.display()
                )));
            }
            let fourcc = match fmt {
                PixelFormat::Grey => PIX_FMT_GREY,
                PixelFormat::Yuyv => PIX_FMT_YUYV,
                PixelFormat::Mjpg => PIX_FMT_MJPEG,
            };
            let mut f = Format {
                type_: BUF_TYPE_VIDEO_CAPTURE,
                ..Format::default()
            };
            f.pix.width = width as u32;
            f.pix.height = height as u32;
            f.pix.pixelformat = fourcc;
            f.pix.field = FIELD_ANY;
            ioctl(fd, VIDIOC_S_FMT, &mut f).map_err(|e| err("VIDIOC_S_FMT", e))?;
            if f.pix.pixelformat != fourcc
                || (f.pix.width as usize, f.pix.height as usize) != (width, height)
            {
                let got = f.pix.pixelformat.to_le_bytes();
                return Err(FrameError::Config(format!(
                    "{} ({card}) does not capture {width}x{height} {}: it offers {}x{} {} \
                     (the camera calibration must match the capture size)",
                    device.display(),
                    fmt.fourcc_name(),
                    f.pix.width,
                    f.pix.height,
                    String::from_utf8_lossy(&got)
                )));
            }
            me.bytes_per_line = f.pix.bytesperline as usize;
            me.start_streaming()?;
            info!("{}: V4L2 capture from {card}", me.describe());
            Ok(me)
        }

        /// Asks the driver for memory-mapped capture buffers, maps and queues them, and starts
        /// streaming.
        fn start_streaming(&mut self) -> Result<(), FrameError> {
            let device = self.device.clone();
            let err = |what: &str, e: std::io::Error| FrameError::Io {
                path: device.clone(),
                cause: std::io::Error::new(e.kind(), format!("{what}: {e}")),
            };
            let fd = self.fd.as_raw_fd();
            let mut req = RequestBuffers {
                count: 4,
                type_: BUF_TYPE_VIDEO_CAPTURE,
                memory: MEMORY_MMAP,
                ..RequestBuffers::default()
            };
            ioctl(fd, VIDIOC_REQBUFS, &mut req).map_err(|e| err("VIDIOC_REQBUFS", e))?;
            if req.count < 2 {
                return Err(FrameError::Config(format!(
                    "{}: only {} capture buffers",
                    self.device.display(),
                    req.count
                )));
            }
            for i in 0..req.count {
                let mut b = Buffer {
                    index: i,
                    type_: BUF_TYPE_VIDEO_CAPTURE,
                    memory: MEMORY_MMAP,
                    ..Buffer::default()
                };
                ioctl(fd, VIDIOC_QUERYBUF, &mut b).map_err(|e| err("VIDIOC_QUERYBUF", e))?;
                let len = b.length as usize;
                let offset = (b.m & 0xffff_ffff) as libc::off_t;
                // SAFETY: maps the driver's buffer `i` (length and offset from QUERYBUF);
                // unmapped in Drop.
                let p = unsafe {
                    libc::mmap(
                        std::ptr::null_mut(),
                        len,
                        libc::PROT_READ | libc::PROT_WRITE,
                        libc::MAP_SHARED,
                        fd,
                        offset,
                    )
                };
                if p == libc::MAP_FAILED {
                    return Err(err("mmap", std::io::Error::last_os_error()));
                }
                self.buffers.push((p, len));
                ioctl(fd, VIDIOC_QBUF, &mut b).map_err(|e| err("VIDIOC_QBUF", e))?;
            }
            let mut t = BUF_TYPE_VIDEO_CAPTURE as i32;
            ioctl(fd, VIDIOC_STREAMON, &mut t).map_err(|e| err("VIDIOC_STREAMON", e))?;
            self.streaming = true;
            Ok(())
        }

        fn ferr(&self, reason: String) -> FrameError {
            FrameError::Image {
                path: self.device.clone(),
                frame: self.seq,
                reason,
            }
        }
    }

    /// The CLOCK_MONOTONIC time `tv` as an `Instant` (None when in the future or unreadable).
    fn monotonic_instant(tv: [i64; 2]) -> Option<Instant> {
        let now_i = Instant::now();
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: writes one timespec.
        if unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) } != 0 {
            return None;
        }
        let now_ns = i128::from(ts.tv_sec) * 1_000_000_000 + i128::from(ts.tv_nsec);
        let t_ns = i128::from(tv[0]) * 1_000_000_000 + i128::from(tv[1]) * 1000;
        let age_ns = u64::try_from(now_ns - t_ns).ok()?;
        now_i.checked_sub(Duration::from_nanos(age_ns))
    }

    impl FrameSource for V4l2Source {
        fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
            let fd = self.fd.as_raw_fd();
            let deadline = Instant::now() + self.timeout;
            let mut b = loop {
                let mut b = Buffer {
                    type_: BUF_TYPE_VIDEO_CAPTURE,
                    memory: MEMORY_MMAP,
                    ..Buffer::default()
                };
                match ioctl(fd, VIDIOC_DQBUF, &mut b) {
                    Ok(()) => break b,
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                    Err(e) => {
                        return Err(FrameError::Io {
                            path: self.device.clone(),
                            cause: e,
                        });
                    }
                }
                let left = deadline.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    return Err(self.ferr(format!(
                        "no frame for {:.1} s (frames.timeout_s)",
                        self.timeout.as_secs_f64()
                    )));
                }
                let mut pfd = libc::pollfd {
                    fd,
                    events: libc::POLLIN,
                    revents: 0,
                };
                // SAFETY: one pollfd.
                unsafe { libc::poll(&mut pfd, 1, left.as_millis().min(1000) as i32) };
            };
            let arrival = Instant::now();
            let idx = b.index as usize;
            let result = match self.buffers.get(idx) {
                Some(&(p, len)) if b.flags & BUF_FLAG_ERROR == 0 => {
                    let used = (b.bytesused as usize).min(len);
                    // SAFETY: buffer `idx` is mapped with `len` bytes and dequeued (the driver
                    // does not write it until it is queued again below).
                    let data = unsafe { std::slice::from_raw_parts(p as *const u8, used) };
                    v4l2_luma(self.fmt, data, self.width, self.height, self.bytes_per_line)
                }
                Some(_) => Err(BadFrame::Corrupt),
                None => Err(BadFrame::BufferIndex(idx)),
            };
            let stamp = if b.flags & BUF_FLAG_TIMESTAMP_MASK == BUF_FLAG_TIMESTAMP_MONOTONIC {
                monotonic_instant(b.timestamp).unwrap_or(arrival)
            } else {
                arrival
            };
            if idx < self.buffers.len() {
                ioctl(fd, VIDIOC_QBUF, &mut b).map_err(|e| FrameError::Io {
                    path: self.device.clone(),
                    cause: e,
                })?;
            }
            let seq = self.seq;
            self.seq += 1;
            let image = result.map_err(|r| FrameError::Image {
                path: self.device.clone(),
                frame: seq,
                reason: r.to_string(),
            })?;
            Ok(Some(Frame {
                image,
                t_capture: CaptureTime::Companion(stamp.checked_sub(self.latency).unwrap_or(stamp)),
                t_rel_s: 0.0,
                seq,
            }))
        }

        fn describe(&self) -> String {
            format!(
                "V4L2 {} ({}x{} {})",
                self.device.display(),
                self.width,
                self.height,
                self.fmt.fourcc_name()
            )
        }
    }

    impl Drop for V4l2Source {
        fn drop(&mut self) {
            let fd = self.fd.as_raw_fd();
            if self.streaming {
                let mut t = BUF_TYPE_VIDEO_CAPTURE as i32;
                let _ = ioctl(fd, VIDIOC_STREAMOFF, &mut t);
            }
            for &(p, len) in &self.buffers {
                // SAFETY: mapped in open() with this length; not used after this.
                unsafe { libc::munmap(p, len) };
            }
        }
    }
}
