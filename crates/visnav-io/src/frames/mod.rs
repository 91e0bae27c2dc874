//! Camera frame sources (I/O, synchronous: call them from a blocking thread, never from an async
//! task). Each source yields [`Frame`]s: a grayscale image, its capture time and a sequence number.
//!
//! Sources:
//! * [`DirectorySource`]: an image directory with a `frames.csv` timestamps file (format below).
//! * [`Y4mSource`]: a YUV4MPEG2 (`.y4m`) file; only the luma plane is used.
//! * [`CommandSource`]: live capture through a capture process that writes YUV4MPEG2 to its
//!   stdout (`source = "command"`, or `source = "gstreamer"` which runs `gst-launch-1.0`).
//! * `V4l2Source` (cargo feature `v4l2`, off by default): direct V4L2 capture (`source =
//!   "v4l2"`, `path` = the device, `width_px`, `height_px`, `pixel_format` = `YUYV` | `GREY` |
//!   `MJPG`), memory-mapped streaming, stamped with the driver's CLOCK_MONOTONIC timestamp. The
//!   kernel ABI is written out in [`v4l2_abi`] (the `v4l` crate needs bindgen/libclang to build).
//!   Without the feature, [`open`] and the validation reject `v4l2` and point to `gstreamer` /
//!   `command` (`v4l2src` reads the same devices).
//!
//! # Live capture (`command`, `gstreamer`)
//! ```toml
//! [frames]
//! source = "gstreamer"
//! pipeline = "v4l2src device=/dev/video0 ! video/x-raw,width=1280,height=960,framerate=10/1"
//! latency_s = 0.03   # exposure to arrival, subtracted from the arrival stamp (default 0)
//! timeout_s = 5.0    # no frame for this long: error, the process is stopped (default 5)
//! ```
//! runs `gst-launch-1.0 -q <pipeline> ! videoconvert ! video/x-raw,format=I420 ! y4menc ! fdsink
//! fd=1` ([`gstreamer_command`]; the pipeline is split at whitespace). Any other program:
//! ```toml
//! [frames]
//! source = "command"
//! command = ["ffmpeg", "-loglevel", "error", "-f", "v4l2", "-i", "/dev/video0",
//!            "-pix_fmt", "gray", "-f", "yuv4mpegpipe", "-"]
//! ```
//! The program is started without a shell (a relative path with a `/` is relative to the config
//! file's folder, a bare name is looked up in `PATH`), with stdin closed, stdout read as y4m and
//! stderr kept (its tail goes into error messages, its lines into the debug log). Frames are
//! stamped with the companion clock when their last byte arrives, minus `latency_s`; a pump
//! thread reads continuously, so a frame never waits in the pipe (which would make its stamp
//! late): with `realtime = true` (default) a frame not yet taken is replaced by the newer one,
//! with `realtime = false` the pump waits (for replay commands; `rate_hz` is not used: the
//! process sets the rate, e.g. `ffmpeg -re`). The process is killed when the source is dropped
//! (daemon shutdown). Errors name the command, its exit status and its stderr: a program that
//! cannot start, output that is not y4m, a process that exits (exit status 0 at a frame boundary
//! is the clean end of the stream), and no frame within `timeout_s`.
//!
//! # `frames.csv`
//! ```text
//! # comment lines start with '#'; blank lines are ignored
//! file,t_boot_us            <- header: first column `file`, second `t_boot_us` or `t_s`
//! 000001.png,81234567       <- file relative to the directory, capture time
//! 000002.png,81334567
//! ```
//! * `t_boot_us`: capture time on the autopilot's boot clock, integer microseconds (what the
//!   autopilot's CAMERA_FEEDBACK / a hardware trigger logs). Usable with `stamp = "source"`: in
//!   real time the daemon then releases each frame when the connected autopilot's clock reaches
//!   it and skips those taken more than `max_age_s` before ([`releases_on_autopilot_clock`]).
//! * `t_s`: capture time in seconds from any origin (e.g. the companion's clock when recorded);
//!   only the differences are used, for pacing; frames are then stamped on arrival.
//!
//! Times no recording has are refused when the file is read, naming the line: `t_boot_us` above
//! [`MAX_T_BOOT_US`] (31.7 years after boot), `t_s` beyond ±[`MAX_T_S`] (the year 2286 as seconds
//! since 1970). Legal times may still lie far apart: [`Paced`] never sleeps longer than
//! [`PACE_POLL`] in one call, whatever the gap to the next frame.
//!
//! Times must be strictly increasing. A leading UTF-8 byte order mark is ignored; the file is at
//! most [`crate::files::FRAMES_CSV`]'s size and each image at most [`crate::files::IMAGE`]'s.
//! [`check_files`] reads it as [`open`] does, for `visnav check-config`. Images are any format
//! the `image` crate reads (PNG, JPEG, TIFF), converted to gray with the BT.601 luma weights
//! (`vision::GrayImageFile::load`).
//!
//! # YUV4MPEG2
//! Header `YUV4MPEG2 W<width> H<height> F<num>:<den> [I..] [A..] [C<colour space>] [X..]`, then
//! per frame `FRAME[ params]\n` and the planes. Supported colour spaces: `420jpeg`, `420paldv`,
//! `420mpeg2`, `420` (the default), `422`, `444`, `444alpha`, `mono` (8 bit) and the 16-bit
//! containers `420p10/12/16`, `422p10/12/16`, `444p10/12/16`, `mono16` (little endian, scaled to
//! 0..255). Luma values are used as they are (no limited-range expansion of 16..235 video).
//! Frame rate from `F` unless `rate_hz` overrides it. At most [`MAX_Y4M_PIXELS`] per frame.
//!
//! # Capture time
//! [`CaptureTime::AutopilotBootUs`] when the source knows the autopilot boot time of the capture,
//! else [`CaptureTime::Companion`] (the companion's monotonic clock when the frame was read or, with
//! pacing, when it was released); the daemon maps the latter with `link::Clock::to_autopilot_us`.
//! [`Paced`] releases frames at the source's recorded rate (real-time replay).

