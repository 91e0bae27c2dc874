//! The daemon's counters (atomics, updated from any task or thread) and their snapshot. The
//! optional Prometheus endpoint (`daemon.metrics_listen`, [`crate::prometheus`]) renders
//! them together with the link's counters.

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use serde::Serialize;

use crate::imu_bias::{G0_M_S2, RestoreStatus};
use visnav_link::Health as LinkHealth;

/// Live counters.
#[derive(Debug, Default)]
pub struct DaemonMetrics {
    pub telemetry_lagged: AtomicU64,
    pub imu_samples: AtomicU64,
    pub nav_outputs: AtomicU64,
    pub autopilot_reboots: AtomicU64,
    pub imu_timeouts: AtomicU64,
    pub health_changes: AtomicU64,
    pub frames_in: AtomicU64,
    pub frames_superseded: AtomicU64,
    pub frames_stale: AtomicU64,
    pub frames_no_time: AtomicU64,
    pub frame_errors: AtomicU64,
    pub frames_frozen: AtomicU64,
    pub queue_depth_max: AtomicU64,
    pub fixes_attempted: AtomicU64,
    pub fixes_accepted: AtomicU64,
    pub fixes_filter_rejected: AtomicU64,
    pub fixes_too_old: AtomicU64,
    pub fixes_invalid: AtomicU64,
    pub fixes_unused_before_init: AtomicU64,
    pub fixes_dropped_at_shutdown: AtomicU64,
    pub fix_latency_ms_last: AtomicU64,
    pub fix_latency_ms_max: AtomicU64,
    pub fix_latency_ms_sum: AtomicU64,
    /// Number of latencies recorded (the count behind `fix_latency_ms_sum`).
    pub fix_latency_count: AtomicU64,
    /// Navigation health as a [`HealthState`] code (0 = no solution yet).
    pub health: AtomicU64,
    /// Engine rejections by reason.
    pub engine_rejected: Mutex<BTreeMap<String, u64>>,
    /// The IMU bias restorer's state (`daemon.imu_bias_restore`; `None` when off).
    pub imu_bias: Mutex<Option<RestoreStatus>>,
    /// Visual odometry (`[vo]`).
    pub vo: VoMetrics,
    /// DTM navigation (`[dtm_nav]`): `started` counts the frames kept without a partner yet,
    /// `motions` the poses solved, `fused` / `filter_rejected` / `unused` what the filter did.
    pub dtm: VoMetrics,
}

/// Visual odometry's counters.
#[derive(Debug, Default)]
pub struct VoMetrics {
    /// Frames given to the odometer.
    pub frames: AtomicU64,
    /// Frames that started a sequence (the first, or after a gap or a missing prior).
    pub started: AtomicU64,
    /// Motions measured.
    pub motions: AtomicU64,
    /// Motions the filter fused.
    pub fused: AtomicU64,
    /// Motions the filter's innovation gate rejected.
    pub filter_rejected: AtomicU64,
    /// Motions the filter did not use otherwise (not initialised, too old, malformed).
    pub unused: AtomicU64,
    /// Frames without a motion, by reason (numbers as `N`).
    pub refused: Mutex<BTreeMap<String, u64>>,
    /// Computation time of a frame, sum (µs) and largest (µs).
    pub us_sum: AtomicU64,
    pub us_max: AtomicU64,
}

/// Visual odometry in a snapshot.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct VoSnapshot {
    pub frames: u64,
    pub started: u64,
    pub motions: u64,
    pub fused: u64,
    pub filter_rejected: u64,
    pub unused: u64,
    pub refused: BTreeMap<String, u64>,
    /// Mean and largest computation time of a frame, ms.
    pub ms_mean: f64,
    pub ms_max: f64,
}

impl VoMetrics {
    /// Count one frame without a motion.
    pub fn refuse(&self, reason: &str) {
        count_reason(&self.refused, reason);
    }

    /// Record one frame's computation time.
    pub fn time(&self, us: u64) {
        self.frames.fetch_add(1, Ordering::Relaxed);
        self.us_sum.fetch_add(us, Ordering::Relaxed);
        self.us_max.fetch_max(us, Ordering::Relaxed);
    }

