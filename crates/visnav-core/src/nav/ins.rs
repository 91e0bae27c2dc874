//! Strapdown inertial navigation in a local-level NED frame on the WGS84 ellipsoid.
//!
//! Follows Sheta 2012 ch. 2 / Savage 1998 ("Strapdown inertial navigation integration algorithm
//! design", parts 1-2) / Shin 2001, with a two-sample (current + previous increment) algorithm:
//!
//! * Attitude: rotation vector with coning correction
//!   `phi_k = dtheta_k + (1/12) dtheta_{k-1} x dtheta_k`, body update `q_{b(k-1) b(k)} = exp(phi_k)`,
//!   navigation-frame update `q_{n(k) n(k-1)} = exp(-zeta_k)`, `zeta_k = w_in^n(k-1/2) dt`,
//!   `q_nb(k) = q_{n(k)n(k-1)} * q_nb(k-1) * q_{b(k-1)b(k)}`.
//! * Velocity: `dv_sf^b = dv_k + 1/2 dtheta_k x dv_k` (rotation) `+ 1/12 (dtheta_{k-1} x dv_k +
//!   dv_{k-1} x dtheta_k)` (sculling); `dv_sf^n = (I - 1/2 [zeta x]) C_b^n(k-1) dv_sf^b`;
//!   `v_k = v_{k-1} + dv_sf^n + (g^n - (2 w_ie^n + w_en^n) x v) dt` with the gravity/Coriolis term
//!   evaluated at the interval midpoint (predictor-corrector).
//! * Position: trapezoidal integration of the geodetic rates with the radii at the midpoint.
//!
//! Conventions: `q_nb` rotates body FRD vectors into NED (`v_ned = q_nb * v_body_frd`); Euler
//! angles are ZYX (yaw, pitch, roll): `C_b^n = Rz(yaw) Ry(pitch) Rx(roll)`. Increments are the
//! integrals over one IMU interval of the body angular rate w.r.t. inertial space (`dtheta`, rad)
//! and of the specific force (`dv`, m/s), both in body FRD.

use super::earth;
use nalgebra::{Matrix3, UnitQuaternion, Vector3};

/// Navigation state of the strapdown integrator.
#[derive(Debug, Clone, PartialEq)]
pub struct InsState {
    /// Geodetic latitude, rad.
    pub lat_rad: f64,
    /// Longitude, rad.
    pub lon_rad: f64,
    /// Height above the WGS84 ellipsoid, m.
    pub h_m: f64,
    /// Velocity w.r.t. the earth in NED, m/s.
    pub v_ned_m_s: Vector3<f64>,
    /// Attitude: rotates body FRD vectors into NED.
    pub q_nb: UnitQuaternion<f64>,
}

impl InsState {
    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.lat_rad.is_finite()
            && self.lon_rad.is_finite()
            && self.h_m.is_finite()
            && self.v_ned_m_s.iter().all(|x| x.is_finite())
            && self.q_nb.coords.iter().all(|x| x.is_finite())
    }
}

/// Strapdown integrator: state plus the previous increments for coning/sculling.
#[derive(Debug, Clone, PartialEq)]
pub struct Strapdown {
    /// Current navigation state.
    pub state: InsState,
    prev_dtheta_rad: Vector3<f64>,
    prev_dv_m_s: Vector3<f64>,
}

fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

impl Strapdown {
    /// Start from `state`; the first step has no previous increment (coning/sculling terms zero).
    pub fn new(state: InsState) -> Self {
        Self {
            state,
            prev_dtheta_rad: Vector3::zeros(),
            prev_dv_m_s: Vector3::zeros(),
        }
    }

    /// Forget the previous increments (after a gap in the IMU stream).
    pub fn clear_history(&mut self) {
        self.prev_dtheta_rad = Vector3::zeros();
        self.prev_dv_m_s = Vector3::zeros();
    }

