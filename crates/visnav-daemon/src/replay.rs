//! Offline replay of a recorded `.tlog` through the daemon's telemetry conversion ([`Inputs`])
//! and navigation filter ([`NavFilter`]), the same way the navigation task feeds them, for
//! post-flight analysis: every aiding measurement with its outcome, normalised innovation squared
//! (`NIS = dz^T S^-1 dz`, chi-square with `dof` degrees of freedom when the filter is
//! consistent) and innovation, per-type NIS statistics, the filter's resets, and its state over
//! time.
//!
//! What differs from the live daemon: vision fixes are not in a tlog (they are computed inside
//! the daemon); they come from the daemon's fix log (`[daemon] fix_log`), each given to the
//! filter when it arrived in the recorded flight (by the companion's Unix time, the tlog's
//! clock), once the filter is initialised; visual odometry motions likewise come from the VO log
//! (`[daemon] vo_log`), with the terrain model's height sigma given again (the log does not
//! carry it);
//! the autopilot boot time at each packet's arrival (used for GPS messages stamped in Unix time)
//! is the recorded arrival time minus the smallest arrival-minus-boot-time offset seen in IMU
//! and ATTITUDE messages so far (the link's TIMESYNC mapping is not recorded).
//!
//! Innovations are `measurement - filter` at the moment the measurement is applied (NED, m or
//! m/s), before the update; a delayed measurement is compared with the current state, so its
//! position innovation includes `velocity x delay`.

use std::collections::BTreeMap;

use mavlink::Message;
use mavlink::dialects::ardupilotmega::MavMessage;
use serde::Serialize;

use crate::config::{DaemonConfig, GpsSource};
use crate::fixlog::FixLogRecord;
use crate::inputs::{InitSpacing, Inputs, NavInput, vision_measurement};
use visnav_core::nav::{Measurement, NavConfig, NavFilter, Outcome, VoFix};
use visnav_core::stats::percentile;
use visnav_link::Telemetry;
use visnav_link::time::{BootClock, BootVerdict};

const R_EARTH_M: f64 = 6_378_137.0;

/// What to replay and how.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// The daemon's settings (sigmas, GPS source).
    pub daemon: DaemonConfig,
    /// The GPS message used for aiding (resolved like the daemon: see `DaemonConfig::gps_source`).
    pub gps: GpsSource,
    /// The navigation filter's settings.
    pub nav: NavConfig,
    /// The autopilot's system id; `None`: the first HEARTBEAT of an autopilot.
    pub autopilot_system_id: Option<u8>,
    /// The autopilot's component id (`[link] autopilot_component_id`, normally 1).
    pub autopilot_component_id: u8,
    /// Interval of the state rows, s.
    pub state_interval_s: f64,
}

/// One aiding measurement and what the filter did with it.
#[derive(Debug, Clone, Serialize)]
pub struct MeasRow {
    /// Filter time when applied (autopilot boot time), s.
    pub t_s: f64,
    /// Capture time minus filter time, s (negative: late).
    pub lag_s: f64,
    /// `gps_position`, `gps_velocity`, `altitude`, `attitude`.
    pub kind: &'static str,
    /// `accepted`, `rejected`, `reset`, `too_old`, `invalid`, `initialised`, `held`, `ignored`.
    pub outcome: &'static str,
    /// Normalised innovation squared (NaN when the gate was not reached).
    pub nis: f64,
    /// Measurement minus filter, NED (attitude: roll, pitch, yaw in deg), before the update.
    pub innov: [f64; 3],
    /// The measurement's sigma per axis.
    pub sigma: [f64; 3],
    /// The filter's sigma per axis (position or velocity; NaN for the others).
    pub filter_sigma: [f64; 3],
}

/// The filter's state at one time.
#[derive(Debug, Clone, Serialize)]
pub struct StateRow {
    /// Autopilot boot time, s.
    pub t_s: f64,
    /// Latitude, deg.
    pub lat_deg: f64,
    /// Longitude, deg.
    pub lon_deg: f64,
    /// Ellipsoidal height, m.
    pub h_m: f64,
    /// Velocity NED, m/s.
    pub v_ned_m_s: [f64; 3],
    /// Roll, pitch, yaw, deg.
    pub rpy_deg: [f64; 3],
    /// Accelerometer bias, micro-g.
    pub accel_bias_ug: [f64; 3],
    /// Gyro bias, deg/h.
    pub gyro_bias_deg_h: [f64; 3],
    /// Position sigma NED, m.
    pub pos_sigma_m: [f64; 3],
    /// Health: `ok`, `degraded`, `lost`.
    pub health: String,
}