    fn snapshot(&self) -> VoSnapshot {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let frames = g(&self.frames);
        VoSnapshot {
            frames,
            started: g(&self.started),
            motions: g(&self.motions),
            fused: g(&self.fused),
            filter_rejected: g(&self.filter_rejected),
            unused: g(&self.unused),
            refused: self
                .refused
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            ms_mean: if frames > 0 {
                g(&self.us_sum) as f64 * 1e-3 / frames as f64
            } else {
                0.0
            },
            ms_max: g(&self.us_max) as f64 * 1e-3,
        }
    }
}

/// Count `reason` in `map`, keyed by its wording ([`reason_wording`]: every number becomes `N`,
/// so the reasons group and the map stays small), at most 64 wordings (then "other").
fn count_reason(map: &Mutex<BTreeMap<String, u64>>, reason: &str) {
    let mut m = map.lock().unwrap_or_else(|e| e.into_inner());
    let worded = reason_wording(reason);
    let key = if m.len() < 64 || m.contains_key(&worded) {
        worded
    } else {
        "other".to_string()
    };
    *m.entry(key).or_default() += 1;
}

/// The IMU bias restorer in a snapshot (`daemon.imu_bias_restore = "scaled_imu"`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ImuBiasSnapshot {
    /// SCALED_IMU paired with a HIGHRES_IMU.
    pub paired: u64,
    /// SCALED_IMU no HIGHRES_IMU matched.
    pub unpaired: u64,
    /// Estimates bootstrapped (1 after a normal start; more after autopilot bias resets).
    pub bootstraps: u64,
    /// HIGHRES_IMU samples passed on without the estimate (none yet, or older than 5 s).
    pub not_restored: u64,
    /// The newest HIGHRES_IMU sample had the estimate added back.
    pub restoring: bool,
    /// Time since the newest pair behind the estimate, s (at the newest sample).
    pub age_s: Option<f64>,
    /// The autopilot's gyro bias estimate added back, deg/h (body FRD); `None` before the first.
    pub gyro_bias_deg_h: Option<[f64; 3]>,
    /// The autopilot's accelerometer bias estimate added back, mg.
    pub accel_bias_mg: Option<[f64; 3]>,
}

impl From<RestoreStatus> for ImuBiasSnapshot {
    fn from(s: RestoreStatus) -> Self {
        Self {
            paired: s.paired,
            unpaired: s.unpaired,
            bootstraps: s.bootstraps,
            not_restored: s.not_restored,
            restoring: s.restoring,
            age_s: s.age_s(),
            gyro_bias_deg_h: s.bias.map(|b| b.0.map(|v| v.to_degrees() * 3600.0)),
            accel_bias_mg: s.bias.map(|b| b.1.map(|v| v / G0_M_S2 * 1e3)),
        }
    }
}

/// Navigation health as the daemon last published it (the injector's view).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum HealthState {
    /// No filter output yet.
    #[default]
    None,
    /// Fixes arriving and consistent.
    Ok,
    /// Usable with inflated covariance.
    Degraded,
    /// Not usable; nothing injected.
    Lost,
}

impl HealthState {
    /// All states, in code order.
    pub const ALL: [HealthState; 4] = [Self::None, Self::Ok, Self::Degraded, Self::Lost];

    /// Lower-case name (the `state` label of `visnav_nav_health`).
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Ok => "ok",
            Self::Degraded => "degraded",
            Self::Lost => "lost",
        }
    }

    fn code(self) -> u64 {
        match self {
            Self::None => 0,
            Self::Ok => 1,
            Self::Degraded => 2,
            Self::Lost => 3,
        }
    }

    fn from_code(c: u64) -> Self {
        match c {
            1 => Self::Ok,
            2 => Self::Degraded,
            3 => Self::Lost,
            _ => Self::None,
        }
    }
}

impl From<&LinkHealth> for HealthState {
    fn from(h: &LinkHealth) -> Self {
        match h {
            LinkHealth::Ok => Self::Ok,
            LinkHealth::Degraded { .. } => Self::Degraded,
            LinkHealth::Lost { .. } => Self::Lost,
        }
    }
}

