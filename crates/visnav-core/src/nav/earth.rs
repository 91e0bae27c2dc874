//! Earth model for local-level (NED) mechanization on the WGS84 ellipsoid.
//!
//! * Radii of curvature: meridian `R_M = a (1 - e^2) / (1 - e^2 sin^2 lat)^(3/2)`, transverse
//!   (prime vertical) `R_N = a / sqrt(1 - e^2 sin^2 lat)` (Sheta 2012 ch. 2; Titterton & Weston 3.7).
//! * Normal gravity (Somigliana closed form with the height series, Sheta 2012 eq. 2.x, after
//!   Schwarz & Wei 1990):
//!   `g = a1 (1 + a2 sin^2 lat + a3 sin^4 lat) + (a4 + a5 sin^2 lat) h + a6 h^2`, positive down.
//! * Earth rate in NED: `w_ie^n = [W cos lat, 0, -W sin lat]`.
//! * Transport rate in NED: `w_en^n = [vE/(R_N+h), -vN/(R_M+h), -vE tan(lat)/(R_N+h)]`.
//!
//! Angles are radians, `h_m` is the height above the WGS84 ellipsoid in metres.

use crate::geo::wgs84;
use nalgebra::Vector3;

/// Somigliana/normal-gravity coefficients a1..a6 (m/s^2, 1, 1, 1/s^2, 1/s^2, 1/(m s^2)).
pub const GRAVITY_A: [f64; 6] = [
    9.780_326_771_4,
    0.005_279_041_4,
    0.000_023_271_8,
    -0.000_003_087_691_089,
    0.000_000_004_397_731_1,
    0.000_000_000_000_721_1,
];

/// Meridian (`R_M`) and transverse (`R_N`) radii of curvature, metres.
pub fn radii_m(lat_rad: f64) -> (f64, f64) {
    let s = lat_rad.sin();
    let w2 = 1.0 - wgs84::E2 * s * s;
    let w = w2.sqrt();
    let rn = wgs84::A_M / w;
    let rm = wgs84::A_M * (1.0 - wgs84::E2) / (w2 * w);
    (rm, rn)
}

/// Magnitude of normal gravity (positive, pointing down in NED), m/s^2.
pub fn normal_gravity_m_s2(lat_rad: f64, h_m: f64) -> f64 {
    let s2 = lat_rad.sin().powi(2);
    let [a1, a2, a3, a4, a5, a6] = GRAVITY_A;
    a1 * (1.0 + a2 * s2 + a3 * s2 * s2) + (a4 + a5 * s2) * h_m + a6 * h_m * h_m
}

/// Earth rotation rate expressed in NED, rad/s.
pub fn earth_rate_ned(lat_rad: f64) -> Vector3<f64> {
    let w = wgs84::OMEGA_E_RAD_S;
    Vector3::new(w * lat_rad.cos(), 0.0, -w * lat_rad.sin())
}

/// Transport rate (rotation of NED w.r.t. the earth) in NED, rad/s.
pub fn transport_rate_ned(lat_rad: f64, h_m: f64, v_ned_m_s: &Vector3<f64>) -> Vector3<f64> {
    let (rm, rn) = radii_m(lat_rad);
    Vector3::new(
        v_ned_m_s.y / (rn + h_m),
        -v_ned_m_s.x / (rm + h_m),
        -v_ned_m_s.y * lat_rad.tan() / (rn + h_m),
    )
}

/// Geodetic position rates (lat, lon, h) from NED velocity.
pub fn position_rates(lat_rad: f64, h_m: f64, v_ned_m_s: &Vector3<f64>) -> Vector3<f64> {
    let (rm, rn) = radii_m(lat_rad);
    Vector3::new(
        v_ned_m_s.x / (rm + h_m),
        v_ned_m_s.y / ((rn + h_m) * lat_rad.cos()),
        -v_ned_m_s.z,
    )
}

/// NED offset (metres) of geodetic point `a` relative to `b`, first order (small separations):
/// `[dlat (R_M+h), dlon (R_N+h) cos lat, -(h_a - h_b)]`, evaluated at `b`.
pub fn ned_offset_m(a: (f64, f64, f64), b: (f64, f64, f64)) -> Vector3<f64> {
    let (rm, rn) = radii_m(b.0);
    let mut dlon = a.1 - b.1;
    if dlon > std::f64::consts::PI {
        dlon -= 2.0 * std::f64::consts::PI;
    } else if dlon < -std::f64::consts::PI {
        dlon += 2.0 * std::f64::consts::PI;
    }
    Vector3::new(
        (a.0 - b.0) * (rm + b.2),
        dlon * (rn + b.2) * b.0.cos(),
        -(a.2 - b.2),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Geodetic offsets built from the radii of curvature come back through `ned_offset_m`.
        #[test]
        fn ned_offset_round_trip(lat in -1.4f64..1.4, lon in -3.1f64..3.1, h in -100.0f64..5000.0,
                                 dn in -500.0f64..500.0, de in -500.0f64..500.0, dd in -100.0f64..100.0) {
            let (rm, rn) = radii_m(lat);
            let a = (lat + dn / (rm + h), lon + de / ((rn + h) * lat.cos()), h - dd);
            let d = ned_offset_m(a, (lat, lon, h));
            prop_assert!((d - Vector3::new(dn, de, dd)).norm() < 1e-6);
        }
    }

    #[test]
    fn gravity_equator_and_pole() {
        // Somigliana normal gravity on the ellipsoid: 9.7803267714 (equator), 9.8321863685 (pole).
        assert!((normal_gravity_m_s2(0.0, 0.0) - 9.780_326_771_4).abs() < 1e-9);
        let pole = normal_gravity_m_s2(std::f64::consts::FRAC_PI_2, 0.0);
        assert!((pole - 9.832_186_368_5).abs() < 5e-5, "{pole}");
        // Free-air gradient about -3.086e-6 1/s^2.
        let g0 = normal_gravity_m_s2(0.8, 0.0);
        let g1 = normal_gravity_m_s2(0.8, 1000.0);
        assert!(((g1 - g0) / 1000.0 + 3.086e-6).abs() < 2e-8);
    }

    #[test]
    fn radii_limits() {
        let (rm, rn) = radii_m(0.0);
        assert!((rn - wgs84::A_M).abs() < 1e-6);
        assert!((rm - wgs84::A_M * (1.0 - wgs84::E2)).abs() < 1e-6);
        let (rm, rn) = radii_m(std::f64::consts::FRAC_PI_2);
        assert!((rm - rn).abs() < 1e-6);
    }
}