    /// Advance by one IMU interval of `dt_s` with compensated increments (body FRD).
    pub fn step(&mut self, dtheta_rad: &Vector3<f64>, dv_m_s: &Vector3<f64>, dt_s: f64) {
        let s = &self.state;
        let (lat0, h0, v0) = (s.lat_rad, s.h_m, s.v_ned_m_s);

        // Body-frame corrections.
        let phi = dtheta_rad + self.prev_dtheta_rad.cross(dtheta_rad) / 12.0;
        let dv_rot = 0.5 * dtheta_rad.cross(dv_m_s);
        let dv_scul =
            (self.prev_dtheta_rad.cross(dv_m_s) + self.prev_dv_m_s.cross(dtheta_rad)) / 12.0;
        let dv_sf_b = dv_m_s + dv_rot + dv_scul;
        let c_bn = s.q_nb.to_rotation_matrix().into_inner();

        // Predictor: gravity/Coriolis and w_in at the start of the interval.
        let grav_cor = |lat: f64, h: f64, v: &Vector3<f64>| -> (Vector3<f64>, Vector3<f64>) {
            let w_ie = earth::earth_rate_ned(lat);
            let w_en = earth::transport_rate_ned(lat, h, v);
            let g = Vector3::new(0.0, 0.0, earth::normal_gravity_m_s2(lat, h));
            (g - (2.0 * w_ie + w_en).cross(v), w_ie + w_en)
        };
        let (gc0, w_in0) = grav_cor(lat0, h0, &v0);
        let zeta0 = w_in0 * dt_s;
        let dv_sf_n0 = (Matrix3::identity() - 0.5 * skew(&zeta0)) * c_bn * dv_sf_b;
        let v_pred = v0 + dv_sf_n0 + gc0 * dt_s;
        // Midpoint state.
        let v_mid = 0.5 * (v0 + v_pred);
        let rates0 = earth::position_rates(lat0, h0, &v_mid);
        let lat_mid = lat0 + 0.5 * rates0.x * dt_s;
        let h_mid = h0 + 0.5 * rates0.z * dt_s;
        // Corrector.
        let (gc, w_in) = grav_cor(lat_mid, h_mid, &v_mid);
        let zeta = w_in * dt_s;
        let dv_sf_n = (Matrix3::identity() - 0.5 * skew(&zeta)) * c_bn * dv_sf_b;
        let v1 = v0 + dv_sf_n + gc * dt_s;

        // Attitude.
        let q_b = UnitQuaternion::from_scaled_axis(phi);
        let q_n = UnitQuaternion::from_scaled_axis(-zeta);
        let mut q1 = q_n * s.q_nb * q_b;
        q1.renormalize();

        // Position (trapezoid, radii at midpoint).
        let v_avg = 0.5 * (v0 + v1);
        let rates = earth::position_rates(lat_mid, h_mid, &v_avg);
        let lat1 = lat0 + rates.x * dt_s;
        let mut lon1 = s.lon_rad + rates.y * dt_s;
        if lon1 > std::f64::consts::PI {
            lon1 -= 2.0 * std::f64::consts::PI;
        } else if lon1 < -std::f64::consts::PI {
            lon1 += 2.0 * std::f64::consts::PI;
        }
        let h1 = h0 + rates.z * dt_s;

        self.state = InsState {
            lat_rad: lat1,
            lon_rad: lon1,
            h_m: h1,
            v_ned_m_s: v1,
            q_nb: q1,
        };
        self.prev_dtheta_rad = *dtheta_rad;
        self.prev_dv_m_s = *dv_m_s;
    }
}

/// Skew-symmetric (cross-product) matrix `[v x]`.
pub fn skew_matrix(v: &Vector3<f64>) -> Matrix3<f64> {
    skew(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stationary, level, north-facing IMU at 45 deg: a perfect IMU keeps the state put.
    #[test]
    fn stationary_perfect_imu_short() {
        let lat = 45f64.to_radians();
        let st = InsState {
            lat_rad: lat,
            lon_rad: 0.1,
            h_m: 300.0,
            v_ned_m_s: Vector3::zeros(),
            q_nb: UnitQuaternion::from_euler_angles(0.01, -0.02, 0.7),
        };
        let c_nb = st.q_nb.inverse().to_rotation_matrix().into_inner();
        let w_b = c_nb * earth::earth_rate_ned(lat);
        let f_b = c_nb * Vector3::new(0.0, 0.0, -earth::normal_gravity_m_s2(lat, 300.0));
        let mut ins = Strapdown::new(st.clone());
        let dt = 0.01;
        for _ in 0..6000 {
            ins.step(&(w_b * dt), &(f_b * dt), dt);
        }
        let d = earth::ned_offset_m(
            (ins.state.lat_rad, ins.state.lon_rad, ins.state.h_m),
            (st.lat_rad, st.lon_rad, st.h_m),
        );
        assert!(d.norm() < 0.01, "drift {d:?}");
        assert!(ins.state.v_ned_m_s.norm() < 1e-4);
    }
}
