//! The local horizontal frame an autopilot keeps about its EKF origin, as the autopilot itself
//! computes it.
//!
//! A local position sent to an autopilot (VISION_POSITION_ESTIMATE, ODOMETRY) is fused in the
//! autopilot's own local frame and turned back into latitude and longitude with the autopilot's
//! own projection; waypoints given in latitude and longitude go through the same projection. The
//! exact tangent plane is therefore not what makes the autopilot's position right: the
//! autopilot's projection is. ArduPilot's and PX4's differ from the exact local frame by
//! 0.1-0.3 % of the distance from the origin (1.5-2 m at 700 m, 13-30 m at 10 km), which a
//! position estimate good to a metre cannot ignore.
//!
//! * [`AutopilotFrame::ArduPilot`]: `Location::get_distance_NE` / `Location::offset_latlng`
//!   (libraries/AP_Common/Location.cpp, 4.5): an equirectangular projection on a sphere of
//!   radius 6 378 100 m (`RADIUS_OF_EARTH`), `north = dlat * R`, `east = dlon * R *
//!   cos(mean latitude of the origin and the point)` (the cosine at least 0.01), longitudes
//!   wrapped across the antimeridian. EKF3's external navigation position is taken in this frame
//!   (`NavEKF3_core::writeExtNavData`, offsets from the public origin by the same function).
//! * [`AutopilotFrame::Px4`]: `MapProjection::project` / `reproject` (src/lib/geo/geo.cpp): an
//!   azimuthal equidistant projection on a sphere of radius 6 371 000 m
//!   (`CONSTANTS_RADIUS_OF_EARTH`). EKF2 fuses a LOCAL_NED vision position in this frame.
//! * [`AutopilotFrame::Tangent`]: the exact local tangent plane (WGS84, through ECEF), for an
//!   autopilot whose projection is not known.
//!
//! Down, for ArduPilot and PX4, is the altitude difference to the origin (`down = origin alt -
//! alt`, no curvature drop: both keep height as altitude); for the tangent plane it is along the
//! origin's normal (10 km away a point at the origin's altitude is 7.8 m below the plane).
//!
//! The projections are computed in `f64` on continuous angles; ArduPilot's integer 1e-7 degrees
//! (1.1 cm) and both autopilots' `f32` local positions round finer than any fix.

use nalgebra::Vector3;

use super::ecef::{Geodetic, ecef_to_geodetic};
use super::error::wrap_lon_deg;
use super::local::r_ned_ecef_at;

/// ArduPilot's `RADIUS_OF_EARTH` (libraries/AP_Math/definitions.h), m.
pub const ARDUPILOT_EARTH_RADIUS_M: f64 = 6_378_100.0;
/// ArduPilot's `longitude_scale` floor: the cosine of the latitude is not taken below this.
pub const ARDUPILOT_MIN_LONGITUDE_SCALE: f64 = 0.01;
/// PX4's `CONSTANTS_RADIUS_OF_EARTH` (src/lib/geo/geo.h), m.
pub const PX4_EARTH_RADIUS_M: f64 = 6_371_000.0;

/// The autopilot's EKF origin (the local NED frame's origin): latitude and longitude in
/// degrees, altitude above mean sea level in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoOrigin {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude AMSL, metres.
    pub alt_amsl_m: f64,
}

/// Which projection maps latitude and longitude to the autopilot's local north and east (see
/// the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AutopilotFrame {
    /// The exact WGS84 tangent plane at the origin.
    Tangent,
    /// ArduPilot's equirectangular sphere.
    ArduPilot,
    /// PX4's azimuthal equidistant sphere.
    Px4,
}