/// A copy of the counters.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct MetricsSnapshot {
    /// Telemetry messages lost because the navigation task fell behind.
    pub telemetry_lagged: u64,
    /// IMU samples given to the filter.
    pub imu_samples: u64,
    /// Filter outputs published.
    pub nav_outputs: u64,
    /// Autopilot reboots seen (filter restarted).
    pub autopilot_reboots: u64,
    /// IMU stream timeouts (solution declared lost).
    pub imu_timeouts: u64,
    /// Health state changes.
    pub health_changes: u64,
    /// Frames read from the source.
    pub frames_in: u64,
    /// Frames replaced in the queue by a newer one before a worker took them.
    pub frames_superseded: u64,
    /// Frames older than `frames.max_age_s` when a worker was free.
    pub frames_stale: u64,
    /// Frames dropped because their capture time could not be mapped (no time sync yet).
    pub frames_no_time: u64,
    /// Frames that could not be read.
    pub frame_errors: u64,
    /// Frames dropped as identical to the previous one (a frozen camera).
    pub frames_frozen: u64,
    /// Largest number of frames waiting at once (the queue bound is 1).
    pub queue_depth_max: u64,
    /// Frames given to the fix engine.
    pub fixes_attempted: u64,
    /// Fixes accepted by the filter.
    pub fixes_accepted: u64,
    /// Fixes rejected by the filter's innovation gate.
    pub fixes_filter_rejected: u64,
    /// Fixes older than the filter's history.
    pub fixes_too_old: u64,
    /// Fixes the filter found malformed.
    pub fixes_invalid: u64,
    /// Fixes not given to the filter while it waits for two fixes spaced for initialisation.
    pub fixes_unused_before_init: u64,
    /// Fixes finished by a worker after the navigation task had stopped (shutdown).
    pub fixes_dropped_at_shutdown: u64,
    /// Engine rejections by reason.
    pub engine_rejected: BTreeMap<String, u64>,
    /// Frame-to-fix latency of the last fix, ms.
    pub fix_latency_ms_last: u64,
    /// Largest frame-to-fix latency, ms.
    pub fix_latency_ms_max: u64,
    /// Mean frame-to-fix latency, ms.
    pub fix_latency_ms_mean: f64,
    /// Sum of all frame-to-fix latencies, ms.
    pub fix_latency_ms_sum: u64,
    /// Number of latencies recorded.
    pub fix_latency_count: u64,
    /// Navigation health last published.
    pub health: HealthState,
    /// The IMU bias restorer (absent when `daemon.imu_bias_restore` is off).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub imu_bias: Option<ImuBiasSnapshot>,
    /// Visual odometry.
    pub vo: VoSnapshot,
    /// DTM navigation (`DaemonMetrics::dtm`).
    pub dtm: VoSnapshot,
}

/// `reason` with each number (digits with an optional sign and decimals) replaced by `N`.
pub fn reason_wording(reason: &str) -> String {
    let mut out = String::with_capacity(reason.len());
    let mut chars = reason.chars().peekable();
    while let Some(c) = chars.next() {
        let sign_digit = (c == '-' || c == '+') && chars.peek().is_some_and(|d| d.is_ascii_digit());
        if c.is_ascii_digit() || sign_digit {
            while chars
                .peek()
                .is_some_and(|d| d.is_ascii_digit() || *d == '.')
            {
                chars.next();
            }
            out.push('N');
        } else {
            out.push(c);
        }
    }
    out
}

impl DaemonMetrics {
    /// Count one engine rejection.
    pub fn engine_reject(&self, reason: &str) {
        count_reason(&self.engine_rejected, reason);
    }

    /// Record one fix latency.
    pub fn latency(&self, ms: u64) {
        self.fix_latency_ms_last.store(ms, Ordering::Relaxed);
        self.fix_latency_ms_max.fetch_max(ms, Ordering::Relaxed);
        self.fix_latency_ms_sum.fetch_add(ms, Ordering::Relaxed);
        self.fix_latency_count.fetch_add(1, Ordering::Relaxed);
    }