/// NIS statistics of one measurement type.
#[derive(Debug, Clone, Default, Serialize)]
pub struct KindStats {
    /// Measurements seen.
    pub n: u64,
    /// Accepted.
    pub accepted: u64,
    /// Rejected by the gate (resets included).
    pub rejected: u64,
    /// Degrees of freedom of the NIS.
    pub dof: u32,
    /// Mean NIS of the gated measurements (accepted or rejected); `dof` when consistent.
    pub nis_mean: f64,
    /// Median NIS.
    pub nis_p50: f64,
    /// 95th percentile NIS.
    pub nis_p95: f64,
}

/// The replay's result.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReplayReport {
    /// Packets in the log.
    pub packets: u64,
    /// Bytes of the log that were no record (damage, junk, a truncated end), skipped to
    /// resynchronise on the next record ([`visnav_link::tlog::scan_tlog`]).
    pub skipped_bytes: u64,
    /// Places where bytes were skipped.
    pub skipped_runs: u64,
    /// Packets that did not decode (CRC, unknown message, a time stamp past the year 2262).
    pub undecodable: u64,
    /// Packets from the autopilot.
    pub from_autopilot: u64,
    /// Autopilot packets dropped as behind its clock (stale; the link's rule).
    pub stale: u64,
    /// The autopilot's system id.
    pub autopilot_system_id: Option<u8>,
    /// IMU samples given to the filter.
    pub imu_samples: u64,
    /// First and last filter time, s.
    pub t_span_s: [f64; 2],
    /// Per measurement type.
    pub kinds: BTreeMap<String, KindStats>,
    /// Divergence, covariance and hard resets: (time s, reason).
    pub resets: Vec<(f64, String)>,
    /// Autopilot reboots seen.
    pub reboots: u64,
    /// Vision fix results read from the fix log and reached in the replay.
    pub vision_results: u64,
    /// Visual odometry motions read from the VO log and reached in the replay.
    pub vo_motions: u64,
    /// Every aiding measurement.
    #[serde(skip)]
    pub meas: Vec<MeasRow>,
    /// The state every `state_interval_s`.
    #[serde(skip)]
    pub states: Vec<StateRow>,
}

fn kind_of(m: &Measurement, att_tilt: bool) -> (&'static str, u32) {
    match m {
        Measurement::Vision(_) => ("vision", 3),
        Measurement::VisionPose(_) => ("vision_pose", 6),
        Measurement::GpsPosition(_) => ("gps_position", 3),
        Measurement::GpsVelocity(_) => ("gps_velocity", 3),
        Measurement::Altitude(_) => ("altitude", 1),
        Measurement::Attitude(_) => ("attitude", if att_tilt { 3 } else { 1 }),
        Measurement::Drag(d) => ("drag", d.model.iter().flatten().count() as u32),
        Measurement::Vo(f) => ("vo", 3 + u32::from(f.rotation.is_some())),
    }
}

fn outcome_name(o: &Outcome) -> (&'static str, f64) {
    match o {
        Outcome::Accepted { nis } => ("accepted", *nis),
        Outcome::Rejected { nis, .. } => ("rejected", *nis),
        Outcome::TooOld => ("too_old", f64::NAN),
        Outcome::Invalid(_) => ("invalid", f64::NAN),
        Outcome::Initialised => ("initialised", f64::NAN),
        Outcome::Held => ("held", f64::NAN),
        Outcome::Ignored => ("ignored", f64::NAN),
        Outcome::Reset => ("reset", f64::NAN),
    }
}

fn sd(c: &[[f64; 3]; 3]) -> [f64; 3] {
    [c[0][0].sqrt(), c[1][1].sqrt(), c[2][2].sqrt()]
}

fn wrap_deg(a: f64) -> f64 {
    (a + 180.0).rem_euclid(360.0) - 180.0
}

