//! WGS84 geodetic coordinates and their conversion to and from ECEF.
//!
//! * ECEF (earth-centred, earth-fixed, WGS84): x through (lat 0, lon 0), y through (lat 0, lon 90 E),
//!   z through the north pole; metres. Vectors in this frame carry the suffix `_ecef`.
//! * Geodetic: latitude and longitude in degrees (north and east positive), height above the WGS84
//!   ellipsoid `h_ellip_m` (not above mean sea level: see `geo::geoid` for that).
//!
//! Forward: the closed form X = (N + h) cos(lat) cos(lon), Y = (N + h) cos(lat) sin(lon),
//! Z = (N (1 - e^2) + h) sin(lat), with N = a / sqrt(1 - e^2 sin^2 lat) (NIMA TR8350.2, eq. 4-14).
//!
//! Inverse: the exact closed-form solution of H. Vermeille, "An analytical method to transform
//! geocentric into geodetic coordinates", J. Geodesy 85 (2011) 105-117, in the arrangement of
//! GeographicLib's `Geocentric::IntReverse` (C. F. F. Karney), which stays accurate at the poles,
//! on the equator, far from the earth and inside the evolute near the centre. Round trips agree to
//! far below a millimetre everywhere (see the property tests).

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use super::error::{GeoError, check_finite, check_lat_deg, wrap_lon_deg};
use super::wgs84::{A_M, E2, F};

/// A WGS84 geodetic position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Geodetic {
    /// Geodetic latitude, degrees, north positive, in [-90, 90].
    pub lat_deg: f64,
    /// Longitude, degrees, east positive (any finite value; results use [-180, 180)).
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, metres.
    pub h_ellip_m: f64,
}

impl Geodetic {
    /// A validated geodetic position: all fields finite and |lat| <= 90 deg. The longitude is
    /// wrapped into [-180, 180).
    pub fn new(lat_deg: f64, lon_deg: f64, h_ellip_m: f64) -> Result<Self, GeoError> {
        let g = Self {
            lat_deg,
            lon_deg,
            h_ellip_m,
        };
        g.validate()?;
        Ok(Self {
            lon_deg: wrap_lon_deg(lon_deg),
            ..g
        })
    }

    /// Checks that the (public) fields hold a usable position.
    pub fn validate(&self) -> Result<(), GeoError> {
        check_lat_deg(self.lat_deg)?;
        check_finite("lon_deg", self.lon_deg)?;
        check_finite("h_ellip_m", self.h_ellip_m)?;
        Ok(())
    }

    /// ECEF position of this point, metres.
    pub fn to_ecef(&self) -> Result<Vector3<f64>, GeoError> {
        self.validate()?;
        Ok(geodetic_to_ecef_unchecked(
            self.lat_deg,
            self.lon_deg,
            self.h_ellip_m,
        ))
    }

    /// Geodetic position of an ECEF point (metres); errors only on non-finite input.
    pub fn from_ecef(p_ecef_m: &Vector3<f64>) -> Result<Self, GeoError> {
        ecef_to_geodetic(p_ecef_m)
    }
}

/// Prime-vertical radius of curvature N(lat) = a / sqrt(1 - e^2 sin^2 lat), metres.
pub fn prime_vertical_radius_m(lat_deg: f64) -> f64 {
    let s = lat_deg.to_radians().sin();
    A_M / (1.0 - E2 * s * s).sqrt()
}

/// Meridian radius of curvature M(lat) = a (1 - e^2) / (1 - e^2 sin^2 lat)^(3/2), metres.
pub fn meridian_radius_m(lat_deg: f64) -> f64 {
    let s = lat_deg.to_radians().sin();
    let w2 = 1.0 - E2 * s * s;
    A_M * (1.0 - E2) / (w2 * w2.sqrt())
}

/// Geodetic (degrees, metres above the ellipsoid) to ECEF (metres), with input validation.
pub fn geodetic_to_ecef(
    lat_deg: f64,
    lon_deg: f64,
    h_ellip_m: f64,
) -> Result<Vector3<f64>, GeoError> {
    Geodetic {
        lat_deg,
        lon_deg,
        h_ellip_m,
    }
    .to_ecef()
}