    /// Record the navigation health just published.
    pub fn set_health(&self, h: &LinkHealth) {
        self.health
            .store(HealthState::from(h).code(), Ordering::Relaxed);
    }

    /// Copy the counters.
    pub fn snapshot(&self) -> MetricsSnapshot {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let attempted = g(&self.fixes_attempted);
        let n_latency = g(&self.fix_latency_count);
        let sum_latency = g(&self.fix_latency_ms_sum);
        MetricsSnapshot {
            telemetry_lagged: g(&self.telemetry_lagged),
            imu_samples: g(&self.imu_samples),
            nav_outputs: g(&self.nav_outputs),
            autopilot_reboots: g(&self.autopilot_reboots),
            imu_timeouts: g(&self.imu_timeouts),
            health_changes: g(&self.health_changes),
            frames_in: g(&self.frames_in),
            frames_superseded: g(&self.frames_superseded),
            frames_stale: g(&self.frames_stale),
            frames_no_time: g(&self.frames_no_time),
            frame_errors: g(&self.frame_errors),
            frames_frozen: g(&self.frames_frozen),
            queue_depth_max: g(&self.queue_depth_max),
            fixes_attempted: attempted,
            fixes_accepted: g(&self.fixes_accepted),
            fixes_filter_rejected: g(&self.fixes_filter_rejected),
            fixes_too_old: g(&self.fixes_too_old),
            fixes_invalid: g(&self.fixes_invalid),
            fixes_unused_before_init: g(&self.fixes_unused_before_init),
            fixes_dropped_at_shutdown: g(&self.fixes_dropped_at_shutdown),
            engine_rejected: self
                .engine_rejected
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
            fix_latency_ms_last: g(&self.fix_latency_ms_last),
            fix_latency_ms_max: g(&self.fix_latency_ms_max),
            fix_latency_ms_mean: if n_latency > 0 {
                sum_latency as f64 / n_latency as f64
            } else {
                0.0
            },
            fix_latency_ms_sum: sum_latency,
            fix_latency_count: n_latency,
            health: HealthState::from_code(g(&self.health)),
            vo: self.vo.snapshot(),
            dtm: self.dtm.snapshot(),
            imu_bias: self
                .imu_bias
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .map(ImuBiasSnapshot::from),
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn reasons_group_by_wording() {
        use super::reason_wording as w;
        assert_eq!(
            w("only 2 matches where chance gives 3 (need 17)"),
            "only N matches where chance gives N (need N)"
        );
        assert_eq!(
            w("prior altitude 580.1 m AMSL is not above the terrain"),
            "prior altitude N m AMSL is not above the terrain"
        );
        assert_eq!(w("offset -12.5 m, x-ray"), "offset N m, x-ray");
        assert_eq!(w("no map"), "no map");
        let m = super::DaemonMetrics::default();
        for i in 0..200 {
            m.engine_reject(&format!("only {i} features in the frame"));
        }
        let s = m.snapshot();
        assert_eq!(s.engine_rejected.len(), 1);
        assert_eq!(s.engine_rejected["only N features in the frame"], 200);
    }

    use super::*;

    #[test]
    fn latency_mean_and_health_round_trip() {
        let m = DaemonMetrics::default();
        assert_eq!(m.snapshot().health, HealthState::None);
        assert_eq!(m.snapshot().fix_latency_ms_mean, 0.0);
        m.latency(100);
        m.latency(300);
        let s = m.snapshot();
        assert_eq!((s.fix_latency_count, s.fix_latency_ms_sum), (2, 400));
        assert_eq!(s.fix_latency_ms_mean, 200.0);
        assert_eq!((s.fix_latency_ms_last, s.fix_latency_ms_max), (300, 300));
        for (h, want) in [
            (LinkHealth::Ok, HealthState::Ok),
            (
                LinkHealth::Degraded { reason: "x".into() },
                HealthState::Degraded,
            ),
            (LinkHealth::Lost { reason: "y".into() }, HealthState::Lost),
        ] {
            m.set_health(&h);
            assert_eq!(m.snapshot().health, want);
            assert_eq!(HealthState::from_code(want.code()), want);
        }
    }
}
