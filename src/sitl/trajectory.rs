//! Truth trajectory generator: straight lines, coordinated turns and climbs with smooth
//! transitions, plus the ideal IMU increments that the trajectory implies.
//!
//! Kinematic model (no wind, zero angle of attack and sideslip): the aircraft flies at speed `V`
//! with flight-path angle `gamma` and heading `psi`; `v_ned = V [cos g cos psi, cos g sin psi,
//! -sin g]`. Attitude: yaw = `psi`, pitch = `gamma`, roll = `atan(V psi_dot / g0)` (coordinated
//! turn). Each segment moves (V, psi_dot, gamma) from the previous segment's values to its own over
//! `ramp_s` with the smoothstep `S(u) = 3u^2 - 2u^3`, so rates and accelerations are continuous;
//! `psi(t)` uses the closed form `int S = u^3 - u^4/2`. Position is integrated with RK4 on the
//! ellipsoid. The IMU increments are the exact integrals (3-point Gauss-Legendre) of
//! `w_ib^b = w_nb^b + C_n^b (w_ie^n + w_en^n)` and `f^b = C_n^b (dv/dt + (2 w_ie + w_en) x v - g)`,
//! with `w_nb^b` from the ZYX Euler-angle rates:
//! `p = rdot - ydot sin(pitch)`, `q = pdot cos(roll) + ydot sin(roll) cos(pitch)`,
//! `r = -pdot sin(roll) + ydot cos(roll) cos(pitch)`.

use crate::nav::earth;
use crate::nav::ins::InsState;
use nalgebra::{UnitQuaternion, Vector3};

/// Standard gravity used for the bank angle of a coordinated turn, m/s^2.
const G0: f64 = 9.806_65;

/// Flight segment targets, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    /// Duration, s.
    pub duration_s: f64,
    /// Speed at the end of the ramp, m/s.
    pub speed_m_s: f64,
    /// Heading rate, rad/s (positive = turning right/clockwise seen from above).
    pub turn_rate_rad_s: f64,
    /// Flight-path angle, rad (positive = climbing).
    pub path_angle_rad: f64,
    /// Transition time from the previous segment's values, s.
    pub ramp_s: f64,
}

/// Kinematics at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kinematics {
    /// Velocity NED, m/s.
    pub v_ned_m_s: Vector3<f64>,
    /// Acceleration (d v_ned / dt), m/s^2.
    pub a_ned_m_s2: Vector3<f64>,
    /// Roll, pitch, yaw (ZYX), rad.
    pub rpy_rad: Vector3<f64>,
    /// Body angular rate w.r.t. NED, body FRD, rad/s.
    pub w_nb_body_rad_s: Vector3<f64>,
}

/// A piecewise trajectory.
#[derive(Debug, Clone)]
pub struct Trajectory {
    start_lat_rad: f64,
    start_lon_rad: f64,
    start_h_m: f64,
    segs: Vec<Segment>,
    t0_s: Vec<f64>,
    psi0: Vec<f64>,
    from: Vec<(f64, f64, f64)>,
}

fn smooth(u: f64) -> (f64, f64, f64) {
    if u >= 1.0 {
        return (1.0, 0.0, 0.5);
    }
    let u = u.max(0.0);
    (
        3.0 * u * u - 2.0 * u * u * u,
        6.0 * u - 6.0 * u * u,
        u * u * u - 0.5 * u * u * u * u,
    )
}

