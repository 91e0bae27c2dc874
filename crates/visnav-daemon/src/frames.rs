//! The frame path: a reader thread pulls frames from the [`FrameSource`] into a one-frame
//! [`Slot`] (the newest frame wins; a replaced frame is dropped and counted), fix worker threads
//! take from the slot, drop frames older than `frames.max_age_s`, build the prior at the capture
//! time and call the [`FrameFixer`]; results go to the navigation task over a bounded channel.
//! Nothing here runs on the async runtime, so a slow fix never delays telemetry or injection.
//! Lossless replay (`realtime = false`): the reader waits until the slot is empty instead.
//! A frame bit-identical to the one before it is dropped and counted ([`FreezeDetector`]): a
//! frozen camera repeats its last buffer with new time stamps, and a fix on it would put the
//! aircraft where it was when the camera froze, stamped now.
//! Unreadable frames are skipped, counted (`visnav_frame_errors_total`) and warned about through
//! a [`LogLimiter`]: a folder whose images are all missing says so in a few lines, not one per
//! frame.

use std::panic::AssertUnwindSafe;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use tokio::sync::mpsc;
use tracing::{Instrument, error, info, warn};

use crate::fixer::FrameFixer;
use crate::handoff::capture_time_us;
pub use crate::handoff::{PriorSource, Slot, Take};
use crate::metrics::DaemonMetrics;
use visnav_core::fix::{FixPrior, FixReport};
use visnav_core::vision::GrayImage;
use visnav_io::frames::{CaptureTime, Frame, FrameError, FrameSource};
use visnav_link::{Clock, LogLimiter};

/// Recognises a frozen camera: an image bit-identical to the previous one. A live sensor's
/// noise makes two real frames differ in some pixel; a driver that stopped capturing hands out
/// its last buffer again. (A blank frame repeated, a lens cap, is dropped too: it carries no
/// fix either.) Images are compared by a 64-bit hash of their pixels.
#[derive(Debug, Default)]
pub struct FreezeDetector {
    last: Option<u64>,
    /// Frozen frames so far (for logging on the 1st, 2nd, 4th ...).
    frozen: u64,
}

impl FreezeDetector {
    /// True when `image` repeats the previous image exactly (then counted and, on the 1st, 2nd,
    /// 4th ... time, logged).
    pub fn repeats(&mut self, image: &GrayImage, seq: u64) -> bool {
        let h = pixel_hash(image);
        let repeat = self.last == Some(h);
        self.last = Some(h);
        if repeat {
            self.frozen += 1;
            if self.frozen.is_power_of_two() {
                warn!(
                    "frames: frame {seq} is identical to the one before (a frozen camera): dropped ({} so far)",
                    self.frozen
                );
            }
        }
        repeat
    }
}

/// A 64-bit hash of the image's size and pixels (multiply-xorshift per pixel; not
/// cryptographic, a repeat is what it finds).
fn pixel_hash(image: &GrayImage) -> u64 {
    const K: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut h = (image.width() as u64) << 32 | image.height() as u64;
    for v in image.data() {
        h = (h ^ u64::from(v.to_bits())).wrapping_mul(K);
        h ^= h >> 29;
    }
    h
}

/// A finished fix attempt, for the navigation task.
#[derive(Debug, Clone)]
pub struct FixResult {
    /// Capture time of the frame, autopilot boot µs.
    pub t_capture_us: u64,
    /// Frame sequence number.
    pub seq: u64,
    /// The engine's report.
    pub report: FixReport,
    /// Time from taking the frame to the report, ms.
    pub latency_ms: u64,
}

/// When the reader hands on a frame stamped on the autopilot's boot clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Release {
    /// As the source delivers it (the source paces itself).
    AsRead,
    /// When the autopilot's clock reaches the frame's capture time; frames taken longer than
    /// `max_age_s` before the clock's present are skipped (`visnav_io::frames::
    /// releases_on_autopilot_clock`).
    /// When the autopilot's clock reaches the capture time; older than `max_age_s` skipped.
    OnAutopilotClock {
        /// Frames older than this when released are skipped, s.
        max_age_s: f64,
    },
}