/// Innovation, measurement sigma and filter sigma of `m` against the filter's current output.
fn innovation(filter: &NavFilter, m: &Measurement) -> ([f64; 3], [f64; 3], [f64; 3]) {
    let nan = [f64::NAN; 3];
    let Some(o) = filter.output() else {
        return (nan, nan, nan);
    };
    match m {
        Measurement::Vision(_) | Measurement::GpsPosition(_) | Measurement::VisionPose(_) => {
            // Position part only (the CSV has three innovation columns).
            let Some((f, _)) = m.position_fix() else {
                return (nan, nan, nan);
            };
            let lat0 = o.lat_deg.to_radians();
            let d = [
                (f.lat_rad - lat0) * R_EARTH_M,
                (f.lon_rad - o.lon_deg.to_radians()) * R_EARTH_M * lat0.cos(),
                -(f.h_m - o.h_m),
            ];
            let c = &f.cov_ned_m2;
            (
                d,
                [c[(0, 0)].sqrt(), c[(1, 1)].sqrt(), c[(2, 2)].sqrt()],
                sd(&o.cov_pos_ned_m2),
            )
        }
        Measurement::GpsVelocity(v) => {
            let c = &v.cov_ned_m2_s2;
            (
                [
                    v.v_ned_m_s[0] - o.v_ned_m_s[0],
                    v.v_ned_m_s[1] - o.v_ned_m_s[1],
                    v.v_ned_m_s[2] - o.v_ned_m_s[2],
                ],
                [c[(0, 0)].sqrt(), c[(1, 1)].sqrt(), c[(2, 2)].sqrt()],
                sd(&o.cov_vel_ned_m2_s2),
            )
        }
        Measurement::Altitude(a) => (
            [0.0, 0.0, -(a.h_m - o.h_m)],
            [f64::NAN, f64::NAN, a.var_m2.sqrt()],
            [f64::NAN, f64::NAN, o.cov_pos_ned_m2[2][2].sqrt()],
        ),
        Measurement::Attitude(a) => {
            let (r, p, y) = a.q_nb.euler_angles();
            (
                [
                    wrap_deg(r.to_degrees() - o.rpy_deg[0]),
                    wrap_deg(p.to_degrees() - o.rpy_deg[1]),
                    wrap_deg(y.to_degrees() - o.rpy_deg[2]),
                ],
                nan,
                o.att_sigma_deg,
            )
        }
        // Generated inside the filter from its own IMU samples (nav::drag): not replayed here.
        Measurement::Drag(_) => (nan, nan, nan),
        // As the mean velocity over the frame interval (m/s), like a GPS velocity.
        Measurement::Vo(f) => {
            let dt = f.span_s();
            let c = &f.cov_ned_m2;
            (
                [
                    f.dp_ned_m[0] / dt - o.v_ned_m_s[0],
                    f.dp_ned_m[1] / dt - o.v_ned_m_s[1],
                    f.dp_ned_m[2] / dt - o.v_ned_m_s[2],
                ],
                [
                    c[(0, 0)].sqrt() / dt,
                    c[(1, 1)].sqrt() / dt,
                    c[(2, 2)].sqrt() / dt,
                ],
                sd(&o.cov_vel_ned_m2_s2),
            )
        }
    }
}

fn apply_meas(
    filter: &mut NavFilter,
    m: Measurement,
    rep: &mut ReplayReport,
    nis: &mut BTreeMap<&'static str, Vec<f64>>,
    opts: &ReplayOptions,
) {
    let (kind, dof) = kind_of(&m, opts.nav.autopilot_attitude_tilt);
    let (innov, sigma, filter_sigma) = innovation(filter, &m);
    let t_filter = filter.t_us();
    let t_c = m.t_capture_us();
    let out = filter.measure(m);
    let (outcome, v) = outcome_name(&out);
    let st = rep.kinds.entry(kind.to_string()).or_default();
    st.n += 1;
    st.dof = dof;
    match out {
        Outcome::Accepted { .. } => st.accepted += 1,
        Outcome::Rejected { .. } | Outcome::Reset => st.rejected += 1,
        _ => {}
    }
    if v.is_finite() {
        nis.entry(kind).or_default().push(v);
    }
    rep.meas.push(MeasRow {
        t_s: t_filter.map_or(t_c as f64 * 1e-6, |t| t as f64 * 1e-6),
        lag_s: t_filter.map_or(0.0, |t| (t_c as f64 - t as f64) * 1e-6),
        kind,
        outcome,
        nis: v,
        innov,
        sigma,
        filter_sigma,
    });
}

/// Replay the records of a .tlog read with [`visnav_link::tlog::scan_tlog`] ([`replay`]), the
/// report counting what the reading skipped.
pub fn replay_tlog(
    log: &visnav_link::tlog::TlogContents,
    fixes: &[FixLogRecord],
    vo: &[(u64, VoFix)],
    opts: &ReplayOptions,
) -> ReplayReport {
    let mut rep = replay(&log.records, fixes, vo, opts);
    rep.skipped_bytes = log.skipped_bytes;
    rep.skipped_runs = log.skipped_runs;
    rep
}

