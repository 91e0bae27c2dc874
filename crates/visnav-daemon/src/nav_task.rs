//! The navigation task (tokio): owns the `NavFilter`; reads the link's telemetry and feeds IMU
//! samples at full rate, GPS (`[daemon] gps`), autopilot attitude and barometric altitude
//! (`inputs`); takes fix results and visual odometry from bounded channels and applies them at
//! their capture time; publishes every output (the estimate for the injector, `NavOutput` for
//! observers, the output history for fix priors); a 100 ms watchdog declares the solution lost
//! when the IMU stream stops.

use std::sync::Arc;
use std::time::Duration;
// tokio's clock: real time, or the lock-step simulator's when the runtime runs paused.
use tokio::time::Instant;

use tokio::sync::{broadcast, mpsc, watch};
use tracing::{info, warn};

use crate::config::{DaemonConfig, GpsSource};
use crate::frames::FixResult;
use crate::inputs::{Inputs, NavInput};
use crate::metrics::DaemonMetrics;
use crate::priors::SharedPriors;
use crate::{fixlog, inputs, vo_path, volog};
use visnav_core::camera::Attitude;
use visnav_core::dtm_nav::DtmStep;
use visnav_core::nav::filter::{HealthCause, HealthReason};
use visnav_core::nav::{
    Health as NavHealth, Measurement, NavConfig, NavFilter, NavOutput, Outcome,
};
use visnav_core::vo::{VoMotion, VoStep};
use visnav_link::sensors::Sensor;
use visnav_link::{Health as LinkHealth, Link, LogLimiter, NavEstimate, Telemetry};

/// The last solution before a restart and the companion time (ns) it was made, waiting to be
/// re-stamped on the new boot clock once the link maps it.
pub(crate) struct PendingReacquire {
    pub(crate) out: NavOutput,
    pub(crate) made_ns: i64,
}

/// The navigation task: owns the filter, takes the link's telemetry and the frame path's
/// results, publishes every output (module doc).
pub(crate) struct NavTask {
    pub(crate) filter: NavFilter,
    pub(crate) nav_cfg: NavConfig,
    pub(crate) inputs: Inputs,
    pub(crate) dcfg: DaemonConfig,
    pub(crate) gps: GpsSource,
    pub(crate) gps_hz: f64,
    pub(crate) link: Arc<Link>,
    pub(crate) shared: Arc<SharedPriors>,
    pub(crate) metrics: Arc<DaemonMetrics>,
    pub(crate) est_tx: watch::Sender<Option<NavEstimate>>,
    pub(crate) out_tx: watch::Sender<Option<NavOutput>>,
    pub(crate) last_health: Option<LinkHealth>,
    /// The reason `last_health` was built from (its causes' kinds decide whether the next is
    /// news).
    pub(crate) last_reason: HealthReason,
    pub(crate) last_est: Option<NavEstimate>,
    pub(crate) reset_sum: u64,
    pub(crate) reset_counter: u8,
    pub(crate) last_imu_at: Option<Instant>,
    /// Companion time (ns) of the last published output that was not lost.
    pub(crate) last_out_ns: Option<i64>,
    /// The last solution before an autopilot reboot, until the new boot clock is mapped.
    pub(crate) pending_reacquire: Option<PendingReacquire>,
    pub(crate) imu_lost: bool,
    pub(crate) gps2_asked: Option<Instant>,
    pub(crate) last_log: Instant,
    /// The IMU bias restorer was restoring at the last watchdog tick (for its log lines).
    pub(crate) imu_bias_restoring: bool,
    /// Whether the learned drag law of body x / y was logged (`nav::drag`).
    pub(crate) drag_logged: [bool; 2],
    pub(crate) init_spacing: inputs::InitSpacing,
    pub(crate) fix_log: Option<fixlog::FixLog>,
    pub(crate) vo_log: Option<volog::VoLog>,
    /// Visual odometry's last state (motions or refusals), for logging its changes.
    pub(crate) vo_working: Option<bool>,
    /// The DTM navigator's (poses or refusals).
    pub(crate) dtm_working: Option<bool>,
    /// Rate limit of the "fell behind" warning (a starved task lags again and again).
    pub(crate) lag_log: LogLimiter,
}

