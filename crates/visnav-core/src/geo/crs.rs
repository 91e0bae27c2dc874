//! Coordinate reference systems understood by visnav.
//!
//! All projected systems here are on the WGS84 ellipsoid (NAD83 is treated as WGS84; the difference
//! is below 2 m in the conterminous US, which is documented as a limitation in `docs/conventions.md`).
//! Projected coordinates are `(x_m, y_m)` = (easting, northing) in metres; geographic coordinates are
//! `(lat_deg, lon_deg)`.

use serde::{Deserialize, Serialize};

use crate::validate::{Problems, Validate};

/// A horizontal coordinate reference system.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Crs {
    /// EPSG:4326, x = longitude in degrees, y = latitude in degrees (GeoTIFF axis order).
    Geographic,
    /// Universal Transverse Mercator on WGS84 (EPSG:326zz north, 327zz south; NAD83 269zz treated as WGS84).
    Utm {
        /// Zone number, 1..=60.
        zone: u8,
        /// Northern hemisphere (false northing 0); false: southern (10 000 km).
        north: bool,
    },
    /// Generic transverse Mercator on WGS84: `+proj=tmerc +lat_0 +lon_0 +k +x_0 +y_0`.
    TransverseMercator {
        /// Latitude of origin, degrees.
        lat0_deg: f64,
        /// Central meridian, degrees east.
        lon0_deg: f64,
        /// Scale factor on the central meridian (0.9..1.1).
        k0: f64,
        /// Easting of the origin, metres.
        false_easting_m: f64,
        /// Northing of the origin, metres.
        false_northing_m: f64,
    },
    /// EPSG:3857, spherical ("web") Mercator on the WGS84 semi-major axis.
    WebMercator,
}

/// What a user reads: `UTM zone 10N (WGS84)`, `WGS84 longitude / latitude (EPSG:4326)`, ...
impl std::fmt::Display for Crs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Crs::Geographic => write!(f, "WGS84 longitude / latitude (EPSG:4326)"),
            Crs::Utm { zone, north } => {
                write!(
                    f,
                    "UTM zone {zone}{} (WGS84)",
                    if north { 'N' } else { 'S' }
                )
            }
            Crs::TransverseMercator {
                lat0_deg,
                lon0_deg,
                k0,
                false_easting_m,
                false_northing_m,
            } => write!(
                f,
                "transverse Mercator on WGS84 (lat_0 {lat0_deg} deg, lon_0 {lon0_deg} deg, \
                 k {k0}, x_0 {false_easting_m} m, y_0 {false_northing_m} m)"
            ),
            Crs::WebMercator => write!(f, "web Mercator (EPSG:3857)"),
        }
    }
}

/// A CRS given in a configuration (`[map] crs_override`): its parameters in range.
impl Validate for Crs {
    fn validate(&self, p: &mut Problems) {
        match *self {
            Crs::Geographic | Crs::WebMercator => {}
            Crs::Utm { zone, .. } => {
                if !(1..=60).contains(&zone) {
                    p.push("zone", format!("{zone} is not a UTM zone (1..=60)"));
                }
            }
            Crs::TransverseMercator {
                lat0_deg,
                lon0_deg,
                k0,
                false_easting_m,
                false_northing_m,
            } => {
                p.range("lat0_deg", lat0_deg, -90.0, 90.0);
                p.range("lon0_deg", lon0_deg, -180.0, 180.0);
                p.range("k0", k0, 0.9, 1.1);
                p.range("false_easting_m", false_easting_m, -1e8, 1e8);
                p.range("false_northing_m", false_northing_m, -1e8, 1e8);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Crs;

    /// What a user reads names the projection, never the Rust structure.
    #[test]
    fn a_crs_is_shown_in_words() {
        let utm = Crs::Utm {
            zone: 10,
            north: true,
        };
        assert_eq!(utm.to_string(), "UTM zone 10N (WGS84)");
        let south = Crs::Utm {
            zone: 34,
            north: false,
        };
        assert_eq!(south.to_string(), "UTM zone 34S (WGS84)");
        let tm = Crs::TransverseMercator {
            lat0_deg: 0.0,
            lon0_deg: 25.0,
            k0: 1.0,
            false_easting_m: 0.0,
            false_northing_m: 0.0,
        };
        assert!(tm.to_string().contains("lon_0 25 deg"), "{tm}");
        for c in [utm, tm, Crs::Geographic, Crs::WebMercator] {
            assert!(!c.to_string().contains('{'), "{c}");
        }
    }
}
