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
use crate::vision::GrayImage;
use visnav_core::validate::{Base, Problems, Validate};

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
    #[error("{path}: {cause}")]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },
    #[error("{path}: not a usable YUV4MPEG2 file: {reason}")]
    Y4mHeader { path: PathBuf, reason: String },
    #[error("{path}: frame {frame}: {reason}")]
    Y4mFrame {
        path: PathBuf,
        frame: u64,
        reason: String,
    },
    #[error("{path}:{line}: {reason}")]
    Csv {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{path} (frame {frame}): {reason}")]
    Image {
        path: PathBuf,
        frame: u64,
        reason: String,
    },
    #[error(
        "frame source \"{kind}\" is not available: visnav was built without live capture ({reason})"
    )]
    NotBuilt { kind: &'static str, reason: String },
    #[error("frames: {0}")]
    Config(String),
    #[error("{command}: {reason}")]
    Command { command: String, reason: String },
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

// ---------------------------------------------------------------------------------------------
// Configuration

/// Kind of frame source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// Image directory with `frames.csv`.
    Directory,
    /// YUV4MPEG2 file.
    Y4m,
    /// A capture process writing YUV4MPEG2 to stdout (`command = [...]`).
    Command,
    /// A GStreamer pipeline run by `gst-launch-1.0` (`pipeline = "..."`), see
    /// [`gstreamer_command`].
    Gstreamer,
    /// Video4Linux2 direct capture (not built into this binary).
    V4l2,
}

/// `directory`, `y4m`, `command`, `gstreamer`, `v4l2` (as written in `[frames] source`).
impl std::fmt::Display for SourceKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SourceKind::Directory => "directory",
            SourceKind::Y4m => "y4m",
            SourceKind::Command => "command",
            SourceKind::Gstreamer => "gstreamer",
            SourceKind::V4l2 => "v4l2",
        })
    }
}

/// Which clock the frames are stamped with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum StampMode {
    /// The companion's monotonic clock when the frame is released (mapped to the autopilot clock
    /// through TIMESYNC).
    #[default]
    Arrival,
    /// The source's own autopilot boot times (`frames.csv` with a `t_boot_us` column).
    Source,
}

/// `[frames]`: where camera frames come from.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FramesConfig {
    /// `directory` (with `frames.csv`), `y4m`, `command` or `gstreamer`.
    pub source: SourceKind,
    /// The directory or the `.y4m` file; relative to the config file's folder unless absolute.
    /// Not used by `command` / `gstreamer`.
    #[serde(default)]
    pub path: PathBuf,
    /// `command`: the program and its arguments (no shell). A relative program path containing
    /// a `/` is relative to the config file's folder; a bare name is looked up in `PATH`.
    #[serde(default)]
    pub command: Vec<String>,
    /// `gstreamer`: the pipeline up to the raw video (e.g. `"v4l2src device=/dev/video0"`); the
    /// conversion to I420 y4m on stdout is appended.
    #[serde(default)]
    pub pipeline: Option<String>,
    /// `command` / `gstreamer`: no frame for this long is an error (the process is stopped), s.
    #[serde(default = "default_timeout_s")]
    pub timeout_s: f64,
    /// `command` / `gstreamer` / `v4l2`: time from exposure to the frame's arrival (or to the
    /// driver's timestamp), subtracted from the stamp, s.
    #[serde(default)]
    pub latency_s: f64,
    /// `v4l2`: capture width, pixels (must match the camera calibration).
    #[serde(default)]
    pub width_px: Option<usize>,
    /// `v4l2`: capture height, pixels.
    #[serde(default)]
    pub height_px: Option<usize>,
    /// `v4l2`: pixel format asked from the device: `"YUYV"` (default), `"GREY"` or `"MJPG"`.
    #[serde(default)]
    pub pixel_format: PixelFormat,
    /// Capture-time clock.
    #[serde(default)]
    pub stamp: StampMode,
    /// Release frames at the recorded rate (true) or as fast as the fix pipeline takes them,
    /// without dropping any (false).
    #[serde(default = "default_true")]
    pub realtime: bool,
    /// Replay rate override, Hz (absent: the y4m header rate / the frames.csv times).
    #[serde(default)]
    pub rate_hz: Option<f64>,
    /// Frames older than this when a fix worker is free are dropped, s.
    #[serde(default = "default_max_age_s")]
    pub max_age_s: f64,
    /// Fix worker threads.
    #[serde(default = "default_workers")]
    pub workers: usize,
}

fn default_true() -> bool {
    true
}
fn default_max_age_s() -> f64 {
    1.0
}
fn default_workers() -> usize {
    1
}
fn default_timeout_s() -> f64 {
    5.0
}

/// Whether `p` is a regular file (the OS error when it cannot be examined).
fn is_file(p: &Path) -> std::io::Result<bool> {
    std::fs::metadata(p).map(|m| m.is_file())
}

/// Is `prog` an executable name found in `PATH`?
fn in_path(prog: &str) -> bool {
    std::env::var_os("PATH")
        .is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(prog).is_file()))
}

impl FramesConfig {
    /// Defaults for a source at `path`.
    pub fn new(source: SourceKind, path: impl Into<PathBuf>) -> Self {
        Self {
            source,
            path: path.into(),
            command: Vec::new(),
            pipeline: None,
            timeout_s: default_timeout_s(),
            latency_s: 0.0,
            width_px: None,
            height_px: None,
            pixel_format: PixelFormat::default(),
            stamp: StampMode::Arrival,
            realtime: true,
            rate_hz: None,
            max_age_s: default_max_age_s(),
            workers: default_workers(),
        }
    }

    /// A capture process source (`command` or `gstreamer`) with this argv.
    pub fn command(argv: &[&str]) -> Self {
        let mut c = Self::new(SourceKind::Command, "");
        c.command = argv.iter().map(|a| a.to_string()).collect();
        c
    }

    /// The argv run for `command` / `gstreamer` (empty for the other sources).
    pub fn argv(&self) -> Vec<String> {
        match (self.source, &self.pipeline) {
            (SourceKind::Command, _) => self.command.clone(),
            (SourceKind::Gstreamer, Some(p)) => gstreamer_command(p),
            _ => Vec::new(),
        }
    }

