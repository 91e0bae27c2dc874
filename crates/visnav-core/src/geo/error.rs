//! Errors of the geodesy functions (`ecef`, `local`, `projection`, `geoid`).
//!
//! Every function that takes coordinates from outside (configuration, files, the network, sensor
//! data) validates them and returns one of these instead of producing NaN or panicking.

use thiserror::Error;

/// Why a geodetic computation was refused.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum GeoError {
    /// An input was NaN or infinite.
    #[error("{field} is not finite ({value})")]
    NonFinite {
        /// Name of the input.
        field: &'static str,
        /// The value given.
        value: f64,
    },
    /// A latitude outside [-90, 90] degrees.
    #[error("latitude {lat_deg} deg is outside [-90, 90]")]
    LatitudeOutOfRange {
        /// The latitude given, degrees.
        lat_deg: f64,
    },
    /// A UTM zone outside 1..=60.
    #[error("UTM zone {zone} is outside 1..=60")]
    InvalidUtmZone {
        /// The zone given.
        zone: u8,
    },
    /// A projection parameter that makes no sense (for example a scale factor <= 0).
    #[error("projection parameter {name} = {value} is invalid: {reason}")]
    InvalidParameter {
        /// Name of the parameter.
        name: &'static str,
        /// The value given.
        value: f64,
        /// The rule it breaks.
        reason: &'static str,
    },
    /// The point lies where the projection is not defined or not accurate.
    #[error("point is outside the domain of {projection}: {reason}")]
    OutsideProjectionDomain {
        /// Name of the projection.
        projection: &'static str,
        /// Where the point is and the limit it passes.
        reason: String,
    },
    /// The operation needs a projected CRS but got geographic coordinates.
    #[error("{operation} is not defined for the geographic CRS (EPSG:4326)")]
    NotProjected {
        /// The operation asked for.
        operation: &'static str,
    },
}

/// Returns `Err(NonFinite)` unless `value` is finite.
pub(crate) fn check_finite(field: &'static str, value: f64) -> Result<f64, GeoError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(GeoError::NonFinite { field, value })
    }
}

/// Returns `Err` unless `lat_deg` is finite and within [-90, 90].
pub(crate) fn check_lat_deg(lat_deg: f64) -> Result<f64, GeoError> {
    check_finite("lat_deg", lat_deg)?;
    if (-90.0..=90.0).contains(&lat_deg) {
        Ok(lat_deg)
    } else {
        Err(GeoError::LatitudeOutOfRange { lat_deg })
    }
}

/// Wraps a longitude into [-180, 180).
pub fn wrap_lon_deg(lon_deg: f64) -> f64 {
    let w = (lon_deg + 180.0).rem_euclid(360.0) - 180.0;
    // rem_euclid can return exactly 360.0 - tiny rounding for inputs just below a multiple of 360.
    if w >= 180.0 { w - 360.0 } else { w }
}
