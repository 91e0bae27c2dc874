//! Pure conversions between the autopilot's telemetry, the navigation filter, the vision fix and
//! the injector (no I/O, no async; unit-tested here). The telemetry arrives as the link's typed
//! readings (`Telemetry::sensor`, `visnav_link::sensors`: SI units, each with its own time), so
//! nothing here decodes MAVLink.
//!
//! * IMU: HIGHRES_IMU (SI units, `time_usec` boot time) is preferred; else SCALED_IMU
//!   (mG, mrad/s, `time_boot_ms`); else RAW_IMU (ArduPilot fills it with the same scaled mG /
//!   mrad/s values, `time_usec` boot time). A lower-priority message is used only when no
//!   higher-priority one arrived within [`IMU_SOURCE_HOLD_S`], so samples are never double
//!   counted. Each sample is the rate at `t` held over the interval since the previous sample:
//!   `dtheta = w dt`, `dv = f dt` (body FRD, `ImuSample::from_rates`). The gyro of the 16-bit
//!   messages (1 mrad/s steps, truncated by ArduPilot) is replaced by ATTITUDE's float body
//!   rates when they are at most [`ATT_RATES_MAX_AGE_US`] from the sample
//!   (`DaemonConfig::gyro_from_attitude`). With `imu_bias_restore = "scaled_imu"`, or `"auto"`
//!   once a HEARTBEAT says MAV_AUTOPILOT_PX4 (PX4's HIGHRES_IMU is the IMU minus EKF2's bias
//!   estimates), every SCALED_IMU goes to an [`ImuBiasRestorer`] and HIGHRES_IMU samples leave
//!   with the estimates added back ([`crate::imu_bias`]); before the first estimate (or
//!   without SCALED_IMU) they pass as sent.
//! * Attitude: ATTITUDE roll/pitch/yaw (ZYX, `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`) at
//!   `time_boot_ms`.
//! * GPS: GPS_RAW_INT or GPS2_RAW with a 3D fix or better: position (AMSL `alt` converted to
//!   ellipsoidal height with EGM96), sigma from `h_acc`/`v_acc` (mm) when non-zero else the
//!   configuration; horizontal velocity from `vel` (cm/s) and `cog` (cdeg) when both are known,
//!   with a zero vertical velocity of large sigma. Capture time: `time_usec` when it is a
//!   plausible boot time (within 2 s of the arrival), else the arrival time mapped through
//!   TIMESYNC (ArduPilot sends Unix time there). The GPS latency (~0.1-0.2 s) is not modelled.
//! * Barometer: SCALED_PRESSURE `press_abs` (hPa) to the ISA altitude
//!   `h = (1 - (p / 1013.25)^(1/5.25588)) / 2.25577e-5`, plus an offset calibrated against the
//!   GPS ellipsoidal height (running mean) or, without GPS, once against a healthy filter
//!   height; not used before the offset is known.
//! * Autopilot reboot: the link's confirmed reboot (`Telemetry::boot_epoch` changes; the link
//!   needs several streams on a new clock and the old one silent, `visnav_link::time::BootClock`).
//!   An IMU sample whose time is not after the previous one is dropped (a duplicate, a reordered
//!   or a stale packet): one message is never enough to restart the filter.
//! * Output: `NavOutput` to the injector's `NavEstimate` (AMSL = h - N, quaternion, covariances,
//!   health with a reason whose wording is kept while only its numbers change, so the link's
//!   health STATUSTEXT is sent on real changes only).
//! * Fix prior at a capture time and an accepted `FixReport` to `Measurement::Vision`.

use std::collections::VecDeque;

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

use crate::config::{DaemonConfig, GpsSource, ImuBiasRestore};
use crate::imu_bias::{ImuBiasRestorer, RestoreStatus};
use visnav_core::camera::Attitude;
use visnav_core::fix::{AltitudePrior, AttitudePriorNed, FixPrior, FixReport, PositionPriorGeo};
use visnav_core::geo::geoid::geoid_undulation_m;
use visnav_core::geo::local::offset_geodetic;
use visnav_core::nav::filter::HealthReason;
use visnav_core::nav::{
    AltitudeFix, AttitudeFix, Health as NavHealth, ImuSample, Measurement, NavConfig, NavOutput,
    PoseFix, PositionFix, VelocityFix, earth,
};
use visnav_link::sensors::{AttitudeReading, Autopilot, GpsReading, ImuReading, ImuSource, Sensor};
use visnav_link::{Health as LinkHealth, NavEstimate, Telemetry};

/// A lower-priority IMU message is ignored while a higher-priority one arrived this recently, s.
pub const IMU_SOURCE_HOLD_S: f64 = 0.5;
/// ATTITUDE rates replace a 16-bit IMU message's gyro when within this of its time, µs.
pub const ATT_RATES_MAX_AGE_US: u64 = 60_000;

/// What one telemetry message means for the filter.
// A pose fix (6x6 covariance) is about 400 bytes, the others under 110: measurements are few
// per second and short-lived (the late-measurement history keeps a few seconds), so they stay
// unboxed and `Copy`.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
pub enum NavInput {
    /// An IMU sample.
    Imu(ImuSample),
    /// An aiding measurement.
    Meas(Measurement),
    /// The autopilot's clock went backwards: restart the filter.
    Reboot,
    /// The autopilot's HEARTBEAT says (again, or now differently) whether the vehicle is a
    /// multirotor (`[nav.drag] mode = "auto"`).
    Vehicle {
        /// Quad/hexa/octo/tri/coaxial rotorcraft or helicopter.
        multirotor: bool,
    },
}

/// Before initialisation the filter derives the velocity from two position fixes of the same
/// kind taken `init.vision_init_min_dt_s..=vision_init_max_dt_s` apart, using the previous fix it
/// was given: fixes arriving faster would never initialise it. So until it is initialised,
/// position fixes of each kind are passed at most every 1.5 x `vision_init_min_dt_s` (capped at
/// 0.9 x `vision_init_max_dt_s`). The filter pairs a fix only with the previous fix of the same
/// kind: interleaved GPS and vision fixes would never initialise it, so while GPS arrives it
/// alone initialises the filter.
#[derive(Debug, Clone, Default)]
pub struct InitSpacing {
    last_us: [Option<u64>; 2],
}

impl InitSpacing {
    /// Whether `m` goes to the filter (`gps_recent`: a GPS fix arrived within 2 s).
    pub fn ok(
        &mut self,
        initialised: bool,
        m: &Measurement,
        gps_recent: bool,
        ic: &visnav_core::nav::config::InitConfig,
    ) -> bool {
        if initialised {
            return true;
        }
        let (i, t) = match m {
            Measurement::GpsPosition(f) => (0, f.t_capture_us),
            Measurement::Vision(f) => (1, f.t_capture_us),
            _ => return true,
        };
        if i == 1 && gps_recent {
            return false;
        }
        let spacing_us =
            ((ic.vision_init_min_dt_s * 1.5).min(ic.vision_init_max_dt_s * 0.9) * 1e6) as u64;
        match self.last_us[i] {
            Some(prev) if t >= prev && t - prev < spacing_us => false,
            _ => {
                self.last_us[i] = Some(t);
                true
            }
        }
    }
}

/// An IMU interval longer than this many usual intervals is a gap (samples not sent): its
/// increment is integrated from the rates on both sides ([`Inputs`], `gap_bridged`). 2.5: the
/// jitter of a 250 Hz stream over MAVLink (2-8 ms between samples) stays below it.
pub const IMU_GAP_FACTOR: f64 = 2.5;
/// Gain of the running mean of the usual IMU interval (about 50 samples).
const IMU_USUAL_INTERVAL_GAIN: f64 = 0.02;

/// Telemetry-to-filter conversion state.
#[derive(Debug, Clone)]
pub struct Inputs {
    cfg: DaemonConfig,
    gps: GpsSource,
    last_kind_ns: [Option<i64>; 3],
    last_imu_t_us: Option<u64>,
    /// The link's reboot count of the latest message.
    boot_epoch: Option<u32>,
    /// The last IMU sample's rates (gyro rad/s, specific force m/s^2) and the usual interval
    /// between samples (s, a running mean over intervals without a gap).
    last_imu_rates: Option<(Vector3<f64>, Vector3<f64>, f64)>,
    baro_isa_m: Option<(u64, f64)>,
    /// Barometric offset: ellipsoidal height minus ISA altitude, m, and the number of samples.
    baro_offset: Option<(f64, u32)>,
    /// Latest autopilot attitudes (for fix priors).
    attitudes: VecDeque<(u64, Attitude)>,
    /// A GPS fix was used recently (arrival, companion ns).
    last_gps_ns: Option<i64>,
    /// Latest ATTITUDE body rates (boot time µs, rad/s).
    att_rates: Option<(u64, Vector3<f64>)>,
    /// Adds the autopilot's bias estimates back to HIGHRES_IMU (`imu_bias_restore`).
    restorer: Option<ImuBiasRestorer>,
    /// Whether the autopilot's HEARTBEAT says multirotor (None before the first).
    multirotor: Option<bool>,
}

/// ISA altitude of a static pressure (inverse of the emulator's / ICAO troposphere model), m.
pub fn isa_altitude_m(p_hpa: f64) -> f64 {
    (1.0 - (p_hpa / 1013.25).powf(1.0 / 5.255_88)) / 2.255_77e-5
}

