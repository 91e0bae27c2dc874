//! The `[frames]` section: which source, its settings and their checks, and [`open`], which
//! builds the source they name.

use super::*;

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