use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStderr, ChildStdout, Command, Stdio};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use serde::Deserialize;
use tracing::{debug, info};

use crate::image_file::GrayImageFile;
use visnav_core::validate::{Base, Problems, Validate};
use visnav_core::vision::GrayImage;

/// Capture time of a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CaptureTime {
    /// Autopilot boot time, microseconds.
    AutopilotBootUs(u64),
    /// Companion monotonic clock.
    Companion(Instant),
}

/// One camera frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Gray image, 8-bit scale.
    pub image: GrayImage,
    /// When the frame was captured.
    pub t_capture: CaptureTime,
    /// Time within the recording, seconds from its first frame (pacing only).
    pub t_rel_s: f64,
    /// 0-based sequence number within the source.
    pub seq: u64,
}

/// Why a frame could not be read. Every message names the file (and frame where relevant).
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    /// A file or device could not be read.
    #[error("{path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// The YUV4MPEG2 header is missing or not usable.
    #[error("{path}: not a usable YUV4MPEG2 file: {reason}")]
    Y4mHeader {
        /// The file.
        path: PathBuf,
        /// What is wrong, in words.
        reason: String,
    },
    /// One YUV4MPEG2 frame is truncated or malformed.
    #[error("{path}: frame {frame}: {reason}")]
    Y4mFrame {
        /// The file.
        path: PathBuf,
        /// The frame's sequence number (0-based).
        frame: u64,
        /// What is wrong, in words.
        reason: String,
    },
    /// A `frames.csv` line is malformed.
    #[error("{path}:{line}: {reason}")]
    Csv {
        /// The file.
        path: PathBuf,
        /// Line number in the file (1-based).
        line: usize,
        /// What is wrong, in words.
        reason: String,
    },
    /// A frame's image could not be read or decoded.
    #[error("{path} (frame {frame}): {reason}")]
    Image {
        /// The file.
        path: PathBuf,
        /// The frame's sequence number (0-based).
        frame: u64,
        /// What is wrong, in words.
        reason: String,
    },
    /// A source of a cargo feature this build does not have.
    #[error(
        "frame source \"{kind}\" is not available: visnav was built without live capture ({reason})"
    )]
    NotBuilt {
        /// The source kind (`source` in `[frames]`).
        kind: &'static str,
        /// What is wrong, in words.
        reason: String,
    },
    /// The `[frames]` settings are not usable.
    #[error("frames: {0}")]
    Config(String),
    /// The capture process failed: could not start, wrote no y4m, exited or stalled.
    #[error("{command}: {reason}")]
    Command {
        /// The capture command, as run.
        command: String,
        /// What is wrong, in words.
        reason: String,
    },
    /// A source paced by its caller (the lock-step simulator's camera) has no frame at this
    /// instant: not a fault, the caller asks again at its next tick.
    #[error("no frame ready")]
    NotReady,
}

/// A source of camera frames (blocking I/O).
pub trait FrameSource: Send {
    /// The next frame; `Ok(None)` at the end of a recording.
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError>;
    /// Human-readable description (file name, size, rate).
    fn describe(&self) -> String;
    /// Nominal frame rate, Hz, when known.
    fn rate_hz(&self) -> Option<f64> {
        None
    }
}

mod command;
mod directory;
mod pace;
mod spec;
mod v4l2;
mod y4m;