impl Inputs {
    /// New state; `gps` is the resolved source ([`DaemonConfig::gps_source`]).
    pub fn new(cfg: DaemonConfig, gps: GpsSource) -> Self {
        let restorer =
            (cfg.imu_bias_restore == ImuBiasRestore::ScaledImu).then(ImuBiasRestorer::new);
        Self {
            restorer,
            cfg,
            gps,
            last_kind_ns: [None; 3],
            last_imu_t_us: None,
            boot_epoch: None,
            last_imu_rates: None,
            baro_isa_m: None,
            baro_offset: None,
            attitudes: VecDeque::new(),
            last_gps_ns: None,
            att_rates: None,
            multirotor: None,
        }
    }

    /// Whether the autopilot's HEARTBEAT said multirotor (false before the first).
    pub fn multirotor(&self) -> bool {
        self.multirotor.unwrap_or(false)
    }

    /// Forget times (after an autopilot reboot).
    pub fn reset_times(&mut self) {
        self.last_imu_t_us = None;
        self.last_imu_rates = None;
        self.attitudes.clear();
        self.baro_isa_m = None;
        if let Some(r) = &mut self.restorer {
            r.reset();
        }
    }

    /// The bias restorer's counters and estimate (`None` when `imu_bias_restore` is off).
    pub fn imu_bias_status(&self) -> Option<RestoreStatus> {
        self.restorer.as_ref().map(ImuBiasRestorer::status)
    }

    /// The barometric offset is known.
    pub fn baro_calibrated(&self) -> bool {
        self.baro_offset.is_some()
    }

    /// A GPS fix was used within `s` seconds of `now_ns`.
    pub fn gps_recent(&self, now_ns: i64, s: f64) -> bool {
        self.last_gps_ns
            .is_some_and(|t| (now_ns - t) as f64 * 1e-9 < s)
    }

    /// Calibrate the barometric offset once from a trusted filter height (no GPS available).
    pub fn calibrate_baro_from_filter(&mut self, h_m: f64) {
        if self.baro_offset.is_none()
            && let Some((_, isa)) = self.baro_isa_m
            && h_m.is_finite()
        {
            self.baro_offset = Some((h_m - isa, 1));
        }
    }

    /// The autopilot attitude nearest `t_us` within `max_dt_us`.
    pub fn attitude_at(&self, t_us: u64, max_dt_us: u64) -> Option<Attitude> {
        self.attitudes
            .iter()
            .min_by_key(|(t, _)| t.abs_diff(t_us))
            .filter(|(t, _)| t.abs_diff(t_us) <= max_dt_us)
            .map(|(_, a)| *a)
    }

    fn imu_allowed(&mut self, kind: ImuSource, t_ns: i64) -> bool {
        self.last_kind_ns[kind as usize] = Some(t_ns);
        self.last_kind_ns[..kind as usize]
            .iter()
            .all(|t| t.is_none_or(|t| (t_ns - t) as f64 * 1e-9 > IMU_SOURCE_HOLD_S))
    }

    /// The gyro of a 16-bit IMU message, or ATTITUDE's float body rates when they are enabled
    /// and recent (see `DaemonConfig::gyro_from_attitude`).
    fn fine_gyro(&self, t_us: u64, coarse: Vector3<f64>) -> Vector3<f64> {
        match self.att_rates {
            Some((t, w))
                if self.cfg.gyro_from_attitude && t.abs_diff(t_us) <= ATT_RATES_MAX_AGE_US =>
            {
                w
            }
            _ => coarse,
        }
    }

    fn imu(&mut self, t_us: u64, gyro: Vector3<f64>, acc: Vector3<f64>, out: &mut Vec<NavInput>) {
        if !(gyro.iter().all(|v| v.is_finite()) && acc.iter().all(|v| v.is_finite())) {
            return;
        }
        match self.last_imu_t_us {
            Some(prev) if t_us > prev => {
                let dt_s = (t_us - prev) as f64 * 1e-6;
                self.last_imu_t_us = Some(t_us);
                out.push(NavInput::Imu(self.gap_bridged(t_us, gyro, acc, dt_s)));
            }
            Some(_) => {} // duplicate, out of order or stale: dropped
            None => self.last_imu_t_us = Some(t_us),
        }
    }

    /// The IMU increment over `dt_s` ending with rate sample `(gyro, acc)`. A rate sample (an
    /// average over its own short interval) held over a longer gap (samples the autopilot did
    /// not send) would put its rate on the whole gap: in PX4 flight v6 a 37 ms gap ended at
    /// 232 deg/s of pitch rate after 4 deg/s, and holding it gave 8.5 deg of pitch where the
    /// copter turned about 1.5, which the GPS-aided filter then could not recover (docs/real-sitl.md,
    /// PX4 verdict). Across a gap (more than [`IMU_GAP_FACTOR`] usual intervals) the rates are
    /// interpolated linearly between the samples on either side (trapezoid), and what that
    /// cannot know (the rates inside the gap) goes into the sample's gap sigmas, which the filter
    /// adds to its attitude and velocity covariance; otherwise the sample is held as before.
    fn gap_bridged(
        &mut self,
        t_us: u64,
        gyro: Vector3<f64>,
        acc: Vector3<f64>,
        dt_s: f64,
    ) -> ImuSample {
        let sample = match self.last_imu_rates {
            Some((g0, a0, usual_s)) if dt_s > IMU_GAP_FACTOR * usual_s => {
                // The rates inside the gap are unknown: the trapezoid's error is up to half the
                // change across it over the gap (a uniform error's sigma is that over sqrt 3).
                let spread = 0.5 * dt_s / 3f64.sqrt();
                ImuSample {
                    gap_sigma_dtheta_rad: (gyro - g0).amax() * spread,
                    gap_sigma_dv_m_s: (acc - a0).amax() * spread,
                    ..ImuSample::from_rates(t_us, (g0 + gyro) * 0.5, (a0 + acc) * 0.5, dt_s)
                }
            }
            _ => ImuSample::from_rates(t_us, gyro, acc, dt_s),
        };
        let usual_s = match self.last_imu_rates {
            None => dt_s,
            Some((_, _, u)) if dt_s > IMU_GAP_FACTOR * u => u,
            Some((_, _, u)) => u + IMU_USUAL_INTERVAL_GAIN * (dt_s - u),
        };
        self.last_imu_rates = Some((gyro, acc, usual_s));
        sample
    }

    /// Convert one telemetry message (may produce nothing).
    pub fn convert(&mut self, tel: &Telemetry) -> Vec<NavInput> {
        let mut out = Vec::new();
        if self.boot_epoch.is_some_and(|e| e != tel.boot_epoch) {
            self.reset_times();
            out.push(NavInput::Reboot);
        }
        self.boot_epoch = Some(tel.boot_epoch);
        let t_ns = tel.t_companion_ns;
        match tel.sensor() {
            Some(Sensor::Heartbeat {
                autopilot,
                multirotor,
            }) if autopilot != Autopilot::Invalid => {
                self.heartbeat(autopilot, multirotor, &mut out)
            }
            Some(Sensor::Imu(r)) => self.imu_reading(&r, t_ns, &mut out),
            Some(Sensor::Attitude(a)) => self.attitude(&a, &mut out),
            Some(Sensor::Gps(g)) if g.receiver == self.gps_receiver() => {
                self.gps_fix(&g, tel, &mut out);
            }
            Some(Sensor::Baro {
                t_boot_us,
                press_abs_hpa,
            }) if self.cfg.baro => self.baro(t_boot_us, press_abs_hpa, &mut out),
            _ => {}
        }
        out
    }

    /// The receiver `[daemon] gps` reads (0: none).
    fn gps_receiver(&self) -> u8 {
        match self.gps {
            GpsSource::Gps1 => 1,
            GpsSource::Gps2 => 2,
            _ => 0,
        }
    }

    /// A flight controller's HEARTBEAT: the vehicle type (for the drag model) and, on PX4, the
    /// IMU bias restoration `imu_bias_restore = "auto"` asks for.
    fn heartbeat(&mut self, autopilot: Autopilot, multirotor: bool, out: &mut Vec<NavInput>) {
        if self.multirotor != Some(multirotor) {
            self.multirotor = Some(multirotor);
            out.push(NavInput::Vehicle { multirotor });
        }
        if self.cfg.imu_bias_restore == ImuBiasRestore::Auto
            && self.restorer.is_none()
            && autopilot == Autopilot::Px4
        {
            tracing::info!(
                "PX4: its HIGHRES_IMU is the IMU minus EKF2's bias estimates; restoring the \
                 raw IMU with SCALED_IMU (daemon.imu_bias_restore = \"auto\")"
            );
            self.restorer = Some(ImuBiasRestorer::new());
        }
    }

    /// An IMU reading: the preferred source only, the bias restored on PX4, the 16-bit
    /// messages' gyro refined by ATTITUDE's rates.
    fn imu_reading(&mut self, r: &ImuReading, t_ns: i64, out: &mut Vec<NavInput>) {
        let (t_us, gyro, acc) = (
            r.t_boot_us,
            Vector3::from(r.gyro_rad_s),
            Vector3::from(r.accel_m_s2),
        );
        match r.source {
            ImuSource::Highres if self.imu_allowed(ImuSource::Highres, t_ns) => {
                let (mut g, mut a) = (gyro, acc);
                if let Some(rs) = &mut self.restorer {
                    let (rg, ra, _) = rs.on_highres(t_us, g.into(), a.into());
                    g = rg.into();
                    a = ra.into();
                }
                self.imu(t_us, g, a, out);
            }
            ImuSource::Scaled => {
                if let (Some(rs), Some((g16, a16))) = (&mut self.restorer, r.counts) {
                    rs.on_scaled(t_us, g16, a16);
                }
                if self.imu_allowed(ImuSource::Scaled, t_ns) {
                    let g = self.fine_gyro(t_us, gyro);
                    self.imu(t_us, g, acc, out);
                }
            }
            ImuSource::Raw if self.imu_allowed(ImuSource::Raw, t_ns) => {
                let g = self.fine_gyro(t_us, gyro);
                self.imu(t_us, g, acc, out);
            }
            _ => {}
        }
    }

