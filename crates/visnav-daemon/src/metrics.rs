//! The daemon's metrics, each declared once in [`DaemonMetrics`] (name, help, kind, labels:
//! [`visnav_metrics::metric_set!`]): atomics updated from any task or thread, registered in the one
//! registry of `visnav run`'s Prometheus endpoint ([`registry`]: build info, heap, the daemon's
//! and the link's metrics; `daemon.metrics_listen`, [`crate::prometheus`]) and copied into a
//! typed [`MetricsSnapshot`] (the end-of-run JSON, `visnav sim`, the tests).
//!
//! The daemon's own kinds beside the link's ([`visnav_link::metrics`]): [`Health`] (one-hot by
//! state), [`ImuBias`] (the restorer's families, present while it runs) and [`Sequence`] (a
//! frame-sequence navigator's families: visual odometry, DTM navigation).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::MetricType;
use prometheus_client::metrics::info::Info;
use serde::Serialize;

use crate::imu_bias::{G0_M_S2, RestoreStatus};
use visnav_core::reasons::ReasonCount;
use visnav_link::Health as LinkHealth;
use visnav_link::metrics::Metrics as LinkMetrics;
use visnav_metrics::{Counter, Declare, Gauge, Histogram, Label, Reasons, Registrar, Registry};

visnav_metrics::metric_set! {
    /// The daemon's metrics (atomics; `Clone` shares them).
    pub struct DaemonMetrics => MetricsSnapshot {
        /// Navigation health as the daemon last published it (the injector's view).
        health: Health "visnav_nav_health"
            "navigation health, one-hot over state (none = no solution yet)",
        /// Health state changes.
        health_changes: Counter "visnav_nav_health_changes" "navigation health state changes",
        /// Filter outputs published.
        nav_outputs: Counter "visnav_nav_outputs" "filter outputs published",
        /// Autopilot reboots seen (filter restarted).
        autopilot_reboots: Counter "visnav_nav_filter_restarts"
            "filter restarts after an autopilot reboot",
        /// IMU samples given to the filter.
        imu_samples: Counter "visnav_imu_samples" "IMU samples given to the filter",
        /// IMU stream timeouts (solution declared lost).
        imu_timeouts: Counter "visnav_imu_timeouts" "IMU stream timeouts (solution declared lost)",
        /// Telemetry messages lost because the navigation task fell behind.
        telemetry_lagged: Counter "visnav_telemetry_lagged_messages"
            "telemetry messages lost because the navigation task fell behind",
        /// The IMU bias restorer (`daemon.imu_bias_restore`; `None` when off).
        imu_bias: ImuBias "visnav_imu_bias" "the IMU bias restorer",
        /// Frames read from the source.
        frames_in: Counter "visnav_frames_read" "frames read from the source",
        /// Frames replaced in the queue by a newer one before a worker took them.
        frames_superseded: Counter "visnav_frames_dropped" "frames dropped before a fix, by reason"
            ["reason" = "superseded"],
        /// Frames older than `frames.max_age_s` when a worker was free.
        frames_stale: Counter "visnav_frames_dropped" "frames dropped before a fix, by reason"
            ["reason" = "stale"],
        /// Frames dropped because their capture time could not be mapped (no time sync yet).
        frames_no_time: Counter "visnav_frames_dropped" "frames dropped before a fix, by reason"
            ["reason" = "no_time"],
        /// Frames that could not be read.
        frame_errors: Counter "visnav_frame_errors" "frames that could not be read",
        /// Frames dropped as identical to the previous one (a frozen camera).
        frames_frozen: Counter "visnav_frames_frozen"
            "frames dropped as identical to the one before (a frozen camera)",
        /// Largest number of frames waiting at once (the queue bound is 1).
        queue_depth_max: Gauge "visnav_frame_queue_depth_max"
            "largest number of frames waiting at once",
        /// Frames given to the fix engine.
        fixes_attempted: Counter "visnav_fixes_attempted" "frames given to the fix engine",
        /// Frames given to the fix engine with the heading search widened when nothing is found
        /// at the prior's heading (after repeated rejections).
        fixes_heading_widened: Counter "visnav_fixes_heading_widened"
            "frames whose heading search the engine widens when none is found at the prior's heading",
        /// Fixes accepted by the filter.
        fixes_accepted: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them" ["outcome" = "accepted"],
        /// Fixes rejected by the filter's innovation gate.
        fixes_filter_rejected: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them"
            ["outcome" = "filter_rejected"],
        /// Fixes older than the filter's history.
        fixes_too_old: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them" ["outcome" = "too_old"],
        /// Fixes the filter found malformed.
        fixes_invalid: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them" ["outcome" = "invalid"],
        /// Fixes not given to the filter while it waits for two fixes spaced for initialisation.
        fixes_unused_before_init: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them"
            ["outcome" = "unused_before_init"],
        /// Fixes finished by a worker after the navigation task had stopped (shutdown).
        fixes_dropped_at_shutdown: Counter "visnav_fixes"
            "fixes the engine returned, by what the filter did with them"
            ["outcome" = "dropped_at_shutdown"],
        /// Engine rejections by class (the first check that refused, without numbers), each
        /// with its latest reason, most frequent first.
        engine_rejected: Reasons "visnav_fix_engine_rejections"
            "fixes the engine rejected, by reason",
        /// Visual odometry (`[vo]`).
        vo: Sequence "visnav_vo" "visual odometry" ["motion" = "motions"],
        /// DTM navigation (`[dtm_nav]`): `started` counts the frames kept without a partner yet,
        /// `motions` the poses solved, `fused` / `filter_rejected` / `unused` what the filter did.
        dtm: Sequence "visnav_dtm" "DTM navigation" ["pose" = "poses"],
        /// The fix engine's computing time per frame, ms.
        fix_latency_ms: Histogram "visnav_fix_latency_seconds"
            "the fix engine's computing time per frame" / 1e3,
        /// The last frame's, ms.
        fix_latency_ms_last: Gauge "visnav_fix_latency_last_seconds"
            "the fix engine's computing time of the last frame" / 1e3,
        /// The largest, ms.
        fix_latency_ms_max: Gauge "visnav_fix_latency_max_seconds"
            "the fix engine's largest computing time of a frame" / 1e3,
        /// A tiled map's tiles loaded so far (`[map] file` a folder; 0 with a single file).
        map_tile_loads: Gauge "visnav_map_tile_loads"
            "tiles of the tiled map loaded into memory so far",
        /// Tiles dropped for the memory budget.
        map_tile_evictions: Gauge "visnav_map_tile_evictions"
            "tiles of the tiled map dropped for its memory budget so far",
        /// Tiles asked for while not in memory (the fix went on without them).
        map_tile_misses: Gauge "visnav_map_tile_misses"
            "tiles asked for while not in memory (the fix went on without them) so far",
        /// Tiles of a frame's own footprint that were not in memory when it was fixed.
        map_tiles_late: Gauge "visnav_map_tiles_late"
            "tiles of a frame's own footprint not in memory when it was fixed, so far",
        /// Tiles that could not be loaded (unreadable, or not the checksum the index records).
        map_tile_load_errors: Gauge "visnav_map_tile_load_errors"
            "tiles that could not be loaded (unreadable or damaged)",
        /// Tiles in memory now.
        map_tiles_resident: Gauge "visnav_map_tiles_resident" "tiles of the tiled map in memory",
        /// Their size, bytes.
        map_tile_bytes_resident: Gauge "visnav_map_tile_bytes_resident"
            "bytes of the tiled map's tiles in memory",
    }
}