impl Trajectory {
    /// Build from the start point/speed/heading and the segments.
    pub fn new(
        start_lat_rad: f64,
        start_lon_rad: f64,
        start_h_m: f64,
        start_speed_m_s: f64,
        start_heading_rad: f64,
        segs: Vec<Segment>,
    ) -> Self {
        let mut t0_s = Vec::new();
        let mut psi0 = Vec::new();
        let mut from = Vec::new();
        let (mut t, mut psi) = (0.0, start_heading_rad);
        let mut prev = (start_speed_m_s, 0.0, 0.0);
        for s in &segs {
            t0_s.push(t);
            psi0.push(psi);
            from.push(prev);
            let tr = s.ramp_s.min(s.duration_s).max(1e-6);
            let (r0, r1) = (prev.1, s.turn_rate_rad_s);
            psi += if s.duration_s <= tr {
                let u = s.duration_s / tr;
                r0 * s.duration_s + (r1 - r0) * tr * smooth(u).2
            } else {
                r0 * tr + (r1 - r0) * tr * 0.5 + r1 * (s.duration_s - tr)
            };
            t += s.duration_s;
            prev = (s.speed_m_s, s.turn_rate_rad_s, s.path_angle_rad);
        }
        Self {
            start_lat_rad,
            start_lon_rad,
            start_h_m,
            segs,
            t0_s,
            psi0,
            from,
        }
    }

    /// Total duration, s.
    pub fn duration_s(&self) -> f64 {
        match (self.t0_s.last(), self.segs.last()) {
            (Some(t), Some(s)) => t + s.duration_s,
            _ => 0.0,
        }
    }

    /// Kinematics at time `t_s` (the last segment continues beyond the end).
    pub fn kinematics(&self, t_s: f64) -> Kinematics {
        let i = self.t0_s.iter().rposition(|&t0| t0 <= t_s).unwrap_or(0);
        let s = &self.segs[i]; // ok: a trajectory has at least one segment (validated)
        let (v0, r0, g0) = self.from[i];
        let tau = (t_s - self.t0_s[i]).max(0.0);
        let tr = s.ramp_s.min(s.duration_s).max(1e-6);
        let (sv, sd, si) = smooth(tau / tr);
        let sd = if tau < tr { sd / tr } else { 0.0 };
        let v = v0 + (s.speed_m_s - v0) * sv;
        let vd = (s.speed_m_s - v0) * sd;
        let r = r0 + (s.turn_rate_rad_s - r0) * sv;
        let rd = (s.turn_rate_rad_s - r0) * sd;
        let g = g0 + (s.path_angle_rad - g0) * sv;
        let gd = (s.path_angle_rad - g0) * sd;
        let psi = self.psi0[i]
            + if tau <= tr {
                r0 * tau + (s.turn_rate_rad_s - r0) * tr * si
            } else {
                r0 * tr + (s.turn_rate_rad_s - r0) * tr * 0.5 + s.turn_rate_rad_s * (tau - tr)
            };
        let (sg, cg) = g.sin_cos();
        let (sp, cp) = psi.sin_cos();
        let v_ned = Vector3::new(v * cg * cp, v * cg * sp, -v * sg);
        let a_ned = vd * Vector3::new(cg * cp, cg * sp, -sg)
            + v * gd * Vector3::new(-sg * cp, -sg * sp, -cg)
            + v * cg * r * Vector3::new(-sp, cp, 0.0);
        let x = v * r / G0;
        let roll = x.atan();
        let roll_d = (vd * r + v * rd) / G0 / (1.0 + x * x);
        let (pitch, pitch_d, yaw_d) = (g, gd, r);
        let (sr, cr) = roll.sin_cos();
        let (sth, cth) = pitch.sin_cos();
        let w = Vector3::new(
            roll_d - yaw_d * sth,
            pitch_d * cr + yaw_d * sr * cth,
            -pitch_d * sr + yaw_d * cr * cth,
        );
        Kinematics {
            v_ned_m_s: v_ned,
            a_ned_m_s2: a_ned,
            rpy_rad: Vector3::new(roll, pitch, psi),
            w_nb_body_rad_s: w,
        }
    }

    /// Truth integrator positioned at the start.
    pub fn truth(&self) -> TruthIntegrator<'_> {
        let k = self.kinematics(0.0);
        TruthIntegrator {
            traj: self,
            t_s: 0.0,
            lat_rad: self.start_lat_rad,
            lon_rad: self.start_lon_rad,
            h_m: self.start_h_m,
            kin: k,
        }
    }
}