    /// ATTITUDE: its body rates (for the 16-bit IMU messages), the attitude for fix priors and
    /// as the filter's attitude measurement.
    fn attitude(&mut self, m: &AttitudeReading, out: &mut Vec<NavInput>) {
        let w = Vector3::from(m.rates_rad_s);
        if w.iter().all(|v| v.is_finite()) {
            self.att_rates = Some((m.t_boot_us, w));
        }
        let (r, p, y) = (m.roll_rad, m.pitch_rad, m.yaw_rad);
        if r.is_finite() && p.is_finite() && y.is_finite() {
            let t_us = m.t_boot_us;
            self.attitudes.push_back((t_us, Attitude::new(r, p, y)));
            while self.attitudes.len() > 200 {
                self.attitudes.pop_front();
            }
            out.push(NavInput::Meas(Measurement::Attitude(AttitudeFix {
                t_capture_us: t_us,
                q_nb: UnitQuaternion::from_euler_angles(r, p, y),
            })));
        }
    }

    /// SCALED_PRESSURE: the ISA altitude, and with the offset known an altitude measurement.
    fn baro(&mut self, t_us: u64, p_hpa: f64, out: &mut Vec<NavInput>) {
        if p_hpa.is_finite() && (10.0..=1200.0).contains(&p_hpa) {
            let isa = isa_altitude_m(p_hpa);
            self.baro_isa_m = Some((t_us, isa));
            if let Some((off, _)) = self.baro_offset {
                out.push(NavInput::Meas(Measurement::Altitude(AltitudeFix {
                    t_capture_us: t_us,
                    h_m: isa + off,
                    var_m2: self.cfg.baro_sigma_m.powi(2),
                })));
            }
        }
    }

    fn gps_fix(&mut self, g: &GpsReading, tel: &Telemetry, out: &mut Vec<NavInput>) {
        if !g.fix_3d {
            return;
        }
        // Capture time: a plausible boot time in the message, else the mapped arrival time.
        let t_stamp_us = match tel.t_boot_us {
            Some(arr) if g.time_usec.abs_diff(arr) < 2_000_000 => g.time_usec,
            Some(arr) => arr,
            None => return,
        };
        // The receiver's latency (`gps_delay_s`): the fix describes an earlier time.
        let t_us = t_stamp_us.saturating_sub((self.cfg.gps_delay_s * 1e6) as u64);
        let (lat, lon) = (g.lat_deg, g.lon_deg);
        let Ok(n) = geoid_undulation_m(lat, lon) else {
            return;
        };
        if !(-90.0..=90.0).contains(&lat) || !(-180.0..=180.0).contains(&lon) {
            return;
        }
        let h = g.alt_amsl_m + n;
        // The receiver's accuracy, floored (the message is time-stamped on arrival: config doc).
        let sh = g
            .h_acc_m
            .unwrap_or(self.cfg.gps_sigma_h_m)
            .max(self.cfg.gps_min_sigma_h_m);
        let sv = g
            .v_acc_m
            .unwrap_or(self.cfg.gps_sigma_v_m)
            .max(self.cfg.gps_min_sigma_v_m);
        out.push(NavInput::Meas(Measurement::GpsPosition(PositionFix {
            t_capture_us: t_us,
            lat_rad: lat.to_radians(),
            lon_rad: lon.to_radians(),
            h_m: h,
            cov_ned_m2: Matrix3::from_diagonal(&Vector3::new(sh * sh, sh * sh, sv * sv)),
            att_dependence_ned: None,
        })));
        if let (Some(v), Some(course_deg)) = (g.ground_speed_m_s, g.course_deg) {
            let c = course_deg.to_radians();
            let s = g
                .vel_acc_m_s
                .unwrap_or(self.cfg.gps_vel_sigma_m_s)
                .max(self.cfg.gps_min_sigma_vel_m_s);
            let sz = self.cfg.gps_vz_sigma_m_s;
            out.push(NavInput::Meas(Measurement::GpsVelocity(VelocityFix {
                t_capture_us: t_us,
                v_ned_m_s: Vector3::new(v * c.cos(), v * c.sin(), 0.0),
                cov_ned_m2_s2: Matrix3::from_diagonal(&Vector3::new(s * s, s * s, sz * sz)),
            })));
        }
        self.last_gps_ns = Some(tel.t_companion_ns);
        // Barometric offset: running mean of GPS height minus ISA altitude (baro within 0.5 s).
        if let Some((tb, isa)) = self.baro_isa_m
            && tb.abs_diff(t_stamp_us) < 500_000
        {
            let d = h - isa;
            self.baro_offset = Some(match self.baro_offset {
                None => (d, 1),
                Some((m, k)) => {
                    let k = (k + 1).min(100);
                    (m + (d - m) / f64::from(k), k)
                }
            });
        }
    }
}

/// Map the filter's health to the injector's. `prev` is the health sent last with the reason it
/// was built from: while the causes are of the same kinds (only their numbers changed) its words
/// are kept, so the link's health STATUSTEXT is sent on a real change only.
pub fn link_health(
    h: NavHealth,
    reason: &HealthReason,
    prev: Option<(&LinkHealth, &HealthReason)>,
) -> LinkHealth {
    let words = |p: &str, was: &HealthReason| {
        if reason.same_kind(was) {
            p.to_string()
        } else {
            reason.to_string()
        }
    };
    match (h, prev) {
        (NavHealth::Ok, _) => LinkHealth::Ok,
        (NavHealth::Degraded, Some((LinkHealth::Degraded { reason: p }, was))) => {
            LinkHealth::Degraded {
                reason: words(p, was),
            }
        }
        (NavHealth::Degraded, _) => LinkHealth::Degraded {
            reason: reason.to_string(),
        },
        (NavHealth::Lost, Some((LinkHealth::Lost { reason: p }, was))) => LinkHealth::Lost {
            reason: words(p, was),
        },
        (NavHealth::Lost, _) => LinkHealth::Lost {
            reason: reason.to_string(),
        },
    }
}

fn mat3(m: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|r, c| m[r][c])
}

/// Largest eigenvalue of the north-east block of a covariance.
fn lambda_max_ne(p: &Matrix3<f64>) -> f64 {
    let (a, b, d) = (p[(0, 0)], 0.5 * (p[(0, 1)] + p[(1, 0)]), p[(1, 1)]);
    let m = 0.5 * (a + d);
    (m + (0.25 * (a - d) * (a - d) + b * b).sqrt()).max(0.0)
}

/// The injector's estimate from a filter output (None when the geoid cannot be evaluated).
pub fn estimate_from_output(
    o: &NavOutput,
    health: LinkHealth,
    reset_counter: u8,
) -> Option<NavEstimate> {
    let n = geoid_undulation_m(o.lat_deg, o.lon_deg).ok()?;
    let [w, x, y, z] = o.q_nb_wxyz;
    Some(NavEstimate {
        t_boot_us: o.t_us,
        lat_deg: o.lat_deg,
        lon_deg: o.lon_deg,
        alt_amsl_m: o.h_m - n,
        geoid_undulation_m: Some(n),
        vel_ned_m_s: Vector3::from(o.v_ned_m_s),
        q_ned_body: UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        pos_cov_ned_m2: mat3(&o.cov_pos_ned_m2),
        vel_cov_ned_m2_s2: mat3(&o.cov_vel_ned_m2_s2),
        att_sigma_rad: Vector3::from(o.att_sigma_deg).map(f64::to_radians),
        health,
        reset_counter,
    })
}

/// The filter's recent outputs, for priors at a frame's capture time.
#[derive(Debug, Default)]
pub struct OutputBook {
    outs: VecDeque<NavOutput>,
}

impl OutputBook {
    /// Keep `o` (and the last 3 s before it).
    pub fn push(&mut self, o: NavOutput) {
        let t = o.t_us;
        self.outs.push_back(o);
        while self
            .outs
            .front()
            .is_some_and(|f| f.t_us + 3_000_000 < t || f.t_us > t)
        {
            self.outs.pop_front();
        }
    }

    /// Forget everything (filter restarted).
    pub fn clear(&mut self) {
        self.outs.clear();
    }

    /// The newest output.
    pub fn last(&self) -> Option<&NavOutput> {
        self.outs.back()
    }

    /// The output nearest `t_us` within 1 s.
    pub fn nearest(&self, t_us: u64) -> Option<&NavOutput> {
        self.outs
            .iter()
            .min_by_key(|o| o.t_us.abs_diff(t_us))
            .filter(|o| o.t_us.abs_diff(t_us) <= 1_000_000)
    }