impl DaemonMetrics {
    /// Count one engine rejection by its `class` (`visnav_core::fix::Rejection::class`: the
    /// first check that refused, a name without numbers; the same classes as `visnav sim`'s),
    /// keeping the `reason` itself for the snapshot.
    pub fn engine_reject(&self, class: &'static str, reason: &str) {
        self.engine_rejected.count(class, reason);
    }

    /// Copy a tiled map's paging counters (`map::paged::PagedMap::stats`).
    pub fn map_paging(&self, p: &visnav_io::map::paged::PagingStats) {
        self.map_tile_loads.set(p.loads);
        self.map_tile_evictions.set(p.evictions);
        self.map_tile_misses.set(p.misses);
        self.map_tiles_late.set(p.late);
        self.map_tile_load_errors.set(p.load_errors);
        self.map_tiles_resident.set(p.resident_tiles as u64);
        self.map_tile_bytes_resident.set(p.resident_bytes);
    }

    /// Record one fix latency.
    pub fn latency(&self, ms: u64) {
        self.fix_latency_ms.observe(ms);
        self.fix_latency_ms_last.set(ms);
        self.fix_latency_ms_max.max(ms);
    }
}

/// The registry of `visnav run`'s endpoint: build info, heap, the daemon's and the link's
/// metrics.
pub fn registry(daemon: &DaemonMetrics, link: &LinkMetrics) -> Registry {
    let mut reg = Registry::default();
    reg.register(
        "visnav_build",
        "visnav version (always 1)",
        Info::new([("version", env!("CARGO_PKG_VERSION"))]),
    );
    reg.register(
        "visnav_heap_bytes",
        "bytes allocated on the heap and not freed (the process's own count)",
        HeapBytes,
    );
    daemon.register(&mut reg);
    link.register(&mut reg);
    reg
}

