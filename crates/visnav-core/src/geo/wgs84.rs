//! WGS84 ellipsoid constants (NIMA TR8350.2, 3rd edition, table 3.1 and 3.5).
//!
//! Shared by the geodesy (geodetic <-> ECEF, projections) and the navigation filter (radii of
//! curvature, normal gravity, earth rate).

/// Semi-major axis a, metres.
pub const A_M: f64 = 6_378_137.0;
/// Flattening f = 1 / 298.257223563.
pub const F: f64 = 1.0 / 298.257_223_563;
/// Semi-minor axis b = a (1 - f), metres.
pub const B_M: f64 = A_M * (1.0 - F);
/// First eccentricity squared e^2 = f (2 - f).
pub const E2: f64 = F * (2.0 - F);
/// Earth rotation rate omega_e, rad/s.
pub const OMEGA_E_RAD_S: f64 = 7.292_115e-5;
/// Earth gravitational constant GM (with atmosphere), m^3/s^2.
pub const GM_M3_S2: f64 = 3.986_004_418e14;
