//! What the closed loop records while the flight runs, kept compact so that an hour's soak
//! measures the daemons' memory and not the simulator's notes (the soak's budget: RSS growth
//! ≤ 5 MB per hour).
//!
//! * a 10 Hz step is 80 bytes ([`StepSample`]): the time in ms, each filter's position as an
//!   `f32` offset from the truth at that time (a metre is 1e-5 deg: the offset keeps 1e-7 of
//!   itself, far below a millimetre), its NED error, horizontal sigma, horizontal velocity error
//!   and heading error in `f32`, the health as a code (64 bytes until the heading errors, which
//!   did not fit in its one byte of padding: 0.29 MB more per hour, reserved up front);
//! * the emulators' received messages are folded into 40-byte [`InjectionSample`]s each tick
//!   ([`InjectionCollector`]: the origin in force, GPS_INPUT time steps back, non-finite values,
//!   senders), instead of keeping every message (312 bytes each);
//! * a vision fix is scored when it is recorded (`FixRow`, 112 bytes) instead of keeping its
//!   report (832 bytes).
//!
//! Everything is expanded into the public rows (`StepRow`, `InjectionRow`, `FixRow`) once the
//! flight has ended. What the compact form loses: sub-millisecond step times and sub-centimetre
//! injected positions in the reports (the errors are computed in `f64` before they are stored).

use std::collections::BTreeMap;

use mavlink::MavHeader;
use mavlink::dialects::ardupilotmega::MavMessage;
use nalgebra::Vector3;

use super::{InjectionRow, StepRow, TruthTable, ned_diff_m};
use crate::autopilot::Received;
use visnav_core::geo::AutopilotFrame;

/// An empty vector with room for `n` elements whose memory is already resident: filled once with
/// `fill` (not zero: a zeroed allocation is mapped lazily) and cleared. The closed loop's
/// recordings are made this way, so the process's resident memory during a run changes only
/// with the daemons', emulators' and camera's memory (the soak's RSS figures).
pub(super) fn resident_vec<T: Clone>(n: usize, fill: T) -> Vec<T> {
    let mut v = vec![fill; n];
    v.clear();
    v
}

/// Health names by code ([`StepSample`]).
const HEALTHS: [&str; 4] = ["uninitialised", "ok", "degraded", "lost"];

/// The code of a health name (unknown names count as uninitialised).
pub(super) fn health_code(name: &str) -> u8 {
    HEALTHS.iter().position(|h| *h == name).unwrap_or(0) as u8
}

/// One filter's output at a step (NaN before its first output).
#[derive(Debug, Clone, Copy)]
pub(super) struct OutputSample {
    /// Output position minus the truth at the step's time, deg.
    pub dlat_deg: f32,
    pub dlon_deg: f32,
    /// Error against the truth at the output's own time, NED, m.
    pub err_ned_m: [f32; 3],
    pub sigma_h_m: f32,
    pub vel_err_h_m_s: f32,
    /// Heading error at the output's own time, wrapped to [-180, 180), deg.
    pub yaw_err_deg: f32,
    /// Largest absolute error of the three Euler angles (roll, pitch, yaw; each wrapped) at the
    /// output's own time, deg.
    pub euler_err_deg: f32,
}

impl OutputSample {
    pub const NONE: Self = Self {
        dlat_deg: f32::NAN,
        dlon_deg: f32::NAN,
        err_ned_m: [f32::NAN; 3],
        sigma_h_m: f32::NAN,
        vel_err_h_m_s: f32::NAN,
        yaw_err_deg: f32::NAN,
        euler_err_deg: f32::NAN,
    };
}

/// One 10 Hz step, compact (80 bytes).
#[derive(Debug, Clone, Copy)]
pub(super) struct StepSample {
    /// Scenario (run) time, ms.
    pub t_ms: u32,
    pub gps_on: bool,
    pub vis_health: u8,
    pub ctl_health: u8,
    pub vis: OutputSample,
    pub ctl: OutputSample,
}

impl StepSample {
    /// A filler (not all zero bits: [`resident_vec`]).
    pub const FILL: Self = Self {
        t_ms: u32::MAX,
        gps_on: false,
        vis_health: 0,
        ctl_health: 0,
        vis: OutputSample::NONE,
        ctl: OutputSample::NONE,
    };