/// The heap in use (absent when the binary does not count it).
#[derive(Debug)]
struct HeapBytes;

impl EncodeMetric for HeapBytes {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        encoder.encode_gauge(&crate::heap::heap_in_use_bytes().unwrap_or(0))
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Gauge
    }

    fn is_empty(&self) -> bool {
        crate::heap::heap_in_use_bytes().is_none()
    }
}

/// Navigation health as a [`HealthState`] code; exposed one-hot by `state`.
#[derive(Debug, Clone, Default)]
pub struct Health(Arc<AtomicU64>);

impl Health {
    /// Record the navigation health just published.
    pub fn set(&self, h: &LinkHealth) {
        self.0.store(HealthState::from(h).code(), Ordering::Relaxed);
    }
}

impl EncodeMetric for Health {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        let now = self.value();
        for s in HealthState::ALL {
            encoder
                .encode_family(&[("state", s.name())])?
                .encode_gauge(&u64::from(s == now))?;
        }
        Ok(())
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Gauge
    }
}

impl Declare for Health {
    type Value = HealthState;

    fn new(_divisor: f64) -> Self {
        Self::default()
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, _: Label) {
        r.metric(name, help, self.clone());
    }

    fn value(&self) -> HealthState {
        HealthState::from_code(self.0.load(Ordering::Relaxed))
    }
}

/// The IMU bias restorer's state (`None` until it reports; it runs with
/// `daemon.imu_bias_restore`). Its families are exposed while it reports.
#[derive(Debug, Clone, Default)]
pub struct ImuBias(Arc<Mutex<Option<RestoreStatus>>>);

impl ImuBias {
    /// Record the restorer's state.
    pub fn set(&self, s: RestoreStatus) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(s);
    }
}

impl Declare for ImuBias {
    type Value = Option<ImuBiasSnapshot>;

    fn new(_divisor: f64) -> Self {
        Self::default()
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, _: &'static str, _: Label) {
        r.collector(ImuBiasFamilies {
            prefix: name,
            state: self.clone(),
        });
    }

    fn value(&self) -> Option<ImuBiasSnapshot> {
        self.0
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .map(ImuBiasSnapshot::from)
    }
}

/// The restorer's families, found at each scrape.
#[derive(Debug)]
struct ImuBiasFamilies {
    prefix: &'static str,
    state: ImuBias,
}

impl Collector for ImuBiasFamilies {
    fn encode(&self, mut encoder: DescriptorEncoder) -> Result<(), std::fmt::Error> {
        let Some(b) = self.state.value() else {
            return Ok(());
        };
        let p = self.prefix;
        for (name, help, v) in [
            (
                format!("{p}_pairs"),
                "SCALED_IMU paired with a HIGHRES_IMU (daemon.imu_bias_restore)",
                b.paired,
            ),
            (
                format!("{p}_unpaired"),
                "SCALED_IMU that no HIGHRES_IMU matched",
                b.unpaired,
            ),
            (
                format!("{p}_bootstraps"),
                "autopilot bias estimates bootstrapped (more than 1: the autopilot's estimate jumped)",
                b.bootstraps,
            ),
            (
                "visnav_imu_samples_not_restored".to_string(),
                "HIGHRES_IMU samples passed on without the autopilot's bias added back",
                b.not_restored,
            ),
        ] {
            encoder
                .encode_descriptor(&name, help, None, MetricType::Counter)?
                .encode_counter::<NoLabelSet, u64, u64>(&v, None)?;
        }
        let mut gauge = |name: String, help: &str, v: f64| {
            encoder
                .encode_descriptor(&name, help, None, MetricType::Gauge)?
                .encode_gauge(&v)
        };
        if let Some(a) = b.age_s {
            gauge(
                format!("{p}_age_seconds"),
                "time since the last SCALED_IMU / HIGHRES_IMU pair (the estimate is dropped after 5 s)",
                a,
            )?;
        }
        gauge(
            format!("{p}_restoring"),
            "1 while HIGHRES_IMU samples get the autopilot's bias estimate added back",
            if b.restoring { 1.0 } else { 0.0 },
        )?;
        for (name, help, v) in [
            (
                format!("{p}_gyro_deg_per_hour"),
                "the autopilot's gyro bias estimate added back to HIGHRES_IMU, body FRD",
                b.gyro_bias_deg_h,
            ),
            (
                format!("{p}_accel_mg"),
                "the autopilot's accelerometer bias estimate added back to HIGHRES_IMU, body FRD",
                b.accel_bias_mg,
            ),
        ] {
            if let Some(v) = v {
                let mut m = encoder.encode_descriptor(&name, help, None, MetricType::Gauge)?;
                for (axis, x) in ["x", "y", "z"].into_iter().zip(v) {
                    m.encode_family(&[("axis", axis)])?.encode_gauge(&x)?;
                }
            }
        }
        Ok(())
    }
}

