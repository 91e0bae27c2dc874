//! Local tangent-plane frames (NED and ENU) about a geodetic origin.
//!
//! Conventions (copy of the entries for `docs/conventions.md`):
//! * NED: x north, y east, z down (along the inward ellipsoid normal at the origin); origin at the
//!   `LocalFrame` origin point (including its ellipsoidal height). Suffix `_ned`.
//! * ENU: x east, y north, z up. Suffix `_enu`. ENU = (NED.y, NED.x, -NED.z).
//! * `R_a_b` (written `r_a_b`) rotates vector components from frame b into frame a:
//!   `v_a = R_a_b * v_b`. So `r_ned_ecef()` maps ECEF components to NED components, and
//!   `r_ecef_ned() = r_ned_ecef().transpose()` maps NED components back to ECEF.
//! * Positions: `p_ned = R_ned_ecef (p_ecef - origin_ecef)`, `p_ecef = origin_ecef + R_ecef_ned p_ned`.
//!
//! With phi = origin latitude and lambda = origin longitude (Groves, "Principles of GNSS, Inertial,
//! and Multisensor Integrated Navigation Systems", 2nd ed., chapter 2):
//! ```text
//!              | -sin(phi) cos(lambda)   -sin(phi) sin(lambda)    cos(phi) |
//! R_ned_ecef = | -sin(lambda)             cos(lambda)             0        |
//!              | -cos(phi) cos(lambda)   -cos(phi) sin(lambda)   -sin(phi) |
//! ```
//! The frame is the tangent plane at the origin: it does not follow the earth's curvature, so a
//! point 10 km away on the ellipsoid has a NED z of about +7.8 m (below the plane).

use nalgebra::{Matrix3, Rotation3, Vector3};

use super::ecef::{
    Geodetic, ecef_to_geodetic, meridian_radius_m, prime_vertical_radius_m, sin_cos_deg,
};
use super::error::GeoError;
use super::error::wrap_lon_deg;

/// Rotation taking NED components to ENU components (and, being its own inverse, back):
/// `v_enu = R_ENU_NED * v_ned`.
pub fn r_enu_ned() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(
        0.0, 1.0, 0.0, //
        1.0, 0.0, 0.0, //
        0.0, 0.0, -1.0,
    ))
}

/// NED vector to ENU vector (x east, y north, z up).
pub fn ned_to_enu(v_ned: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(v_ned.y, v_ned.x, -v_ned.z)
}

/// ENU vector to NED vector.
pub fn enu_to_ned(v_enu: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(v_enu.y, v_enu.x, -v_enu.z)
}

/// `R_ned_ecef` for a point at geodetic latitude/longitude (degrees); see the module docs.
pub fn r_ned_ecef_at(lat_deg: f64, lon_deg: f64) -> Rotation3<f64> {
    let (sphi, cphi) = sin_cos_deg(lat_deg);
    let (slam, clam) = sin_cos_deg(lon_deg);
    Rotation3::from_matrix_unchecked(Matrix3::new(
        -sphi * clam,
        -sphi * slam,
        cphi,
        -slam,
        clam,
        0.0,
        -cphi * clam,
        -cphi * slam,
        -sphi,
    ))
}

/// A local tangent frame (NED and ENU) about a fixed geodetic origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalFrame {
    origin: Geodetic,
    origin_ecef_m: Vector3<f64>,
    r_ned_ecef: Rotation3<f64>,
}

impl LocalFrame {
    /// A frame about `origin`; errors if the origin is not finite or its latitude is outside
    /// [-90, 90]. At a pole the frame's north is the direction of the origin's longitude meridian.
    pub fn new(origin: Geodetic) -> Result<Self, GeoError> {
        let origin_ecef_m = origin.to_ecef()?;
        let origin = Geodetic::new(origin.lat_deg, origin.lon_deg, origin.h_ellip_m)?;
        Ok(Self {
            origin,
            origin_ecef_m,
            r_ned_ecef: r_ned_ecef_at(origin.lat_deg, origin.lon_deg),
        })
    }

    /// The origin (longitude wrapped into [-180, 180)).
    pub fn origin(&self) -> Geodetic {
        self.origin
    }

    /// The origin in ECEF, metres.
    pub fn origin_ecef_m(&self) -> Vector3<f64> {
        self.origin_ecef_m
    }

    /// `R_ned_ecef`: `v_ned = r_ned_ecef() * v_ecef`.
    pub fn r_ned_ecef(&self) -> Rotation3<f64> {
        self.r_ned_ecef
    }

    /// `R_ecef_ned`: `v_ecef = r_ecef_ned() * v_ned`.
    pub fn r_ecef_ned(&self) -> Rotation3<f64> {
        self.r_ned_ecef.inverse()
    }

    /// `R_enu_ecef`: `v_enu = r_enu_ecef() * v_ecef`.
    pub fn r_enu_ecef(&self) -> Rotation3<f64> {
        r_enu_ned() * self.r_ned_ecef
    }