    /// Validate, checking the paths against `base` (the config file's folder, or the current
    /// directory for a `--camera` override).
    pub fn validate_in(&self, base: &Base, p: &mut Problems) {
        self.validate(p);
        let needs_path = matches!(self.source, SourceKind::Directory | SourceKind::Y4m);
        if needs_path && self.path.as_os_str().is_empty() {
            return; // reported by validate()
        }
        match self.source {
            SourceKind::Command | SourceKind::Gstreamer => self.check_program(base, p),
            SourceKind::Directory => {
                let full = base.resolve(&self.path);
                match std::fs::metadata(&full) {
                    Err(e) => p.push("path", base.io_problem(&self.path, &e)),
                    Ok(m) if !m.is_dir() => {
                        p.push("path", base.problem(&self.path, "is not a directory"))
                    }
                    Ok(_) if !full.join(FRAMES_CSV).is_file() => p.push(
                        "path",
                        base.problem(&self.path, &format!("has no {FRAMES_CSV}")),
                    ),
                    Ok(_) => {}
                }
            }
            SourceKind::Y4m => {
                if let Some(why) = base.file_problem(&self.path, is_file(&base.resolve(&self.path)))
                {
                    p.push("path", why);
                }
            }
            SourceKind::V4l2 => {}
        }
    }

    /// `command` / `gstreamer`: the program must be a file (a path with a `/`, relative to
    /// `base`) or a name in `PATH`.
    fn check_program(&self, base: &Base, p: &mut Problems) {
        let Some(prog) = self.argv().into_iter().next().filter(|s| !s.is_empty()) else {
            return;
        };
        let key = if self.source == SourceKind::Command {
            "command"
        } else {
            "pipeline"
        };
        if prog.contains('/') {
            if let Some(why) =
                base.file_problem(Path::new(&prog), is_file(&base.resolve(Path::new(&prog))))
            {
                p.push(key, format!("the program {why}"));
            }
        } else if !in_path(&prog) {
            p.push(
                key,
                format!(
                    "the program {} is not found (not a file / not in PATH)",
                    visnav_core::text::quote(&prog)
                ),
            );
        }
    }

    /// Make `path` (and a relative program path in `command`) absolute against `base`.
    pub fn resolve_paths(&mut self, base: &Base) {
        if !self.path.as_os_str().is_empty() {
            self.path = base.resolve(&self.path);
        }
        if let Some(prog) = self.command.first_mut()
            && prog.contains('/')
        {
            *prog = base
                .resolve(Path::new(prog.as_str()))
                .to_string_lossy()
                .into_owned();
        }
    }

    /// The source in a few words: `y4m /data/flight.y4m`, `v4l2 /dev/video0 640x480 YUYV`,
    /// `command ffmpeg -f v4l2 ...`, `gstreamer "v4l2src ..."`.
    pub fn describe_source(&self) -> String {
        match self.source {
            SourceKind::Directory => format!("directory {}", self.path.display()),
            SourceKind::Y4m => format!("y4m {}", self.path.display()),
            SourceKind::Command => format!("command {}", self.command.join(" ")),
            SourceKind::Gstreamer => format!(
                "gstreamer \"{}\"",
                self.pipeline.as_deref().unwrap_or_default()
            ),
            SourceKind::V4l2 => format!(
                "v4l2 {} {}x{} {}",
                self.path.display(),
                self.width_px.unwrap_or(0),
                self.height_px.unwrap_or(0),
                self.pixel_format.fourcc_name()
            ),
        }
    }

    /// A frame source from a compact spec (`visnav run --camera SPEC`), sized `size` (the
    /// camera's `[camera] width_px, height_px`, what a `v4l2` capture asks for):
    ///
    /// | spec | source |
    /// | --- | --- |
    /// | `dir:PATH`, or a PATH that is a folder | `directory` (with `frames.csv`) |
    /// | `y4m:PATH`, or a PATH ending in `.y4m` | `y4m` |
    /// | `v4l2:DEVICE` | `v4l2` at the camera's size, `YUYV` |
    /// | `gst:PIPELINE` (or `gstreamer:`) | `gstreamer` |
    /// | `cmd:PROGRAM ARG...` (or `command:`) | `command`, split at whitespace (no shell) |
    ///
    /// A bare PATH is relative to `base`. Every other key has its default.
    pub fn from_spec(spec: &str, base: &Base, size: (usize, usize)) -> Result<Self, SpecError> {
        let spec = spec.trim();
        let (kind, rest) = match spec.split_once(':') {
            Some((k, rest)) if SPEC_KINDS.contains(&k) => (k, rest.trim()),
            _ => return Self::from_path_spec(spec, base),
        };
        if rest.is_empty() {
            return Err(SpecError(format!(
                "nothing after \"{kind}:\"; {SPEC_FORMS}"
            )));
        }
        Ok(match kind {
            "dir" => Self::new(SourceKind::Directory, rest),
            "y4m" => Self::new(SourceKind::Y4m, rest),
            "v4l2" => {
                let mut c = Self::new(SourceKind::V4l2, rest);
                c.width_px = Some(size.0);
                c.height_px = Some(size.1);
                c
            }
            "gst" | "gstreamer" => {
                let mut c = Self::new(SourceKind::Gstreamer, "");
                c.pipeline = Some(rest.to_string());
                c
            }
            _ => {
                let argv: Vec<&str> = rest.split_whitespace().collect();
                Self::command(&argv)
            }
        })
    }

    /// A spec without a kind: a folder of frames or a `.y4m` file.
    fn from_path_spec(spec: &str, base: &Base) -> Result<Self, SpecError> {
        if spec.is_empty() {
            return Err(SpecError(format!("empty; {SPEC_FORMS}")));
        }
        let path = Path::new(spec);
        let is_y4m = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("y4m"));
        if is_y4m {
            Ok(Self::new(SourceKind::Y4m, path))
        } else if base.resolve(path).is_dir() {
            Ok(Self::new(SourceKind::Directory, path))
        } else {
            Err(SpecError(format!(
                "{} is neither a folder of frames nor a .y4m file ({}); {SPEC_FORMS}",
                visnav_core::text::excerpt(&base.resolve(path).display().to_string()),
                base.rule()
            )))
        }
    }
}

