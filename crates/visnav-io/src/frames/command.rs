//! Live capture through a process writing YUV4MPEG2 to its stdout (GStreamer, ffmpeg, any
//! program), read by a pump thread so a frame never waits in the pipe.

use super::*;

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