/// Forward conversion without validation (callers have validated).
pub(crate) fn geodetic_to_ecef_unchecked(
    lat_deg: f64,
    lon_deg: f64,
    h_ellip_m: f64,
) -> Vector3<f64> {
    let (sphi, cphi) = sin_cos_deg(lat_deg);
    let (slam, clam) = sin_cos_deg(lon_deg);
    let n = A_M / (1.0 - E2 * sphi * sphi).sqrt();
    let r = (n + h_ellip_m) * cphi;
    Vector3::new(r * clam, r * slam, (n * (1.0 - E2) + h_ellip_m) * sphi)
}

/// sin and cos of an angle in degrees, exact at multiples of 90 deg (so that cos(90 deg) is 0 and
/// points on the pole have x = y = 0 exactly).
pub(crate) fn sin_cos_deg(x_deg: f64) -> (f64, f64) {
    // Reduce to [-45, 45] about the nearest quadrant, as GeographicLib's Math::sincosd does.
    let r = x_deg.rem_euclid(360.0);
    let q = (r / 90.0).round();
    let t = (r - 90.0 * q).to_radians();
    let (s, c) = t.sin_cos();
    match (q as i64).rem_euclid(4) {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// ECEF (metres) to geodetic, exact closed form (Vermeille 2011 / GeographicLib).
pub fn ecef_to_geodetic(p_ecef_m: &Vector3<f64>) -> Result<Geodetic, GeoError> {
    let x = check_finite("x_ecef_m", p_ecef_m.x)?;
    let y = check_finite("y_ecef_m", p_ecef_m.y)?;
    let z = check_finite("z_ecef_m", p_ecef_m.z)?;

    let e2m = (1.0 - F) * (1.0 - F); // 1 - e^2
    let e4a = E2 * E2;
    // Beyond this radius squaring would overflow; treat the earth as a point (GeographicLib).
    let max_rad = 2.0 * A_M / f64::EPSILON;

    let mut r = x.hypot(y);
    let (slam, clam) = if r != 0.0 { (y / r, x / r) } else { (0.0, 1.0) };
    let mut h = r.hypot(z);
    let (sphi, cphi);
    if h > max_rad {
        // Far away: the geodetic and geocentric latitudes coincide.
        r = (x / 2.0).hypot(y / 2.0);
        let hh = (z / 2.0).hypot(r);
        sphi = (z / 2.0) / hh;
        cphi = r / hh;
        // h stays the distance from the centre (minus a, negligible at this range).
    } else {
        let p = (r / A_M) * (r / A_M);
        let q = e2m * (z / A_M) * (z / A_M);
        let rr = (p + q - e4a) / 6.0;
        if !(e4a * q == 0.0 && rr <= 0.0) {
            // Vermeille (2011) eqs. (19)-(24).
            let s = e4a * p * q / 4.0;
            let r2 = rr * rr;
            let r3 = rr * r2;
            let disc = s * (2.0 * r3 + s);
            let mut u = rr;
            if disc >= 0.0 {
                let mut t3 = s + r3;
                // Pick the sign of the root that avoids cancellation.
                t3 += if t3 < 0.0 { -disc.sqrt() } else { disc.sqrt() };
                let t = t3.cbrt();
                u += t + if t != 0.0 { r2 / t } else { 0.0 };
            } else {
                // Inside the evolute, off the equatorial plane: trigonometric solution.
                let ang = (-disc).sqrt().atan2(-(s + r3));
                u += 2.0 * rr * (ang / 3.0).cos();
            }
            let v = (u * u + e4a * q).sqrt();
            let uv = if u < 0.0 { e4a * q / (v - u) } else { u + v };
            let w = (E2 * (uv - q) / (2.0 * v)).max(0.0);
            let k = uv / ((uv + w * w).sqrt() + w);
            let k1 = k;
            let k2 = k + E2;
            let d = k1 * r / k2;
            let hh = (z / k1).hypot(r / k2);
            sphi = (z / k1) / hh;
            cphi = (r / k2) / hh;
            h = (1.0 - e2m / k1) * d.hypot(z);
        } else {
            // On the singular disc of the equatorial plane within the evolute (|r| < a e^2).
            let zz = ((e4a - p) / e2m).sqrt();
            let xx = p.sqrt();
            let hh = zz.hypot(xx);
            sphi = if z < 0.0 { -zz / hh } else { zz / hh };
            cphi = xx / hh;
            h = -A_M * e2m * hh / E2;
        }
    }
    let lat_deg = sphi.atan2(cphi).to_degrees();
    let lon_deg = wrap_lon_deg(slam.atan2(clam).to_degrees());
    Ok(Geodetic {
        lat_deg,
        lon_deg,
        h_ellip_m: h,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::wgs84::B_M;
    use proptest::prelude::*;

    fn ecef_err_m(g: &Geodetic, back: &Geodetic) -> f64 {
        let a = geodetic_to_ecef_unchecked(g.lat_deg, g.lon_deg, g.h_ellip_m);
        let b = geodetic_to_ecef_unchecked(back.lat_deg, back.lon_deg, back.h_ellip_m);
        (a - b).norm()
    }

    #[test]
    fn axes_and_poles() {
        let p = geodetic_to_ecef(0.0, 0.0, 0.0).unwrap();
        assert!((p - Vector3::new(A_M, 0.0, 0.0)).norm() < 1e-9);
        let p = geodetic_to_ecef(0.0, 90.0, 10.0).unwrap();
        assert!((p - Vector3::new(0.0, A_M + 10.0, 0.0)).norm() < 1e-9);
        let p = geodetic_to_ecef(90.0, 33.0, 0.0).unwrap();
        assert_eq!(p.x, 0.0);
        assert_eq!(p.y, 0.0);
        assert!((p.z - B_M).abs() < 1e-9);
        let g = ecef_to_geodetic(&Vector3::new(0.0, 0.0, -B_M - 123.0)).unwrap();
        assert_eq!(g.lat_deg, -90.0);
        assert!((g.h_ellip_m - 123.0).abs() < 1e-9);
        let g = ecef_to_geodetic(&Vector3::new(0.0, 0.0, B_M + 5.0)).unwrap();
        assert_eq!(g.lat_deg, 90.0);
        assert!((g.h_ellip_m - 5.0).abs() < 1e-9);
        // Centre of the earth: defined, finite output (on the singular disc).
        let g = ecef_to_geodetic(&Vector3::zeros()).unwrap();
        assert!(g.lat_deg.is_finite() && g.h_ellip_m.is_finite());
        assert!((g.h_ellip_m + B_M).abs() < 1e-6, "{g:?}");
    }

    /// Published example: GeographicLib CartConvert(1) manual page, EXAMPLES
    /// (https://geographiclib.sourceforge.io/C++/doc/CartConvert.1.html):
    /// `echo 33.3 44.4 6000 | CartConvert` => `3816209.60 3737108.55 3485109.57` and
    /// `echo 30000 30000 0 | CartConvert -r` => `6.483 45 -6335709.73` (a point deep inside the earth).
    #[test]
    fn cartconvert_examples() {
        let p = geodetic_to_ecef(33.3, 44.4, 6000.0).unwrap();
        assert!((p.x - 3_816_209.60).abs() < 0.006, "{p:?}");
        assert!((p.y - 3_737_108.55).abs() < 0.006, "{p:?}");
        assert!((p.z - 3_485_109.57).abs() < 0.006, "{p:?}");
        let g = ecef_to_geodetic(&Vector3::new(3_816_209.60, 3_737_108.55, 3_485_109.57)).unwrap();
        assert!((g.lat_deg - 33.3).abs() < 1e-7, "{g:?}");
        assert!((g.lon_deg - 44.4).abs() < 1e-7, "{g:?}");
        assert!((g.h_ellip_m - 6000.0).abs() < 0.01, "{g:?}");
        let g = ecef_to_geodetic(&Vector3::new(30_000.0, 30_000.0, 0.0)).unwrap();
        assert!((g.lat_deg - 6.483).abs() < 0.0006, "{g:?}");
        assert!((g.lon_deg - 45.0).abs() < 1e-12, "{g:?}");
        assert!((g.h_ellip_m + 6_335_709.73).abs() < 0.006, "{g:?}");
    }

    #[test]
    fn rejects_bad_input() {
        assert!(matches!(
            geodetic_to_ecef(91.0, 0.0, 0.0),
            Err(GeoError::LatitudeOutOfRange { .. })
        ));
        assert!(matches!(
            geodetic_to_ecef(f64::NAN, 0.0, 0.0),
            Err(GeoError::NonFinite { .. })
        ));
        assert!(geodetic_to_ecef(0.0, f64::INFINITY, 0.0).is_err());
        assert!(geodetic_to_ecef(0.0, 0.0, f64::NAN).is_err());
        assert!(ecef_to_geodetic(&Vector3::new(f64::NAN, 0.0, 0.0)).is_err());
        assert!(Geodetic::new(-90.000001, 0.0, 0.0).is_err());
        assert_eq!(Geodetic::new(10.0, 190.0, 0.0).unwrap().lon_deg, -170.0);
    }

    #[test]
    fn radii_of_curvature() {
        // At the equator M = a (1 - e^2), N = a; at the poles M = N = a^2 / b.
        assert!((meridian_radius_m(0.0) - A_M * (1.0 - E2)).abs() < 1e-6);
        assert!((prime_vertical_radius_m(0.0) - A_M).abs() < 1e-9);
        assert!((meridian_radius_m(90.0) - A_M * A_M / B_M).abs() < 1e-6);
        assert!((prime_vertical_radius_m(-90.0) - A_M * A_M / B_M).abs() < 1e-6);
    }

    #[test]
    fn sin_cos_deg_exact_quadrants() {
        assert_eq!(sin_cos_deg(90.0), (1.0, 0.0));
        assert_eq!(sin_cos_deg(-90.0), (-1.0, 0.0));
        assert_eq!(sin_cos_deg(180.0), (0.0, -1.0));
        let (s, c) = sin_cos_deg(33.0);
        assert!((s - 33f64.to_radians().sin()).abs() < 1e-15);
        assert!((c - 33f64.to_radians().cos()).abs() < 1e-15);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        /// Round trip near the earth (aircraft to satellites): < 0.1 mm in position.
        #[test]
        fn round_trip_near_earth(lat in -90.0f64..=90.0, lon in -180.0f64..180.0,
                                 h in -10_000.0f64..1_000_000.0) {
            let g = Geodetic::new(lat, lon, h).unwrap();
            let back = ecef_to_geodetic(&g.to_ecef().unwrap()).unwrap();
            prop_assert!(ecef_err_m(&g, &back) < 1e-4, "{g:?} -> {back:?}");
            prop_assert!((back.h_ellip_m - h).abs() < 1e-4);
            prop_assert!((back.lat_deg - lat).abs() < 1e-9);
        }

        /// Points within 1 km of the poles and at exact poles.
        #[test]
        fn round_trip_poles(dlat in 0.0f64..0.01, lon in -180.0f64..180.0, h in -5_000.0f64..50_000.0,
                            north in any::<bool>()) {
            let lat = if north { 90.0 - dlat } else { -90.0 + dlat };
            let g = Geodetic::new(lat, lon, h).unwrap();
            let back = ecef_to_geodetic(&g.to_ecef().unwrap()).unwrap();
            prop_assert!(ecef_err_m(&g, &back) < 1e-4, "{g:?} -> {back:?}");
            prop_assert!((back.h_ellip_m - h).abs() < 1e-4);
        }

        /// ECEF -> geodetic -> ECEF for arbitrary points, including deep inside the earth.
        #[test]
        fn round_trip_from_ecef(x in -2.0e7f64..2.0e7, y in -2.0e7f64..2.0e7, z in -2.0e7f64..2.0e7) {
            let p = Vector3::new(x, y, z);
            let g = ecef_to_geodetic(&p).unwrap();
            prop_assert!(g.lat_deg.is_finite() && g.lon_deg.is_finite() && g.h_ellip_m.is_finite());
            let q = geodetic_to_ecef_unchecked(g.lat_deg, g.lon_deg, g.h_ellip_m);
            // Relative accuracy: 1e-4 m near the surface, slightly more for far points.
            prop_assert!((p - q).norm() < 1e-4 + 1e-13 * p.norm(), "{p:?} -> {g:?} -> {q:?}");
        }
    }
}