/// Integrates the truth position along a trajectory and produces ideal IMU increments.
#[derive(Debug, Clone)]
pub struct TruthIntegrator<'a> {
    traj: &'a Trajectory,
    /// Current time, s.
    pub t_s: f64,
    /// Latitude, rad.
    pub lat_rad: f64,
    /// Longitude, rad.
    pub lon_rad: f64,
    /// Height above the ellipsoid, m.
    pub h_m: f64,
    /// Kinematics at `t_s`.
    pub kin: Kinematics,
}

fn q_of(rpy: &Vector3<f64>) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(rpy.x, rpy.y, rpy.z)
}

impl TruthIntegrator<'_> {
    /// Truth navigation state now.
    pub fn state(&self) -> InsState {
        InsState {
            lat_rad: self.lat_rad,
            lon_rad: self.lon_rad,
            h_m: self.h_m,
            v_ned_m_s: self.kin.v_ned_m_s,
            q_nb: q_of(&self.kin.rpy_rad),
        }
    }

    fn body_rates(&self, t: f64, lat: f64, h: f64) -> (Vector3<f64>, Vector3<f64>) {
        let k = self.traj.kinematics(t);
        let c_nb = q_of(&k.rpy_rad).inverse().to_rotation_matrix().into_inner();
        let w_ie = earth::earth_rate_ned(lat);
        let w_en = earth::transport_rate_ned(lat, h, &k.v_ned_m_s);
        let g = Vector3::new(0.0, 0.0, earth::normal_gravity_m_s2(lat, h));
        let f_n = k.a_ned_m_s2 + (2.0 * w_ie + w_en).cross(&k.v_ned_m_s) - g;
        (k.w_nb_body_rad_s + c_nb * (w_ie + w_en), c_nb * f_n)
    }

    /// Advance by `dt_s`; returns the ideal increments `(dtheta_rad, dv_m_s)` in body FRD.
    pub fn step(&mut self, dt_s: f64) -> (Vector3<f64>, Vector3<f64>) {
        let t0 = self.t_s;
        let (lat0, lon0, h0) = (self.lat_rad, self.lon_rad, self.h_m);
        // RK4 on (lat, lon, h).
        let rate = |t: f64, lat: f64, h: f64| {
            earth::position_rates(lat, h, &self.traj.kinematics(t).v_ned_m_s)
        };
        let k1 = rate(t0, lat0, h0);
        let k2 = rate(
            t0 + dt_s / 2.0,
            lat0 + k1.x * dt_s / 2.0,
            h0 + k1.z * dt_s / 2.0,
        );
        let k3 = rate(
            t0 + dt_s / 2.0,
            lat0 + k2.x * dt_s / 2.0,
            h0 + k2.z * dt_s / 2.0,
        );
        let k4 = rate(t0 + dt_s, lat0 + k3.x * dt_s, h0 + k3.z * dt_s);
        let d = (k1 + 2.0 * k2 + 2.0 * k3 + k4) * (dt_s / 6.0);
        let (lat1, h1) = (lat0 + d.x, h0 + d.z);
        // Gauss-Legendre 3-point quadrature of the body rates.
        let c = (0.6f64).sqrt() / 2.0;
        let mut dth = Vector3::zeros();
        let mut dv = Vector3::zeros();
        for (x, w) in [
            (0.5 - c, 5.0 / 18.0),
            (0.5, 8.0 / 18.0),
            (0.5 + c, 5.0 / 18.0),
        ] {
            let (wb, fb) = self.body_rates(t0 + x * dt_s, lat0 + x * d.x, h0 + x * d.z);
            dth += wb * (w * dt_s);
            dv += fb * (w * dt_s);
        }
        self.t_s = t0 + dt_s;
        self.lat_rad = lat1;
        self.lon_rad = lon0 + d.y;
        self.h_m = h1;
        self.kin = self.traj.kinematics(self.t_s);
        (dth, dv)
    }
}