/// A `--camera` spec that names no frame source; the message says which forms there are.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct SpecError(pub String);

/// The kinds a `--camera` spec may start with (`KIND:...`).
const SPEC_KINDS: [&str; 7] = ["dir", "y4m", "v4l2", "gst", "gstreamer", "cmd", "command"];

/// The forms of a `--camera` spec, for messages.
pub const SPEC_FORMS: &str = "give a folder with frames.csv or a .y4m file (or dir:PATH, \
y4m:PATH), v4l2:DEVICE, gst:PIPELINE or cmd:PROGRAM ARGS";

impl Validate for FramesConfig {
    fn validate(&self, p: &mut Problems) {
        let kind = self.source.to_string();
        let live = matches!(self.source, SourceKind::Command | SourceKind::Gstreamer);
        match self.source {
            SourceKind::V4l2 if !cfg!(feature = "v4l2") => p.push(
                "source",
                "v4l2: direct V4L2 capture is not built into this binary (cargo feature \"v4l2\"); \
                 use source = \"gstreamer\" (pipeline = \"v4l2src device=/dev/video0\"; on the \
                 command line --camera \"gst:v4l2src device=/dev/video0\") or \"command\"",
            ),
            SourceKind::V4l2 => {
                if self.path.as_os_str().is_empty() {
                    p.push("path", "required with source = \"v4l2\": the device, e.g. /dev/video0");
                }
                for (k, v) in [("width_px", self.width_px), ("height_px", self.height_px)] {
                    match v {
                        None => p.push(k, "required with source = \"v4l2\""),
                        Some(v) if !(1..=16384).contains(&v) => {
                            p.push(k, format!("{v} is outside [1, 16384]"))
                        }
                        Some(_) => {}
                    }
                }
            }
            SourceKind::Directory | SourceKind::Y4m if self.path.as_os_str().is_empty() => {
                p.push("path", format!("required with source = \"{kind}\""))
            }
            SourceKind::Command if self.command.first().is_none_or(|c| c.is_empty()) => p.push(
                "command",
                "required with source = \"command\": the program and its arguments, e.g. \
                 [\"ffmpeg\", \"-f\", \"v4l2\", \"-i\", \"/dev/video0\", \"-f\", \"yuv4mpegpipe\", \"-\"]",
            ),
            SourceKind::Gstreamer if self.pipeline.as_deref().is_none_or(|s| s.trim().is_empty()) => {
                p.push(
                    "pipeline",
                    "required with source = \"gstreamer\", e.g. \"v4l2src device=/dev/video0\"",
                )
            }
            // gst-launch refuses an empty element ("syntax error") only once it runs: "!", a
            // leading or trailing "!" (visnav appends "! videoconvert ! ..."), or "! !".
            SourceKind::Gstreamer
                if self
                    .pipeline
                    .as_deref()
                    .is_some_and(|s| s.split('!').any(|e| e.trim().is_empty())) =>
            {
                p.push(
                    "pipeline",
                    format!(
                        "{} has an empty element (a leading or trailing \"!\", or \"! !\"): \
                         give the elements up to the raw video, e.g. \"v4l2src device=/dev/video0\"; \
                         visnav appends \"! videoconvert ! ... ! fdsink\"",
                        visnav_core::text::quote(self.pipeline.as_deref().unwrap_or_default())
                    ),
                )
            }
            _ => {}
        }
        if self.stamp == StampMode::Source && self.source != SourceKind::Directory {
            p.push(
                "stamp",
                format!(
                    "\"source\" needs autopilot boot times, which a {kind} source does not carry; \
                     use \"arrival\""
                ),
            );
        }
        if !self.command.is_empty() && self.source != SourceKind::Command {
            p.push(
                "command",
                format!("only used with source = \"command\", not \"{kind}\""),
            );
        }
        if self.pipeline.is_some() && self.source != SourceKind::Gstreamer {
            p.push(
                "pipeline",
                format!("only used with source = \"gstreamer\", not \"{kind}\""),
            );
        }
        if self.source != SourceKind::V4l2 {
            for (k, v) in [("width_px", self.width_px), ("height_px", self.height_px)] {
                if v.is_some() {
                    p.push(
                        k,
                        format!("only used with source = \"v4l2\", not \"{kind}\""),
                    );
                }
            }
        }
        if self.source == SourceKind::V4l2 {
            p.range("timeout_s", self.timeout_s, 0.1, 600.0);
            p.range("latency_s", self.latency_s, 0.0, 10.0);
        }
        if live {
            if !self.path.as_os_str().is_empty() {
                p.push("path", format!("not used with source = \"{kind}\""));
            }
            if self.rate_hz.is_some() {
                p.push(
                    "rate_hz",
                    format!(
                        "not used with source = \"{kind}\": the process sets the rate (replay a \
                         video at its rate with ffmpeg -re)"
                    ),
                );
            }
            p.range("timeout_s", self.timeout_s, 0.1, 600.0);
            p.range("latency_s", self.latency_s, 0.0, 10.0);
        }
        if let Some(r) = self.rate_hz {
            p.range("rate_hz", r, 0.01, 1000.0);
        }
        p.range("max_age_s", self.max_age_s, 0.01, 60.0);
        if !(1..=16).contains(&self.workers) {
            p.push("workers", format!("{} is outside [1, 16]", self.workers));
        }
    }
}