    /// The step's time, s.
    pub fn t_s(&self) -> f64 {
        f64::from(self.t_ms) * 1e-3
    }

    /// The public row: the truth at the step's time and both outputs against it.
    pub fn expand(&self, table: &TruthTable) -> StepRow {
        let t_s = self.t_s();
        let s = table.at(t_s);
        let f = |v: f32| f64::from(v);
        let e3 = |e: [f32; 3]| [f(e[0]), f(e[1]), f(e[2])];
        StepRow {
            t_s,
            gps_on: self.gps_on,
            truth_lat_deg: s.lat_deg,
            truth_lon_deg: s.lon_deg,
            truth_alt_amsl_m: s.alt_amsl_m,
            vis_lat_deg: s.lat_deg + f(self.vis.dlat_deg),
            vis_lon_deg: s.lon_deg + f(self.vis.dlon_deg),
            vis_err_ned_m: e3(self.vis.err_ned_m),
            vis_sigma_h_m: f(self.vis.sigma_h_m),
            vis_health: HEALTHS[usize::from(self.vis_health).min(HEALTHS.len() - 1)],
            ctl_lat_deg: s.lat_deg + f(self.ctl.dlat_deg),
            ctl_lon_deg: s.lon_deg + f(self.ctl.dlon_deg),
            ctl_err_ned_m: e3(self.ctl.err_ned_m),
            ctl_sigma_h_m: f(self.ctl.sigma_h_m),
            ctl_health: HEALTHS[usize::from(self.ctl_health).min(HEALTHS.len() - 1)],
            vis_vel_err_h_m_s: f(self.vis.vel_err_h_m_s),
            ctl_vel_err_h_m_s: f(self.ctl.vel_err_h_m_s),
            vis_yaw_err_deg: f(self.vis.yaw_err_deg),
            ctl_yaw_err_deg: f(self.ctl.yaw_err_deg),
            vis_euler_err_deg: f(self.vis.euler_err_deg),
            ctl_euler_err_deg: f(self.ctl.euler_err_deg),
        }
    }
}

/// A position that is not finite or beyond the range of 1e-7 degrees in an `i32`
/// ([`InjectionSample`]).
const NO_E7: i32 = i32::MIN;

/// Degrees in 1e-7 units, [`NO_E7`] when not representable.
fn to_e7(deg: f64) -> i32 {
    let v = (deg * 1e7).round();
    if v.is_finite() && v > f64::from(i32::MIN) && v <= f64::from(i32::MAX) {
        v as i32
    } else {
        NO_E7
    }
}

/// The inverse of [`to_e7`] (NaN for [`NO_E7`]).
fn from_e7(v: i32) -> f64 {
    if v == NO_E7 {
        f64::NAN
    } else {
        f64::from(v) * 1e-7
    }
}

/// Injection kinds by code ([`InjectionSample`]).
const KINDS: [&str; 3] = ["gps_input", "vision_position_estimate", "odometry"];

/// A position injection as the emulator received it, compact (40 bytes).
#[derive(Debug, Clone, Copy)]
pub(super) struct InjectionSample {
    /// Emulator run time at arrival, µs.
    pub t_run_us: u64,
    /// The injected position, 1e-7 deg (GPS_INPUT's own unit) and m.
    pub lat_e7: i32,
    pub lon_e7: i32,
    pub alt_amsl_m: f32,
    pub horiz_accuracy_m: f32,
    /// Against the truth at arrival, NED, m (computed in f64).
    pub err_ned_m: [f32; 3],
    pub kind: u8,
    pub control: bool,
}

impl InjectionSample {
    pub fn expand(&self) -> InjectionRow {
        let f = |v: f32| f64::from(v);
        InjectionRow {
            t_s: self.t_run_us as f64 * 1e-6,
            kind: KINDS[usize::from(self.kind).min(KINDS.len() - 1)],
            lat_deg: from_e7(self.lat_e7),
            lon_deg: from_e7(self.lon_e7),
            alt_amsl_m: f(self.alt_amsl_m),
            horiz_accuracy_m: f(self.horiz_accuracy_m),
            err_ned_m: [
                f(self.err_ned_m[0]),
                f(self.err_ned_m[1]),
                f(self.err_ned_m[2]),
            ],
            control: self.control,
        }
    }
}

