//! An image folder with its `frames.csv` (the module doc of [`super`] gives the format).

use super::*;

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