/// Open the configured source (paths already resolved), paced when `realtime`.
pub fn open(cfg: &FramesConfig) -> Result<Box<dyn FrameSource>, FrameError> {
    let inner: Box<dyn FrameSource> = match cfg.source {
        SourceKind::Directory => Box::new(DirectorySource::open(&cfg.path)?),
        SourceKind::Y4m => Box::new(Y4mSource::open(&cfg.path)?),
        #[cfg(not(feature = "v4l2"))]
        SourceKind::V4l2 => {
            return Err(FrameError::NotBuilt {
                kind: "v4l2",
                reason: "no direct V4L2 backend is compiled in (cargo feature \"v4l2\"); use \
                         source = \"gstreamer\" (--camera \"gst:v4l2src device=/dev/video0\") \
                         or \"command\""
                    .into(),
            });
        }
        #[cfg(feature = "v4l2")]
        SourceKind::V4l2 => {
            if cfg.stamp != StampMode::Arrival {
                return Err(FrameError::Config(
                    "stamp = \"source\" needs a directory source with t_boot_us times".into(),
                ));
            }
            let (Some(w), Some(h)) = (cfg.width_px, cfg.height_px) else {
                return Err(FrameError::Config(
                    "source = \"v4l2\" needs width_px and height_px".into(),
                ));
            };
            return Ok(Box::new(V4l2Source::open(
                &cfg.path,
                w,
                h,
                cfg.pixel_format,
                cfg.timeout_s,
                cfg.latency_s,
            )?));
        }
        SourceKind::Command | SourceKind::Gstreamer => {
            if cfg.stamp != StampMode::Arrival {
                return Err(FrameError::Config(
                    "stamp = \"source\" needs a directory source with t_boot_us times".into(),
                ));
            }
            // Live: stamped on arrival by the source itself, never paced.
            return Ok(Box::new(CommandSource::spawn(
                &cfg.argv(),
                cfg.timeout_s,
                cfg.latency_s,
                !cfg.realtime,
            )?));
        }
    };
    let stamp_arrival = cfg.stamp == StampMode::Arrival;
    if !stamp_arrival && !matches!(cfg.source, SourceKind::Directory) {
        return Err(FrameError::Config(
            "stamp = \"source\" needs a directory source with t_boot_us times".into(),
        ));
    }
    if !stamp_arrival && cfg.realtime {
        // Frames on the autopilot's boot clock: the daemon releases each when that clock
        // reaches it ([`releases_on_autopilot_clock`]), not this pacer.
        let mut p = Paced::new(inner, false, None, false);
        p.on_autopilot_clock = true;
        return Ok(Box::new(p));
    }
    Ok(Box::new(Paced::new(
        inner,
        cfg.realtime,
        cfg.rate_hz,
        stamp_arrival,
    )))
}

/// Whether the daemon releases this configuration's frames on the autopilot's clock: a directory
/// with `t_boot_us` times read with `stamp = "source"` in real time. Each frame is then handed on
/// when the autopilot's boot clock (through TIMESYNC) reaches its capture time, and frames taken
/// longer than `max_age_s` before the clock's present are skipped: a recording made on this
/// autopilot's boot clock (a SITL flight replayed with its camera) lines up with the flight
/// whenever the daemon starts. `rate_hz` is not used.
pub fn releases_on_autopilot_clock(cfg: &FramesConfig) -> bool {
    cfg.stamp == StampMode::Source && cfg.realtime && cfg.source == SourceKind::Directory
}

// ---------------------------------------------------------------------------------------------
// Pacing

/// Longest one [`Paced::next_frame`] call sleeps for a frame not yet due. A recording's next
/// frame may be due hours or years later (a gap in `frames.csv`); a call that slept until then
/// would hold its thread past any shutdown deadline, so the pacer sleeps at most this long and
/// answers [`FrameError::NotReady`]. 20 ms keeps the caller's stop checks within a frame period
/// at 50 Hz while costing about 50 wake-ups a second only while waiting. A caller that waits
/// between calls on `NotReady` must wait less than this to keep frames released on time (the
/// pacer returns with at least this much still to wait).
pub const PACE_POLL: Duration = Duration::from_millis(20);

/// Most seconds a frame is paced after the first: `Duration::from_secs_f64` panics on what it
/// cannot hold and `Instant + Duration` on overflow. Twice [`MAX_T_S`] covers every span
/// `frames.csv` may hold (the times lie in `[-MAX_T_S, MAX_T_S]`); a fixed `rate_hz` reaches it
/// only after more frames than any recording has.
const MAX_PACE_S: f64 = 2.0 * MAX_T_S;

/// Releases the frames of a recording at its rate (or a fixed `rate_hz`), restamping them with
/// the release instant when `stamp_arrival`. A frame not yet due is held and
/// [`FrameError::NotReady`] answered after at most [`PACE_POLL`], so that the caller keeps
/// control (checks its stop flag) however far apart the recorded frames are.
pub struct Paced {
    inner: Box<dyn FrameSource>,
    realtime: bool,
    rate_hz: Option<f64>,
    stamp_arrival: bool,
    start: Option<(Instant, f64)>,
    /// Frames released (the next one's index at a fixed `rate_hz`).
    n: u64,
    /// A frame read from `inner` but not yet due, with its due instant (`None`: never, its time
    /// is beyond what an `Instant` holds).
    pending: Option<(Frame, Option<Instant>)>,
    /// Not paced here: the daemon releases the frames on the autopilot's clock (describe only).
    on_autopilot_clock: bool,
}

impl Paced {
    /// Wrap `inner`.
    pub fn new(
        inner: Box<dyn FrameSource>,
        realtime: bool,
        rate_hz: Option<f64>,
        stamp_arrival: bool,
    ) -> Self {
        Self {
            inner,
            realtime,
            rate_hz,
            stamp_arrival,
            start: None,
            n: 0,
            pending: None,
            on_autopilot_clock: false,
        }
    }

    /// When `f` is due: its time after the first frame's (or its index at a fixed `rate_hz`)
    /// after the first frame's release; `None` when that instant is beyond what an `Instant`
    /// holds (never due).
    fn due(&mut self, f: &Frame) -> Option<Instant> {
        let t_rel = match self.rate_hz {
            Some(r) => self.n as f64 / r,
            None => f.t_rel_s,
        };
        let (t0, rel0) = *self.start.get_or_insert((Instant::now(), t_rel));
        // A NaN (no valid rate) counts as due now (`clamp` would keep it), and the bounds keep
        // the conversion below from panicking.
        let after = t_rel - rel0;
        let after = if after > 0.0 {
            after.min(MAX_PACE_S)
        } else {
            0.0
        };
        t0.checked_add(Duration::from_secs_f64(after))
    }
}