/// Replay `records` (from [`visnav_link::tlog::read_tlog`]), with the vision fixes of a fix log
/// (`[daemon] fix_log`) and the visual odometry motions of a VO log (`[daemon] vo_log`, as
/// `(arrival Unix µs, motion)`: [`crate::volog::VoLogRecord::vo_fix`]) given to the filter when
/// they arrived in the recorded flight.
pub fn replay(
    records: &[(u64, Vec<u8>)],
    fixes: &[FixLogRecord],
    vo: &[(u64, VoFix)],
    opts: &ReplayOptions,
) -> ReplayReport {
    let mut r = Replayer::new(opts);
    let mut fixes = fixes.iter().peekable();
    let mut vo = vo.iter().peekable();
    for (unix_us, packet) in records {
        r.rep.packets += 1;
        // Motions that arrived before this packet, as the navigation task got them.
        while let Some((_, f)) = vo.next_if(|(arrival, _)| *arrival <= *unix_us) {
            r.rep.vo_motions += 1;
            if r.filter.is_initialised() {
                r.apply(Measurement::Vo(*f));
            }
        }
        // Vision fixes that arrived before this packet.
        while let Some(fx) = fixes.next_if(|f| f.arrival_unix_us <= *unix_us) {
            r.rep.vision_results += 1;
            let Ok(m) = vision_measurement(
                &fx.report(),
                fx.t_capture_us,
                opts.nav.vision_attitude,
                opts.nav.vision_prior_dependence,
            ) else {
                continue;
            };
            if r.filter.is_initialised() {
                r.apply(m);
            }
        }
        if let Some(tel) = r.telemetry(*unix_us, packet) {
            r.feed(&tel);
        }
    }
    r.finish()
}

/// The replay's state: the daemon's input conversion and filter, the link's clock rules, and
/// the report being written.
struct Replayer<'a> {
    opts: &'a ReplayOptions,
    rep: ReplayReport,
    inputs: Inputs,
    filter: NavFilter,
    spacing: InitSpacing,
    autopilot: Option<(u32, u8)>,
    boot_clock: BootClock,
    boot_epoch: u32,
    /// Smallest arrival-minus-boot-time offset, µs (the boot time at arrival is arrival - this).
    min_offset_us: Option<i64>,
    last_gps_arrival_ns: Option<i64>,
    next_state_t_s: f64,
    nis: BTreeMap<&'static str, Vec<f64>>,
    /// (divergence, covariance, initialisation) resets reported so far.
    resets_seen: (u64, u64, u64),
}

impl<'a> Replayer<'a> {
    fn new(opts: &'a ReplayOptions) -> Self {
        Self {
            opts,
            rep: ReplayReport {
                autopilot_system_id: opts.autopilot_system_id,
                t_span_s: [f64::NAN; 2],
                ..Default::default()
            },
            inputs: Inputs::new(opts.daemon.clone(), opts.gps),
            filter: NavFilter::new(opts.nav.clone()),
            spacing: InitSpacing::default(),
            autopilot: None,
            boot_clock: BootClock::default(),
            boot_epoch: 0,
            min_offset_us: None,
            last_gps_arrival_ns: None,
            next_state_t_s: f64::NEG_INFINITY,
            nis: BTreeMap::new(),
            resets_seen: (0, 0, 0),
        }
    }

    fn apply(&mut self, m: Measurement) {
        apply_meas(&mut self.filter, m, &mut self.rep, &mut self.nis, self.opts);
    }