impl AutopilotFrame {
    /// Local NED position, metres, of a point (latitude, longitude in degrees, altitude AMSL in
    /// metres) about `origin`. Non-finite input gives non-finite output.
    pub fn to_ned(
        self,
        origin: &GeoOrigin,
        lat_deg: f64,
        lon_deg: f64,
        alt_amsl_m: f64,
    ) -> Vector3<f64> {
        let down = origin.alt_amsl_m - alt_amsl_m;
        match self {
            AutopilotFrame::Tangent => tangent_ned(origin, lat_deg, lon_deg, alt_amsl_m),
            AutopilotFrame::ArduPilot => {
                let dlon = wrap_lon_deg(lon_deg - origin.lon_deg);
                let scale = ardupilot_longitude_scale(0.5 * (lat_deg + origin.lat_deg));
                let r = ARDUPILOT_EARTH_RADIUS_M;
                Vector3::new(
                    (lat_deg - origin.lat_deg).to_radians() * r,
                    dlon.to_radians() * r * scale,
                    down,
                )
            }
            AutopilotFrame::Px4 => {
                let (n, e) = px4_project(origin, lat_deg, lon_deg);
                Vector3::new(n, e, down)
            }
        }
    }

    /// The inverse of [`Self::to_ned`]: (latitude, longitude in degrees, altitude AMSL in metres)
    /// of a local NED position about `origin`.
    pub fn from_ned(self, origin: &GeoOrigin, p_ned_m: &Vector3<f64>) -> (f64, f64, f64) {
        let alt = origin.alt_amsl_m - p_ned_m.z;
        match self {
            AutopilotFrame::Tangent => tangent_geodetic(origin, p_ned_m),
            AutopilotFrame::ArduPilot => {
                // offset_latlng: the latitude first, then the longitude scaled at the mean latitude.
                let r = ARDUPILOT_EARTH_RADIUS_M;
                let lat = origin.lat_deg + (p_ned_m.x / r).to_degrees();
                let scale = ardupilot_longitude_scale(0.5 * (lat + origin.lat_deg));
                let lon = wrap_lon_deg(origin.lon_deg + (p_ned_m.y / (r * scale)).to_degrees());
                (lat, lon, alt)
            }
            AutopilotFrame::Px4 => {
                let (lat, lon) = px4_reproject(origin, p_ned_m.x, p_ned_m.y);
                (lat, lon, alt)
            }
        }
    }
}

/// ArduPilot's `longitude_scale`: the cosine of the latitude, at least
/// [`ARDUPILOT_MIN_LONGITUDE_SCALE`].
fn ardupilot_longitude_scale(lat_deg: f64) -> f64 {
    lat_deg
        .to_radians()
        .cos()
        .max(ARDUPILOT_MIN_LONGITUDE_SCALE)
}

/// PX4's `MapProjection::project`: (north, east) metres on the azimuthal equidistant sphere.
fn px4_project(origin: &GeoOrigin, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
    let (s0, c0) = origin.lat_deg.to_radians().sin_cos();
    let (s, c) = lat_deg.to_radians().sin_cos();
    let dlon = (lon_deg - origin.lon_deg).to_radians();
    let cos_dlon = dlon.cos();
    let arg = (s0 * s + c0 * c * cos_dlon).clamp(-1.0, 1.0);
    let angle = arg.acos();
    let k = if angle.abs() > 0.0 {
        angle / angle.sin()
    } else {
        1.0
    };
    (
        k * (c0 * s - s0 * c * cos_dlon) * PX4_EARTH_RADIUS_M,
        k * c * dlon.sin() * PX4_EARTH_RADIUS_M,
    )
}

/// PX4's `MapProjection::reproject`: latitude and longitude, degrees, of (north, east) metres.
fn px4_reproject(origin: &GeoOrigin, north_m: f64, east_m: f64) -> (f64, f64) {
    let (s0, c0) = origin.lat_deg.to_radians().sin_cos();
    let x = north_m / PX4_EARTH_RADIUS_M;
    let y = east_m / PX4_EARTH_RADIUS_M;
    let angle = x.hypot(y);
    if angle.abs() == 0.0 {
        return (origin.lat_deg, origin.lon_deg);
    }
    let (sin_c, cos_c) = angle.sin_cos();
    let lat = (cos_c * s0 + x * sin_c * c0 / angle).asin();
    let dlon = (y * sin_c).atan2(angle * c0 * cos_c - x * s0 * sin_c);
    (
        lat.to_degrees(),
        wrap_lon_deg(origin.lon_deg + dlon.to_degrees()),
    )
}

