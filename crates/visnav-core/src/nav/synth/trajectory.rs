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
//!
//! Multirotor ([`Trajectory::with_multirotor_drag`]): the path (position, velocity, acceleration,
//! heading) is the same, but the attitude is a multirotor's. Its thrust acts along body -z and
//! its rotors and body feel a drag `D(v) = a v + b v |v|` on each of the body x and y velocity
//! components (ArduCopter SITL's fitted law: a = -0.215 1/s, b = -0.028 1/m), so the specific
//! force is `f_b = (D(v_bx), D(v_by), -T)`. With yaw = heading, the body z axis is
//! `z_b = -(a_ned - g_ned - f_drag_ned) / T`, `f_drag_ned = C_b^n (D(v_bx), D(v_by), 0)`. The
//! body velocity depends on the attitude, so the pair is solved by a relaxed fixed-point
//! iteration, started from the drag of the horizontal velocity in the heading frame (forward,
//! right). The accelerometer computed by the integrator (`C_n^b (a + coriolis - g)`) then reads
//! the drag in body x / y and the thrust in z, like a real copter's (the tilt uses the normal
//! gravity at the start point and no Coriolis term: 1e-3 m/s^2 at 12 m/s). Roll and pitch rates
//! are central finite differences over +-[`MULTIROTOR_RATE_STEP_S`] (1 ms: truncation error of
//! order `h^2` of the third derivative, far below the IMU's noise; the fixed point is solved to
//! 1e-12 m/s^2 so the difference is not rounding noise). In level flight the pitch solves
//! `sin(pitch) = D(V cos(pitch)) / g`: -25.5 deg at 10 m/s, -31.5 deg at 12 m/s with SITL's law.

use crate::nav::earth;
use crate::nav::ins::InsState;
use nalgebra::{UnitQuaternion, Vector3};

/// Standard gravity used for the bank angle of a coordinated turn, m/s^2.
const G0: f64 = 9.806_65;

/// Half step of the central differences of a multirotor's roll and pitch, s.
pub const MULTIROTOR_RATE_STEP_S: f64 = 1e-3;

/// Relaxation of the multirotor attitude's fixed-point iteration (converges for any contraction
/// factor of the plain iteration in (-2.3, 1); about -0.5 at 12 m/s with SITL's law).
const MULTIROTOR_RELAX: f64 = 0.6;

/// Convergence threshold of that iteration (change of the drag vector), m/s^2.
const MULTIROTOR_TOL_M_S2: f64 = 1e-12;

/// Iteration limit of that fixed point.
const MULTIROTOR_MAX_ITER: usize = 200;

/// A multirotor's drag law per body axis, `D(v) = a v + b v |v|` (specific force, m/s^2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DragLaw {
    /// `a`, 1/s (negative: opposes the motion).
    pub linear_per_s: f64,
    /// `b`, 1/m (negative).
    pub quadratic_per_m: f64,
}

impl DragLaw {
    /// The specific force along an axis whose velocity component is `v_m_s`, m/s^2.
    pub fn force(&self, v_m_s: f64) -> f64 {
        self.linear_per_s * v_m_s + self.quadratic_per_m * v_m_s * v_m_s.abs()
    }
}

/// Multirotor attitude at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MultirotorTilt {
    /// Roll, rad.
    pub roll_rad: f64,
    /// Pitch, rad.
    pub pitch_rad: f64,
    /// Whether the fixed point converged (otherwise the last iterate).
    pub converged: bool,
}

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
    /// Multirotor kinematics: the drag law and the gravity the tilt balances, m/s^2.
    multirotor: Option<(DragLaw, f64)>,
}