    /// The packet recorded at `unix_us` as the link would have handed it on: decoded, from the
    /// autopilot it locked onto, not stale, stamped on the boot clock. `None` for any other.
    fn telemetry(&mut self, unix_us: u64, packet: &[u8]) -> Option<Telemetry> {
        let mut reader = mavlink::MavlinkReader::new(packet);
        let Ok((header, msg)) = reader.read_any_message::<MavMessage>() else {
            self.rep.undecodable += 1;
            return None;
        };
        if self.autopilot.is_none()
            && let MavMessage::HEARTBEAT(hb) = &msg
            && let Ok(sys) = u8::try_from(header.system_id)
            && visnav_link::is_lock_candidate(
                self.opts.autopilot_system_id,
                self.opts.autopilot_component_id,
                sys,
                header.component_id,
                hb,
            )
        {
            self.autopilot = Some((header.system_id, header.component_id));
            self.rep.autopilot_system_id = u8::try_from(header.system_id).ok();
        }
        if self.autopilot != Some((header.system_id, header.component_id)) {
            return None;
        }
        // The stamp as the companion clock's i64 ns: one past the year 2262 is a corrupt record
        // (the arithmetic below overflowed on it: found by fuzzing).
        let Some(t_companion_ns) = i64::try_from(unix_us)
            .ok()
            .and_then(|t| t.checked_mul(1000))
        else {
            self.rep.undecodable += 1;
            return None;
        };
        self.rep.from_autopilot += 1;
        // The link's own rule for stale messages and reboots (`visnav_link::time::BootClock`).
        if let Some(b) = visnav_link::boot_time_us(&msg) {
            match self.boot_clock.observe(msg.message_id(), b, t_companion_ns) {
                BootVerdict::Current => {}
                BootVerdict::Stale => {
                    self.rep.stale += 1;
                    return None;
                }
                BootVerdict::Reboot => self.boot_epoch += 1,
            }
        }
        let arrival_us = t_companion_ns / 1000;
        self.follow_boot_offset(&msg, arrival_us);
        Some(Telemetry {
            t_companion_ns,
            t_boot_us: self
                .min_offset_us
                .and_then(|o| arrival_us.checked_sub(o))
                .filter(|t| *t >= 0)
                .map(|t| t as u64),
            boot_epoch: self.boot_epoch,
            header,
            msg,
        })
    }

    /// The boot clock's offset from the arrival times, from the messages that carry the sensor
    /// time.
    fn follow_boot_offset(&mut self, msg: &MavMessage, arrival_us: i64) {
        let boot_us = match msg {
            MavMessage::ATTITUDE(m) => Some(i64::from(m.time_boot_ms) * 1000),
            MavMessage::SCALED_IMU(m) => Some(i64::from(m.time_boot_ms) * 1000),
            MavMessage::HIGHRES_IMU(m) => Some(m.time_usec as i64),
            MavMessage::RAW_IMU(m) => Some(m.time_usec as i64),
            _ => None,
        };
        if let Some(b) = boot_us
            && b > 0
        {
            let off = arrival_us.saturating_sub(b);
            // A reboot moves the offset up: follow it when it jumps by more than a second.
            self.min_offset_us = Some(match self.min_offset_us {
                Some(o) if off > o.saturating_add(1_000_000) => off,
                Some(o) => o.min(off),
                None => off,
            });
        }
    }

    /// One message through the daemon's input conversion into the filter.
    fn feed(&mut self, tel: &Telemetry) {
        if matches!(
            tel.msg,
            MavMessage::GPS_RAW_INT(_) | MavMessage::GPS2_RAW(_)
        ) {
            self.last_gps_arrival_ns = Some(tel.t_companion_ns);
        }
        for input in self.inputs.convert(tel) {
            match input {
                NavInput::Imu(s) => {
                    self.rep.imu_samples += 1;
                    self.filter.imu(&s);
                    self.record_state(s.t_us as f64 * 1e-6);
                }
                NavInput::Meas(m) => {
                    let gps_recent = self
                        .last_gps_arrival_ns
                        .is_some_and(|t| (tel.t_companion_ns - t) as f64 * 1e-9 < 2.0);
                    let init = self.filter.is_initialised();
                    if !self.spacing.ok(init, &m, gps_recent, &self.opts.nav.init) {
                        continue;
                    }
                    self.apply(m);
                }
                NavInput::Reboot => {
                    self.rep.reboots += 1;
                    self.filter = NavFilter::new(self.opts.nav.clone());
                    self.filter.set_multirotor(self.inputs.multirotor());
                    self.spacing = InitSpacing::default();
                }
                NavInput::Vehicle { multirotor } => self.filter.set_multirotor(multirotor),
            }
            self.note_resets();
        }
    }

    /// The span of IMU time, and a state row every `state_interval_s`.
    fn record_state(&mut self, t_s: f64) {
        if self.rep.t_span_s[0].is_nan() {
            self.rep.t_span_s[0] = t_s;
        }
        self.rep.t_span_s[1] = t_s;
        if t_s >= self.next_state_t_s
            && let Some(o) = self.filter.output()
        {
            self.next_state_t_s = t_s + self.opts.state_interval_s;
            self.rep.states.push(StateRow {
                t_s,
                lat_deg: o.lat_deg,
                lon_deg: o.lon_deg,
                h_m: o.h_m,
                v_ned_m_s: o.v_ned_m_s,
                rpy_deg: o.rpy_deg,
                accel_bias_ug: o.accel_bias_ug,
                gyro_bias_deg_h: o.gyro_bias_deg_h,
                pos_sigma_m: sd(&o.cov_pos_ned_m2),
                health: o.health.to_string(),
            });
        }
    }