    /// The filter's solution at `t_us` (visual odometry's pose of a frame): interpolated between
    /// the two outputs around it when they are at most [`MAX_OUTPUT_GAP_US`] apart (position and
    /// velocity linearly, attitude along the great arc), or moved on from the newest output by its
    /// velocity and body rate when `t_us` is at most [`MAX_OUTPUT_GAP_US`] after it. The
    /// covariance and health are the earlier output's. `None` otherwise.
    pub fn at(&self, t_us: u64) -> Option<NavOutput> {
        let after = self.outs.iter().position(|o| o.t_us >= t_us);
        match after {
            Some(0) => {
                let o = self.outs.front()?;
                (o.t_us == t_us).then(|| o.clone())
            }
            Some(i) => {
                let (a, b) = (&self.outs[i - 1], &self.outs[i]);
                if b.t_us - a.t_us > MAX_OUTPUT_GAP_US {
                    return None;
                }
                let f = (t_us - a.t_us) as f64 / (b.t_us - a.t_us) as f64;
                Some(interpolate(a, b, f, t_us))
            }
            None => {
                let o = self.outs.back()?;
                (t_us - o.t_us <= MAX_OUTPUT_GAP_US).then(|| extrapolate(o, t_us))
            }
        }
    }

    /// The body's rotation over the ground from `t0_us` to `t1_us` by the outputs' body rates less
    /// the local level frame's own turn (`rate_over_ground`; `R_b0_b1`: vectors of the body at
    /// `t1` into the body at `t0`), trapezoidal between outputs, the newest rate
    /// held beyond the newest output, and what sampling the rates leaves unknown, rad: the rate
    /// between two outputs may have taken any path between their values (a multirotor's attitude
    /// loop moves it by tens of deg/s within one output period), so each interval adds
    /// `|w_b - w_a| dt / 2` (the trapezoid's largest error for a monotonic path), summed.
    /// `None` unless outputs cover the span without a gap over [`MAX_OUTPUT_GAP_US`] (the first
    /// at most that long before or at `t0`).
    pub fn body_rotation(&self, t0_us: u64, t1_us: u64) -> Option<(nalgebra::Rotation3<f64>, f64)> {
        if t1_us <= t0_us {
            return None;
        }
        let start = self.outs.iter().rposition(|o| o.t_us <= t0_us)?;
        let rate = rate_over_ground;
        let mut r = nalgebra::Rotation3::identity();
        let mut unknown_rad = 0.0;
        let (mut t, mut w) = (t0_us, rate(&self.outs[start]));
        if t0_us - self.outs[start].t_us > MAX_OUTPUT_GAP_US {
            return None;
        }
        for o in self.outs.iter().skip(start + 1) {
            if o.t_us - t > MAX_OUTPUT_GAP_US {
                return None;
            }
            let end = o.t_us.min(t1_us);
            let dt = (end - t) as f64 * 1e-6;
            let w_end = rate(o);
            r *= nalgebra::Rotation3::from_scaled_axis((w + w_end) * 0.5 * dt);
            unknown_rad += (w_end - w).norm() * dt * 0.5;
            (t, w) = (end, w_end);
            if o.t_us >= t1_us {
                return Some((r, unknown_rad));
            }
        }
        if t1_us - t > MAX_OUTPUT_GAP_US {
            return None;
        }
        r *= nalgebra::Rotation3::from_scaled_axis(w * ((t1_us - t) as f64 * 1e-6));
        Some((r, unknown_rad))
    }
}

/// An output's body rate against the local level frame (NED at the aircraft; a camera sees the
/// body's turn against the ground, which the odometer's map grid holds still, the grid's north
/// turning against NED by the convergence): the gyros' bias-compensated rate, which is against
/// inertial space, less the earth's rotation and the transport rate in body axes,
/// `w_nb = w_ib - C_n^b (w_ie + w_en)` (as the filter's attitude propagation). Without it the
/// odometer's rotation between frames is wrong by the earth's rate: at 47 deg latitude 11 deg/h
/// about the vertical (which the VO rotation measurement would take for a gyro bias) and 10 deg/h
/// about north (0.07 m/s of sideways displacement at 1500 m above ground).
fn rate_over_ground(o: &NavOutput) -> Vector3<f64> {
    let [w, x, y, z] = o.q_nb_wxyz;
    let q_nb = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
    let lat = o.lat_deg.to_radians();
    let v = Vector3::from(o.v_ned_m_s);
    let w_in = earth::earth_rate_ned(lat) + earth::transport_rate_ned(lat, o.h_m, &v);
    Vector3::from(o.w_body_rad_s) - q_nb.inverse() * w_in
}

/// Longest gap between filter outputs (or after the newest) that [`OutputBook::at`] and
/// [`OutputBook::body_rotation`] bridge: five periods of the default 50 Hz output.
pub const MAX_OUTPUT_GAP_US: u64 = 100_000;

/// `a` and `b` mixed at `f` (0: `a`, 1: `b`), stamped `t_us`.
fn interpolate(a: &NavOutput, b: &NavOutput, f: f64, t_us: u64) -> NavOutput {
    let lerp = |x: f64, y: f64| x + (y - x) * f;
    let q = |o: &NavOutput| {
        let [w, x, y, z] = o.q_nb_wxyz;
        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
    };
    let qi = q(a).slerp(&q(b), f);
    let (r, p, y) = qi.euler_angles();
    NavOutput {
        t_us,
        lat_deg: lerp(a.lat_deg, b.lat_deg),
        lon_deg: lerp(a.lon_deg, b.lon_deg),
        h_m: lerp(a.h_m, b.h_m),
        v_ned_m_s: std::array::from_fn(|i| lerp(a.v_ned_m_s[i], b.v_ned_m_s[i])),
        q_nb_wxyz: [qi.w, qi.i, qi.j, qi.k],
        rpy_deg: [r.to_degrees(), p.to_degrees(), y.to_degrees()],
        w_body_rad_s: std::array::from_fn(|i| lerp(a.w_body_rad_s[i], b.w_body_rad_s[i])),
        ..a.clone()
    }
}

/// `o` moved on to `t_us` by its velocity and body rate over the ground ([`rate_over_ground`]).
fn extrapolate(o: &NavOutput, t_us: u64) -> NavOutput {
    let dt = (t_us as f64 - o.t_us as f64) * 1e-6;
    let (lat, lon, h) = offset_geodetic(
        o.lat_deg,
        o.lon_deg,
        o.h_m,
        &(Vector3::from(o.v_ned_m_s) * dt),
    );
    let [w, x, y, z] = o.q_nb_wxyz;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
        * UnitQuaternion::from_scaled_axis(rate_over_ground(o) * dt);
    let (r, p, yaw) = q.euler_angles();
    NavOutput {
        t_us,
        lat_deg: lat,
        lon_deg: lon,
        h_m: h,
        q_nb_wxyz: [q.w, q.i, q.j, q.k],
        rpy_deg: [r.to_degrees(), p.to_degrees(), yaw.to_degrees()],
        ..o.clone()
    }
}

/// A lost solution (its sigma over `[nav.health] lost_pos_sigma_m`, or no fix for
/// `lost_no_fix_s`: the filter's only two reasons) still has an honest covariance: up to this
/// horizontal sigma its position is the fixes' prior (the engine gates at 3 sigma: 900 m), so
/// the fixes find the aircraft again by the gated search rather than by a relocalisation
/// without a prior (after an IMU burst or a bridged link silence on vision alone); beyond it,
/// the gated window is most of a map and relocalisation's ambiguity checks are the better tool.
pub const LOST_PRIOR_MAX_SIGMA_H_M: f64 = 300.0;

/// Whether an output's position can be a fix prior: not lost, or lost with a horizontal sigma
/// up to [`LOST_PRIOR_MAX_SIGMA_H_M`].
pub fn usable_as_prior(o: &NavOutput) -> bool {
    o.health != NavHealth::Lost
        || lambda_max_ne(&mat3(&o.cov_pos_ned_m2)).sqrt() <= LOST_PRIOR_MAX_SIGMA_H_M
}

/// Longest a solution from before a restart serves as the fix prior, s: its sigma has grown
/// past what a prior can help with by then (3 m/s^2 unseen: 0.6 x 3 x 60^2 = 6 km).
pub const REACQUIRE_MAX_AGE_S: f64 = 60.0;

/// The fix prior at `t_us` from the last solution before a restart (an autopilot reboot), `o`
/// re-stamped on the new boot clock: its position moved by its velocity, the sigma grown by
/// the velocity's and by the vehicle's unseen manoeuvres since (`[nav]
/// imu_bridge_accel_sigma_m_s2`, as a bridged IMU gap: `sigma_a t^2 / sqrt 3`); the attitude
/// from the autopilot (the old solution's is as old as its position). Without position
/// beyond [`REACQUIRE_MAX_AGE_S`].
pub fn reacquisition_prior(
    t_us: u64,
    o: &NavOutput,
    ap_attitude: Option<Attitude>,
    nav: &NavConfig,
) -> FixPrior {
    let dt = (t_us as f64 - o.t_us as f64) * 1e-6;
    let mut prior = prior_at(t_us, None, ap_attitude, nav);
    if !(0.0..=REACQUIRE_MAX_AGE_S).contains(&dt) {
        return prior;
    }
    let moved = prior_at(t_us, Some(o), None, nav);
    let unseen = nav.imu_bridge_accel_sigma_m_s2 * dt * dt / 3f64.sqrt();
    prior.position = moved.position.map(|mut p| {
        p.sigma_h_m = p.sigma_h_m.hypot(unseen);
        p.sigma_v_m = p.sigma_v_m.hypot(unseen);
        p
    });
    prior
}

