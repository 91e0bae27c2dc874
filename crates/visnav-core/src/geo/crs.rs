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
    Utm { zone: u8, north: bool },
    /// Generic transverse Mercator on WGS84: `+proj=tmerc +lat_0 +lon_0 +k +x_0 +y_0`.
    TransverseMercator {
        lat0_deg: f64,
        lon0_deg: f64,
        k0: f64,
        false_easting_m: f64,
        false_northing_m: f64,
    },
    /// EPSG:3857, spherical ("web") Mercator on the WGS84 semi-major axis.
    WebMercator,
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