    /// A reset or initialisation of the filter since the last look, with the filter's reason.
    fn note_resets(&mut self) {
        let c = self.filter.counters();
        let now = (
            c.divergence_resets,
            c.covariance_resets,
            c.hard_resets + c.initialisations,
        );
        if now == self.resets_seen {
            return;
        }
        let t = self.filter.t_us().map_or(f64::NAN, |t| t as f64 * 1e-6);
        let what = if now.0 > self.resets_seen.0 {
            "divergence reset"
        } else if now.1 > self.resets_seen.1 {
            "covariance reset"
        } else {
            "initialised"
        };
        let (_, reason) = self.filter.health();
        self.rep.resets.push((t, format!("{what}: {reason}")));
        self.resets_seen = now;
    }

    /// The report with the drag measurements and each kind's NIS statistics.
    fn finish(mut self) -> ReplayReport {
        // Drag measurements are made inside the filter from its IMU samples: counted, not gated
        // here.
        let d = self.filter.counters().drag;
        if d.accepted + d.rejected > 0 {
            self.rep.kinds.insert(
                "drag".to_string(),
                KindStats {
                    n: d.accepted + d.rejected + d.too_old + d.invalid,
                    accepted: d.accepted,
                    rejected: d.rejected,
                    dof: 2,
                    nis_mean: f64::NAN,
                    nis_p50: f64::NAN,
                    nis_p95: f64::NAN,
                },
            );
        }
        for (kind, v) in self.nis {
            if let Some(st) = self.rep.kinds.get_mut(kind) {
                st.nis_mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
                st.nis_p50 = percentile(&v, 0.5);
                st.nis_p95 = percentile(&v, 0.95);
            }
        }
        self.rep
    }
}

/// The measurement rows as CSV.
pub fn meas_csv(rep: &ReplayReport) -> String {
    let mut s = String::from(
        "t_s,lag_s,kind,outcome,nis,innov_0,innov_1,innov_2,sigma_0,sigma_1,sigma_2,\
         filter_sigma_0,filter_sigma_1,filter_sigma_2\n",
    );
    for r in &rep.meas {
        s.push_str(&format!(
            "{:.4},{:.4},{},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4}\n",
            r.t_s,
            r.lag_s,
            r.kind,
            r.outcome,
            r.nis,
            r.innov[0],
            r.innov[1],
            r.innov[2],
            r.sigma[0],
            r.sigma[1],
            r.sigma[2],
            r.filter_sigma[0],
            r.filter_sigma[1],
            r.filter_sigma[2]
        ));
    }
    s
}

/// The state rows as CSV.
pub fn states_csv(rep: &ReplayReport) -> String {
    let mut s = String::from(
        "t_s,lat_deg,lon_deg,h_m,vn,ve,vd,roll_deg,pitch_deg,yaw_deg,ba_x_ug,ba_y_ug,ba_z_ug,\
         bg_x_deg_h,bg_y_deg_h,bg_z_deg_h,sigma_n_m,sigma_e_m,sigma_d_m,health\n",
    );
    for r in &rep.states {
        s.push_str(&format!(
            "{:.4},{:.8},{:.8},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.3},{:.1},{:.1},{:.1},\
             {:.2},{:.2},{:.2},{:.3},{:.3},{:.3},{}\n",
            r.t_s,
            r.lat_deg,
            r.lon_deg,
            r.h_m,
            r.v_ned_m_s[0],
            r.v_ned_m_s[1],
            r.v_ned_m_s[2],
            r.rpy_deg[0],
            r.rpy_deg[1],
            r.rpy_deg[2],
            r.accel_bias_ug[0],
            r.accel_bias_ug[1],
            r.accel_bias_ug[2],
            r.gyro_bias_deg_h[0],
            r.gyro_bias_deg_h[1],
            r.gyro_bias_deg_h[2],
            r.pos_sigma_m[0],
            r.pos_sigma_m[1],
            r.pos_sigma_m[2],
            r.health
        ));
    }
    s
}