/// What [`wait_for_capture_time`] decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Due {
    Now,
    /// Older than the largest age: skip it.
    Stale,
    Stopped,
}

/// The longest single sleep while waiting for the autopilot's clock, so `stop` is seen.
const RELEASE_POLL: Duration = Duration::from_millis(20);

/// Waits until the autopilot's clock reaches `t_capture_us` (module doc of `Release`).
fn wait_for_capture_time(
    clock: &Clock,
    t_capture_us: u64,
    max_age_s: f64,
    stop: &AtomicBool,
) -> Due {
    loop {
        if stop.load(Ordering::Relaxed) {
            return Due::Stopped;
        }
        let Some(now) = clock.autopilot_now_us() else {
            std::thread::sleep(RELEASE_POLL);
            continue;
        };
        if now >= t_capture_us {
            let age_s = (now - t_capture_us) as f64 * 1e-6;
            return if age_s > max_age_s {
                Due::Stale
            } else {
                Due::Now
            };
        }
        std::thread::sleep(Duration::from_micros(t_capture_us - now).min(RELEASE_POLL));
    }
}

/// The reader thread: source -> slot until the source ends, fails or `stop` is set. It starts
/// reading once the link's clock mapping is available (frames before that could not be stamped
/// on the autopilot clock).
#[allow(clippy::too_many_arguments)]
pub fn spawn_reader(
    mut source: Box<dyn FrameSource>,
    slot: Arc<Slot<Frame>>,
    vo_slot: Option<Arc<Slot<Frame>>>,
    lossless: bool,
    release: Release,
    clock: Clock,
    stop: Arc<AtomicBool>,
    metrics: Arc<DaemonMetrics>,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    let span = tracing::Span::current();
    std::thread::Builder::new()
        .name("visnav-frames".into())
        .spawn(move || {
            let _span = span.enter();
            while clock.autopilot_now_us().is_none() {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            info!("frames: {}", source.describe());
            let mut freeze = FreezeDetector::default();
            let mut unreadable = LogLimiter::default();
            let mut skipped_before_now = 0u64;
            while !stop.load(Ordering::Relaxed) {
                match source.next_frame() {
                    Ok(Some(f)) => {
                        if let (Release::OnAutopilotClock { max_age_s }, CaptureTime::AutopilotBootUs(t)) =
                            (release, f.t_capture)
                        {
                            match wait_for_capture_time(&clock, t, max_age_s, &stop) {
                                Due::Now => {}
                                Due::Stale => {
                                    skipped_before_now += 1;
                                    metrics.frames_stale.inc();
                                    continue;
                                }
                                Due::Stopped => break,
                            }
                            if skipped_before_now > 0 {
                                info!(
                                    "frames: skipped the {skipped_before_now} frames taken before the autopilot's clock reached {:.1} s",
                                    t as f64 * 1e-6
                                );
                                skipped_before_now = 0;
                            }
                        }
                        metrics.frames_in.inc();
                        if freeze.repeats(&f.image, f.seq) {
                            metrics.frames_frozen.inc();
                            continue;
                        }
                        metrics.queue_depth_max.max(1);
                        if let Some(v) = &vo_slot {
                            // Every frame to visual odometry too (its own thread; the newest
                            // wins there as well unless lossless).
                            if lossless {
                                if !v.put_wait(f.clone()) {
                                    break;
                                }
                            } else {
                                v.put_latest(f.clone());
                            }
                        }
                        if lossless {
                            if !slot.put_wait(f) {
                                break;
                            }
                        } else if slot.put_latest(f).is_some() {
                            metrics.frames_superseded.inc();
                        }
                    }
                    Ok(None) => {
                        info!("frames: end of the recording");
                        break;
                    }
                    Err(FrameError::NotReady) => {
                        std::thread::sleep(Duration::from_millis(10));
                    }
                    Err(e @ FrameError::Image { .. }) => {
                        // One unreadable image in a directory: skip it.
                        metrics.frame_errors.inc();
                        let t_s = clock.companion_now_ns() as f64 * 1e-9;
                        if let Some(line) = unreadable.hit(t_s) {
                            warn!("frames: {e}; skipped{}", line.suffix());
                        }
                    }
                    Err(e) => {
                        metrics.frame_errors.inc();
                        error!("frames: {e}; the frame source is stopped");
                        break;
                    }
                }
            }
            if let Some(line) = unreadable.flush() {
                warn!(
                    "frames: {} more unreadable frames skipped since the last such line ({} in all)",
                    line.suppressed, line.total
                );
            }
        })
}

/// Context of a fix worker.
pub struct WorkerCtx {
    /// Where the newest frame waits for a worker.
    pub slot: Arc<Slot<Frame>>,
    /// The fix engine.
    pub fixer: Arc<dyn FrameFixer>,
    /// The priors at a capture time.
    pub priors: Arc<dyn PriorSource>,
    /// The autopilot's clock mapping.
    pub clock: Clock,
    /// Frames older than this are not fixed, s.
    pub max_age_s: f64,
    /// Where the results go (the navigation task).
    pub results: mpsc::Sender<FixResult>,
    /// The counters.
    pub metrics: Arc<DaemonMetrics>,
    /// Shared by the workers: when a frame's heading search is widened.
    pub widening: Arc<HeadingWidening>,
}

/// Rejections in a row before a frame's heading search is widened
/// ([`visnav_core::fix::FixPrior::widen_heading`]): a heading that is wrong fails every frame,
/// while ground that does not match (water, a changed field) fails one here and there; three in a
/// row at 2-30 Hz is a fraction of a second to a second and a half of evidence.
const WIDEN_AFTER_REJECTIONS: u32 = 3;

/// After a widened search that failed, seconds (capture time) before the next: a widened search
/// costs a heading sweep (about ten times a fix), and over ground that matches at no heading
/// every frame would pay it; at most one in this time keeps the worker for the frames that can
/// fix while still finding a wrong heading within seconds.
const WIDEN_RETRY_S: f64 = 5.0;

/// When the daemon asks the fix engine to widen the heading search of a frame that finds no fix
/// at the filter's heading: after `WIDEN_AFTER_REJECTIONS` rejections in a row, and not again
/// within `WIDEN_RETRY_S` of a widened search that failed. A fix accepted starts the count
/// again. Times are capture times on the autopilot clock (the same decisions in lock-step).
#[derive(Debug, Default)]
pub struct HeadingWidening {
    state: std::sync::Mutex<WidenState>,
}

#[derive(Debug, Default)]
struct WidenState {
    rejected_in_a_row: u32,
    last_failed_widening_us: Option<u64>,
}

impl HeadingWidening {
    /// Whether the frame captured at `t_us` gets the widened search.
    pub fn wanted(&self, t_us: u64) -> bool {
        let s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.rejected_in_a_row >= WIDEN_AFTER_REJECTIONS
            && s.last_failed_widening_us
                .is_none_or(|t0| t_us < t0 || (t_us - t0) as f64 * 1e-6 >= WIDEN_RETRY_S)
    }

    /// The outcome of the frame captured at `t_us` (`widened`: it had the widened search).
    pub fn record(&self, t_us: u64, widened: bool, accepted: bool) {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if accepted {
            s.rejected_in_a_row = 0;
            return;
        }
        s.rejected_in_a_row = s.rejected_in_a_row.saturating_add(1);
        if widened {
            s.last_failed_widening_us = Some(t_us);
        }
    }
}

/// The factor a widened frame's position prior sigma is multiplied by. Rejections in a row are
/// also what a filter that drifted from its stated sigma produces: each fix then fails the
/// engine's prior consistency check (the filter's position as the resection's prior, a
/// chi-square(3) gate), so none comes to correct the filter. In ArduCopter SITL over Autzen a run
/// of fixes 1-2 m off over trees (each within 1.7 of its sigma) left the filter 4-8 of its sigmas
/// from the next ones (d^2 20-60 against 16.3) and 20-40 s without a fix followed, the filter
/// running 20-40 m along the track. Three times the sigma takes a drift of up to 12 prior sigmas
/// back inside the gate; the engine's chance test and gate grow with it (docs/real-sitl.md).
const WIDEN_POSITION_FACTOR: f64 = 3.0;

/// `prior` for a widened search: the heading searched wider by the engine
/// ([`visnav_core::fix::FixPrior::widen_heading`]) and the position sigmas times
/// [`WIDEN_POSITION_FACTOR`].
fn widened(mut prior: FixPrior) -> FixPrior {
    prior.widen_heading = true;
    if let Some(p) = prior.position.as_mut() {
        p.sigma_h_m *= WIDEN_POSITION_FACTOR;
        p.sigma_v_m *= WIDEN_POSITION_FACTOR;
    }
    prior
}

/// One fix worker thread: slot -> engine -> results, until the slot is closed.
pub fn spawn_worker(i: usize, ctx: WorkerCtx) -> std::io::Result<std::thread::JoinHandle<()>> {
    let span = tracing::Span::current();
    std::thread::Builder::new()
        .name(format!("visnav-fix-{i}"))
        .spawn(move || {
            let _span = span.enter();
            loop {
                let f = match ctx.slot.take(Duration::from_millis(200)) {
                    Take::Item(f) => f,
                    Take::Timeout => continue,
                    Take::Closed => return,
                };
                if !process(&ctx, f) {
                    return;
                }
            }
        })
}

/// Returns false when the navigation task is gone.
fn process(ctx: &WorkerCtx, f: Frame) -> bool {
    let Some(result) = fix_frame(ctx, f) else {
        return true;
    };
    let sent = ctx.results.blocking_send(result).is_ok();
    if !sent {
        ctx.metrics.fixes_dropped_at_shutdown.inc();
    }
    sent
}

/// The fix of one frame (`None`: dropped, no time or too old; counted).
fn fix_frame(ctx: &WorkerCtx, f: Frame) -> Option<FixResult> {
    let (t_c, prior) = prepare(ctx, &f)?;
    Some(fix_prepared(ctx, f, t_c, prior))
}

/// A frame's capture time on the autopilot clock and its prior (`None`: dropped, no time or
/// too old; counted).
fn prepare(ctx: &WorkerCtx, f: &Frame) -> Option<(u64, FixPrior)> {
    let m = &ctx.metrics;
    let (Some(t_c), Some(now)) = (capture_time_us(&ctx.clock, f), ctx.clock.autopilot_now_us())
    else {
        m.frames_no_time.inc();
        return None;
    };
    let age_s = (now as f64 - t_c as f64) * 1e-6;
    if age_s > ctx.max_age_s {
        m.frames_stale.inc();
        return None;
    }
    let mut prior = ctx.priors.prior_at(t_c);
    if prior.position.is_some() && ctx.widening.wanted(t_c) {
        prior = widened(prior);
    }
    m.fixes_attempted.inc();
    if prior.widen_heading {
        m.fixes_heading_widened.inc();
    }
    Some((t_c, prior))
}

/// The engine's fix of a prepared frame.
fn fix_prepared(ctx: &WorkerCtx, f: Frame, t_c: u64, prior: FixPrior) -> FixResult {
    let m = &ctx.metrics;
    // Wall time of the computation (reported, never used by an algorithm).
    let start = std::time::Instant::now();
    let mut report = std::panic::catch_unwind(AssertUnwindSafe(|| ctx.fixer.fix(&f.image, &prior)))
        .unwrap_or_else(|_| {
            error!("fix engine panicked on frame {}", f.seq);
            FixReport::rejected(
                visnav_core::fix::Rejection::Internal {
                    stage: "fix engine",
                    detail: "panicked".into(),
                },
                t_c,
                0.0,
            )
        });
    let elapsed = start.elapsed();
    ctx.widening
        .record(t_c, prior.widen_heading, report.accepted);
    report.ms = elapsed.as_secs_f64() * 1e3;
    let latency_ms = elapsed.as_millis() as u64;
    m.latency(latency_ms);
    if let Some(p) = ctx.fixer.paging() {
        m.map_paging(&p);
    }
    FixResult {
        t_capture_us: t_c,
        seq: f.seq,
        report,
        latency_ms,
    }
}

/// The lock-step frame path (the simulator's one clock, `FramePipeline::lockstep`): a task on
/// the runtime takes a frame every `period` of the runtime's clock, renders and fixes it on the
/// blocking pool (a paused runtime does not advance its clock while a blocking task runs, so the
/// computation takes no simulated time) and delivers the result `latency` later, as a camera and
/// engine with that latency would. Same inputs, same results, whatever the CPU's speed: the
/// frame's capture time, age and prior are taken on the runtime's thread, at a fixed point of
/// its schedule (read on the blocking thread they would race the runtime still handling the
/// telemetry of the same instant, and two runs could differ), and the blocking pool only
/// renders and fixes.
pub async fn lockstep_frames(
    source: Box<dyn FrameSource>,
    ctx: WorkerCtx,
    mut vo: Option<crate::vo_path::VoCtx>,
    period: Duration,
    latency: Duration,
    mut stop: tokio::sync::watch::Receiver<bool>,
) {
    let ctx = Arc::new(ctx);
    while ctx.clock.autopilot_now_us().is_none() {
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(50)) => {}
            _ = stop.changed() => return,
        }
    }
    info!("frames: {} (lock-step)", source.describe());
    let mut source = Some(source);
    let mut freeze = FreezeDetector::default();
    let mut unreadable = LogLimiter::default();
    let mut tick = tokio::time::interval(period);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = stop.changed() => return,
        }
        let Some(mut src) = source.take() else { return };
        let span = tracing::Span::current();
        let Ok((src, next)) = tokio::task::spawn_blocking(move || {
            let _span = span.enter();
            let r = src.next_frame();
            (src, r)
        })
        .await
        else {
            return;
        };
        source = Some(src);
        let f = match next {
            Ok(Some(f)) => f,
            Ok(None) => {
                info!("frames: end of the source");
                return;
            }
            Err(FrameError::NotReady) => continue,
            Err(e) => {
                ctx.metrics.frame_errors.inc();
                let t_s = ctx.clock.companion_now_ns() as f64 * 1e-9;
                if let Some(line) = unreadable.hit(t_s) {
                    warn!("frames: {e}; skipped{}", line.suffix());
                }
                continue;
            }
        };
        ctx.metrics.frames_in.inc();
        if freeze.repeats(&f.image, f.seq) {
            ctx.metrics.frames_frozen.inc();
            continue;
        }
        let Some((t_c, prior)) = prepare(&ctx, &f) else {
            continue;
        };
        if let Some(v) = vo.take() {
            vo = lockstep_vo(v, &f, t_c, latency).await;
        }
        let c = ctx.clone();
        let span = tracing::Span::current();
        let Ok(result) = tokio::task::spawn_blocking(move || {
            let _span = span.enter();
            fix_prepared(&c, f, t_c, prior)
        })
        .await
        else {
            continue;
        };
        let results = ctx.results.clone();
        tokio::spawn(
            async move {
                tokio::time::sleep(latency).await;
                let _ = results.send(result).await;
            }
            .in_current_span(),
        );
    }
}