impl FrameSource for Paced {
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        let (mut f, due) = match self.pending.take() {
            Some(held) => held,
            None => {
                let Some(f) = self.inner.next_frame()? else {
                    return Ok(None);
                };
                let due = self.realtime.then(|| self.due(&f)).flatten();
                (f, due)
            }
        };
        if self.realtime {
            let now = Instant::now();
            let left = due.map(|d| d.saturating_duration_since(now));
            match left {
                Some(left) if left <= PACE_POLL => std::thread::sleep(left),
                _ => {
                    // Not due within one poll: sleep part of it, leaving at least one poll to
                    // go, so that a caller's own short wait on `NotReady` does not make the
                    // release late.
                    let nap = left.map_or(PACE_POLL, |l| (l - PACE_POLL).min(PACE_POLL));
                    std::thread::sleep(nap);
                    self.pending = Some((f, due));
                    return Err(FrameError::NotReady);
                }
            }
        }
        self.n += 1;
        if self.stamp_arrival {
            f.t_capture = CaptureTime::Companion(Instant::now());
        }
        Ok(Some(f))
    }

    fn describe(&self) -> String {
        let pace = match (self.realtime, self.rate_hz) {
            _ if self.on_autopilot_clock => {
                "each released when the autopilot's clock reaches its t_boot_us".to_string()
            }
            (false, _) => "as fast as processed".to_string(),
            (true, Some(r)) => format!("at {r} Hz"),
            (true, None) => "at the recorded rate".to_string(),
        };
        format!("{}, {pace}", self.inner.describe())
    }

    fn rate_hz(&self) -> Option<f64> {
        self.rate_hz.or(self.inner.rate_hz())
    }
}

// ---------------------------------------------------------------------------------------------
// Directory + frames.csv

/// Name of the timestamps file in an image directory.
pub const FRAMES_CSV: &str = "frames.csv";

/// Largest magnitude of a `frames.csv` `t_s`, s. The column is "seconds from any origin", and
/// the likeliest far origin is 1970 (a companion's wall clock, a ROS stamp: 1.8e9 s today), so
/// 1e10 s (the year 2286) passes every real clock; beyond it the value is a typo or hostile,
/// and pacing to it would mean waiting centuries. At this magnitude an `f64` still resolves
/// 2 µs, so the differences used for pacing stay exact enough.
pub const MAX_T_S: f64 = 1e10;

/// Largest `frames.csv` `t_boot_us`, µs: 1e15 µs is 31.7 years since the autopilot booted, past
/// any flight; a larger value is a typo, a Unix-epoch time in the wrong column (1.8e15 µs today),
/// or hostile, and the daemon would wait for the autopilot's clock to reach it.
pub const MAX_T_BOOT_US: u64 = 1_000_000_000_000_000;

#[derive(Debug, Clone, PartialEq)]
struct Entry {
    file: PathBuf,
    t_rel_s: f64,
    t_boot_us: Option<u64>,
}

/// Images listed in `frames.csv` (see the module docs).
pub struct DirectorySource {
    dir: PathBuf,
    entries: Vec<Entry>,
    next: usize,
}

impl DirectorySource {
    /// Read `dir/frames.csv` (the images are read one by one by [`FrameSource::next_frame`]).
    pub fn open(dir: &Path) -> Result<Self, FrameError> {
        let csv = dir.join(FRAMES_CSV);
        let text = crate::files::read_text(&csv, crate::files::FRAMES_CSV).map_err(|source| {
            FrameError::Io {
                path: csv.clone(),
                cause: source,
            }
        })?;
        let entries = parse_frames_csv(&text, &csv)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            entries,
            next: 0,
        })
    }

    /// Number of frames listed.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// No frames listed.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// The entries of a `frames.csv` (see the module docs); a leading UTF-8 byte order mark is not
/// part of the header.
fn parse_frames_csv(text: &str, path: &Path) -> Result<Vec<Entry>, FrameError> {
    use visnav_core::text::{num, quote};
    let err = |line: usize, reason: String| FrameError::Csv {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let text = text.strip_prefix(crate::files::BOM).unwrap_or(text);
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let Some((hl, header)) = lines.next() else {
        return Err(err(
            1,
            "empty: expected a header \"file,t_boot_us\" or \"file,t_s\"".into(),
        ));
    };
    let cols: Vec<&str> = header.split(',').map(str::trim).collect();
    let boot = match cols.as_slice() {
        ["file", "t_boot_us"] => true,
        ["file", "t_s"] => false,
        _ => {
            return Err(err(
                hl,
                format!(
                    "header {}: expected \"file,t_boot_us\" or \"file,t_s\"",
                    quote(header)
                ),
            ));
        }
    };
    let mut out: Vec<Entry> = Vec::new();
    let mut t0: Option<f64> = None;
    // The previous row's time as read: comparing against `t_rel_s + t0` would round and could
    // let two equal times far from zero pass as increasing.
    let mut prev: Option<(f64, Option<u64>)> = None;
    for (ln, l) in lines {
        let parts: Vec<&str> = l.split(',').map(str::trim).collect();
        let [file, t] = parts.as_slice() else {
            return Err(err(
                ln,
                format!("expected 2 columns, found {}", parts.len()),
            ));
        };
        if file.is_empty() {
            return Err(err(ln, "empty file name".into()));
        }
        let (t_s, t_boot_us) = if boot {
            let too_large = || {
                err(
                    ln,
                    format!(
                        "t_boot_us {} is beyond {MAX_T_BOOT_US} (31.7 years after the \
                         autopilot's boot): no recording has it",
                        quote(t)
                    ),
                )
            };
            let us: u64 = t.parse().map_err(|_| {
                // All digits but no u64: a number too large, not a malformed one.
                if !t.is_empty() && t.bytes().all(|b| b.is_ascii_digit()) {
                    too_large()
                } else {
                    err(
                        ln,
                        format!("t_boot_us {} is not a non-negative integer", quote(t)),
                    )
                }
            })?;
            if us > MAX_T_BOOT_US {
                return Err(too_large());
            }
            (us as f64 * 1e-6, Some(us))
        } else {
            let s: f64 = t
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| err(ln, format!("t_s {} is not a finite number", quote(t))))?;
            if s.abs() > MAX_T_S {
                return Err(err(
                    ln,
                    format!(
                        "t_s {} is outside [-{max}, {max}] s (seconds since 1970 are about \
                         1.8e9): no recording has it",
                        num(s),
                        max = format!("{MAX_T_S:e}")
                    ),
                ));
            }
            (s, None)
        };
        if let Some((prev_s, prev_us)) = prev {
            let after = match (t_boot_us, prev_us) {
                (Some(us), Some(p)) => us > p,
                _ => t_s > prev_s,
            };
            if !after {
                return Err(err(
                    ln,
                    format!("time {} is not after the previous frame's", quote(t)),
                ));
            }
        }
        prev = Some((t_s, t_boot_us));
        let base = *t0.get_or_insert(t_s);
        out.push(Entry {
            file: PathBuf::from(file),
            t_rel_s: t_s - base,
            t_boot_us,
        });
    }
    if out.is_empty() {
        return Err(err(hl, "no frames listed".into()));
    }
    Ok(out)
}