/// Folds an emulator's received messages into injections and the counters the fault table
/// needs, batch by batch (the emulator's recording is drained every tick).
#[derive(Debug)]
pub(super) struct InjectionCollector {
    control: bool,
    /// The EKF origin in force (SET_GPS_GLOBAL_ORIGIN as received): local positions
    /// (VISION_POSITION_ESTIMATE, ODOMETRY) are NED about it ...
    origin: Option<visnav_core::geo::GeoOrigin>,
    /// ... in the projection of the flight stack the emulator announces: read back as that
    /// autopilot would read them.
    frame: AutopilotFrame,
    pub samples: Vec<InjectionSample>,
    last_gps_time_usec: Option<u64>,
    /// GPS_INPUT messages whose `time_usec` went back.
    pub gps_time_backsteps: usize,
    /// Injections with a non-finite value.
    pub non_finite: usize,
    /// Injections per sending system id.
    senders: BTreeMap<u32, usize>,
}

impl InjectionCollector {
    /// A collector with room for `capacity` injections (resident: [`resident_vec`]).
    pub fn new(control: bool, capacity: usize, frame: AutopilotFrame) -> Self {
        Self {
            control,
            origin: None,
            frame,
            samples: resident_vec(
                capacity,
                InjectionSample {
                    t_run_us: u64::MAX,
                    lat_e7: 0,
                    lon_e7: 0,
                    alt_amsl_m: f32::NAN,
                    horiz_accuracy_m: f32::NAN,
                    err_ned_m: [f32::NAN; 3],
                    kind: 0,
                    control,
                },
            ),
            last_gps_time_usec: None,
            gps_time_backsteps: 0,
            non_finite: 0,
            senders: BTreeMap::new(),
        }
    }

    /// Injections from a system other than `companion` (none when no companion was heard: there
    /// is nothing to call foreign).
    pub fn foreign(&self, companion: Option<(u8, u8)>) -> usize {
        match companion {
            Some((sys, _)) => self
                .senders
                .iter()
                .filter(|(s, _)| **s != u32::from(sys))
                .map(|(_, n)| n)
                .sum(),
            None => 0,
        }
    }

    /// Bytes the samples hold (their buffer).
    pub fn recorded_bytes(&self) -> usize {
        self.samples.capacity() * std::mem::size_of::<InjectionSample>()
    }

    /// Folds one batch, in arrival order.
    pub fn take(&mut self, received: Vec<Received>, table: &TruthTable) {
        for r in received {
            self.count(&r.header, &r.msg);
            self.collect(&r, table);
        }
    }

    /// The counters of one message: time steps back, non-finite values, its sender.
    fn count(&mut self, header: &MavHeader, msg: &MavMessage) {
        let finite = match msg {
            MavMessage::GPS_INPUT(g) => {
                if self.last_gps_time_usec.is_some_and(|l| g.time_usec < l) {
                    self.gps_time_backsteps += 1;
                }
                self.last_gps_time_usec = Some(g.time_usec);
                [
                    g.alt,
                    g.hdop,
                    g.vdop,
                    g.vn,
                    g.ve,
                    g.vd,
                    g.speed_accuracy,
                    g.horiz_accuracy,
                    g.vert_accuracy,
                ]
                .iter()
                .all(|v| v.is_finite())
            }
            // A NaN first covariance element is MAVLink's "covariance unknown", not a bad value.
            MavMessage::VISION_POSITION_ESTIMATE(v) => [v.x, v.y, v.z, v.roll, v.pitch, v.yaw]
                .iter()
                .all(|v| v.is_finite()),
            MavMessage::ODOMETRY(o) => [o.x, o.y, o.z, o.vx, o.vy, o.vz]
                .iter()
                .all(|v| v.is_finite()),
            _ => return,
        };
        if !finite {
            self.non_finite += 1;
        }
        *self.senders.entry(header.system_id).or_default() += 1;
    }