/// The path at one instant (the fixed-wing attitude beside it).
struct PathPoint {
    v_ned: Vector3<f64>,
    a_ned: Vector3<f64>,
    psi: f64,
    psi_d: f64,
    /// Fixed-wing roll, pitch and their rates.
    roll: f64,
    roll_d: f64,
    pitch: f64,
    pitch_d: f64,
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
            multirotor: None,
        }
    }

    /// The same path flown by a multirotor with the drag law `D(v) = a v + b v |v|` per body
    /// axis (`a` = `linear_per_s`, `b` = `quadratic_per_m`; module doc).
    pub fn with_multirotor_drag(mut self, linear_per_s: f64, quadratic_per_m: f64) -> Self {
        let g = earth::normal_gravity_m_s2(self.start_lat_rad, self.start_h_m);
        self.multirotor = Some((
            DragLaw {
                linear_per_s,
                quadratic_per_m,
            },
            g,
        ));
        self
    }

    /// The multirotor drag law, if this is a multirotor's trajectory.
    pub fn drag_law(&self) -> Option<DragLaw> {
        self.multirotor.map(|(d, _)| d)
    }

    /// Total duration, s.
    pub fn duration_s(&self) -> f64 {
        match (self.t0_s.last(), self.segs.last()) {
            (Some(t), Some(s)) => t + s.duration_s,
            _ => 0.0,
        }
    }

    /// The path (and the fixed-wing attitude) at time `t_s`.
    fn path(&self, t_s: f64) -> PathPoint {
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
        PathPoint {
            v_ned,
            a_ned,
            psi,
            psi_d: r,
            roll: x.atan(),
            roll_d: (vd * r + v * rd) / G0 / (1.0 + x * x),
            pitch: g,
            pitch_d: gd,
        }
    }

    /// A multirotor's roll and pitch on the path point `p` (module doc).
    fn multirotor_tilt(p: &PathPoint, law: &DragLaw, g_m_s2: f64) -> MultirotorTilt {
        let g = Vector3::new(0.0, 0.0, g_m_s2);
        let (sy, cy) = p.psi.sin_cos();
        let tilt_of = |f_drag_n: &Vector3<f64>| {
            let thrust = p.a_ned - g - f_drag_n;
            let n = thrust.norm();
            // No thrust (free fall) leaves the attitude undefined: level.
            let z = if n > 1e-9 { -thrust / n } else { Vector3::z() };
            // z_b in the heading frame is (sin(pitch) cos(roll), -sin(roll), cos(pitch) cos(roll)).
            let (zx, zy) = (cy * z.x + sy * z.y, -sy * z.x + cy * z.y);
            ((-zy).clamp(-1.0, 1.0).asin(), zx.atan2(z.z))
        };
        let drag_of = |roll: f64, pitch: f64| {
            let q = UnitQuaternion::from_euler_angles(roll, pitch, p.psi);
            let v_b = q.inverse() * p.v_ned;
            q * Vector3::new(law.force(v_b.x), law.force(v_b.y), 0.0)
        };
        // Start: the drag of the horizontal velocity in the heading frame (forward, right).
        let (fwd, right) = (
            cy * p.v_ned.x + sy * p.v_ned.y,
            -sy * p.v_ned.x + cy * p.v_ned.y,
        );
        let (df, dr) = (law.force(fwd), law.force(right));
        let mut d = Vector3::new(cy * df - sy * dr, sy * df + cy * dr, 0.0);
        let mut converged = false;
        for _ in 0..MULTIROTOR_MAX_ITER {
            let (roll, pitch) = tilt_of(&d);
            let next = d + (drag_of(roll, pitch) - d) * MULTIROTOR_RELAX;
            let change = (next - d).norm();
            d = next;
            if change <= MULTIROTOR_TOL_M_S2 {
                converged = true;
                break;
            }
        }
        let (roll_rad, pitch_rad) = tilt_of(&d);
        MultirotorTilt {
            roll_rad,
            pitch_rad,
            converged,
        }
    }

    /// The multirotor attitude at `t_s` (`None` for a fixed-wing trajectory).
    pub fn multirotor_tilt_at(&self, t_s: f64) -> Option<MultirotorTilt> {
        let (law, g) = self.multirotor?;
        Some(Self::multirotor_tilt(&self.path(t_s), &law, g))
    }

    /// Kinematics at time `t_s` (the last segment continues beyond the end).
    pub fn kinematics(&self, t_s: f64) -> Kinematics {
        let p = self.path(t_s);
        let (roll, roll_d, pitch, pitch_d) = match &self.multirotor {
            None => (p.roll, p.roll_d, p.pitch, p.pitch_d),
            Some((law, g)) => {
                // Central differences; one-sided at the start (the path is held before t = 0).
                let h = MULTIROTOR_RATE_STEP_S;
                let (t0, t1) = ((t_s - h).max(0.0), t_s + h);
                let now = Self::multirotor_tilt(&p, law, *g);
                let ahead = Self::multirotor_tilt(&self.path(t1), law, *g);
                let behind = Self::multirotor_tilt(&self.path(t0), law, *g);
                (
                    now.roll_rad,
                    (ahead.roll_rad - behind.roll_rad) / (t1 - t0),
                    now.pitch_rad,
                    (ahead.pitch_rad - behind.pitch_rad) / (t1 - t0),
                )
            }
        };
        let yaw_d = p.psi_d;
        let (sr, cr) = roll.sin_cos();
        let (sth, cth) = pitch.sin_cos();
        let w = Vector3::new(
            roll_d - yaw_d * sth,
            pitch_d * cr + yaw_d * sr * cth,
            -pitch_d * sr + yaw_d * cr * cth,
        );
        Kinematics {
            v_ned_m_s: p.v_ned,
            a_ned_m_s2: p.a_ned,
            rpy_rad: Vector3::new(roll, pitch, p.psi),
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
        // RK4 on (lat, lon, h) (the path's velocity: no attitude needed).
        let rate =
            |t: f64, lat: f64, h: f64| earth::position_rates(lat, h, &self.traj.path(t).v_ned);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// ArduCopter SITL's fitted drag law.
    const SITL_A: f64 = -0.215;
    const SITL_B: f64 = -0.028;

    fn straight(speed: f64, from_speed: f64, ramp_s: f64, duration_s: f64) -> Trajectory {
        Trajectory::new(
            47.02f64.to_radians(),
            (-99.15f64).to_radians(),
            2383.0,
            from_speed,
            0.0,
            vec![Segment {
                duration_s,
                speed_m_s: speed,
                turn_rate_rad_s: 0.0,
                path_angle_rad: 0.0,
                ramp_s,
            }],
        )
    }

    /// The level-flight pitch: `sin(pitch) = D(V cos(pitch)) / g`, solved by bisection.
    fn level_pitch(v: f64, g: f64) -> f64 {
        let law = DragLaw {
            linear_per_s: SITL_A,
            quadratic_per_m: SITL_B,
        };
        let (mut lo, mut hi) = (-1.5f64, 0.0f64);
        for _ in 0..100 {
            let m = 0.5 * (lo + hi);
            if m.sin() - law.force(v * m.cos()) / g < 0.0 {
                lo = m;
            } else {
                hi = m;
            }
        }
        0.5 * (lo + hi)
    }

    #[test]
    fn a_cruising_copter_leans_into_its_drag_and_its_accelerometer_reads_it() {
        for (v, pitch_deg) in [(10.0, -25.5), (12.0, -31.5)] {
            let traj = straight(v, v, 1.0, 60.0).with_multirotor_drag(SITL_A, SITL_B);
            let g = earth::normal_gravity_m_s2(47.02f64.to_radians(), 2383.0);
            let k = traj.kinematics(30.0);
            let pitch = k.rpy_rad.y;
            assert!(
                (pitch - level_pitch(v, g)).abs() < 1e-9,
                "{v} m/s: pitch {} deg, expected {} deg",
                pitch.to_degrees(),
                level_pitch(v, g).to_degrees()
            );
            assert!(
                (pitch.to_degrees() - pitch_deg).abs() < 0.1,
                "{v} m/s: pitch {} deg",
                pitch.to_degrees()
            );
            assert!(k.rpy_rad.x.abs() < 1e-9 && k.rpy_rad.z.abs() < 1e-12);
            assert!(k.w_nb_body_rad_s.norm() < 1e-9, "{:?}", k.w_nb_body_rad_s);
            // The accelerometer (the integrator's exact specific force) against the law at the
            // body-x velocity.
            let mut integ = traj.truth();
            while integ.t_s < 30.0 - 1e-9 {
                integ.step(0.005);
            }
            let st = integ.state();
            let v_b = st.q_nb.inverse() * st.v_ned_m_s;
            let (_, dv) = integ.step(0.005);
            let f_b = dv / 0.005;
            let law = DragLaw {
                linear_per_s: SITL_A,
                quadratic_per_m: SITL_B,
            };
            let want = law.force(v_b.x);
            assert!(
                ((f_b.x - want) / want).abs() < 0.01,
                "{v} m/s: body x {} m/s^2, law {} m/s^2 at {} m/s",
                f_b.x,
                want,
                v_b.x
            );
            // Body y: the Coriolis acceleration the tilt leaves out (2 Omega sin(lat) v).
            assert!(f_b.y.abs() < 2e-3, "{}", f_b.y);
            // Thrust along -z: the rest of gravity.
            assert!(f_b.z < -0.8 * G0 && f_b.z > -G0, "{}", f_b.z);
        }
    }

    #[test]
    fn a_copter_tilts_back_to_brake_and_banks_into_a_turn() {
        // 12 -> 4 m/s in 3 s: a braking copter pitches nose up.
        let traj = straight(4.0, 12.0, 3.0, 10.0).with_multirotor_drag(SITL_A, SITL_B);
        let k = traj.kinematics(1.5);
        assert!(k.a_ned_m_s2.x < -3.5, "{:?}", k.a_ned_m_s2);
        assert!(k.rpy_rad.y > 0.0, "pitch {} deg", k.rpy_rad.y.to_degrees());
        // A right turn at 4 m/s and 18 deg/s banks right.
        let traj = Trajectory::new(
            0.8,
            -1.7,
            2383.0,
            4.0,
            0.0,
            vec![Segment {
                duration_s: 10.0,
                speed_m_s: 4.0,
                turn_rate_rad_s: 18f64.to_radians(),
                path_angle_rad: 0.0,
                ramp_s: 1.0,
            }],
        )
        .with_multirotor_drag(SITL_A, SITL_B);
        let k = traj.kinematics(5.0);
        let bank = (4.0 * 18f64.to_radians() / G0).atan();
        assert!(
            (k.rpy_rad.x - bank).abs() < 1f64.to_radians(),
            "roll {} deg against {} deg",
            k.rpy_rad.x.to_degrees(),
            bank.to_degrees()
        );
        assert!(traj.multirotor_tilt_at(5.0).is_some_and(|t| t.converged));
    }

    /// The body rates (finite differences of roll and pitch, analytic yaw rate) integrate to the
    /// attitude: a copter accelerating, braking and turning.
    #[test]
    fn multirotor_body_rates_integrate_to_its_attitude() {
        let seg = |duration_s: f64, speed_m_s: f64, turn_deg_s: f64, ramp_s: f64| Segment {
            duration_s,
            speed_m_s,
            turn_rate_rad_s: turn_deg_s.to_radians(),
            path_angle_rad: 0.0,
            ramp_s,
        };
        let traj = Trajectory::new(
            0.8,
            -1.7,
            2383.0,
            4.0,
            0.3,
            vec![
                seg(12.0, 12.0, 0.0, 10.0),
                seg(6.0, 4.0, 0.0, 6.0),
                seg(5.0, 4.0, 18.0, 1.0),
                seg(1.0, 4.0, 0.0, 1.0),
                seg(12.0, 12.0, 0.0, 10.0),
            ],
        )
        .with_multirotor_drag(SITL_A, SITL_B);
        let dt = 0.001;
        let mut q = q_of(&traj.kinematics(0.0).rpy_rad);
        let mut t = 0.0;
        let mut worst = 0.0f64;
        while t < traj.duration_s() - 1e-9 {
            let w = traj.kinematics(t + 0.5 * dt).w_nb_body_rad_s;
            q *= UnitQuaternion::from_scaled_axis(w * dt);
            t += dt;
            let truth = q_of(&traj.kinematics(t).rpy_rad);
            worst = worst.max(truth.angle_to(&q));
        }
        // Where the jerk jumps (a ramp starts or ends) the differences spread the step of the
        // pitch rate (0.09 rad/s here) over +-1 ms: the integrated attitude is off by up to
        // step x h / 4 within that millisecond, and exact again after it.
        assert!(worst < 5e-5, "attitude from the rates {worst} rad off");
        let end = q_of(&traj.kinematics(t).rpy_rad).angle_to(&q);
        assert!(
            end < 1e-6,
            "attitude from the rates {end} rad off at the end"
        );
        // The corner turned 90 deg.
        let yaw = traj.kinematics(traj.duration_s()).rpy_rad.z;
        assert!(
            (yaw - 0.3 - std::f64::consts::FRAC_PI_2).abs() < 1e-9,
            "{yaw}"
        );
    }

    #[test]
    fn the_fixed_wing_attitude_is_the_flight_path() {
        let traj = Trajectory::new(
            0.8,
            -1.7,
            2000.0,
            25.0,
            0.0,
            vec![Segment {
                duration_s: 30.0,
                speed_m_s: 25.0,
                turn_rate_rad_s: -4.5f64.to_radians(),
                path_angle_rad: 0.05,
                ramp_s: 3.0,
            }],
        );
        assert!(traj.drag_law().is_none() && traj.multirotor_tilt_at(10.0).is_none());
        let k = traj.kinematics(10.0);
        let roll = (25.0 * -4.5f64.to_radians() / G0).atan();
        assert!((k.rpy_rad.x - roll).abs() < 1e-12 && (k.rpy_rad.y - 0.05).abs() < 1e-12);
    }
}