/// The fix prior at `t_us`: position from the filter output nearest the capture time, moved by
/// its velocity to `t_us` (None when there is none within 1 s or the solution is lost: global
/// relocalisation); attitude from that output (sigma: the largest attitude sigma) or else the
/// autopilot ATTITUDE within 0.2 s (sigma: the larger of the `[nav]` attitude sigmas). A lost
/// solution gives its position up to [`LOST_PRIOR_MAX_SIGMA_H_M`], beyond only its altitude
/// ([`FixPrior::altitude`]).
pub fn prior_at(
    t_us: u64,
    out: Option<&NavOutput>,
    ap_attitude: Option<Attitude>,
    nav: &NavConfig,
) -> FixPrior {
    let mut prior = FixPrior {
        t_capture_us: t_us,
        position: None,
        attitude: None,
        altitude: None,
        attitude_from_filter: false,
        widen_heading: false,
    };
    if let Some(o) = out.filter(|o| usable_as_prior(o)) {
        let dt = (t_us as f64 - o.t_us as f64) * 1e-6;
        let v = Vector3::from(o.v_ned_m_s);
        let (lat, lon, h) = offset_geodetic(o.lat_deg, o.lon_deg, o.h_m, &(v * dt));
        let p = mat3(&o.cov_pos_ned_m2) + mat3(&o.cov_vel_ned_m2_s2) * (dt * dt);
        if let Ok(n) = geoid_undulation_m(lat, lon) {
            prior.position = Some(PositionPriorGeo {
                lat_deg: lat,
                lon_deg: lon,
                alt_amsl_m: h - n,
                sigma_h_m: lambda_max_ne(&p).sqrt(),
                sigma_v_m: p[(2, 2)].max(0.0).sqrt(),
            })
            .filter(|q| q.lat_deg.is_finite() && q.lon_deg.is_finite() && q.alt_amsl_m.is_finite());
        }
        let [r, pi, y] = o.rpy_deg;
        // att_sigma_deg is per NED axis: north and east are the tilt, down the heading.
        let [sn, se, sd] = o.att_sigma_deg;
        let tilt = sn.max(se);
        if r.is_finite() && pi.is_finite() && y.is_finite() && tilt.is_finite() && sd.is_finite() {
            prior.attitude = Some(AttitudePriorNed {
                attitude: Attitude::from_deg(r, pi, y),
                sigma_rad: tilt.to_radians(),
                sigma_yaw_rad: sd.to_radians(),
            });
            prior.attitude_from_filter = true;
        }
    }
    // Lost horizontally, the filter still knows its altitude (barometer-aided): the
    // relocalisation's scale.
    if let Some(o) = out.filter(|o| o.health == NavHealth::Lost)
        && prior.position.is_none()
        && let Ok(n) = geoid_undulation_m(o.lat_deg, o.lon_deg)
    {
        let dt = (t_us as f64 - o.t_us as f64) * 1e-6;
        let alt_amsl_m = o.h_m - n - o.v_ned_m_s[2] * dt;
        let var = o.cov_pos_ned_m2[2][2] + o.cov_vel_ned_m2_s2[2][2] * dt * dt;
        if alt_amsl_m.is_finite() && var.is_finite() && var > 0.0 {
            prior.altitude = Some(AltitudePrior {
                alt_amsl_m,
                sigma_m: var.sqrt(),
            });
        }
    }
    if prior.attitude.is_none()
        && let Some(a) = ap_attitude
    {
        prior.attitude = Some(AttitudePriorNed {
            attitude: a,
            sigma_rad: nav.attitude_sigma_tilt_deg.to_radians(),
            sigma_yaw_rad: nav.attitude_sigma_yaw_deg.to_radians(),
        });
    }
    prior
}

/// Why an engine report gives the filter no measurement.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NoMeasurement {
    /// The engine rejected the frame; its reason.
    #[error("{0}")]
    Rejected(visnav_core::fix::Rejection),
    /// An accepted report whose position is not finite (never fused).
    #[error("accepted report with a non-finite position")]
    NonFinite,
    /// The measurement built from an accepted report fails its own check.
    #[error("accepted report unusable: {0}")]
    Unusable(&'static str),
    /// The geoid could not give the ellipsoidal height of the fix.
    #[error("{0}")]
    Geoid(visnav_core::geo::GeoError),
}

impl NoMeasurement {
    /// The class for counting (a metric label without numbers): the engine's rejection's
    /// ([`visnav_core::fix::Rejection::class`]) or the daemon's own reason.
    pub fn class(&self) -> &'static str {
        match self {
            NoMeasurement::Rejected(r) => r.class(),
            NoMeasurement::NonFinite => "non_finite",
            NoMeasurement::Unusable(_) => "unusable_report",
            NoMeasurement::Geoid(_) => "geodesy",
        }
    }
}