/// What the navigation task is wired to: the link, the shared priors, the metrics, its outputs
/// and its logs.
pub(crate) struct NavWiring {
    pub(crate) link: Arc<Link>,
    pub(crate) shared: Arc<SharedPriors>,
    pub(crate) metrics: Arc<DaemonMetrics>,
    pub(crate) est_tx: watch::Sender<Option<NavEstimate>>,
    pub(crate) out_tx: watch::Sender<Option<NavOutput>>,
    pub(crate) fix_log: Option<fixlog::FixLog>,
    pub(crate) vo_log: Option<volog::VoLog>,
}

impl NavTask {
    /// A task with a new filter of `nav_cfg`, before its first message.
    pub(crate) fn new(
        nav_cfg: &NavConfig,
        dcfg: &DaemonConfig,
        gps: GpsSource,
        gps_hz: f64,
        w: NavWiring,
    ) -> Self {
        Self {
            filter: NavFilter::new(nav_cfg.clone()),
            nav_cfg: nav_cfg.clone(),
            inputs: Inputs::new(dcfg.clone(), gps),
            dcfg: dcfg.clone(),
            gps,
            gps_hz,
            link: w.link,
            shared: w.shared,
            metrics: w.metrics,
            est_tx: w.est_tx,
            out_tx: w.out_tx,
            last_health: None,
            last_reason: Default::default(),
            last_est: None,
            reset_sum: 0,
            reset_counter: 0,
            last_imu_at: None,
            last_out_ns: None,
            pending_reacquire: None,
            imu_lost: false,
            gps2_asked: None,
            last_log: Instant::now(),
            imu_bias_restoring: false,
            drag_logged: [false; 2],
            init_spacing: inputs::InitSpacing::default(),
            fix_log: w.fix_log,
            vo_log: w.vo_log,
            vo_working: None,
            dtm_working: None,
            lag_log: LogLimiter::default(),
        }
    }

