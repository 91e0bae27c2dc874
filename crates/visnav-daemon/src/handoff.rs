//! The hand-off of frames between the reader and the threads that use them (the fix workers,
//! visual odometry): a one-frame [`Slot`], the navigation state they ask for priors
//! ([`PriorSource`]) and a frame's capture time on the autopilot's clock.

use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

use visnav_core::fix::FixPrior;
use visnav_io::frames::{CaptureTime, Frame};
use visnav_link::Clock;

/// A one-element queue: `put_latest` replaces, `put_wait` waits for room; `take` blocks.
#[derive(Debug)]
pub struct Slot<T> {
    state: Mutex<(Option<T>, bool)>,
    cv: Condvar,
}

/// Result of [`Slot::take`].
#[derive(Debug, PartialEq)]
pub enum Take<T> {
    /// The newest item.
    Item(T),
    /// Nothing arrived within the wait.
    Timeout,
    /// The producer is gone.
    Closed,
}

impl<T> Default for Slot<T> {
    fn default() -> Self {
        Self {
            state: Mutex::new((None, false)),
            cv: Condvar::new(),
        }
    }
}

impl<T> Slot<T> {
    fn lock(&self) -> std::sync::MutexGuard<'_, (Option<T>, bool)> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Put `item`, returning the item it replaced (dropped) if any.
    pub fn put_latest(&self, item: T) -> Option<T> {
        let old = self.lock().0.replace(item);
        self.cv.notify_all();
        old
    }

    /// Put `item` once the slot is empty; false (item dropped) when closed.
    pub fn put_wait(&self, item: T) -> bool {
        let mut g = self.lock();
        loop {
            if g.1 {
                return false;
            }
            if g.0.is_none() {
                g.0 = Some(item);
                self.cv.notify_all();
                return true;
            }
            g = self
                .cv
                .wait_timeout(g, Duration::from_millis(100))
                .map(|r| r.0)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    /// Take the item, waiting up to `timeout`.
    pub fn take(&self, timeout: Duration) -> Take<T> {
        let deadline = Instant::now() + timeout;
        let mut g = self.lock();
        loop {
            if let Some(x) = g.0.take() {
                self.cv.notify_all();
                return Take::Item(x);
            }
            if g.1 {
                return Take::Closed;
            }
            let now = Instant::now();
            if now >= deadline {
                return Take::Timeout;
            }
            g = self
                .cv
                .wait_timeout(g, deadline - now)
                .map(|r| r.0)
                .unwrap_or_else(|e| e.into_inner().0);
        }
    }

    /// Close: waiting and future `take`s return `Closed` once empty, puts are refused.
    pub fn close(&self) {
        let mut g = self.lock();
        g.1 = true;
        g.0 = None;
        self.cv.notify_all();
    }
}

/// Builds the prior for a capture time (implemented by the navigation task's shared state).
pub trait PriorSource: Send + Sync + 'static {
    /// The fix prior at capture time `t_capture_us` (autopilot boot µs).
    fn prior_at(&self, t_capture_us: u64) -> FixPrior;

    /// The filter's own pose at `t_us` for visual odometry: its solution interpolated to the
    /// instant, no fallback to the autopilot's attitude (`crate::vo_path`).
    fn pose_at(&self, t_us: u64) -> FixPrior {
        self.prior_at(t_us)
    }

    /// The body's rotation from `t0_us` to `t1_us` by the filter's compensated gyro rates
    /// (`R_b0_b1`) and what the rates' sampling leaves unknown of it, rad; `None` when not known.
    fn body_rotation(&self, _t0_us: u64, _t1_us: u64) -> Option<(nalgebra::Rotation3<f64>, f64)> {
        None
    }
}

/// A frame's capture time on the autopilot's boot clock (`None`: no time sync yet).
pub fn capture_time_us(clock: &Clock, f: &Frame) -> Option<u64> {
    match f.t_capture {
        CaptureTime::AutopilotBootUs(t) => Some(t),
        CaptureTime::Companion(i) => clock.to_autopilot_us(i),
    }
}