/// The measurement of an accepted engine report (or why it gives none): the position fix, or
/// with `with_attitude` (`[nav] vision_attitude`) and an image-only pose in the report, that pose
/// with its 6x6 covariance (`Measurement::VisionPose`).
pub fn vision_measurement(
    r: &FixReport,
    t_capture_us: u64,
    with_attitude: bool,
    with_dependence: bool,
) -> Result<Measurement, NoMeasurement> {
    if !r.accepted {
        return Err(NoMeasurement::Rejected(
            visnav_core::fix::Rejection::or_unexplained(r.rejection.clone()),
        ));
    }
    if !(r.lat_deg.is_finite() && r.lon_deg.is_finite()) {
        return Err(NoMeasurement::NonFinite);
    }
    let h = if r.h_ellip_m.is_finite() {
        r.h_ellip_m
    } else {
        let n = geoid_undulation_m(r.lat_deg, r.lon_deg).map_err(NoMeasurement::Geoid)?;
        r.alt_amsl_m + n
    };
    let m = match r.vision_only.filter(|v| with_attitude && v.is_finite()) {
        Some(v) => {
            let c6 = v.cov6();
            let c6 = (c6 + c6.transpose()) * 0.5;
            Measurement::VisionPose(PoseFix {
                position: PositionFix {
                    t_capture_us,
                    lat_rad: v.lat_deg.to_radians(),
                    lon_rad: v.lon_deg.to_radians(),
                    h_m: v.h_ellip_m,
                    cov_ned_m2: c6.fixed_view::<3, 3>(0, 0).into_owned(),
                    att_dependence_ned: None,
                },
                q_nb: UnitQuaternion::from_euler_angles(
                    v.roll_deg.to_radians(),
                    v.pitch_deg.to_radians(),
                    v.yaw_deg.to_radians(),
                ),
                cov6: c6,
            })
        }
        None => {
            // Solved with the filter's own attitude as its prior: the position depends on the
            // filter's attitude error; fuse it with that dependence and the image's covariance.
            let dep = r
                .prior_dependence
                .filter(|d| with_dependence && r.prior_attitude_from_filter && d.is_finite());
            let c = match dep {
                Some(d) => Matrix3::from_fn(|i, j| d.image_cov_ned_m2[i][j]),
                None => r.cov_ned(),
            };
            Measurement::Vision(PositionFix {
                t_capture_us,
                lat_rad: r.lat_deg.to_radians(),
                lon_rad: r.lon_deg.to_radians(),
                h_m: h,
                cov_ned_m2: (c + c.transpose()) * 0.5,
                att_dependence_ned: dep.map(|d| Matrix3::from_fn(|i, j| d.d_pos_d_att[i][j])),
            })
        }
    };
    m.check().map_err(NoMeasurement::Unusable)?;
    Ok(m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::MavHeader;
    use mavlink::dialects::ardupilotmega::{
        ATTITUDE_DATA, GPS_RAW_INT_DATA, GpsFixType, HIGHRES_IMU_DATA, MavMessage, SCALED_IMU_DATA,
        SCALED_PRESSURE_DATA,
    };

    use visnav_core::nav::filter::HealthCause;
    use visnav_link::sensors::G0_M_S2;

    fn tel(t_ms: i64, msg: MavMessage) -> Telemetry {
        Telemetry {
            t_companion_ns: t_ms * 1_000_000,
            t_boot_us: Some(t_ms as u64 * 1000),
            boot_epoch: 0,
            header: MavHeader::default(),
            msg,
        }
    }

    fn scaled(t_ms: u32) -> MavMessage {
        MavMessage::SCALED_IMU(SCALED_IMU_DATA {
            time_boot_ms: t_ms,
            xacc: 0,
            yacc: 0,
            zacc: -1000,
            xgyro: 10,
            ..SCALED_IMU_DATA::DEFAULT
        })
    }

    #[test]
    fn imu_units_priority_and_reboot() {
        let mut s = Inputs::new(DaemonConfig::default(), GpsSource::Gps1);
        assert!(s.convert(&tel(1000, scaled(1000))).is_empty()); // first: time only
        let out = s.convert(&tel(1010, scaled(1010)));
        let NavInput::Imu(i) = &out[0] else {
            panic!("{out:?}")
        };
        assert_eq!(i.t_us, 1_010_000);
        assert!((i.dv_m_s_body_frd.z + G0_M_S2 * 0.01).abs() < 1e-12);
        assert!((i.dtheta_rad_body_frd.x - 0.01 * 0.01).abs() < 1e-15);
        // HIGHRES_IMU takes over; SCALED_IMU is ignored while it is current.
        let hr = |t_us: u64| {
            MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                time_usec: t_us,
                zacc: -9.8,
                ..HIGHRES_IMU_DATA::DEFAULT
            })
        };
        let out = s.convert(&tel(1020, hr(1_020_000)));
        assert!(matches!(&out[0], NavInput::Imu(i) if (i.dv_m_s_body_frd.z + 0.098).abs() < 1e-6));
        assert!(s.convert(&tel(1025, scaled(1025))).is_empty());
        // A sample from the past (stale, replayed, or an unconfirmed reboot) is dropped...
        assert!(s.convert(&tel(1030, hr(5_000))).is_empty());
        // ... and a reboot is the link's: its epoch changes.
        let mut after = tel(1035, hr(6_000));
        after.boot_epoch = 1;
        assert_eq!(s.convert(&after), vec![NavInput::Reboot]);
        // Non-finite samples are dropped.
        let bad = MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
            time_usec: 20_000,
            zacc: f32::NAN,
            ..HIGHRES_IMU_DATA::DEFAULT
        });
        let mut bad = tel(1040, bad);
        bad.boot_epoch = 1;
        assert!(s.convert(&bad).is_empty());
    }

    /// PX4 flight v6 (docs/status.md): a 250 Hz HIGHRES_IMU stream that skips 37 ms
    /// while the pitch rate climbs from 4 to 232 deg/s. Held, the last sample would turn the
    /// filter 8.5 deg; bridged, the increment is the trapezoid and the unknown part is a sigma.
    #[test]
    fn an_imu_gap_is_bridged_by_the_trapezoid_with_its_uncertainty() {
        let mut s = Inputs::new(DaemonConfig::default(), GpsSource::Gps1);
        let hr = |t_us: u64, q_deg_s: f32| {
            MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
                time_usec: t_us,
                ygyro: q_deg_s.to_radians(),
                zacc: -9.8,
                ..HIGHRES_IMU_DATA::DEFAULT
            })
        };
        let mut t_us = 1_000_000u64;
        let mut last = None;
        for k in 0..100 {
            // 4 ms apart with MAVLink jitter (2-8 ms): never a gap.
            t_us += [4000, 2000, 6000, 4000, 8000][k % 5];
            let out = s.convert(&tel((t_us / 1000) as i64, hr(t_us, 4.0)));
            if let Some(NavInput::Imu(i)) = out.first() {
                assert_eq!(i.gap_sigma_dtheta_rad, 0.0, "jitter taken for a gap");
                let dt = i.dtheta_rad_body_frd.y / 4f64.to_radians();
                assert!(dt > 0.0019 && dt < 0.0081, "{dt}");
                last = Some(*i);
            }
        }
        assert!(last.is_some());
        t_us += 36_800;
        let out = s.convert(&tel((t_us / 1000) as i64, hr(t_us, 232.0)));
        let NavInput::Imu(i) = &out[0] else {
            panic!("{out:?}")
        };
        let turned_deg = i.dtheta_rad_body_frd.y.to_degrees();
        assert!(
            (turned_deg - 0.5 * (4.0 + 232.0) * 0.0368).abs() < 0.01,
            "{turned_deg}"
        );
        let sigma_deg = i.gap_sigma_dtheta_rad.to_degrees();
        assert!((2.0..3.0).contains(&sigma_deg), "{sigma_deg}");
        // The next ordinary sample is held again.
        t_us += 4000;
        let out = s.convert(&tel((t_us / 1000) as i64, hr(t_us, 230.0)));
        let NavInput::Imu(i) = &out[0] else {
            panic!("{out:?}")
        };
        assert_eq!(i.gap_sigma_dtheta_rad, 0.0);
        assert!((i.dtheta_rad_body_frd.y.to_degrees() - 230.0 * 0.004).abs() < 1e-3);
    }

    #[test]
    fn gps_attitude_and_baro() {
        let mut s = Inputs::new(DaemonConfig::default(), GpsSource::Gps1);
        let att = MavMessage::ATTITUDE(ATTITUDE_DATA {
            time_boot_ms: 2000,
            roll: 0.1,
            pitch: -0.05,
            yaw: 1.0,
            ..ATTITUDE_DATA::DEFAULT
        });
        let out = s.convert(&tel(2000, att));
        let NavInput::Meas(Measurement::Attitude(a)) = &out[0] else {
            panic!()
        };
        let (r, p, y) = a.q_nb.euler_angles();
        assert!((r - 0.1).abs() < 1e-6 && (p + 0.05).abs() < 1e-6 && (y - 1.0).abs() < 1e-6);
        assert!(s.attitude_at(2_100_000, 200_000).is_some());
        assert!(s.attitude_at(2_300_000, 200_000).is_none());
        let baro = MavMessage::SCALED_PRESSURE(SCALED_PRESSURE_DATA {
            time_boot_ms: 2000,
            press_abs: 898.75,
            ..SCALED_PRESSURE_DATA::DEFAULT
        });
        assert!(
            s.convert(&tel(2000, baro.clone())).is_empty(),
            "no offset yet"
        );
        let gps = |fix| {
            MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
                time_usec: 2_050_000,
                fix_type: fix,
                lat: 470_000_000,
                lon: -970_000_000,
                alt: 1_000_000,
                vel: 1000,
                cog: 9000,
                eph: u16::MAX,
                epv: u16::MAX,
                ..GPS_RAW_INT_DATA::DEFAULT
            })
        };
        assert!(
            s.convert(&tel(2060, gps(GpsFixType::GPS_FIX_TYPE_2D_FIX)))
                .is_empty()
        );
        let out = s.convert(&tel(2060, gps(GpsFixType::GPS_FIX_TYPE_3D_FIX)));
        let NavInput::Meas(Measurement::GpsPosition(p)) = &out[0] else {
            panic!("{out:?}")
        };
        let n = geoid_undulation_m(47.0, -97.0).unwrap();
        // The time stamp minus the receiver delay (gps_delay_s = 0.1).
        assert_eq!(p.t_capture_us, 2_050_000 - 100_000);
        assert!((p.h_m - (1000.0 + n)).abs() < 1e-9);
        assert!((p.cov_ned_m2[(0, 0)] - 2.5f64.powi(2)).abs() < 1e-12);
        let NavInput::Meas(Measurement::GpsVelocity(v)) = &out[1] else {
            panic!()
        };
        assert!((v.v_ned_m_s - Vector3::new(0.0, 10.0, 0.0)).norm() < 1e-9);
        // No vel_acc: the configured sigma; a receiver's 4 cm/s is floored.
        assert!((v.cov_ned_m2_s2[(0, 0)] - 0.5f64.powi(2)).abs() < 1e-12);
        let mut tight = Inputs::new(DaemonConfig::default(), GpsSource::Gps1);
        tight.baro_isa_m = None;
        let mut g = gps(GpsFixType::GPS_FIX_TYPE_3D_FIX);
        if let MavMessage::GPS_RAW_INT(d) = &mut g {
            d.vel_acc = 40;
        }
        let out2 = tight.convert(&tel(2060, g));
        let NavInput::Meas(Measurement::GpsVelocity(v2)) = &out2[1] else {
            panic!("{out2:?}")
        };
        assert!((v2.cov_ned_m2_s2[(1, 1)] - 0.3f64.powi(2)).abs() < 1e-12);
        assert!(s.baro_calibrated());
        // The same pressure now gives the GPS height.
        let out = s.convert(&tel(2100, baro));
        let NavInput::Meas(Measurement::Altitude(a)) = &out[0] else {
            panic!()
        };
        assert!((a.h_m - (1000.0 + n)).abs() < 1e-6, "{}", a.h_m);
        // GPS2_RAW is ignored when the source is GPS_RAW_INT, and vice versa.
        let mut s2 = Inputs::new(DaemonConfig::default(), GpsSource::Gps2);
        assert!(
            s2.convert(&tel(2060, gps(GpsFixType::GPS_FIX_TYPE_3D_FIX)))
                .is_empty()
        );
        // Unix time in time_usec: the arrival time is used.
        let m = MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
            time_usec: 1_700_000_000_000_000,
            fix_type: GpsFixType::GPS_FIX_TYPE_3D_FIX,
            lat: 470_000_000,
            lon: -970_000_000,
            vel: u16::MAX,
            cog: u16::MAX,
            ..GPS_RAW_INT_DATA::DEFAULT
        });
        let out = s.convert(&tel(3000, m));
        assert_eq!(out.len(), 1, "no velocity when unknown");
        assert!(matches!(&out[0], NavInput::Meas(m) if m.t_capture_us() == 3_000_000 - 100_000));
        // A receiver's own (optimistic) accuracy is floored; a larger one is kept.
        for (h_acc, v_acc, sh, sv) in [(300, 500, 1.5, 3.0), (4000, 7000, 4.0, 7.0)] {
            let m = MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
                time_usec: 3_100_000,
                fix_type: GpsFixType::GPS_FIX_TYPE_3D_FIX,
                lat: 470_000_000,
                lon: -970_000_000,
                h_acc,
                v_acc,
                vel: u16::MAX,
                cog: u16::MAX,
                ..GPS_RAW_INT_DATA::DEFAULT
            });
            let out = s.convert(&tel(3100, m));
            let NavInput::Meas(Measurement::GpsPosition(p)) = &out[0] else {
                panic!("{out:?}")
            };
            assert!((p.cov_ned_m2[(0, 0)] - sh * sh).abs() < 1e-9, "{h_acc}");
            assert!((p.cov_ned_m2[(2, 2)] - sv * sv).abs() < 1e-9, "{v_acc}");
        }
    }

    #[test]
    fn isa_inverse() {
        // 898.75 hPa is ~1000 m in the ISA troposphere.
        assert!((isa_altitude_m(898.75) - 1000.0).abs() < 1.0);
        assert!(isa_altitude_m(1013.25).abs() < 1e-9);
    }

    #[test]
    fn health_wording_is_kept_while_only_numbers_change() {
        let no_fix = |s| HealthReason::of(HealthCause::NoFixFor { s });
        let (ra, rb) = (no_fix(10.3), no_fix(11.7));
        let a = link_health(NavHealth::Degraded, &ra, None);
        let b = link_health(NavHealth::Degraded, &rb, Some((&a, &ra)));
        assert_eq!(a, b);
        assert_eq!(
            b,
            LinkHealth::Degraded {
                reason: "no accepted position fix for 10.3 s".into()
            }
        );
        let rc = HealthReason::of(HealthCause::SigmaOver {
            sigma_m: 16.0,
            limit_m: 15.0,
        });
        let c = link_health(NavHealth::Degraded, &rc, Some((&b, &rb)));
        assert_ne!(b, c);
        let ok = HealthReason::default();
        assert_eq!(
            link_health(NavHealth::Ok, &ok, Some((&c, &rc))),
            LinkHealth::Ok
        );
        let imu = HealthReason::of(HealthCause::ImuSilent);
        assert!(matches!(
            link_health(NavHealth::Lost, &imu, Some((&c, &rc))),
            LinkHealth::Lost { .. }
        ));
    }

    fn output(t_us: u64, health: NavHealth) -> NavOutput {
        NavOutput {
            t_us,
            lat_deg: 47.0,
            lon_deg: -97.0,
            h_m: 500.0,
            v_ned_m_s: [10.0, 0.0, 0.0],
            q_nb_wxyz: [1.0, 0.0, 0.0, 0.0],
            rpy_deg: [0.0, 0.0, 30.0],
            cov_pos_ned_m2: [[4.0, 0.0, 0.0], [0.0, 9.0, 0.0], [0.0, 0.0, 16.0]],
            cov_vel_ned_m2_s2: [[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]],
            att_sigma_deg: [0.5, 0.5, 2.0],
            gyro_bias_deg_h: [0.0; 3],
            w_body_rad_s: [0.0; 3],
            accel_bias_ug: [0.0; 3],
            health,
            reason: HealthReason::default(),
        }
    }

    /// A book of 50 Hz outputs turning at 10 deg/s about down, flying 10 m/s north.
    fn turning_book(from_us: u64, to_us: u64) -> OutputBook {
        let mut book = OutputBook::default();
        for t in (from_us..=to_us).step_by(20_000) {
            let mut o = output(t, NavHealth::Ok);
            let yaw = (10.0 * t as f64 * 1e-6).to_radians();
            let q = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
            o.q_nb_wxyz = [q.w, q.i, q.j, q.k];
            o.rpy_deg = [0.0, 0.0, yaw.to_degrees()];
            o.lat_deg = 47.0 + 10.0 * t as f64 * 1e-6 / 111_200.0;
            o.v_ned_m_s = [10.0, 0.0, 0.0];
            // The gyros read the turn plus the level frame's own (earth and transport rates).
            let lat = o.lat_deg.to_radians();
            let v = Vector3::from(o.v_ned_m_s);
            let w_in = earth::earth_rate_ned(lat) + earth::transport_rate_ned(lat, o.h_m, &v);
            let w = Vector3::new(0.0, 0.0, 10f64.to_radians()) + q.inverse() * w_in;
            o.w_body_rad_s = w.into();
            book.push(o);
        }
        book
    }

    /// The solution between outputs is interpolated, after the newest one moved on by its rates,
    /// and nothing across a gap; the body rotation over a frame interval is the rates' integral.
    #[test]
    fn output_book_interpolates_extrapolates_and_integrates_rates() {
        let book = turning_book(1_000_000, 2_000_000);
        let yaw_at = |t: u64| book.at(t).map(|o| o.rpy_deg[2]);
        assert!((yaw_at(1_510_000).unwrap() - 15.1).abs() < 1e-9);
        assert!((yaw_at(2_050_000).unwrap() - 20.5).abs() < 1e-9);
        let lat = book.at(1_510_000).unwrap().lat_deg;
        assert!(((lat - 47.0) * 111_200.0 - 15.1).abs() < 1e-6);
        assert!(book.at(2_150_000).is_none(), "beyond the newest + 0.1 s");
        assert!(book.at(900_000).is_none(), "before the oldest");
        let (r, unknown) = book.body_rotation(1_510_000, 1_710_000).unwrap();
        assert!((r.scaled_axis() - Vector3::new(0.0, 0.0, 2f64.to_radians())).norm() < 1e-12);
        assert!(
            unknown < 1e-15,
            "a constant rate leaves nothing unknown: {unknown}"
        );
        let (r, _) = book.body_rotation(1_950_000, 2_050_000).unwrap();
        assert!((r.angle().to_degrees() - 1.0).abs() < 1e-9);
        // A rate that jumps by 20 deg/s between two outputs 20 ms apart: 0.1 deg unknown.
        let mut jumpy = turning_book(1_000_000, 1_100_000);
        let mut o = jumpy.last().unwrap().clone();
        o.t_us = 1_120_000;
        o.w_body_rad_s[0] += 20f64.to_radians();
        jumpy.push(o);
        let (_, unknown) = jumpy.body_rotation(1_050_000, 1_120_000).unwrap();
        assert!(
            (unknown.to_degrees() - 0.2).abs() < 1e-6,
            "{}",
            unknown.to_degrees()
        );
        assert!(book.body_rotation(1_950_000, 2_200_000).is_none());
        assert!(book.body_rotation(800_000, 1_100_000).is_none());
        // A gap of 0.3 s in the outputs.
        let mut gappy = turning_book(1_000_000, 1_400_000);
        for o in turning_book(1_700_000, 2_000_000).outs {
            gappy.push(o);
        }
        assert!(gappy.at(1_500_000).is_none());
        assert!(gappy.body_rotation(1_300_000, 1_800_000).is_none());
        assert!(gappy.body_rotation(1_700_000, 1_900_000).is_some());
    }

    /// A body at rest on the ground, whose gyros read only the earth's rotation (15 deg/h), has
    /// not turned over the ground: the camera sees the same scene.
    #[test]
    fn a_body_at_rest_has_not_turned_over_the_ground() {
        let mut book = OutputBook::default();
        let q = UnitQuaternion::from_euler_angles(0.02, -0.03, 1.0);
        for t in (1_000_000..=2_000_000).step_by(20_000) {
            let mut o = output(t, NavHealth::Ok);
            o.q_nb_wxyz = [q.w, q.i, q.j, q.k];
            o.lat_deg = 47.0;
            o.v_ned_m_s = [0.0; 3];
            let w_ie = earth::earth_rate_ned(o.lat_deg.to_radians());
            o.w_body_rad_s = (q.inverse() * w_ie).into();
            book.push(o);
        }
        let (r, _) = book.body_rotation(1_000_000, 2_000_000).unwrap();
        assert!(r.angle() < 1e-12, "{} rad", r.angle());
    }

    #[test]
    fn estimate_and_prior() {
        let o = output(1_000_000, NavHealth::Ok);
        let e = estimate_from_output(&o, LinkHealth::Ok, 3).unwrap();
        let n = geoid_undulation_m(47.0, -97.0).unwrap();
        assert!((e.alt_amsl_m + n - 500.0).abs() < 1e-9);
        assert!(visnav_link::inject::check_estimate(&e).is_ok());
        assert_eq!(e.reset_counter, 3);
        let nav = NavConfig::default();
        let p = prior_at(1_500_000, Some(&o), None, &nav);
        let pos = p.position.unwrap();
        // Moved 5 m north at 10 m/s over 0.5 s.
        let dn = (pos.lat_deg - 47.0).to_radians() * 6_367_000.0;
        assert!((dn - 5.0).abs() < 0.05, "{dn}");
        assert!((pos.sigma_h_m - (9.0f64 + 0.0025).sqrt()).abs() < 1e-9);
        assert!((pos.sigma_v_m - (16.0f64 + 0.0025).sqrt()).abs() < 1e-9);
        // The filter's attitude sigmas [0.5, 0.5, 2] deg: tilt 0.5, heading 2.
        assert!((p.attitude.unwrap().sigma_rad - 0.5f64.to_radians()).abs() < 1e-12);
        assert!((p.attitude.unwrap().sigma_yaw_rad - 2f64.to_radians()).abs() < 1e-12);
        // The filter's own attitude: the engine weighs it as a dependent prior.
        assert!(p.attitude_from_filter);
        // Lost with a small sigma (after no fix for a minute): still its position.
        let lost = output(1_000_000, NavHealth::Lost);
        assert!(
            prior_at(1_000_000, Some(&lost), None, &nav)
                .position
                .is_some()
        );
        // Lost with a sigma beyond 300 m / no output: no position; the autopilot attitude is used.
        let mut lost = output(1_000_000, NavHealth::Lost);
        lost.cov_pos_ned_m2[1][1] = 400.0 * 400.0;
        let p = prior_at(
            1_000_000,
            Some(&lost),
            Some(Attitude::new(0.0, 0.0, 1.0)),
            &nav,
        );
        assert!(p.position.is_none());
        // ...but its altitude (AMSL, sigma 4 m) is the relocalisation's scale.
        let alt = p.altitude.unwrap();
        assert!((alt.alt_amsl_m + n - 500.0).abs() < 1e-9, "{alt:?}");
        assert!((alt.sigma_m - 4.0).abs() < 1e-9);
        assert!(prior_at(1_000_000, None, None, &nav).altitude.is_none());
        assert!(prior_at(1_000_000, Some(&o), None, &nav).altitude.is_none());
        assert_eq!(p.attitude.unwrap().attitude.yaw_rad, 1.0);
        assert!(
            !p.attitude_from_filter,
            "the autopilot's attitude is not the filter's"
        );
        // Tilt and heading sigmas from the nav config (1 and 3 deg by default).
        assert!((p.attitude.unwrap().sigma_rad - 1f64.to_radians()).abs() < 1e-12);
        assert!((p.attitude.unwrap().sigma_yaw_rad - 3f64.to_radians()).abs() < 1e-12);
        let mut book = OutputBook::default();
        book.push(output(1_000_000, NavHealth::Ok));
        book.push(output(1_020_000, NavHealth::Ok));
        assert_eq!(book.nearest(1_012_000).unwrap().t_us, 1_020_000);
        assert!(book.nearest(2_100_000).is_none());
    }

    #[test]
    fn the_solution_before_a_restart_is_the_reacquisition_prior() {
        let nav = NavConfig::default();
        let o = output(1_000_000, NavHealth::Ok);
        let ap = Attitude::new(0.0, 0.0, 1.0);
        // 4 s later: moved 40 m north, sigma grown by the unseen manoeuvres (3 x 16 / sqrt 3).
        let p = reacquisition_prior(5_000_000, &o, Some(ap), &nav);
        let pos = p.position.expect("a position");
        let dn = (pos.lat_deg - 47.0).to_radians() * 6_367_000.0;
        assert!((dn - 40.0).abs() < 0.2, "{dn}");
        let unseen = 3.0 * 16.0 / 3f64.sqrt();
        let moved = (9.0f64 + 0.01 * 16.0).sqrt();
        assert!(
            (pos.sigma_h_m - moved.hypot(unseen)).abs() < 1e-9,
            "{pos:?}"
        );
        // The attitude is the autopilot's, not the old solution's.
        assert_eq!(p.attitude.expect("attitude").attitude.yaw_rad, 1.0);
        assert!(!p.attitude_from_filter);
        // Too old, or from the future: no position (a relocalisation).
        assert!(
            reacquisition_prior(62_000_000, &o, Some(ap), &nav)
                .position
                .is_none()
        );
        assert!(
            reacquisition_prior(900_000, &o, Some(ap), &nav)
                .position
                .is_none()
        );
    }

    #[test]
    fn report_to_measurement() {
        let few = visnav_core::fix::Rejection::FewMatches { n: 3, min: 12 };
        let mut r = FixReport::rejected(few.clone(), 5, 1.0);
        let e = vision_measurement(&r, 5, false, false).unwrap_err();
        assert_eq!(e, NoMeasurement::Rejected(few));
        assert_eq!(
            (e.to_string().as_str(), e.class()),
            ("only 3 matches (min 12)", "few_matches")
        );
        r.rejection = None;
        r.accepted = true;
        assert!(
            vision_measurement(&r, 5, false, false).is_err(),
            "NaN position"
        );
        r.lat_deg = 47.0;
        r.lon_deg = -97.0;
        r.alt_amsl_m = 800.0;
        r.cov_ned_m2 = [[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 9.0]];
        let Measurement::Vision(f) = vision_measurement(&r, 7, false, false).unwrap() else {
            panic!()
        };
        assert_eq!(f.t_capture_us, 7);
        assert!((f.lat_rad - 47f64.to_radians()).abs() < 1e-15);
        let n = geoid_undulation_m(47.0, -97.0).unwrap();
        assert!(
            (f.h_m - (800.0 + n)).abs() < 1e-9,
            "h from AMSL + N when h_ellip is NaN"
        );
        r.h_ellip_m = 780.0;
        let Measurement::Vision(f) = vision_measurement(&r, 7, false, false).unwrap() else {
            panic!()
        };
        assert_eq!(f.h_m, 780.0);
        r.cov_ned_m2[0][0] = -1.0;
        assert!(
            vision_measurement(&r, 7, false, false)
                .unwrap_err()
                .to_string()
                .contains("covariance")
        );
        // With `[nav] vision_attitude` and an image-only pose: that pose, its 6x6 covariance.
        r.cov_ned_m2[0][0] = 4.0;
        let mut cov6 = [[0.0; 6]; 6];
        for (i, row) in cov6.iter_mut().enumerate() {
            row[i] = if i < 3 { 900.0 } else { 3e-4 };
        }
        cov6[1][3] = 0.5; // east position with the tilt about north
        cov6[3][1] = 0.5;
        r.vision_only = Some(visnav_core::fix::VisionOnlyPose {
            lat_deg: 47.001,
            lon_deg: -97.0,
            h_ellip_m: 790.0,
            roll_deg: 2.0,
            pitch_deg: 0.0,
            yaw_deg: 90.0,
            cov6_ned: cov6,
        });
        let Measurement::VisionPose(p) = vision_measurement(&r, 7, true, false).unwrap() else {
            panic!("a pose measurement")
        };
        assert!((p.position.lat_rad - 47.001f64.to_radians()).abs() < 1e-15);
        assert_eq!(p.position.h_m, 790.0);
        assert_eq!(p.position.cov_ned_m2[(1, 1)], 900.0);
        assert_eq!(p.cov6[(1, 3)], 0.5);
        assert!((p.q_nb.euler_angles().0 - 2f64.to_radians()).abs() < 1e-12);
        // Without the option the prior-fused position as before.
        assert!(matches!(
            vision_measurement(&r, 7, false, false),
            Ok(Measurement::Vision(f)) if f.h_m == 780.0
        ));
        // A covariance that is not positive definite is refused.
        cov6[1][3] = 1e3;
        cov6[3][1] = 1e3;
        r.vision_only.as_mut().unwrap().cov6_ned = cov6;
        assert!(vision_measurement(&r, 7, true, false).is_err());
        // With `[nav] vision_prior_dependence` and a prior from the filter: the image's
        // covariance and the dependence; otherwise the reported covariance, no dependence.
        r.vision_only = None;
        r.prior_dependence = Some(visnav_core::fix::PriorDependenceNed {
            d_pos_d_att: [[0.0, -900.0, 0.0], [900.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
            image_cov_ned_m2: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]],
        });
        let plain = |r: &FixReport, dep: bool| match vision_measurement(r, 7, false, dep) {
            Ok(Measurement::Vision(f)) => f,
            other => panic!("a position fix, got {other:?}"),
        };
        r.prior_attitude_from_filter = true;
        let f = plain(&r, true);
        assert_eq!(f.att_dependence_ned.unwrap()[(1, 0)], 900.0);
        assert_eq!(f.cov_ned_m2[(2, 2)], 2.0);
        let f = plain(&r, false);
        assert!(f.att_dependence_ned.is_none());
        assert_eq!(f.cov_ned_m2[(0, 0)], 4.0);
        r.prior_attitude_from_filter = false;
        assert!(plain(&r, true).att_dependence_ned.is_none());
    }

    #[test]
    fn gyro_from_attitude_rates_replaces_the_16_bit_gyro() {
        let att = |t_ms: u32, w: [f32; 3]| {
            MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms: t_ms,
                rollspeed: w[0],
                pitchspeed: w[1],
                yawspeed: w[2],
                ..ATTITUDE_DATA::DEFAULT
            })
        };
        // The rate of the sample at t_ms (the previous one was at t_ms - 10).
        let gyro = |s: &mut Inputs, t_ms: u32| {
            let out = s.convert(&tel(i64::from(t_ms), scaled(t_ms)));
            let NavInput::Imu(i) = &out[0] else {
                panic!("{out:?}")
            };
            i.dtheta_rad_body_frd / 0.01
        };
        // A slow rotation (0.4 mrad/s: zero in SCALED_IMU) comes through from ATTITUDE.
        let mut s = Inputs::new(DaemonConfig::default(), GpsSource::Gps1);
        s.convert(&tel(1000, scaled(1000)));
        s.convert(&tel(1005, att(1005, [4e-4, -2e-4, 1e-4])));
        let w = gyro(&mut s, 1010);
        assert!((w - Vector3::new(4e-4, -2e-4, 1e-4)).norm() < 1e-9, "{w}");
        // Rates older than 60 ms: the message's own (10 mrad/s about x).
        s.convert(&tel(1060, scaled(1060)));
        let w = gyro(&mut s, 1070);
        assert!((w - Vector3::new(0.01, 0.0, 0.0)).norm() < 1e-12, "{w}");
        // Non-finite rates are not taken.
        s.convert(&tel(1075, att(1075, [f32::NAN, 0.0, 0.0])));
        let w = gyro(&mut s, 1080);
        assert!((w - Vector3::new(0.01, 0.0, 0.0)).norm() < 1e-12, "{w}");
        // Switched off: always the message's gyro.
        let cfg = DaemonConfig {
            gyro_from_attitude: false,
            ..DaemonConfig::default()
        };
        let mut s = Inputs::new(cfg, GpsSource::Gps1);
        s.convert(&tel(1000, scaled(1000)));
        s.convert(&tel(1005, att(1005, [4e-4, -2e-4, 1e-4])));
        let w = gyro(&mut s, 1010);
        assert!((w - Vector3::new(0.01, 0.0, 0.0)).norm() < 1e-12, "{w}");
    }
}