    pub(crate) async fn run(
        mut self,
        mut tel: broadcast::Receiver<Telemetry>,
        mut fixes: mpsc::Receiver<FixResult>,
        mut vo: mpsc::Receiver<vo_path::VoResult>,
        mut stop: watch::Receiver<bool>,
    ) {
        let mut tick = tokio::time::interval(Duration::from_millis(100));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = stop.changed() => {
                    // Results already queued, and any a worker finishes from now on (its send
                    // fails on the closed channel), are counted, not silently lost.
                    fixes.close();
                    while fixes.try_recv().is_ok() {
                        self.metrics.fixes_dropped_at_shutdown.inc();
                    }
                    return;
                }
                r = tel.recv() => match r {
                    Ok(t) => self.telemetry(&t),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        self.metrics.telemetry_lagged.inc_by(n);
                        let t_s = self.link.companion_now_ns() as f64 * 1e-9;
                        if let Some(line) = self.lag_log.hit(t_s) {
                            warn!(
                                "navigation task fell behind: {n} telemetry messages lost{}",
                                line.suffix()
                            );
                        }
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                },
                Some(f) = fixes.recv() => self.fix(f),
                Some(r) = vo.recv() => self.vo(r),
                _ = tick.tick() => self.watchdog().await,
            }
        }
    }

    fn telemetry(&mut self, t: &Telemetry) {
        if let Some(tb) = t.t_boot_us
            && let Some(p) = self.pending_reacquire.take()
        {
            // Re-stamp the old solution on the new boot clock: as old as it is on the
            // companion's clock.
            let age_us = ((t.t_companion_ns - p.made_ns).max(0) / 1000) as u64;
            let mut o = p.out;
            o.t_us = tb.saturating_sub(age_us);
            info!(
                "reacquiring from the solution of {:.1} s before the reboot",
                age_us as f64 * 1e-6
            );
            *self
                .shared
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner()) = Some(o);
        }
        if let Some(Sensor::Attitude(a)) = t.sensor() {
            let mut q = self
                .shared
                .attitudes
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            q.push_back((
                a.t_boot_us,
                Attitude::new(a.roll_rad, a.pitch_rad, a.yaw_rad),
            ));
            while q.len() > 200 {
                q.pop_front();
            }
        }
        for input in self.inputs.convert(t) {
            match input {
                NavInput::Imu(s) => {
                    self.metrics.imu_samples.inc();
                    self.last_imu_at = Some(Instant::now());
                    if self.imu_lost {
                        self.imu_lost = false;
                        info!("IMU data resumed");
                    }
                    if let Some(o) = self.filter.imu(&s) {
                        self.publish(o);
                    }
                }
                NavInput::Meas(m) => {
                    if self.init_spacing_ok(&m) {
                        self.filter.measure(m);
                    }
                }
                NavInput::Vehicle { multirotor } => self.filter.set_multirotor(multirotor),
                NavInput::Reboot => {
                    warn!("autopilot reboot: navigation filter restarted");
                    self.metrics.autopilot_reboots.inc();
                    self.filter = NavFilter::new(self.nav_cfg.clone());
                    self.filter.set_multirotor(self.inputs.multirotor());
                    self.drag_logged = [false; 2];
                    let last = {
                        let mut book = self.shared.book.lock().unwrap_or_else(|e| e.into_inner());
                        let last = book.last().cloned();
                        book.clear();
                        last
                    };
                    *self
                        .shared
                        .reacquire
                        .lock()
                        .unwrap_or_else(|e| e.into_inner()) = None;
                    self.pending_reacquire = last
                        .filter(inputs::usable_as_prior)
                        .zip(self.last_out_ns)
                        .map(|(out, made_ns)| PendingReacquire { out, made_ns });
                    self.publish_lost(&HealthReason::of(HealthCause::AutopilotRebooted));
                }
            }
        }
    }

    fn fix(&mut self, f: FixResult) {
        let m = self.metrics.clone();
        let outcome = match inputs::vision_measurement(
            &f.report,
            f.t_capture_us,
            self.filter.config().vision_attitude,
            self.filter.config().vision_prior_dependence,
        ) {
            Err(reason) => {
                m.engine_reject(reason.class(), &reason.to_string());
                "engine_rejected"
            }
            Ok(meas) if !self.init_spacing_ok(&meas) => {
                m.fixes_unused_before_init.inc();
                "unused_before_init"
            }
            Ok(meas) => {
                let (c, name) = match self.filter.measure(meas) {
                    Outcome::Accepted { .. } => (&m.fixes_accepted, "accepted"),
                    Outcome::Initialised => (&m.fixes_accepted, "initialised"),
                    Outcome::Held => (&m.fixes_accepted, "held"),
                    Outcome::Reset => (&m.fixes_accepted, "reset"),
                    Outcome::Rejected { .. } => (&m.fixes_filter_rejected, "rejected"),
                    Outcome::TooOld => (&m.fixes_too_old, "too_old"),
                    Outcome::Invalid(_) | Outcome::Ignored => (&m.fixes_invalid, "invalid"),
                };
                c.inc();
                name
            }
        };
        if let Some(log) = self.fix_log.as_mut() {
            let r = fixlog::FixLogRecord::new(
                visnav_link::tlog::unix_now_us(),
                f.seq,
                f.latency_ms,
                &f.report,
                outcome,
            );
            if let Err(e) = log.write(&r) {
                warn!("fix log {}: {e}; logging stopped", log.path().display());
                self.fix_log = None;
            }
        }
    }

    /// A visual odometry result: a motion to the filter, everything counted; the first motion
    /// after refusals (and the first refusal after motions) logged with its reason.
    fn vo(&mut self, r: vo_path::VoResult) {
        if let Some(d) = &r.dtm {
            self.dtm(r.seq, d);
        }
        let Some(step) = &r.step else { return };
        let (outcome, nis) = match step {
            VoStep::Motion(motion) => self.vo_motion(r.seq, motion),
            VoStep::Refused(why) => {
                if self.vo_working != Some(false) {
                    info!("visual odometry: no motion from frame {}: {why}", r.seq);
                    self.vo_working = Some(false);
                }
                ("", None)
            }
            VoStep::Started => ("", None),
        };
        if let Some(log) = self.vo_log.as_mut() {
            let rec = volog::VoLogRecord::new(
                visnav_link::tlog::unix_now_us(),
                r.seq,
                r.t_capture_us,
                step,
                outcome,
                nis,
            )
            .with_prior_attitude(r.prior_attitude_deg);
            if let Err(e) = log.write(&rec) {
                warn!("VO log {}: {e}; logging stopped", log.path().display());
                self.vo_log = None;
            }
        }
    }

    /// A DTM navigation result: a pose to the filter (gated as a map fix's pose), everything
    /// counted; the first pose after refusals (and the first refusal after poses) logged.
    fn dtm(&mut self, seq: u64, step: &DtmStep) {
        let m = &self.metrics.dtm;
        match step {
            DtmStep::Fix(f) => {
                let c = match self.filter.measure(Measurement::VisionPose(f.fix)) {
                    Outcome::Accepted { .. } => &m.fused,
                    Outcome::Rejected { .. } => &m.filter_rejected,
                    _ => &m.unused,
                };
                c.inc();
                if self.dtm_working != Some(true) {
                    info!(
                        "DTM navigation: pose from frame {seq} ({:.0} m baseline, {} of {} flow vectors, {:.2} px, {:.1} m horizontal sigma given the attitude)",
                        f.baseline_m, f.inliers, f.tracks, f.rms_px, f.sigma_h_given_attitude_m
                    );
                    self.dtm_working = Some(true);
                }
            }
            DtmStep::Refused(why) => {
                if self.dtm_working != Some(false) {
                    info!("DTM navigation: no pose from frame {seq}: {why}");
                    self.dtm_working = Some(false);
                }
            }
            DtmStep::Waiting => {}
        }
    }

    /// A motion to the filter; returns what the filter did (the VO log's `outcome`) and its NIS.
    fn vo_motion(&mut self, seq: u64, motion: &VoMotion) -> (&'static str, Option<f64>) {
        let m = &self.metrics.vo;
        let (c, outcome, nis) = match self.filter.measure(Measurement::Vo(motion.fix)) {
            Outcome::Accepted { nis } => (&m.fused, "fused", Some(nis)),
            Outcome::Rejected { nis, .. } => (&m.filter_rejected, "filter_rejected", Some(nis)),
            _ => (&m.unused, "unused", None),
        };
        c.inc();
        if self.vo_working != Some(true) {
            info!(
                "visual odometry: measuring from frame {seq} ({} tracks, {} inliers, {:.2} px)",
                motion.tracks, motion.inliers, motion.rms_px
            );
            self.vo_working = Some(true);
        }
        (outcome, nis)
    }

    /// See [`inputs::InitSpacing`].
    fn init_spacing_ok(&mut self, m: &Measurement) -> bool {
        if self.filter.is_initialised() {
            return true; // the common case: no clock read per measurement
        }
        let gps_recent = self.inputs.gps_recent(self.link.companion_now_ns(), 2.0);
        self.init_spacing.ok(
            self.filter.is_initialised(),
            m,
            gps_recent,
            &self.nav_cfg.init,
        )
    }

    fn health(&mut self, h: NavHealth, reason: &HealthReason) -> LinkHealth {
        let prev = self.last_health.as_ref().map(|p| (p, &self.last_reason));
        let new = inputs::link_health(h, reason, prev);
        let changed = self
            .last_health
            .as_ref()
            .is_none_or(|p| std::mem::discriminant(p) != std::mem::discriminant(&new));
        self.metrics.health.set(&new);
        if changed {
            self.metrics.health_changes.inc();
            info!("navigation health {new}");
        }
        self.last_health = Some(new.clone());
        self.last_reason = reason.clone();
        new
    }

    fn publish(&mut self, o: NavOutput) {
        self.metrics.nav_outputs.inc();
        let c = self.filter.counters();
        let sum = c.initialisations + c.divergence_resets + c.covariance_resets + c.hard_resets;
        if sum != self.reset_sum {
            self.reset_sum = sum;
            self.reset_counter = self.reset_counter.wrapping_add(1);
        }
        let health = self.health(o.health, &o.reason);
        if inputs::usable_as_prior(&o) {
            self.last_out_ns = Some(self.link.companion_now_ns());
            // The new filter has its own solution: the reacquisition prior is done.
            let mut r = self
                .shared
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            if r.take().is_some() {
                info!("reacquired: the filter has its own solution again");
            }
        }
        let est = inputs::estimate_from_output(&o, health, self.reset_counter);
        self.shared
            .book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(o.clone());
        if est.is_some() {
            self.last_est = est.clone();
        }
        self.est_tx.send_replace(est);
        self.out_tx.send_replace(Some(o));
    }

    /// Republish the last estimate as lost (the injector then stops, and the link reports it).
    fn publish_lost(&mut self, reason: &HealthReason) {
        let h = self.health(NavHealth::Lost, reason);
        if let Some(mut e) = self.last_est.clone() {
            e.health = h;
            self.est_tx.send_replace(Some(e));
        }
    }

    async fn watchdog(&mut self) {
        let imu_silent = self
            .last_imu_at
            .is_some_and(|t| t.elapsed().as_secs_f64() > self.dcfg.imu_timeout_s);
        if imu_silent {
            if !self.imu_lost {
                self.imu_lost = true;
                self.metrics.imu_timeouts.inc();
                warn!(
                    "no IMU data for {} s: solution lost",
                    self.dcfg.imu_timeout_s
                );
            }
            self.publish_lost(&HealthReason::of(HealthCause::ImuSilent));
        } else if !self.filter.is_initialised() && self.last_est.is_some() {
            let (_, why) = self.filter.health();
            self.publish_lost(&why);
        }
        for (k, law) in self.filter.drag_status().into_iter().enumerate() {
            if let (Ok(m), false) = (law, self.drag_logged[k]) {
                self.drag_logged[k] = true;
                info!(
                    axis = ["x", "y"][k],
                    linear_per_s = (m.a * 1e4).round() / 1e4,
                    quadratic_per_m = (m.b * 1e5).round() / 1e5,
                    residual_m_s2 = (m.resid_m_s2 * 1e3).round() / 1e3,
                    quadratic_form = match m.form {
                        visnav_core::nav::drag::QuadForm::PerAxis => "per axis v|v|",
                        visnav_core::nav::drag::QuadForm::Vector => "vector v|v_h|",
                    },
                    forms_undecided = m.alternative.is_some(),
                    "multirotor drag law learned (fused when the GPS is gone, nav.drag)"
                );
            }
        }
        if let Some(st) = self.inputs.imu_bias_status() {
            if st.restoring != self.imu_bias_restoring {
                self.imu_bias_restoring = st.restoring;
                if st.restoring {
                    info!("autopilot IMU bias: restoring HIGHRES_IMU with SCALED_IMU");
                } else if st.bias.is_some() {
                    warn!(
                        unpaired = st.unpaired,
                        paired = st.paired,
                        "autopilot IMU bias: no consistent SCALED_IMU / HIGHRES_IMU pair for 5 s \
                         (SCALED_IMU stopped, the two come from different IMUs, or their gyro \
                         scales differ); HIGHRES_IMU is used as sent"
                    );
                }
            }
            self.metrics.imu_bias.set(st);
        }
        let now_ns = self.link.companion_now_ns();
        if self.dcfg.baro
            && !self.inputs.baro_calibrated()
            && !self.inputs.gps_recent(now_ns, 5.0)
            && let Some(o) = self.filter.output()
            && o.health == NavHealth::Ok
            && o.cov_pos_ned_m2[2][2] < 25.0
        {
            self.inputs.calibrate_baro_from_filter(o.h_m);
            info!("barometric altitude offset calibrated against the filter");
        }
        if self.gps == GpsSource::Gps2 && self.gps_hz > 0.0 && !self.inputs.gps_recent(now_ns, 5.0)
        {
            self.request_gps2().await;
        }
        if self.dcfg.log_interval_s > 0.0
            && self.last_log.elapsed().as_secs_f64() >= self.dcfg.log_interval_s
        {
            self.last_log = Instant::now();
            let m = self.metrics.snapshot();
            info!(
                imu = m.imu_samples,
                frames_in = m.frames_in,
                dropped = m.frames_superseded + m.frames_stale + m.frames_no_time + m.frames_frozen,
                fixes_accepted = m.fixes_accepted,
                fixes_rejected = m.fixes_filter_rejected
                    + m.engine_rejected.iter().map(|r| r.count).sum::<u64>(),
                latency_ms = m.fix_latency_ms_last,
                "daemon"
            );
            if let Some(b) = &m.imu_bias {
                let f = |v: Option<[f64; 3]>, d: usize| {
                    v.map_or("none".to_string(), |v| {
                        format!("{:.d$} {:.d$} {:.d$}", v[0], v[1], v[2])
                    })
                };
                info!(
                    paired = b.paired,
                    unpaired = b.unpaired,
                    bootstraps = b.bootstraps,
                    not_restored = b.not_restored,
                    restoring = b.restoring,
                    age_s = b.age_s.map_or(-1.0, |a| (a * 10.0).round() / 10.0),
                    gyro_deg_h = %f(b.gyro_bias_deg_h, 1),
                    accel_mg = %f(b.accel_bias_mg, 2),
                    "autopilot IMU bias restored"
                );
            }
        }
    }

    /// GPS2_RAW is not in the link's stream set: ask for it every 5 s while it does not arrive.
    async fn request_gps2(&mut self) {
        if self
            .gps2_asked
            .is_some_and(|t| t.elapsed() < Duration::from_secs(5))
        {
            return;
        }
        if self.link.status().borrow().autopilot.is_none() {
            return;
        }
        self.gps2_asked = Some(Instant::now());
        // 124: GPS2_RAW.
        if let Err(e) = self.link.request_message_rate(124, self.gps_hz).await {
            tracing::debug!("GPS2_RAW request: {e}");
        }
    }
}