/// Lock-step odometry of one frame: inputs read here, on the runtime's thread; the odometer on
/// the blocking pool; the result delivered `latency` later. `None` when the pool is gone.
async fn lockstep_vo(
    v: crate::vo_path::VoCtx,
    f: &Frame,
    t_c: u64,
    latency: Duration,
) -> Option<crate::vo_path::VoCtx> {
    let inputs = v.inputs(t_c);
    let (image, seq) = (f.image.clone(), f.seq);
    let mut v = v;
    let span = tracing::Span::current();
    let (v, r) = tokio::task::spawn_blocking(move || {
        let _span = span.enter();
        let r = v.step(image, seq, inputs);
        (v, r)
    })
    .await
    .ok()?;
    let results = v.results.clone();
    tokio::spawn(
        async move {
            tokio::time::sleep(latency).await;
            let _ = results.send(r).await;
        }
        .in_current_span(),
    );
    Some(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_repeated_image_is_a_frozen_camera_and_a_changed_pixel_is_not() {
        let a = GrayImage::from_fn(64, 48, |x, y| ((x * 7 + y * 13) % 251) as f32);
        let mut b = a.clone();
        b.data_mut()[1000] += 1.0;
        let mut d = FreezeDetector::default();
        assert!(!d.repeats(&a, 0));
        assert!(d.repeats(&a.clone(), 1));
        assert!(d.repeats(&a, 2));
        assert!(!d.repeats(&b, 3), "one pixel differs: a live camera");
        assert!(!d.repeats(&a, 4));
        // Same pixels, other shape: not the same image.
        let c = GrayImage::new(48, 64, a.data().to_vec()).unwrap();
        assert!(!d.repeats(&c, 5));
        assert_eq!(d.frozen, 2);
    }

    #[test]
    fn slot_newest_wins_and_closes() {
        let s = Slot::default();
        assert_eq!(s.put_latest(1), None);
        assert_eq!(s.put_latest(2), Some(1));
        assert_eq!(s.take(Duration::from_millis(1)), Take::Item(2));
        assert_eq!(s.take(Duration::from_millis(1)), Take::Timeout);
        s.close();
        assert_eq!(s.take(Duration::from_secs(5)), Take::Closed);
        assert!(!s.put_wait(3));
    }

    #[test]
    fn slot_put_wait_waits_for_room() {
        let s = Arc::new(Slot::default());
        assert!(s.put_wait(1));
        let s2 = s.clone();
        let h = std::thread::spawn(move || s2.put_wait(2));
        std::thread::sleep(Duration::from_millis(50));
        assert_eq!(s.take(Duration::from_millis(1)), Take::Item(1));
        assert!(h.join().unwrap());
        assert_eq!(s.take(Duration::from_secs(1)), Take::Item(2));
    }

    #[test]
    fn the_heading_search_widens_after_rejections_and_not_again_soon_after_a_failure() {
        let w = HeadingWidening::default();
        let s = |t: f64| (t * 1e6) as u64;
        assert!(!w.wanted(s(1.0)), "nothing rejected yet");
        for k in 0..WIDEN_AFTER_REJECTIONS {
            assert!(!w.wanted(s(1.0 + 0.1 * f64::from(k))));
            w.record(s(1.0 + 0.1 * f64::from(k)), false, false);
        }
        assert!(w.wanted(s(1.5)), "rejections in a row");
        w.record(s(1.5), true, false);
        assert!(!w.wanted(s(1.6)), "a widened search failed just now");
        w.record(s(1.6), false, false);
        assert!(!w.wanted(s(1.5 + WIDEN_RETRY_S - 0.1)));
        assert!(w.wanted(s(1.5 + WIDEN_RETRY_S)), "again after the pause");
        w.record(s(6.6), true, true);
        assert!(!w.wanted(s(6.7)), "an accepted fix starts the count again");
    }

    #[test]
    fn a_widened_prior_widens_the_heading_search_and_the_position_sigmas() {
        let prior = FixPrior {
            t_capture_us: 7,
            position: Some(visnav_core::fix::PositionPriorGeo {
                lat_deg: 44.05,
                lon_deg: -123.07,
                alt_amsl_m: 232.0,
                sigma_h_m: 0.8,
                sigma_v_m: 1.5,
            }),
            attitude: None,
            altitude: None,
            attitude_from_filter: true,
            widen_heading: false,
        };
        let w = widened(prior);
        assert!(w.widen_heading);
        let (p, q) = (w.position.unwrap(), prior.position.unwrap());
        assert_eq!(p.sigma_h_m, q.sigma_h_m * WIDEN_POSITION_FACTOR);
        assert_eq!(p.sigma_v_m, q.sigma_v_m * WIDEN_POSITION_FACTOR);
        assert_eq!(
            (p.lat_deg, p.lon_deg, p.alt_amsl_m),
            (q.lat_deg, q.lon_deg, q.alt_amsl_m)
        );
        assert_eq!(w.t_capture_us, 7);
        assert!(w.attitude_from_filter);
    }
}