/// Read what `open` reads before the first frame, without starting anything: a directory's
/// `frames.csv` (parsed and checked as the source parses it) or a y4m file's header. `visnav
/// check-config` calls it so that what it passes, `visnav run` opens. Live sources (`command`,
/// `gstreamer`, `v4l2`) are not started here.
pub fn check_files(cfg: &FramesConfig) -> Result<(), FrameError> {
    match cfg.source {
        SourceKind::Directory => DirectorySource::open(&cfg.path).map(|_| ()),
        SourceKind::Y4m => Y4mSource::open(&cfg.path).map(|_| ()),
        SourceKind::Command | SourceKind::Gstreamer | SourceKind::V4l2 => Ok(()),
    }
}

impl FrameSource for DirectorySource {
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        let Some(e) = self.entries.get(self.next) else {
            return Ok(None);
        };
        let seq = self.next as u64;
        self.next += 1;
        let path = self.dir.join(&e.file);
        let image = GrayImage::load(&path).map_err(|x| FrameError::Image {
            path: path.clone(),
            frame: seq,
            reason: x.to_string(),
        })?;
        Ok(Some(Frame {
            image,
            t_capture: match e.t_boot_us {
                Some(us) => CaptureTime::AutopilotBootUs(us),
                None => CaptureTime::Companion(Instant::now()),
            },
            t_rel_s: e.t_rel_s,
            seq,
        }))
    }

    fn describe(&self) -> String {
        format!(
            "image directory {} ({} frames)",
            self.dir.display(),
            self.entries.len()
        )
    }

    fn rate_hz(&self) -> Option<f64> {
        let n = self.entries.len();
        let span = self.entries.last()?.t_rel_s;
        (n > 1 && span > 0.0).then(|| (n - 1) as f64 / span)
    }
}