    /// The injection a message makes, scored against the truth at its arrival (GPS_INPUT with a
    /// 3D fix; local positions with the origin in force).
    fn collect(&mut self, r: &Received, table: &TruthTable) {
        use visnav_core::geo::GeoOrigin;
        let t = r.t_run_us as f64 * 1e-6;
        #[allow(deprecated)] // SET_GPS_GLOBAL_ORIGIN: what ArduPilot acts on
        let local = match &r.msg {
            MavMessage::SET_GPS_GLOBAL_ORIGIN(o) => {
                self.origin = Some(GeoOrigin {
                    lat_deg: f64::from(o.latitude) * 1e-7,
                    lon_deg: f64::from(o.longitude) * 1e-7,
                    alt_amsl_m: f64::from(o.altitude) * 1e-3,
                });
                return;
            }
            MavMessage::GPS_INPUT(g) if g.fix_type as u8 >= 3 => {
                let s = table.at(t);
                let (lat, lon) = (f64::from(g.lat) * 1e-7, f64::from(g.lon) * 1e-7);
                let alt = f64::from(g.alt);
                let err = ned_diff_m((s.lat_deg, s.lon_deg, s.alt_amsl_m), (lat, lon, alt));
                self.push(r.t_run_us, 0, (g.lat, g.lon, g.alt), g.horiz_accuracy, err);
                return;
            }
            MavMessage::VISION_POSITION_ESTIMATE(v) => {
                (1, [v.x, v.y, v.z], horizontal_variance(&v.covariance))
            }
            MavMessage::ODOMETRY(o) => {
                (2, [o.x, o.y, o.z], horizontal_variance(&o.pose_covariance))
            }
            _ => return,
        };
        let Some(o) = self.origin else { return };
        let (kind, xyz, var_h) = local;
        let s = table.at(t);
        let p = Vector3::new(f64::from(xyz[0]), f64::from(xyz[1]), f64::from(xyz[2]));
        // Where the autopilot puts the position sent, against the truth there (north and east
        // metres at the truth: a local error in any frame would carry the projection's scale).
        let (lat, lon, alt) = self.frame.from_ned(&o, &p);
        let err = ned_diff_m((s.lat_deg, s.lon_deg, s.alt_amsl_m), (lat, lon, alt));
        let e = Vector3::from(err);
        let sigma = if var_h.is_finite() && var_h >= 0.0 {
            var_h.sqrt() as f32
        } else {
            f32::NAN
        };
        self.push(
            r.t_run_us,
            kind,
            (to_e7(lat), to_e7(lon), alt as f32),
            sigma,
            [e.x, e.y, e.z],
        );
    }

    fn push(
        &mut self,
        t_run_us: u64,
        kind: u8,
        (lat_e7, lon_e7, alt_amsl_m): (i32, i32, f32),
        horiz_accuracy_m: f32,
        err_ned_m: [f64; 3],
    ) {
        self.samples.push(InjectionSample {
            t_run_us,
            lat_e7,
            lon_e7,
            alt_amsl_m,
            horiz_accuracy_m,
            err_ned_m: err_ned_m.map(|v| v as f32),
            kind,
            control: self.control,
        });
    }
}

/// The larger horizontal variance of a MAVLink upper-triangle covariance (x-x first, y-y at 6);
/// NaN when the first element is NaN (MAVLink's "unknown").
fn horizontal_variance(cov: &[f32; 21]) -> f64 {
    if cov[0].is_nan() {
        f64::NAN
    } else {
        f64::from(cov[0].max(cov[6]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_compact_rows_are_as_small_as_the_soak_needs() {
        // An hour at 10 Hz steps and two 5 Hz injection streams: 2.6 + 1.4 MB, reserved and
        // resident from the start (the soak's budget is 5 MB of RSS growth for everything). The
        // step was 64 bytes until each output's heading error took 4 more bytes than
        // its one byte of padding.
        assert_eq!(std::mem::size_of::<StepSample>(), 80);
        assert_eq!(std::mem::size_of::<InjectionSample>(), 40);
    }

    #[test]
    fn positions_out_of_range_are_nan_not_zero() {
        assert_eq!(from_e7(to_e7(47.1234567)), 47.1234567);
        assert!(from_e7(to_e7(f64::NAN)).is_nan());
        assert!(from_e7(to_e7(1e3)).is_nan());
        assert!(horizontal_variance(&[f32::NAN; 21]).is_nan());
        let mut c = [0.0f32; 21];
        c[0] = 4.0;
        c[6] = 9.0;
        assert_eq!(horizontal_variance(&c), 9.0);
    }

    #[test]
    fn health_codes_round_trip() {
        for h in HEALTHS {
            assert_eq!(HEALTHS[usize::from(health_code(h))], h);
        }
        assert_eq!(health_code("no such health"), 0);
    }
}