    /// `R_ecef_enu`: `v_ecef = r_ecef_enu() * v_enu`.
    pub fn r_ecef_enu(&self) -> Rotation3<f64> {
        self.r_enu_ecef().inverse()
    }

    /// ECEF position (m) to NED position (m) relative to the origin.
    pub fn ecef_to_ned(&self, p_ecef_m: &Vector3<f64>) -> Vector3<f64> {
        self.r_ned_ecef * (p_ecef_m - self.origin_ecef_m)
    }

    /// NED position (m) to ECEF position (m).
    pub fn ned_to_ecef(&self, p_ned_m: &Vector3<f64>) -> Vector3<f64> {
        self.origin_ecef_m + self.r_ned_ecef.inverse() * p_ned_m
    }

    /// ECEF position (m) to ENU position (m) relative to the origin.
    pub fn ecef_to_enu(&self, p_ecef_m: &Vector3<f64>) -> Vector3<f64> {
        ned_to_enu(&self.ecef_to_ned(p_ecef_m))
    }

    /// ENU position (m) to ECEF position (m).
    pub fn enu_to_ecef(&self, p_enu_m: &Vector3<f64>) -> Vector3<f64> {
        self.ned_to_ecef(&enu_to_ned(p_enu_m))
    }

    /// Geodetic position to NED (m); errors on invalid input.
    pub fn geodetic_to_ned(&self, p: &Geodetic) -> Result<Vector3<f64>, GeoError> {
        Ok(self.ecef_to_ned(&p.to_ecef()?))
    }

    /// NED position (m) to geodetic; errors on non-finite input.
    pub fn ned_to_geodetic(&self, p_ned_m: &Vector3<f64>) -> Result<Geodetic, GeoError> {
        ecef_to_geodetic(&self.ned_to_ecef(p_ned_m))
    }

    /// Geodetic position to ENU (m); errors on invalid input.
    pub fn geodetic_to_enu(&self, p: &Geodetic) -> Result<Vector3<f64>, GeoError> {
        Ok(self.ecef_to_enu(&p.to_ecef()?))
    }

    /// ENU position (m) to geodetic; errors on non-finite input.
    pub fn enu_to_geodetic(&self, p_enu_m: &Vector3<f64>) -> Result<Geodetic, GeoError> {
        ecef_to_geodetic(&self.enu_to_ecef(p_enu_m))
    }
}