// ---------------------------------------------------------------------------------------------
// YUV4MPEG2

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
fn read_line_limited(r: &mut impl BufRead, max: usize) -> std::io::Result<Option<Vec<u8>>> {
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

// ---------------------------------------------------------------------------------------------
// Capture process (live capture through GStreamer, ffmpeg or any program writing y4m)

/// How long [`CommandSource`] waits for the process to exit after its output ended.
const EXIT_WAIT: Duration = Duration::from_secs(2);
/// Bytes of the process's stderr kept for error messages.
const STDERR_TAIL_BYTES: usize = 2048;

/// The argv of `source = "gstreamer"`: `gst-launch-1.0 -q <pipeline> ! videoconvert !
/// video/x-raw,format=I420 ! y4menc ! fdsink fd=1` (`-q`: gst-launch prints nothing else on
/// stdout). The pipeline is split at whitespace into arguments, as a shell would without quotes
/// (gst-launch escapes the spaces inside one argument); use `source = "command"` for a pipeline
/// that needs quoting.
pub fn gstreamer_command(pipeline: &str) -> Vec<String> {
    let tail = "! videoconvert ! video/x-raw,format=I420 ! y4menc ! fdsink fd=1";
    ["gst-launch-1.0", "-q"]
        .into_iter()
        .chain(pipeline.split_whitespace())
        .chain(tail.split(' '))
        .map(str::to_string)
        .collect()
}

/// Shell-like rendering of an argv for messages.
fn show_argv(argv: &[String]) -> String {
    argv.iter()
        .map(|a| {
            if !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./=:,!+@%".contains(c))
            {
                a.clone()
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

#[derive(Default)]
struct PumpState {
    /// The newest complete frame not yet taken.
    frame: Option<Frame>,
    /// Set once the stream ended: `Ok` for a clean end, else the error.
    end: Option<Result<(), FrameError>>,
    /// Header facts, once parsed: (width, height, fps, colour).
    header: Option<(usize, usize, f64, String)>,
    /// Frames replaced before they were taken.
    dropped: u64,
    /// The consumer is gone (stop reading).
    stop: bool,
}

struct Pump {
    state: Mutex<PumpState>,
    cv: Condvar,
}

impl Pump {
    fn lock(&self) -> std::sync::MutexGuard<'_, PumpState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Live frames from a capture process: runs `argv` (no shell) with stdout piped, reads the
/// YUV4MPEG2 stream it writes with [`Y4mSource`] on a pump thread, and stamps each frame with the
/// companion clock when its last byte arrived, minus `latency_s`. The pump reads continuously, so
/// frames never wait in the pipe (which would make the arrival stamps late); when the consumer is
/// slower, the newest frame replaces the waiting one (`lossless = false`) or the pump waits
/// (`lossless = true`, for replay commands; the process is then throttled by the pipe).
///
/// Errors name the command and carry its exit status and the tail of its stderr: a process that
/// cannot start, exits or stops writing for `timeout_s`, or writes something that is not y4m. A
/// clean end (exit status 0 at a frame boundary) is the end of the stream (`Ok(None)`).
/// The process is killed when the source is dropped. It is started directly (not through a
/// shell); a `sh -c` wrapper should `exec` the program so that the kill reaches it.
pub struct CommandSource {
    label: String,
    child: Arc<Mutex<Child>>,
    pump: Arc<Pump>,
    stderr_tail: Arc<Mutex<Vec<u8>>>,
    timeout: Duration,
    next_seq: u64,
    reported_dropped: u64,
}

impl CommandSource {
    /// Start `argv` (`argv[0]` is looked up in `PATH` unless it contains a `/`).
    pub fn spawn(
        argv: &[String],
        timeout_s: f64,
        latency_s: f64,
        lossless: bool,
    ) -> Result<Self, FrameError> {
        let label = format!("capture command `{}`", show_argv(argv));
        let cerr = |reason: String| FrameError::Command {
            command: label.clone(),
            reason,
        };
        let Some((prog, args)) = argv.split_first() else {
            return Err(cerr("frames.command is empty".into()));
        };
        let sane =
            timeout_s.is_finite() && timeout_s > 0.0 && latency_s.is_finite() && latency_s >= 0.0;
        if !sane {
            return Err(cerr(format!(
                "timeout_s = {timeout_s} must be > 0 and latency_s = {latency_s} >= 0"
            )));
        }
        let mut child = Command::new(prog)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| cerr(format!("cannot start \"{prog}\": {e}")))?;
        let (Some(stdout), Some(stderr)) = (child.stdout.take(), child.stderr.take()) else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(cerr("no stdout/stderr pipe".into())); // ok: piped above; defensive
        };
        info!(pid = child.id(), "{label} started");
        let child = Arc::new(Mutex::new(child));
        let stderr_tail = Arc::new(Mutex::new(Vec::new()));
        let pump = Arc::new(Pump {
            state: Mutex::new(PumpState::default()),
            cv: Condvar::new(),
        });
        let me = Self {
            label: label.clone(),
            child: child.clone(),
            pump: pump.clone(),
            stderr_tail: stderr_tail.clone(),
            timeout: Duration::from_secs_f64(timeout_s.min(3600.0)),
            next_seq: 0,
            reported_dropped: 0,
        };
        let tail = stderr_tail.clone();
        let lab = label.clone();
        std::thread::Builder::new()
            .name("visnav-capture-stderr".into())
            .spawn(move || drain_stderr(stderr, &tail, &lab))
            .map_err(|e| cerr(format!("cannot start a thread: {e}")))?;
        let ctx = PumpCtx {
            label: label.clone(),
            child,
            pump,
            stderr_tail,
            latency: Duration::from_secs_f64(latency_s.min(10.0)),
            lossless,
        };
        std::thread::Builder::new()
            .name("visnav-capture".into())
            .spawn(move || ctx.run(stdout))
            .map_err(|e| cerr(format!("cannot start a thread: {e}")))?;
        Ok(me)
    }

    fn kill(&self) {
        let mut c = self.child.lock().unwrap_or_else(|e| e.into_inner());
        if matches!(c.try_wait(), Ok(None)) {
            let _ = c.kill();
        }
        let _ = c.wait();
    }

    fn error(&self, reason: String) -> FrameError {
        FrameError::Command {
            command: self.label.clone(),
            reason: with_stderr(reason, &self.stderr_tail),
        }
    }
}

/// Keep the last [`STDERR_TAIL_BYTES`] of the process's stderr; log each line at debug level.
fn drain_stderr(stderr: ChildStderr, tail: &Mutex<Vec<u8>>, label: &str) {
    let mut r = BufReader::new(stderr);
    loop {
        match read_line_limited(&mut r, 4096) {
            Ok(Some(line)) => {
                let text = String::from_utf8_lossy(&line);
                debug!("{label} stderr: {}", text.trim_end());
                let mut t = tail.lock().unwrap_or_else(|e| e.into_inner());
                t.extend_from_slice(&line);
                if t.len() > STDERR_TAIL_BYTES {
                    let cut = t.len() - STDERR_TAIL_BYTES;
                    t.drain(..cut);
                }
            }
            Ok(None) | Err(_) => return,
        }
    }
}

/// `reason` plus the stderr tail, if any.
fn with_stderr(reason: String, tail: &Mutex<Vec<u8>>) -> String {
    let t = tail.lock().unwrap_or_else(|e| e.into_inner());
    let text = String::from_utf8_lossy(&t);
    let text = text.trim();
    if text.is_empty() {
        format!("{reason}; its stderr is empty")
    } else {
        format!(
            "{reason}; its stderr ends with: {}",
            text.replace('\n', " | ")
        )
    }
}

struct PumpCtx {
    label: String,
    child: Arc<Mutex<Child>>,
    pump: Arc<Pump>,
    stderr_tail: Arc<Mutex<Vec<u8>>>,
    latency: Duration,
    lossless: bool,
}

impl PumpCtx {
    fn stopped(&self) -> bool {
        self.pump.lock().stop
    }

    fn finish(&self, end: Result<(), FrameError>) {
        let mut g = self.pump.lock();
        g.end.get_or_insert(end);
        self.pump.cv.notify_all();
    }

    /// Exit status once the process exited (waiting up to [`EXIT_WAIT`]); `None`: still running
    /// (then killed).
    fn exit_status(&self) -> Option<std::process::ExitStatus> {
        let t0 = Instant::now();
        loop {
            {
                let mut c = self.child.lock().unwrap_or_else(|e| e.into_inner());
                if let Ok(Some(s)) = c.try_wait() {
                    return Some(s);
                }
                if t0.elapsed() >= EXIT_WAIT {
                    let _ = c.kill();
                    let _ = c.wait();
                    return None;
                }
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// End with an error carrying the exit status and stderr. `garbage`: the output is not y4m,
    /// so the process is stopped at once instead of waiting for it to exit.
    fn fail(&self, what: String, garbage: bool) {
        if self.stopped() {
            return;
        }
        if garbage {
            let mut c = self.child.lock().unwrap_or_else(|e| e.into_inner());
            if matches!(c.try_wait(), Ok(None)) {
                let _ = c.kill();
            }
        }
        let status = match self.exit_status() {
            Some(_) if garbage => "the process was stopped".to_string(),
            Some(s) => format!("the process exited ({s})"),
            None => "the process was still running and was stopped".into(),
        };
        // Give the stderr thread a moment to collect the last words.
        std::thread::sleep(Duration::from_millis(50));
        self.finish(Err(FrameError::Command {
            command: self.label.clone(),
            reason: with_stderr(format!("{what}; {status}"), &self.stderr_tail),
        }));
    }

    fn run(self, stdout: ChildStdout) {
        let name = PathBuf::from(&self.label);
        let reader = Box::new(BufReader::with_capacity(1 << 20, stdout));
        let mut y4m = match Y4mSource::from_reader(reader, &name) {
            Ok(y) => y,
            Err(FrameError::Io { cause: source, .. }) => {
                return self.fail(format!("reading its output: {source}"), false);
            }
            Err(FrameError::Y4mHeader { reason, .. }) if reason.contains("empty") => {
                return self.fail("its output ended before a YUV4MPEG2 header".into(), false);
            }
            Err(FrameError::Y4mHeader { reason, .. }) => {
                return self.fail(
                    format!(
                        "its output is not YUV4MPEG2 ({reason}); the pipeline must end in \
                     `y4menc ! fdsink fd=1` (gst-launch-1.0 with -q) or `-f yuv4mpegpipe -` \
                     (ffmpeg) and print nothing else on stdout"
                    ),
                    true,
                );
            }
            Err(e) => return self.fail(e.to_string(), true),
        };
        let (w, h) = y4m.size();
        self.pump.lock().header = Some((w, h, y4m.fps(), y4m.colour().to_string()));
        loop {
            match y4m.next_frame() {
                Ok(Some(mut f)) => {
                    let arrival = Instant::now();
                    f.t_capture = CaptureTime::Companion(
                        arrival.checked_sub(self.latency).unwrap_or(arrival),
                    );
                    let mut g = self.pump.lock();
                    while self.lossless && g.frame.is_some() && !g.stop {
                        g = self
                            .pump
                            .cv
                            .wait_timeout(g, Duration::from_millis(100))
                            .map(|r| r.0)
                            .unwrap_or_else(|e| e.into_inner().0);
                    }
                    if g.stop {
                        return;
                    }
                    if g.frame.replace(f).is_some() {
                        g.dropped += 1;
                    }
                    self.pump.cv.notify_all();
                }
                Ok(None) => {
                    if self.stopped() {
                        return;
                    }
                    match self.exit_status() {
                        Some(s) if s.success() => {
                            info!("{}: end of its output ({s})", self.label);
                            return self.finish(Ok(()));
                        }
                        _ => return self.fail("its output ended".into(), false),
                    }
                }
                Err(FrameError::Y4mFrame { frame, reason, .. }) => {
                    let garbage = !reason.starts_with("truncated");
                    return self.fail(format!("frame {frame}: {reason}"), garbage);
                }
                Err(e) => return self.fail(e.to_string(), true),
            }
        }
    }
}

impl FrameSource for CommandSource {
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        let deadline = Instant::now() + self.timeout;
        let mut g = self.pump.lock();
        loop {
            if let Some(mut f) = g.frame.take() {
                self.pump.cv.notify_all();
                if g.dropped > self.reported_dropped {
                    debug!(
                        "{}: {} frames replaced before they were taken",
                        self.label, g.dropped
                    );
                    self.reported_dropped = g.dropped;
                }
                drop(g);
                f.seq = self.next_seq;
                self.next_seq += 1;
                return Ok(Some(f));
            }
            if let Some(end) = &g.end {
                return match end {
                    Ok(()) => Ok(None),
                    Err(FrameError::Command { command, reason }) => Err(FrameError::Command {
                        command: command.clone(),
                        reason: reason.clone(),
                    }),
                    Err(e) => Err(self.error(e.to_string())),
                };
            }
            let now = Instant::now();
            if now >= deadline {
                drop(g);
                let what = if self.next_seq == 0 {
                    "no frame"
                } else {
                    "no new frame"
                };
                let reason = with_stderr(
                    format!(
                        "{what} for {:.1} s (frames.timeout_s); the process was stopped",
                        self.timeout.as_secs_f64()
                    ),
                    &self.stderr_tail,
                );
                self.kill();
                let mut g = self.pump.lock();
                g.stop = true;
                g.end = Some(Err(FrameError::Command {
                    command: self.label.clone(),
                    reason: reason.clone(),
                }));
                self.pump.cv.notify_all();
                return Err(FrameError::Command {
                    command: self.label.clone(),
                    reason,
                });
            }
            g = self
                .pump
                .cv
                .wait_timeout(g, deadline - now)
                .map(|r| r.0)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    fn describe(&self) -> String {
        match &self.pump.lock().header {
            Some((w, h, fps, c)) => format!("{} ({w}x{h} C{c}, {fps:.3} fps)", self.label),
            None => format!("{} (no header yet)", self.label),
        }
    }

    fn rate_hz(&self) -> Option<f64> {
        self.pump.lock().header.as_ref().map(|h| h.2)
    }
}

impl Drop for CommandSource {
    fn drop(&mut self) {
        {
            let mut g = self.pump.lock();
            g.stop = true;
            self.pump.cv.notify_all();
        }
        self.kill();
    }
}

// ---------------------------------------------------------------------------------------------
// V4L2 (direct capture with the `v4l2` cargo feature)

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
    #![allow(dead_code)] // used by the `v4l2` feature only

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
    #[error("MJPG frame of {bytes} bytes: {reason}")]
    Jpeg { bytes: usize, reason: String },
    #[error("MJPG frame is {got_width}x{got_height}, the format is {width}x{height}")]
    JpegSize {
        got_width: usize,
        got_height: usize,
        width: usize,
        height: usize,
    },
    #[error("bytes per line {stride} < {row_bytes} for {width} pixels")]
    Stride {
        stride: usize,
        row_bytes: usize,
        width: usize,
    },
    #[error("{len} bytes, {need} needed for {width}x{height} {format}")]
    Short {
        len: usize,
        need: usize,
        width: usize,
        height: usize,
        format: &'static str,
    },
    #[error("the driver flagged the buffer as corrupt")]
    Corrupt,
    #[error("buffer index {0} out of range")]
    BufferIndex(usize),
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
                source: std::io::Error::new(e.kind(), format!("{what}: {e}")),
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
                    device.display(),
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
                me.buffers.push((p, len));
                ioctl(fd, VIDIOC_QBUF, &mut b).map_err(|e| err("VIDIOC_QBUF", e))?;
            }
            let mut t = BUF_TYPE_VIDEO_CAPTURE as i32;
            ioctl(fd, VIDIOC_STREAMON, &mut t).map_err(|e| err("VIDIOC_STREAMON", e))?;
            me.streaming = true;
            info!("{}: V4L2 capture from {card}", me.describe());
            Ok(me)
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
                            source: e,
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
                    source: e,
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