/// The exact tangent plane: `p_ned = R_ned_ecef(origin) (p_ecef - origin_ecef)`, heights AMSL on
/// both sides (the geoid's slope over a flight area is negligible).
fn tangent_ned(origin: &GeoOrigin, lat_deg: f64, lon_deg: f64, alt_amsl_m: f64) -> Vector3<f64> {
    let ecef = |lat_deg, lon_deg, h_ellip_m| {
        Geodetic {
            lat_deg,
            lon_deg,
            h_ellip_m,
        }
        .to_ecef()
        .unwrap_or_else(|_| Vector3::repeat(f64::NAN))
    };
    let p = ecef(lat_deg, lon_deg, alt_amsl_m);
    let o = ecef(origin.lat_deg, origin.lon_deg, origin.alt_amsl_m);
    r_ned_ecef_at(origin.lat_deg, origin.lon_deg) * (p - o)
}

/// The inverse of [`tangent_ned`], exact (through ECEF); NaN for non-finite input.
fn tangent_geodetic(origin: &GeoOrigin, p_ned_m: &Vector3<f64>) -> (f64, f64, f64) {
    let o = Geodetic {
        lat_deg: origin.lat_deg,
        lon_deg: origin.lon_deg,
        h_ellip_m: origin.alt_amsl_m,
    };
    o.to_ecef()
        .and_then(|o_ecef| {
            ecef_to_geodetic(&(o_ecef + r_ned_ecef_at(o.lat_deg, o.lon_deg).transpose() * p_ned_m))
        })
        .map_or((f64::NAN, f64::NAN, f64::NAN), |g| {
            (g.lat_deg, g.lon_deg, g.h_ellip_m)
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::ecef::{meridian_radius_m, prime_vertical_radius_m};
    use proptest::prelude::*;

    fn origin() -> GeoOrigin {
        GeoOrigin {
            lat_deg: -35.363262,
            lon_deg: 149.165237,
            alt_amsl_m: 584.0,
        }
    }

    /// ArduPilot's own arithmetic on integer 1e-7 degrees (Location.cpp), for a cross-check.
    fn ardupilot_get_distance_ne(o: &GeoOrigin, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
        const LOCATION_SCALING_FACTOR: f64 = 0.011_131_884_502_145_034;
        let (lat0, lng0) = (
            (o.lat_deg * 1e7).round() as i64,
            (o.lon_deg * 1e7).round() as i64,
        );
        let (lat1, lng1) = (
            (lat_deg * 1e7).round() as i64,
            (lon_deg * 1e7).round() as i64,
        );
        let mid = ((lat0 + lat1) / 2) as f64 * 1e-7;
        (
            (lat1 - lat0) as f64 * LOCATION_SCALING_FACTOR,
            (lng1 - lng0) as f64 * LOCATION_SCALING_FACTOR * mid.to_radians().cos().max(0.01),
        )
    }

    #[test]
    fn ardupilot_matches_its_integer_arithmetic() {
        let o = origin();
        for (dlat, dlon) in [
            (0.0063, 0.0),
            (0.0, 0.0087),
            (-0.0121, 0.0245),
            (0.09, -0.11),
        ] {
            let (lat, lon) = (o.lat_deg + dlat, o.lon_deg + dlon);
            let p = AutopilotFrame::ArduPilot.to_ned(&o, lat, lon, 700.0);
            let (n, e) = ardupilot_get_distance_ne(&o, lat, lon);
            assert!(
                (p.x - n).abs() < 0.02 && (p.y - e).abs() < 0.02,
                "{p} against {n}, {e}"
            );
            assert!((p.z - (584.0 - 700.0)).abs() < 1e-12);
        }
    }

    #[test]
    fn px4_matches_a_known_distance() {
        // 0.01 deg of latitude on PX4's sphere is R * 0.01 deg in radians, straight north.
        let o = origin();
        let p = AutopilotFrame::Px4.to_ned(&o, o.lat_deg + 0.01, o.lon_deg, o.alt_amsl_m);
        let expect = PX4_EARTH_RADIUS_M * 0.01_f64.to_radians();
        assert!(
            (p.x - expect).abs() < 1e-6 && p.y.abs() < 1e-9 && p.z == 0.0,
            "{p}"
        );
    }

    #[test]
    fn the_autopilots_differ_from_the_tangent_plane_by_their_radii() {
        // 1 km north and 1 km east: each sphere's radius against the ellipsoid's radii of
        // curvature there (at -35 deg: ArduPilot +0.33 % north, -0.12 % east).
        let o = origin();
        let p_true = Vector3::new(1000.0, 1000.0, 0.0);
        let (lat, lon, alt) = AutopilotFrame::Tangent.from_ned(&o, &p_true);
        let m = meridian_radius_m(o.lat_deg) + o.alt_amsl_m;
        let n = prime_vertical_radius_m(o.lat_deg) + o.alt_amsl_m;
        for (f, r) in [
            (AutopilotFrame::ArduPilot, ARDUPILOT_EARTH_RADIUS_M),
            (AutopilotFrame::Px4, PX4_EARTH_RADIUS_M),
        ] {
            let p = f.to_ned(&o, lat, lon, alt);
            let (rel_n, rel_e) = (p.x / 1000.0 - 1.0, p.y / 1000.0 - 1.0);
            assert!((rel_n - (r / m - 1.0)).abs() < 1e-4, "{f:?} north {rel_n}");
            assert!((rel_e - (r / n - 1.0)).abs() < 1e-4, "{f:?} east {rel_e}");
            // Altitude, not the tangent plane's depth: the point 1.4 km out lies 0.16 m above
            // the origin's altitude, 0 m down on the tangent plane.
            assert!((p.z + 0.157).abs() < 0.002, "{f:?} down {}", p.z);
        }
    }

    #[test]
    fn longitudes_wrap_across_the_antimeridian() {
        let o = GeoOrigin {
            lat_deg: 10.0,
            lon_deg: 179.999,
            alt_amsl_m: 0.0,
        };
        for f in [
            AutopilotFrame::ArduPilot,
            AutopilotFrame::Px4,
            AutopilotFrame::Tangent,
        ] {
            let p = f.to_ned(&o, 10.0, -179.999, 0.0);
            assert!((p.y - 219.0).abs() < 1.0, "{f:?}: {p}");
            let (_, lon, _) = f.from_ned(&o, &p);
            assert!((lon + 179.999).abs() < 1e-9, "{f:?}: {lon}");
        }
    }

    #[test]
    fn non_finite_input_gives_non_finite_output() {
        let o = origin();
        for f in [
            AutopilotFrame::ArduPilot,
            AutopilotFrame::Px4,
            AutopilotFrame::Tangent,
        ] {
            assert!(
                !f.to_ned(&o, f64::NAN, o.lon_deg, 0.0)
                    .iter()
                    .all(|v| v.is_finite())
            );
        }
    }

    proptest! {
        #[test]
        fn from_ned_inverts_to_ned(
            lat0 in -70.0f64..70.0,
            lon0 in -180.0f64..180.0,
            n in -30_000.0f64..30_000.0,
            e in -30_000.0f64..30_000.0,
            d in -3000.0f64..100.0,
        ) {
            let o = GeoOrigin { lat_deg: lat0, lon_deg: lon0, alt_amsl_m: 300.0 };
            let p = Vector3::new(n, e, d);
            for f in [AutopilotFrame::ArduPilot, AutopilotFrame::Px4, AutopilotFrame::Tangent] {
                let (lat, lon, alt) = f.from_ned(&o, &p);
                let back = f.to_ned(&o, lat, lon, alt);
                prop_assert!((back - p).norm() < 1e-4, "{:?}: {} -> {}", f, p, back);
            }
        }
    }
}
