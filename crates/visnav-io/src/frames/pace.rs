//! Real-time replay: [`Paced`] releases a recording's frames at the rate they were taken.

use super::*;

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
    pub(super) n: u64,
    /// A frame read from `inner` but not yet due, with its due instant (`None`: never, its time
    /// is beyond what an `Instant` holds).
    pub(super) pending: Option<(Frame, Option<Instant>)>,
    /// Not paced here: the daemon releases the frames on the autopilot's clock (describe only).
    pub(super) on_autopilot_clock: bool,
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