/// A frame-sequence navigator's metrics (visual odometry, DTM navigation). Declared with a
/// prefix as name, what it is as help and `[out = outs]` as label (what a frame gives:
/// "motion" / "motions"), it exposes `{prefix}_frames_total{outcome=out|started|refused}`,
/// `{prefix}_{outs}_total{outcome=fused|filter_rejected|unused}`,
/// `{prefix}_refusals_total{reason}`, `{prefix}_frame_seconds` (histogram) and
/// `{prefix}_frame_seconds_max`.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Frames that started a sequence (the first, or after a gap or a missing prior).
    pub started: Counter,
    /// Motions measured.
    pub motions: Counter,
    /// Frames without a motion.
    refused: Counter,
    /// Motions the filter fused.
    pub fused: Counter,
    /// Motions the filter's innovation gate rejected.
    pub filter_rejected: Counter,
    /// Motions the filter did not use otherwise (not initialised, too old, malformed).
    pub unused: Counter,
    /// Frames without a motion, by reason.
    refusals: Reasons,
    /// Computation time of a frame, µs.
    time_us: Histogram,
    /// The longest, µs.
    time_us_max: Gauge,
}

/// A frame-sequence navigator in a snapshot.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct VoSnapshot {
    /// Frames given to the navigator.
    pub frames: u64,
    /// Frames that started a sequence (the first, or after a gap or a missing prior).
    pub started: u64,
    /// Motions computed.
    pub motions: u64,
    /// Motions the filter fused.
    pub fused: u64,
    /// Motions the filter's innovation gate rejected.
    pub filter_rejected: u64,
    /// Motions the filter did not use otherwise (not initialised, too old, malformed).
    pub unused: u64,
    /// Frames without a motion by class, each with its latest reason, most frequent first.
    pub refused: Vec<ReasonCount>,
    /// Mean and largest computation time of a frame, ms.
    pub ms_mean: f64,
    /// Largest computation time of a frame, ms.
    pub ms_max: f64,
}

impl Sequence {
    /// Count one frame without a motion, by its `class` (the refusal's `class()`: a name
    /// without numbers), keeping the `reason` in words for the snapshot.
    pub fn refuse(&self, class: &'static str, reason: &str) {
        self.refused.inc();
        self.refusals.count(class, reason);
    }

    /// Record one frame's computation time.
    pub fn time(&self, us: u64) {
        self.time_us.observe(us);
        self.time_us_max.max(us);
    }
}

impl Declare for Sequence {
    type Value = VoSnapshot;

    fn new(_divisor: f64) -> Self {
        let c = Counter::default;
        Self {
            started: c(),
            motions: c(),
            refused: c(),
            fused: c(),
            filter_rejected: c(),
            unused: c(),
            refusals: Reasons::default(),
            time_us: Histogram::new(1e6),
            time_us_max: Gauge::new(1e6),
        }
    }