pub use command::*;
pub use directory::*;
pub use pace::*;
pub use spec::*;
pub use v4l2::*;
pub use y4m::*;

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, k: f32) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| ((x + 2 * y) as f32 + k) % 256.0)
    }

    #[test]
    fn y4m_round_trip_420_odd_size() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.y4m");
        let frames: Vec<_> = (0..3).map(|i| img(7, 5, i as f32 * 10.0)).collect();
        write_y4m(&p, &frames, 30000, 1001).unwrap();
        let mut s = Y4mSource::open(&p).unwrap();
        assert_eq!(s.size(), (7, 5));
        assert!((s.rate_hz().unwrap() - 29.97).abs() < 0.01);
        for (i, f) in frames.iter().enumerate() {
            let g = s.next_frame().unwrap().unwrap();
            assert_eq!(g.seq, i as u64);
            assert_eq!(&g.image, f);
            assert!((g.t_rel_s - i as f64 * 1001.0 / 30000.0).abs() < 1e-12);
        }
        assert!(s.next_frame().unwrap().is_none());
    }

    fn y4m_bytes(header: &str, frames: &[Vec<u8>]) -> Vec<u8> {
        let mut b = header.as_bytes().to_vec();
        b.push(b'\n');
        for f in frames {
            b.extend_from_slice(b"FRAME\n");
            b.extend_from_slice(f);
        }
        b
    }

    #[test]
    fn y4m_colour_spaces() {
        let d = tempfile::tempdir().unwrap();
        // 4x2 luma 0..8, then chroma of the right size for each layout.
        let luma: Vec<u8> = (0..8).collect();
        for (c, chroma) in [
            ("mono", 0),
            ("422", 8),
            ("444", 16),
            ("444alpha", 24),
            ("420", 4),
        ] {
            let mut f = luma.clone();
            f.extend(std::iter::repeat_n(200u8, chroma));
            let p = d.path().join(format!("{c}.y4m"));
            let hdr = format!("YUV4MPEG2 W4 H2 F10:1 C{c}");
            std::fs::write(&p, y4m_bytes(&hdr, &[f.clone(), f])).unwrap();
            let mut s = Y4mSource::open(&p).unwrap();
            for _ in 0..2 {
                let g = s.next_frame().unwrap().unwrap();
                assert_eq!(
                    g.image.data(),
                    &(0..8).map(|v| v as f32).collect::<Vec<_>>()[..],
                    "{c}"
                );
            }
            assert!(s.next_frame().unwrap().is_none(), "{c}");
        }
        // 10-bit little endian: 1023 -> 255.
        let mut f: Vec<u8> = Vec::new();
        for v in [0u16, 1023, 512, 1023] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        f.extend(std::iter::repeat_n(0u8, 4)); // 420 chroma of 2x2: 2 planes of 1 sample, 2 bytes
        let p = d.path().join("p10.y4m");
        std::fs::write(&p, y4m_bytes("YUV4MPEG2 W2 H2 F25:1 C420p10", &[f])).unwrap();
        let g = Y4mSource::open(&p).unwrap().next_frame().unwrap().unwrap();
        assert_eq!(g.image.get(1, 0), 255.0);
        assert_eq!(g.image.get(0, 0), 0.0);
    }

    #[test]
    fn corrupt_y4m_errors_name_file_and_frame() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("bad.y4m");
        // Truncated second frame.
        let full = vec![1u8; 4 * 2 + 4];
        let mut b = y4m_bytes("YUV4MPEG2 W4 H2 F10:1 C420jpeg", &[full]);
        b.extend_from_slice(b"FRAME\n\x01\x02");
        std::fs::write(&p, &b).unwrap();
        let mut s = Y4mSource::open(&p).unwrap();
        assert!(s.next_frame().unwrap().is_some());
        let e = s.next_frame().unwrap_err().to_string();
        assert!(
            e.contains("bad.y4m") && e.contains("frame 1") && e.contains("truncated"),
            "{e}"
        );
        // Garbage instead of a FRAME marker.
        std::fs::write(&p, b"YUV4MPEG2 W4 H2 F10:1\nFRAMX\n").unwrap();
        let e = Y4mSource::open(&p)
            .unwrap()
            .next_frame()
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame 0") && e.contains("FRAME"), "{e}");
        // Header problems.
        for (hdr, want) in [
            (&b"P5 4 2 255\n"[..], "signature"),
            (b"YUV4MPEG2 W0 H2 F10:1\n", "W and H"),
            (b"YUV4MPEG2 W4 H2 F10:0\n", "frame rate"),
            (b"YUV4MPEG2 W4 H2 F10:1 C411\n", "C411"),
            (b"", "empty"),
            (&[b'Y'; 3000][..], "1024"),
        ] {
            std::fs::write(&p, hdr).unwrap();
            let e = Y4mSource::open(&p).err().unwrap().to_string();
            assert!(e.contains("bad.y4m") && e.contains(want), "{e}");
        }
        let e = Y4mSource::open(&d.path().join("missing.y4m"))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("missing.y4m"), "{e}");
    }

    #[test]
    fn directory_source_reads_csv_and_images() {
        let d = tempfile::tempdir().unwrap();
        for i in 0..3 {
            img(6, 4, i as f32)
                .save_png(&d.path().join(format!("{i}.png")))
                .unwrap();
        }
        std::fs::write(
            d.path().join(FRAMES_CSV),
            "# recorded\nfile,t_boot_us\n0.png,1000000\n1.png,1100000\n\n2.png,1250000\n",
        )
        .unwrap();
        let mut s = DirectorySource::open(d.path()).unwrap();
        assert_eq!(s.len(), 3);
        let f = s.next_frame().unwrap().unwrap();
        assert_eq!(f.t_capture, CaptureTime::AutopilotBootUs(1_000_000));
        assert_eq!(f.image, img(6, 4, 0.0));
        let f = s.next_frame().unwrap().unwrap();
        assert!((f.t_rel_s - 0.1).abs() < 1e-9);
        assert_eq!(f.seq, 1);
        assert!((s.rate_hz().unwrap() - 8.0).abs() < 1e-9);
        s.next_frame().unwrap().unwrap();
        assert!(s.next_frame().unwrap().is_none());
    }

    #[test]
    fn directory_source_errors() {
        let d = tempfile::tempdir().unwrap();
        let csv = d.path().join(FRAMES_CSV);
        for (text, want) in [
            ("", "header"),
            ("name,t\n", "header"),
            ("file,t_s\n", "no frames"),
            ("file,t_s\na.png,1.0\nb.png,0.5\n", ":3:"),
            ("file,t_boot_us\na.png,-5\n", "non-negative"),
            ("file,t_s\na.png,nan\n", "finite"),
            ("file,t_s\na.png\n", "2 columns"),
        ] {
            std::fs::write(&csv, text).unwrap();
            let e = DirectorySource::open(d.path()).err().unwrap().to_string();
            assert!(
                e.contains("frames.csv") && e.contains(want),
                "{text:?}: {e}"
            );
        }
        // A listed image that is missing / not an image: named with its frame number.
        std::fs::write(&csv, "file,t_s\nmissing.png,0\n").unwrap();
        let e = DirectorySource::open(d.path())
            .unwrap()
            .next_frame()
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.png") && e.contains("frame 0"), "{e}");
        std::fs::write(d.path().join("junk.png"), b"not a png").unwrap();
        std::fs::write(&csv, "file,t_s\njunk.png,0\n").unwrap();
        let e = DirectorySource::open(d.path())
            .unwrap()
            .next_frame()
            .unwrap_err()
            .to_string();
        assert!(e.contains("junk.png"), "{e}");
        let e = DirectorySource::open(&d.path().join("nodir"))
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("nodir"), "{e}");
    }

    /// What `check_files` (so `visnav check-config`) and the source itself (so `visnav run`)
    /// say about each kind of broken `frames.csv` is one answer: both refuse, naming the line.
    #[test]
    fn frames_csv_cases_are_refused_or_accepted_the_same_by_check_and_open() {
        let d = tempfile::tempdir().unwrap();
        let csv = d.path().join(FRAMES_CSV);
        let cfg = FramesConfig::new(SourceKind::Directory, d.path());
        for (text, want) in [
            ("", "empty"),
            ("# only a comment\n", "empty"),
            ("name,t_boot_us\na.png,1\n", "header"),
            (
                "file,t_s\na.png,NaN\n",
                "t_s \"NaN\" is not a finite number",
            ),
            ("file,t_s\na.png,inf\n", "finite"),
            ("file,t_s\na.png,-inf\n", "finite"),
            (
                "file,t_s\na.png,2\nb.png,1\n",
                ":3: time \"1\" is not after",
            ),
            (
                "file,t_boot_us\na.png,5\nb.png,5\n",
                ":3: time \"5\" is not after",
            ),
            ("file,t_s\na.png,9e9\nb.png,9e9\n", ":3:"),
            (
                "file,t_s\na.png,0\nb.png,1e300\n",
                ":3: t_s 1e300 is outside",
            ),
            (
                "file,t_boot_us\na.png,0\nb.png,86400000000000000\n",
                ":3: t_boot_us \"86400000000000000\" is beyond",
            ),
            ("file,t_boot_us\na.png,-5\n", "non-negative integer"),
            ("file,t_boot_us\na.png,1.5\n", "non-negative integer"),
            ("file,t_boot_us\na.png,1e6\n", "non-negative integer"),
        ] {
            std::fs::write(&csv, text).unwrap();
            let open = DirectorySource::open(d.path()).err().unwrap().to_string();
            let check = check_files(&cfg).unwrap_err().to_string();
            assert_eq!(open, check, "{text:?}");
            assert!(
                check.contains("frames.csv") && check.contains(want),
                "{text:?}: {check}"
            );
        }
        // A byte order mark (a Windows editor's) is accepted by both.
        std::fs::write(&csv, "\u{feff}file,t_boot_us\na.png,5\nb.png,6\n").unwrap();
        assert!(check_files(&cfg).is_ok());
        assert_eq!(DirectorySource::open(d.path()).unwrap().len(), 2);
    }

    /// Times no recording has (a day-long gap written as seconds, 1e300, a Unix time in the
    /// boot-clock column) are refused when the file is read, naming the file and line and quoting
    /// a short form of the value; the largest legal times and a Unix time in `t_s` pass.
    #[test]
    fn frames_csv_times_beyond_any_recording_are_refused_with_a_short_quote() {
        let d = tempfile::tempdir().unwrap();
        let csv = d.path().join(FRAMES_CSV);
        let cfg = FramesConfig::new(SourceKind::Directory, d.path());
        let digits = "7".repeat(400);
        for (text, want) in [
            (
                "file,t_s\na.png,1e300\n",
                ":2: t_s 1e300 is outside [-1e10, 1e10] s",
            ),
            ("file,t_s\na.png,-1e300\n", ":2: t_s -1e300 is outside"),
            (
                "file,t_s\na.png,0\nb.png,86400000000\n",
                ":3: t_s 86400000000 is outside",
            ),
            (
                "file,t_s\na.png,10000000000.5\n",
                ":2: t_s 10000000000.5 is outside",
            ),
            (
                "file,t_boot_us\na.png,1000000000000001\n",
                ":2: t_boot_us \"1000000000000001\" is beyond 1000000000000000",
            ),
            (
                "file,t_boot_us\na.png,18446744073709551615\n",
                ":2: t_boot_us \"18446744073709551615\" is beyond",
            ),
            (
                "file,t_boot_us\na.png,99999999999999999999999\n",
                ":2: t_boot_us \"99999999999999999999999\" is beyond",
            ),
            (
                &format!("file,t_boot_us\na.png,{digits}\n"),
                "(400 bytes) is beyond",
            ),
            // Beyond `f64`: infinite when parsed.
            (
                &format!("file,t_s\na.png,{digits}\n"),
                "(400 bytes) is not a finite number",
            ),
            (
                &format!("file,t_s\na.png,{}\n", &digits[..300]),
                ":2: t_s 7.77",
            ),
        ] {
            std::fs::write(&csv, text).unwrap();
            let open = DirectorySource::open(d.path()).err().unwrap().to_string();
            let check = check_files(&cfg).unwrap_err().to_string();
            assert_eq!(open, check, "{text:?}");
            assert!(
                check.contains("frames.csv") && check.contains(want) && check.len() < 300,
                "{text:?}: {check}"
            );
        }
        for text in [
            "file,t_s\na.png,-1e10\nb.png,1760000000.25\nc.png,1e10\n",
            "file,t_s\na.png,0\nb.png,86400000\n",
            "file,t_boot_us\na.png,0\nb.png,1000000000000000\n",
        ] {
            std::fs::write(&csv, text).unwrap();
            assert!(check_files(&cfg).is_ok(), "{text:?}");
            assert!(DirectorySource::open(d.path()).is_ok(), "{text:?}");
        }
    }

    /// Frames at given recording times, for the pacer.
    struct Scripted(std::collections::VecDeque<f64>, u64);

    impl FrameSource for Scripted {
        fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
            let Some(t_rel_s) = self.0.pop_front() else {
                return Ok(None);
            };
            self.1 += 1;
            Ok(Some(Frame {
                image: img(2, 2, 0.0),
                t_capture: CaptureTime::Companion(Instant::now()),
                t_rel_s,
                seq: self.1 - 1,
            }))
        }

        fn describe(&self) -> String {
            "scripted".into()
        }
    }

    /// The pacer's next frame until one is released (or the end), counting the `NotReady`s.
    fn released(p: &mut Paced) -> (Option<Frame>, usize) {
        let mut waits = 0;
        loop {
            match p.next_frame() {
                Err(FrameError::NotReady) => waits += 1,
                r => return (r.unwrap(), waits),
            }
        }
    }

    /// A frame due an hour (or 1e9 s) later does not hold the caller: each call returns within
    /// about the poll, the frame is kept, and nothing behind it is read. Frames a little apart
    /// are released in order, none before it is due.
    #[test]
    fn paced_source_never_sleeps_past_the_poll_and_releases_held_frames_in_order() {
        for late in [3600.0, 1e9] {
            let src = Scripted([0.0, late, late + 1.0].into(), 0);
            let mut p = Paced::new(Box::new(src), true, None, true);
            assert_eq!(p.next_frame().unwrap().unwrap().seq, 0);
            for _ in 0..3 {
                let t = Instant::now();
                assert!(matches!(p.next_frame(), Err(FrameError::NotReady)));
                // Bounded by the poll; loosely, for a loaded machine.
                assert!(t.elapsed() < Duration::from_secs(1), "{:?}", t.elapsed());
            }
            assert_eq!(p.n, 1, "a held frame is not counted");
            assert_eq!(p.pending.as_ref().map(|(f, _)| f.seq), Some(1));
        }

        let gap = Duration::from_millis(50);
        let g = gap.as_secs_f64();
        let src = Scripted([0.0, g, 2.0 * g, 2.0 * g + 1e-3].into(), 0);
        let mut p = Paced::new(Box::new(src), true, None, true);
        let t0 = Instant::now();
        let mut waited = 0;
        for want in 0..4u64 {
            let (f, waits) = released(&mut p);
            let f = f.unwrap();
            waited += waits;
            assert_eq!(f.seq, want);
            assert_eq!(p.n, want + 1);
            // Never before it is due (a lower bound only; an upper one would be timing).
            let due = Duration::from_secs_f64(f.t_rel_s);
            assert!(
                t0.elapsed() + Duration::from_millis(1) >= due,
                "frame {want} early"
            );
            match f.t_capture {
                CaptureTime::Companion(t) => assert!(t >= t0 + due - Duration::from_millis(1)),
                CaptureTime::AutopilotBootUs(_) => panic!("arrival stamp expected"),
            }
        }
        assert!(waited >= 2, "50 ms gaps are waited for in polls: {waited}");
        assert!(released(&mut p).0.is_none());

        // A fixed rate paces by the count of released frames, held ones not included.
        let src = Scripted([0.0, 0.0, 0.0].into(), 0);
        let mut p = Paced::new(Box::new(src), true, Some(1.0 / g), false);
        let t0 = Instant::now();
        for want in 0..3u64 {
            assert_eq!(released(&mut p).0.unwrap().seq, want);
        }
        assert!(t0.elapsed() + Duration::from_millis(1) >= 2 * gap);
    }

    #[test]
    fn a_frame_or_frames_csv_naming_a_device_is_refused_not_read() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join(FRAMES_CSV), "file,t_s\n/dev/zero,0\n").unwrap();
        let e = DirectorySource::open(d.path())
            .unwrap()
            .next_frame()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("/dev/zero") && e.contains("not a regular file"),
            "{e}"
        );
        let link = tempfile::tempdir().unwrap();
        std::os::unix::fs::symlink("/dev/zero", link.path().join(FRAMES_CSV)).unwrap();
        let e = DirectorySource::open(link.path())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("character device"), "{e}");
    }

    #[test]
    fn a_huge_value_is_quoted_by_a_short_prefix() {
        let d = tempfile::tempdir().unwrap();
        let long = "9".repeat(1_000_000);
        std::fs::write(
            d.path().join(FRAMES_CSV),
            format!("file,t_boot_us\na.png,{long}x\n"),
        )
        .unwrap();
        let e = DirectorySource::open(d.path()).err().unwrap().to_string();
        assert!(e.len() < 300 && e.contains("(1000001 bytes)"), "{e}");
    }

    #[test]
    fn pacing_and_arrival_stamps() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("a.y4m");
        let frames: Vec<_> = (0..4).map(|i| img(4, 4, i as f32)).collect();
        write_y4m(&p, &frames, 50, 1).unwrap();
        let cfg = FramesConfig::new(SourceKind::Y4m, &p);
        let mut s = open(&cfg).unwrap();
        let t0 = Instant::now();
        let mut stamps = Vec::new();
        loop {
            let f = match s.next_frame() {
                Err(FrameError::NotReady) => continue,
                r => match r.unwrap() {
                    Some(f) => f,
                    None => break,
                },
            };
            match f.t_capture {
                CaptureTime::Companion(t) => stamps.push(t),
                CaptureTime::AutopilotBootUs(_) => panic!("arrival stamp expected"),
            }
        }
        assert_eq!(stamps.len(), 4);
        // 3 intervals of 20 ms: at least 60 ms of wall time (a lower bound only; never timed upper).
        assert!(t0.elapsed() >= Duration::from_millis(58));
        assert!(stamps.windows(2).all(|w| w[1] > w[0]));
    }

    #[test]
    fn camera_specs() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir(d.path().join("frames")).unwrap();
        let base = Base::config_folder(d.path());
        let spec = |s: &str| FramesConfig::from_spec(s, &base, (640, 480));
        let c = spec("frames").unwrap();
        assert_eq!(
            (c.source, c.path.as_path()),
            (SourceKind::Directory, Path::new("frames"))
        );
        let c = spec("flight.Y4M").unwrap();
        assert_eq!(c.source, SourceKind::Y4m);
        let c = spec("y4m:clip").unwrap();
        assert_eq!(
            (c.source, c.path.as_path()),
            (SourceKind::Y4m, Path::new("clip"))
        );
        let c = spec("dir:elsewhere").unwrap();
        assert_eq!(c.source, SourceKind::Directory);
        let c = spec("v4l2:/dev/video2").unwrap();
        assert_eq!(c.source, SourceKind::V4l2);
        assert_eq!((c.width_px, c.height_px), (Some(640), Some(480)));
        assert_eq!(c.describe_source(), "v4l2 /dev/video2 640x480 YUYV");
        let c = spec("gst:v4l2src device=/dev/video0").unwrap();
        assert_eq!(c.pipeline.as_deref(), Some("v4l2src device=/dev/video0"));
        let c = spec("cmd:ffmpeg -i /dev/video0  -f yuv4mpegpipe -").unwrap();
        assert_eq!(
            c.command,
            ["ffmpeg", "-i", "/dev/video0", "-f", "yuv4mpegpipe", "-"]
        );
        for bad in ["", "nothing-here", "/dev/video0", "v4l2:", "cmd:  "] {
            let e = spec(bad).unwrap_err().to_string();
            assert!(e.contains("v4l2:DEVICE"), "{bad}: {e}");
        }
        let e = spec("nothing-here").unwrap_err().to_string();
        assert!(
            e.contains(&d.path().join("nothing-here").display().to_string())
                && e.contains("relative to the config file's folder"),
            "{e}"
        );
    }

    #[test]
    fn a_missing_path_names_the_value_and_the_rule() {
        let d = tempfile::tempdir().unwrap();
        let base = Base::config_folder(d.path());
        for kind in [SourceKind::Directory, SourceKind::Y4m] {
            let mut p = Problems::default();
            FramesConfig::new(kind, "rec/x").validate_in(&base, &mut p);
            let s = p.list[0].to_string();
            let want = format!(
                "path: \"rec/x\": {} does not exist (paths in the config",
                d.path().join("rec/x").display()
            );
            assert!(s.starts_with(&want), "{s}");
        }
    }

    #[test]
    fn config_validation_names_keys() {
        let d = tempfile::tempdir().unwrap();
        let mut c = FramesConfig::new(SourceKind::Y4m, "nofile.y4m");
        c.stamp = StampMode::Source;
        c.max_age_s = 0.0;
        c.workers = 0;
        c.rate_hz = Some(-1.0);
        let mut p = Problems::default();
        c.validate_in(&Base::config_folder(d.path()), &mut p);
        let s: Vec<String> = p.list.iter().map(|i| i.to_string()).collect();
        for k in ["stamp", "max_age_s", "workers", "rate_hz", "path"] {
            assert!(s.iter().any(|m| m.starts_with(k)), "{k} missing in {s:?}");
        }
        let c = FramesConfig::new(SourceKind::V4l2, "/dev/video0");
        let mut p = Problems::default();
        c.validate(&mut p);
        if cfg!(feature = "v4l2") {
            assert!(p.list[0].to_string().contains("width_px"), "{:?}", p.list);
            assert!(open(&c).is_err());
        } else {
            assert!(p.list[0].to_string().contains("not built"), "{:?}", p.list);
            assert!(matches!(open(&c), Err(FrameError::NotBuilt { .. })));
        }
        assert!(
            toml::from_str::<FramesConfig>("source = \"y4m\"\npath = \"a\"\nfps = 3\n").is_err()
        );
        let c: FramesConfig =
            toml::from_str("source = \"directory\"\npath = \"a\"\nrealtime = false\n").unwrap();
        assert!(!c.realtime && c.workers == 1 && c.stamp == StampMode::Arrival);
    }

    #[test]
    fn v4l2_abi_matches_the_kernel() {
        use v4l2_abi::*;
        // Sizes and request numbers of linux/videodev2.h on 64-bit Linux.
        assert_eq!(size_of::<Capability>(), 104);
        assert_eq!(size_of::<Format>(), 208);
        assert_eq!(size_of::<RequestBuffers>(), 20);
        assert_eq!(size_of::<Buffer>(), 88);
        assert_eq!(std::mem::offset_of!(Buffer, timestamp), 24);
        assert_eq!(std::mem::offset_of!(Buffer, m), 64);
        assert_eq!(VIDIOC_QUERYCAP, 0x8068_5600);
        assert_eq!(VIDIOC_S_FMT, 0xc0d0_5605);
        assert_eq!(VIDIOC_REQBUFS, 0xc014_5608);
        assert_eq!(VIDIOC_QUERYBUF, 0xc058_5609);
        assert_eq!(VIDIOC_QBUF, 0xc058_560f);
        assert_eq!(VIDIOC_DQBUF, 0xc058_5611);
        assert_eq!(VIDIOC_STREAMON, 0x4004_5612);
        assert_eq!(VIDIOC_STREAMOFF, 0x4004_5613);
        assert_eq!(PIX_FMT_YUYV, 0x5659_5559);
        assert_eq!(PIX_FMT_GREY, 0x5945_5247);
        assert_eq!(PIX_FMT_MJPEG, 0x4750_4a4d);
    }

    #[test]
    fn v4l2_luma_of_grey_yuyv_and_mjpg() {
        // GREY 3x2 with a stride of 4 (one padding byte per row).
        let grey = [10u8, 20, 30, 99, 40, 50, 60];
        let g = v4l2_luma(PixelFormat::Grey, &grey, 3, 2, 4).unwrap();
        assert_eq!(g.data(), &[10.0, 20.0, 30.0, 40.0, 50.0, 60.0]);
        // YUYV 2x2 packed: Y0 U Y1 V.
        let yuyv = [1u8, 128, 2, 128, 3, 128, 4, 128];
        let g = v4l2_luma(PixelFormat::Yuyv, &yuyv, 2, 2, 0).unwrap();
        assert_eq!(g.data(), &[1.0, 2.0, 3.0, 4.0]);
        // Short buffer, stride too small, empty size: errors, no panic.
        let e = v4l2_luma(PixelFormat::Yuyv, &yuyv[..7], 2, 2, 0).unwrap_err();
        assert!(e.to_string().contains("7 bytes"), "{e}");
        assert_eq!(e.to_string(), "7 bytes, 8 needed for 2x2 YUYV");
        assert!(v4l2_luma(PixelFormat::Yuyv, &yuyv, 2, 2, 3).is_err());
        assert!(v4l2_luma(PixelFormat::Grey, &grey, 0, 2, 0).is_err());
        // MJPG: a JPEG of a smooth gradient decodes to about the same luma.
        let src = image::GrayImage::from_fn(16, 8, |x, y| image::Luma([(x * 12 + y * 4) as u8]));
        let mut jpg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpg, 95)
            .encode_image(&src)
            .unwrap();
        let g = v4l2_luma(PixelFormat::Mjpg, &jpg, 16, 8, 0).unwrap();
        let err = g
            .data()
            .iter()
            .zip(src.as_raw())
            .map(|(a, &b)| (a - f32::from(b)).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 8.0, "JPEG luma error {err}");
        let e = v4l2_luma(PixelFormat::Mjpg, &jpg, 32, 8, 0).unwrap_err();
        assert!(e.to_string().contains("16x8"), "{e}");
        let e = v4l2_luma(PixelFormat::Mjpg, b"not a jpeg", 16, 8, 0).unwrap_err();
        assert!(e.to_string().contains("MJPG"), "{e}");
    }

    #[test]
    fn v4l2_config_keys() {
        let c: FramesConfig = toml::from_str(
            "source = \"v4l2\"\npath = \"/dev/video0\"\nwidth_px = 640\nheight_px = 480\npixel_format = \"MJPG\"\n",
        )
        .unwrap();
        assert_eq!(c.pixel_format, PixelFormat::Mjpg);
        assert!(
            toml::from_str::<FramesConfig>("source = \"v4l2\"\npixel_format = \"RGB3\"\n").is_err()
        );
        let mut p = Problems::default();
        let mut bad = FramesConfig::new(SourceKind::V4l2, "");
        bad.width_px = Some(0);
        bad.validate(&mut p);
        let keys: Vec<&str> = p.list.iter().map(|i| i.key.as_str()).collect();
        if cfg!(feature = "v4l2") {
            for k in ["path", "width_px", "height_px"] {
                assert!(keys.contains(&k), "{k}: {:?}", p.list);
            }
        } else {
            assert_eq!(keys, ["source"], "{:?}", p.list);
        }
        let mut p = Problems::default();
        let mut y = FramesConfig::new(SourceKind::Y4m, "a.y4m");
        y.width_px = Some(640);
        y.validate(&mut p);
        assert!(p.list.iter().any(|i| i.key == "width_px"), "{:?}", p.list);
    }

    #[cfg(feature = "v4l2")]
    #[test]
    fn v4l2_open_errors_name_the_device() {
        let e = V4l2Source::open(
            Path::new("/dev/null"),
            640,
            480,
            PixelFormat::Yuyv,
            1.0,
            0.0,
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("/dev/null") && e.contains("not a V4L2 device"),
            "{e}"
        );
        let e = V4l2Source::open(
            Path::new("/dev/video-none"),
            640,
            480,
            PixelFormat::Yuyv,
            1.0,
            0.0,
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("/dev/video-none") && e.contains("open"), "{e}");
    }
}