/// A geodetic position moved by a small NED displacement with the meridian and prime-vertical
/// radii of curvature at the start point.
pub fn offset_geodetic(
    lat_deg: f64,
    lon_deg: f64,
    alt_m: f64,
    d_ned_m: &Vector3<f64>,
) -> (f64, f64, f64) {
    let dlat = d_ned_m.x / (meridian_radius_m(lat_deg) + alt_m);
    let dlon =
        d_ned_m.y / ((prime_vertical_radius_m(lat_deg) + alt_m) * lat_deg.to_radians().cos());
    (
        lat_deg + dlat.to_degrees(),
        wrap_lon_deg(lon_deg + dlon.to_degrees()),
        alt_m - d_ned_m.z,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn frame(lat: f64, lon: f64, h: f64) -> LocalFrame {
        LocalFrame::new(Geodetic::new(lat, lon, h).unwrap()).unwrap()
    }

    /// Published example: GeographicLib CartConvert(1) manual page, EXAMPLES
    /// (https://geographiclib.sourceforge.io/C++/doc/CartConvert.1.html):
    /// `echo 33.3 44.4 6000 | CartConvert -l 33 44 20` => `37288.97 33374.29 5783.64`
    /// (local cartesian: x east, y north, z up, i.e. our ENU). PROJ 9.5.1 (`+proj=cart` then
    /// `+proj=topocentric +lat_0=33 +lon_0=44 +h_0=20`, via pyproj 3.7.2) gives
    /// (37288.973197, 33374.294947, 5783.646616): the manual's z is 6.6 mm lower than both PROJ and
    /// this code (it appears truncated rather than rounded), so the manual is checked to 1 cm and
    /// PROJ to 1 micrometre.
    #[test]
    fn cartconvert_local_example() {
        let f = frame(33.0, 44.0, 20.0);
        let p = Geodetic::new(33.3, 44.4, 6000.0).unwrap();
        let enu = f.geodetic_to_enu(&p).unwrap();
        assert!(
            (enu - Vector3::new(37_288.97, 33_374.29, 5_783.64))
                .abs()
                .max()
                < 0.01,
            "{enu:?}"
        );
        let proj = Vector3::new(37_288.973_197, 33_374.294_947, 5_783.646_616);
        assert!((enu - proj).abs().max() < 1e-6, "{enu:?}");
        let ned = f.geodetic_to_ned(&p).unwrap();
        assert!((ned - Vector3::new(proj.y, proj.x, -proj.z)).abs().max() < 1e-6);
        let back = f.enu_to_geodetic(&proj).unwrap();
        assert!((back.lat_deg - 33.3).abs() < 1e-10 && (back.lon_deg - 44.4).abs() < 1e-10);
        assert!((back.h_ellip_m - 6000.0).abs() < 1e-5);
    }

    #[test]
    fn axes_point_where_documented() {
        let f = frame(-33.7, 24.4, 500.0);
        let o = f.origin_ecef_m();
        // 1 m north (along the meridian) changes latitude only; "down" moves towards lower height.
        let north = f.ned_to_geodetic(&Vector3::new(1.0, 0.0, 0.0)).unwrap();
        assert!(north.lat_deg > -33.7 && (north.lon_deg - 24.4).abs() < 1e-12);
        let east = f.ned_to_geodetic(&Vector3::new(0.0, 1.0, 0.0)).unwrap();
        assert!(east.lon_deg > 24.4 && (east.lat_deg + 33.7).abs() < 1e-9);
        let down = f.ned_to_geodetic(&Vector3::new(0.0, 0.0, 1.0)).unwrap();
        assert!((down.h_ellip_m - 499.0).abs() < 1e-6);
        // Up in ENU is minus down in NED.
        assert!((f.enu_to_ecef(&Vector3::z()) - f.ned_to_ecef(&-Vector3::z())).norm() < 1e-9);
        // Matrix form: the rows of R_ned_ecef are the N, E, D unit vectors in ECEF.
        let r = f.r_ned_ecef();
        let d_ecef = r.inverse() * Vector3::z();
        assert!((f.ned_to_ecef(&Vector3::z()) - o - d_ecef).norm() < 1e-9);
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
        assert!((r.matrix() * r.matrix().transpose() - Matrix3::identity()).norm() < 1e-12);
        assert!((f.r_enu_ecef().matrix() - r_enu_ned().matrix() * r.matrix()).norm() < 1e-15);
        assert!(
            (f.r_ecef_enu() * f.r_enu_ecef())
                .matrix()
                .is_identity(1e-12)
        );
    }

    #[test]
    fn pole_and_bad_origin() {
        // At the north pole, north points along the origin meridian towards the far side.
        let f = frame(90.0, 0.0, 0.0);
        let r = f.r_ned_ecef();
        assert!((r * Vector3::new(-1.0, 0.0, 0.0) - Vector3::x()).norm() < 1e-12);
        assert!((r * Vector3::new(0.0, 0.0, -1.0) - Vector3::z()).norm() < 1e-12);
        let bad = Geodetic {
            lat_deg: f64::NAN,
            lon_deg: 0.0,
            h_ellip_m: 0.0,
        };
        assert!(LocalFrame::new(bad).is_err());
        assert!(
            f.ned_to_geodetic(&Vector3::new(f64::NAN, 0.0, 0.0))
                .is_err()
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(1000))]

        #[test]
        fn ned_enu_round_trips(lat0 in -90.0f64..=90.0, lon0 in -180.0f64..180.0, h0 in -500.0f64..5000.0,
                               n in -50_000.0f64..50_000.0, e in -50_000.0f64..50_000.0,
                               d in -10_000.0f64..1_000.0) {
            let f = frame(lat0, lon0, h0);
            let p_ned = Vector3::new(n, e, d);
            // NED -> geodetic -> NED.
            let g = f.ned_to_geodetic(&p_ned).unwrap();
            let back = f.geodetic_to_ned(&g).unwrap();
            prop_assert!((back - p_ned).norm() < 1e-4, "{p_ned:?} -> {g:?} -> {back:?}");
            // ENU is the axis swap of NED, both ways.
            let p_enu = f.geodetic_to_enu(&g).unwrap();
            prop_assert!((p_enu - ned_to_enu(&back)).norm() < 1e-6);
            let g2 = f.enu_to_geodetic(&p_enu).unwrap();
            prop_assert!((f.geodetic_to_ned(&g2).unwrap() - p_ned).norm() < 1e-4);
            // ECEF <-> NED is an isometry.
            let p_ecef = f.ned_to_ecef(&p_ned);
            prop_assert!(((p_ecef - f.origin_ecef_m()).norm() - p_ned.norm()).abs() < 1e-6);
            prop_assert!((f.ecef_to_ned(&p_ecef) - p_ned).norm() < 1e-6);
        }

        /// Geodetic -> NED -> geodetic for points around the origin.
        #[test]
        fn geodetic_ned_round_trip(lat0 in -89.0f64..89.0, lon0 in -180.0f64..180.0,
                                   dlat in -0.5f64..0.5, dlon in -0.5f64..0.5, h in -100.0f64..10_000.0) {
            let f = frame(lat0, lon0, 100.0);
            let g = Geodetic::new(lat0 + dlat, lon0 + dlon, h).unwrap();
            let back = f.ned_to_geodetic(&f.geodetic_to_ned(&g).unwrap()).unwrap();
            let err = (back.to_ecef().unwrap() - g.to_ecef().unwrap()).norm();
            prop_assert!(err < 1e-4, "{g:?} -> {back:?}: {err} m");
        }
    }
}