    fn declare(&self, r: &mut Registrar, prefix: &'static str, what: &'static str, l: Label) {
        let (out, outs) = l.unwrap_or(("motion", "motions"));
        let frames = format!("{prefix}_frames");
        let frames_help = format!("frames given to {what}, by what came out");
        for (outcome, c) in [
            (out, &self.motions),
            ("started", &self.started),
            ("refused", &self.refused),
        ] {
            r.member(&frames, &frames_help, ("outcome", outcome), c);
        }
        let used = format!("{prefix}_{outs}");
        let used_help = format!("{what} {outs}, by what the filter did with them");
        for (outcome, c) in [
            ("fused", &self.fused),
            ("filter_rejected", &self.filter_rejected),
            ("unused", &self.unused),
        ] {
            r.member(&used, &used_help, ("outcome", outcome), c);
        }
        r.metric(
            format!("{prefix}_refusals"),
            format!("frames without a {what} {out}, by reason"),
            self.refusals.clone(),
        );
        r.metric(
            format!("{prefix}_frame_seconds"),
            format!("{what} computation time of a frame"),
            self.time_us.clone(),
        );
        r.metric(
            format!("{prefix}_frame_seconds_max"),
            format!("longest {what} computation of a frame"),
            self.time_us_max.clone(),
        );
    }

    fn value(&self) -> VoSnapshot {
        let t = self.time_us.value();
        VoSnapshot {
            frames: t.count,
            started: self.started.get(),
            motions: self.motions.get(),
            fused: self.fused.get(),
            filter_rejected: self.filter_rejected.get(),
            unused: self.unused.get(),
            refused: self.refusals.value(),
            ms_mean: t.mean / 1e3,
            ms_max: self.time_us_max.get() as f64 / 1e3,
        }
    }
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

#[cfg(test)]
mod tests {
    #[test]
    fn reasons_group_by_class_and_keep_their_numbers() {
        // Reasons with the same wording but for their numbers: `visnav_core::reasons`'s test.
        let m = super::DaemonMetrics::default();
        for i in 0..200 {
            let r = visnav_core::fix::Rejection::FewFeatures { n: i };
            m.engine_reject(r.class(), &r.to_string());
        }
        let s = m.snapshot();
        assert_eq!(s.engine_rejected.len(), 1);
        let r = &s.engine_rejected[0];
        assert_eq!(
            (r.reason.as_str(), r.count, r.class.as_str()),
            ("only 199 features in the frame", 200, "few_features")
        );
        // The area correlation's fallback reason is not counted apart, and stays in the reason
        // shown.
        let sigma = |sigma_m| {
            visnav_core::fix::Rejection::Pose(visnav_core::pose::Rejection::HorizontalSigma {
                sigma_m,
                max_m: 50.0,
            })
        };
        let both = visnav_core::fix::Rejection::Methods(vec![
            (visnav_core::fix::FixMethod::Features, sigma(61.0)),
            (visnav_core::fix::FixMethod::Area, sigma(70.0)),
        ]);
        m.engine_reject(both.class(), &both.to_string());
        let s = m.snapshot();
        let r = &s.engine_rejected[1];
        assert_eq!(
            (r.reason.as_str(), r.count, r.class.as_str()),
            (both.to_string().as_str(), 1, "pose_horizontal_sigma")
        );
        assert!(
            r.reason.contains("61.0 m") && r.reason.contains("area: "),
            "{}",
            r.reason
        );
        // The final counters (`visnav run` logs them as JSON) carry the numbers; no placeholder.
        let json = serde_json::to_string(&s).unwrap();
        assert!(
            json.contains(r#""reason":"only 199 features in the frame","count":200"#),
            "{json}"
        );
        assert!(!json.contains(" N "), "{json}");
    }

    use super::*;

    #[test]
    fn latency_mean_and_health_round_trip() {
        let m = DaemonMetrics::default();
        assert_eq!(m.snapshot().health, HealthState::None);
        assert_eq!(m.snapshot().fix_latency_ms.mean, 0.0);
        m.latency(100);
        m.latency(300);
        let s = m.snapshot();
        assert_eq!((s.fix_latency_ms.count, s.fix_latency_ms.sum), (2, 400));
        assert_eq!(s.fix_latency_ms.mean, 200.0);
        assert_eq!((s.fix_latency_ms_last, s.fix_latency_ms_max), (300, 300));
        for (h, want) in [
            (LinkHealth::Ok, HealthState::Ok),
            (
                LinkHealth::Degraded { reason: "x".into() },
                HealthState::Degraded,
            ),
            (LinkHealth::Lost { reason: "y".into() }, HealthState::Lost),
        ] {
            m.health.set(&h);
            assert_eq!(m.snapshot().health, want);
            assert_eq!(HealthState::from_code(want.code()), want);
        }
    }
}
