//! Map projections of [`Crs`]: geographic <-> projected coordinates, EPSG codes, UTM zones, and the
//! grid convergence / point scale factor of transverse Mercator.
//!
//! * Transverse Mercator (`Crs::TransverseMercator`, `Crs::Utm`): the Krüger series to 6th order in
//!   the third flattening n, in the form of C. F. F. Karney, "Transverse Mercator with an accuracy
//!   of a few nanometers", J. Geodesy 85 (2011) 475-485, eqs. (7)-(13) (forward via the conformal
//!   latitude, series coefficients alpha_j eq. (35), inverse coefficients beta_j eq. (36), the
//!   conformal-to-geodetic latitude by Newton's method, eqs. (19)-(21)). Error below 5 nm within
//!   3900 km of the central meridian; this module refuses points more than 45 deg of longitude
//!   from it, where the series loses accuracy.
//!   A latitude of origin lat0 != 0 subtracts the projected meridian distance of lat0 (as PROJ
//!   `+proj=tmerc +lat_0`, EPSG method 9807).
//! * Web Mercator (EPSG:3857, EPSG method 1024, EPSG Guidance Note 7-2 section 1.3.3.2): spherical
//!   formulas on the WGS84 semi-major axis applied to WGS84 geodetic coordinates:
//!   x = a lon, y = a ln(tan(pi/4 + lat/2)). Defined here for |lat| <= 85.06 deg (the EPSG:3857
//!   area of use).
//! * Geographic (EPSG:4326): x = longitude, y = latitude, degrees (GeoTIFF axis order).
//!
//! Conventions:
//! * Projected coordinates are (x, y) = (easting, northing), metres.
//! * Grid convergence `convergence_deg` (gamma) is the bearing of grid north (the +y axis) measured
//!   clockwise from true north, as in GeographicLib: positive east of the central meridian in the
//!   northern hemisphere. Hence a direction with true azimuth `az_true` has grid azimuth
//!   `az_grid = az_true - gamma`, and a heading measured from grid north converts to true north
//!   as `yaw_true = yaw_grid + gamma`.
//! * Point scale factor k: (length on the grid) / (length on the ellipsoid) at the point.
//!
//! NAD83 UTM zones (EPSG:269zz) are treated as WGS84 UTM (difference below 2 m in the US).

use std::f64::consts::FRAC_PI_2;
use std::sync::OnceLock;

use super::crs::Crs;
use super::ecef::sin_cos_deg;
use super::error::{GeoError, check_finite, check_lat_deg, wrap_lon_deg};
use super::wgs84::{A_M, E2, F};

/// Scale factor of UTM on the central meridian.
pub const UTM_K0: f64 = 0.9996;
/// UTM false easting, metres.
pub const UTM_FALSE_EASTING_M: f64 = 500_000.0;
/// UTM false northing in the southern hemisphere, metres.
pub const UTM_FALSE_NORTHING_SOUTH_M: f64 = 10_000_000.0;
/// Largest |longitude - central meridian| (deg) accepted by the transverse Mercator here.
pub const TM_MAX_DLON_DEG: f64 = 45.0;
/// Largest |latitude| (deg) accepted by web Mercator (EPSG:3857 area of use is +-85.06 deg).
pub const WEB_MERCATOR_MAX_LAT_DEG: f64 = 85.06;

/// Grid convergence and point scale factor at a point of a projection.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridFactors {
    /// Bearing of grid north measured clockwise from true north, degrees (see module docs).
    pub convergence_deg: f64,
    /// Point scale factor k (grid length / ellipsoid length). For web Mercator, which is not
    /// conformal on the ellipsoid, this is the scale along the parallel, a / (N cos lat); the scale
    /// along the meridian is a / (M cos lat), larger by the factor N / M (at most 1.0067).
    pub scale: f64,
}

/// Resolved parameters of a transverse Mercator (UTM or generic).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TmParams {
    /// Latitude of origin, degrees.
    pub lat0_deg: f64,
    /// Central meridian, degrees east.
    pub lon0_deg: f64,
    /// Scale factor on the central meridian.
    pub k0: f64,
    /// Easting of the origin, metres.
    pub false_easting_m: f64,
    /// Northing of the origin, metres.
    pub false_northing_m: f64,
}

/// Krüger-series constants for one ellipsoid (Karney 2011).
#[derive(Debug, Clone)]
pub(crate) struct TmEllipsoid {
    a_m: f64,
    /// First eccentricity e.
    e: f64,
    /// e^2.
    e2: f64,
    /// 1 - e^2.
    e2m: f64,
    /// Rectifying radius A = a / (1 + n) (1 + n^2/4 + n^4/64 + n^6/256) (Karney eq. 14).
    rect_radius_m: f64,
    /// alpha_1..alpha_6 (index 0 unused), Karney eq. (35).
    alp: [f64; 7],
    /// beta_1..beta_6 (index 0 unused), Karney eq. (36).
    bet: [f64; 7],
}

impl TmEllipsoid {
    pub(crate) fn new(a_m: f64, f: f64) -> Self {
        let n = f / (2.0 - f);
        let (n2, n3, n4, n5, n6) = (n * n, n.powi(3), n.powi(4), n.powi(5), n.powi(6));
        let e2 = f * (2.0 - f);
        let alp = [
            0.0,
            n / 2.0 - 2.0 * n2 / 3.0 + 5.0 * n3 / 16.0 + 41.0 * n4 / 180.0 - 127.0 * n5 / 288.0
                + 7891.0 * n6 / 37800.0,
            13.0 * n2 / 48.0 - 3.0 * n3 / 5.0 + 557.0 * n4 / 1440.0 + 281.0 * n5 / 630.0
                - 1983433.0 * n6 / 1935360.0,
            61.0 * n3 / 240.0 - 103.0 * n4 / 140.0
                + 15061.0 * n5 / 26880.0
                + 167603.0 * n6 / 181440.0,
            49561.0 * n4 / 161280.0 - 179.0 * n5 / 168.0 + 6601661.0 * n6 / 7257600.0,
            34729.0 * n5 / 80640.0 - 3418889.0 * n6 / 1995840.0,
            212378941.0 * n6 / 319334400.0,
        ];
        let bet = [
            0.0,
            n / 2.0 - 2.0 * n2 / 3.0 + 37.0 * n3 / 96.0 - n4 / 360.0 - 81.0 * n5 / 512.0
                + 96199.0 * n6 / 604800.0,
            n2 / 48.0 + n3 / 15.0 - 437.0 * n4 / 1440.0 + 46.0 * n5 / 105.0
                - 1118711.0 * n6 / 3870720.0,
            17.0 * n3 / 480.0 - 37.0 * n4 / 840.0 - 209.0 * n5 / 4480.0 + 5569.0 * n6 / 90720.0,
            4397.0 * n4 / 161280.0 - 11.0 * n5 / 504.0 - 830251.0 * n6 / 7257600.0,
            4583.0 * n5 / 161280.0 - 108847.0 * n6 / 3991680.0,
            20648693.0 * n6 / 638668800.0,
        ];
        Self {
            a_m,
            e: e2.sqrt(),
            e2,
            e2m: 1.0 - e2,
            rect_radius_m: a_m / (1.0 + n) * (1.0 + n2 / 4.0 + n4 / 64.0 + n6 / 256.0),
            alp,
            bet,
        }
    }

    /// The WGS84 instance (shared).
    pub(crate) fn wgs84() -> &'static Self {
        static W: OnceLock<TmEllipsoid> = OnceLock::new();
        W.get_or_init(|| {
            let t = TmEllipsoid::new(A_M, F);
            debug_assert!((t.e2 - E2).abs() < 1e-15);
            t
        })
    }

    /// tau' = tan(conformal latitude) from tau = tan(geodetic latitude) (Karney eqs. 7-9).
    fn taupf(&self, tau: f64) -> f64 {
        let tau1 = 1f64.hypot(tau);
        let sig = (self.e * (self.e * tau / tau1).atanh()).sinh();
        1f64.hypot(sig) * tau - sig * tau1
    }

    /// tau from tau' by Newton's method (Karney eqs. 19-21).
    fn tauf(&self, taup: f64) -> f64 {
        let tol = f64::EPSILON.sqrt() / 10.0;
        let stol = tol * taup.abs().max(1.0);
        let mut tau = taup / self.e2m;
        if tau.is_nan() || tau.abs() >= 2.0 / f64::EPSILON.sqrt() {
            return tau;
        }
        for _ in 0..8 {
            let taupa = self.taupf(tau);
            let dtau = (taup - taupa) * (1.0 + self.e2m * tau * tau)
                / (self.e2m * 1f64.hypot(tau) * 1f64.hypot(taupa));
            tau += dtau;
            if dtau.is_nan() || dtau.abs() < stol {
                break;
            }
        }
        tau
    }

    /// Forward projection with k0 = 1 and no false origin. `dlon_deg` in [-90, 90].
    /// Returns (x_m, y_m, convergence_deg, scale).
    pub(crate) fn forward(&self, lat_deg: f64, dlon_deg: f64) -> (f64, f64, f64, f64) {
        let lat_sign = if lat_deg < 0.0 { -1.0 } else { 1.0 };
        let lon_sign = if dlon_deg < 0.0 { -1.0 } else { 1.0 };
        let lat = lat_deg.abs();
        let lon = dlon_deg.abs();
        let (slam, clam) = sin_cos_deg(lon);
        let (xip, etap, gamma_p, k_p);
        if lat < 90.0 {
            let (sphi, cphi) = sin_cos_deg(lat);
            let tau = sphi / cphi;
            let taup = self.taupf(tau);
            let c = clam.max(0.0);
            xip = taup.atan2(c);
            etap = (slam / taup.hypot(c)).asinh();
            // gamma' = atan(tau' tan(lambda) / sqrt(1 + tau'^2)) (Karney eq. 12 with eta'', xi'').
            gamma_p = (slam * taup).atan2(c * 1f64.hypot(taup));
            // k' = sqrt(1 - e^2 sin^2 phi) sqrt(1 + tau^2) / sqrt(tau'^2 + cos^2 lambda).
            k_p = (self.e2m + self.e2 * cphi * cphi).sqrt() * 1f64.hypot(tau) / taup.hypot(c);
        } else {
            xip = FRAC_PI_2;
            etap = 0.0;
            gamma_p = lon.to_radians();
            // Limit of k' at the pole: sqrt(1 - e^2) exp(e atanh(e)).
            k_p = self.e2m.sqrt() * (self.e * self.e.atanh()).exp();
        }
        // Krüger series (Karney eq. 11) and its derivative p' - i q' (eq. 13).
        let (mut xi, mut eta) = (xip, etap);
        let (mut p, mut q) = (1.0, 0.0);
        for j in 1..=6 {
            let jj = 2.0 * j as f64;
            let (s, c) = (jj * xip).sin_cos();
            let (sh, ch) = ((jj * etap).sinh(), (jj * etap).cosh());
            xi += self.alp[j] * s * ch;
            eta += self.alp[j] * c * sh;
            p += jj * self.alp[j] * c * ch;
            q += jj * self.alp[j] * s * sh;
        }
        let gamma = gamma_p + q.atan2(p);
        let k = k_p * self.rect_radius_m / self.a_m * p.hypot(q);
        (
            lon_sign * self.rect_radius_m * eta,
            lat_sign * self.rect_radius_m * xi,
            lat_sign * lon_sign * gamma.to_degrees(),
            k,
        )
    }

    /// Inverse projection with k0 = 1 and no false origin: (lat_deg, dlon_deg).
    pub(crate) fn inverse(&self, x_m: f64, y_m: f64) -> (f64, f64) {
        let xi = y_m / self.rect_radius_m;
        let eta = x_m / self.rect_radius_m;
        let (mut xip, mut etap) = (xi, eta);
        for j in 1..=6 {
            let jj = 2.0 * j as f64;
            let (s, c) = (jj * xi).sin_cos();
            let (sh, ch) = ((jj * eta).sinh(), (jj * eta).cosh());
            xip -= self.bet[j] * s * ch;
            etap -= self.bet[j] * c * sh;
        }
        let (s, c) = xip.sin_cos();
        let r = etap.sinh().hypot(c);
        let (lat_deg, dlon_deg) = if r != 0.0 {
            let taup = s / r;
            let tau = self.tauf(taup);
            (tau.atan().to_degrees(), etap.sinh().atan2(c).to_degrees())
        } else {
            (if s < 0.0 { -90.0 } else { 90.0 }, 0.0)
        };
        (lat_deg, dlon_deg)
    }
}

fn outside(projection: &'static str, reason: String) -> GeoError {
    GeoError::OutsideProjectionDomain { projection, reason }
}

impl Crs {
    /// UTM zone (with the Norway and Svalbard exceptions) and hemisphere of a point.
    /// Any finite latitude in [-90, 90] is accepted (UTM proper stops at 84 N / 80 S, where UPS
    /// takes over; the transverse Mercator math stays valid there).
    pub fn utm_zone_for(lat_deg: f64, lon_deg: f64) -> Result<Crs, GeoError> {
        check_lat_deg(lat_deg)?;
        let lon = wrap_lon_deg(check_finite("lon_deg", lon_deg)?);
        let mut zone = (((lon + 180.0) / 6.0).floor() as i64 + 1).clamp(1, 60) as u8;
        if (56.0..64.0).contains(&lat_deg) && (3.0..12.0).contains(&lon) {
            zone = 32;
        }
        if (72.0..=84.0).contains(&lat_deg) && (0.0..42.0).contains(&lon) {
            zone = if lon < 9.0 {
                31
            } else if lon < 21.0 {
                33
            } else if lon < 33.0 {
                35
            } else {
                37
            };
        }
        Ok(Crs::Utm {
            zone,
            north: lat_deg >= 0.0,
        })
    }

    /// The CRS of an EPSG code: 4326 (geographic), 3857 (web Mercator), 32601-32660 (UTM north),
    /// 32701-32760 (UTM south), 26901-26923 (NAD83 UTM zones 1-23, treated as WGS84).
    pub fn from_epsg(code: u32) -> Option<Crs> {
        match code {
            4326 => Some(Crs::Geographic),
            3857 => Some(Crs::WebMercator),
            32601..=32660 => Some(Crs::Utm {
                zone: (code - 32600) as u8,
                north: true,
            }),
            32701..=32760 => Some(Crs::Utm {
                zone: (code - 32700) as u8,
                north: false,
            }),
            26901..=26923 => Some(Crs::Utm {
                zone: (code - 26900) as u8,
                north: true,
            }),
            _ => None,
        }
    }

    /// The EPSG code of this CRS, if it has one (UTM maps to the WGS84 code 326zz/327zz;
    /// a generic transverse Mercator has none).
    pub fn epsg(&self) -> Option<u32> {
        match *self {
            Crs::Geographic => Some(4326),
            Crs::WebMercator => Some(3857),
            Crs::Utm { zone, north } if (1..=60).contains(&zone) => {
                Some(if north { 32600 } else { 32700 } + u32::from(zone))
            }
            _ => None,
        }
    }

    /// Checks the parameters (zone range, finite values, k0 > 0, |lat0| <= 90).
    pub fn validate(&self) -> Result<(), GeoError> {
        self.tm_params().map(|_| ())
    }

    /// Transverse Mercator parameters (UTM resolved); `Ok(None)` for geographic and web Mercator.
    pub fn tm_params(&self) -> Result<Option<TmParams>, GeoError> {
        match *self {
            Crs::Geographic | Crs::WebMercator => Ok(None),
            Crs::Utm { zone, north } => {
                if !(1..=60).contains(&zone) {
                    return Err(GeoError::InvalidUtmZone { zone });
                }
                Ok(Some(TmParams {
                    lat0_deg: 0.0,
                    lon0_deg: 6.0 * f64::from(zone) - 183.0,
                    k0: UTM_K0,
                    false_easting_m: UTM_FALSE_EASTING_M,
                    false_northing_m: if north {
                        0.0
                    } else {
                        UTM_FALSE_NORTHING_SOUTH_M
                    },
                }))
            }
            Crs::TransverseMercator {
                lat0_deg,
                lon0_deg,
                k0,
                false_easting_m,
                false_northing_m,
            } => {
                check_lat_deg(lat0_deg)?;
                check_finite("lon0_deg", lon0_deg)?;
                check_finite("k0", k0)?;
                check_finite("false_easting_m", false_easting_m)?;
                check_finite("false_northing_m", false_northing_m)?;
                if k0 <= 0.0 {
                    return Err(GeoError::InvalidParameter {
                        name: "k0",
                        value: k0,
                        reason: "scale factor must be > 0",
                    });
                }
                Ok(Some(TmParams {
                    lat0_deg,
                    lon0_deg,
                    k0,
                    false_easting_m,
                    false_northing_m,
                }))
            }
        }
    }

    /// Parameters of a TM/UTM CRS; an error for the other variants.
    fn tm_params_required(&self) -> Result<TmParams, GeoError> {
        self.tm_params()?.ok_or_else(|| {
            outside(
                "transverse Mercator",
                format!("{self} is not a transverse Mercator"),
            )
        })
    }

    /// Geographic (lat_deg, lon_deg) to projected (x, y): metres for UTM / TM / web Mercator,
    /// (lon_deg, lat_deg) for the geographic CRS.
    pub fn from_geodetic(&self, lat_deg: f64, lon_deg: f64) -> Result<(f64, f64), GeoError> {
        check_lat_deg(lat_deg)?;
        check_finite("lon_deg", lon_deg)?;
        match self {
            Crs::Geographic => Ok((wrap_lon_deg(lon_deg), lat_deg)),
            Crs::WebMercator => {
                if lat_deg.abs() > WEB_MERCATOR_MAX_LAT_DEG {
                    return Err(outside(
                        "web Mercator (EPSG:3857)",
                        format!("|lat| {lat_deg} deg > {WEB_MERCATOR_MAX_LAT_DEG}"),
                    ));
                }
                let x = A_M * wrap_lon_deg(lon_deg).to_radians();
                let (s, c) = sin_cos_deg(lat_deg);
                // ln(tan(pi/4 + phi/2)) = asinh(tan(phi)).
                Ok((x, A_M * (s / c).asinh()))
            }
            _ => {
                let p = self.tm_params_required()?;
                let t = TmEllipsoid::wgs84();
                let dlon = wrap_lon_deg(lon_deg - p.lon0_deg);
                if dlon.abs() > TM_MAX_DLON_DEG {
                    return Err(outside(
                        "transverse Mercator",
                        format!(
                            "longitude {lon_deg} deg is {dlon:.3} deg from the central meridian \
                             {} deg (limit {TM_MAX_DLON_DEG})",
                            p.lon0_deg
                        ),
                    ));
                }
                let (x, y, _, _) = t.forward(lat_deg, dlon);
                let y0 = if p.lat0_deg != 0.0 {
                    t.forward(p.lat0_deg, 0.0).1
                } else {
                    0.0
                };
                Ok((
                    p.false_easting_m + p.k0 * x,
                    p.false_northing_m + p.k0 * (y - y0),
                ))
            }
        }
    }

    /// Projected (x, y) to geographic (lat_deg, lon_deg), lon in [-180, 180). For the geographic
    /// CRS, x is the longitude and y the latitude in degrees.
    pub fn to_geodetic(&self, x: f64, y: f64) -> Result<(f64, f64), GeoError> {
        check_finite("x", x)?;
        check_finite("y", y)?;
        match self {
            Crs::Geographic => {
                check_lat_deg(y)?;
                Ok((y, wrap_lon_deg(x)))
            }
            Crs::WebMercator => {
                let lat_deg = (y / A_M).sinh().atan().to_degrees();
                if lat_deg.abs() > WEB_MERCATOR_MAX_LAT_DEG + 1e-9 {
                    return Err(outside(
                        "web Mercator (EPSG:3857)",
                        format!("y {y} m maps to |lat| > {WEB_MERCATOR_MAX_LAT_DEG} deg"),
                    ));
                }
                Ok((lat_deg, wrap_lon_deg((x / A_M).to_degrees())))
            }
            _ => {
                let p = self.tm_params_required()?;
                let t = TmEllipsoid::wgs84();
                let y0 = if p.lat0_deg != 0.0 {
                    t.forward(p.lat0_deg, 0.0).1
                } else {
                    0.0
                };
                let xu = (x - p.false_easting_m) / p.k0;
                let yu = (y - p.false_northing_m) / p.k0 + y0;
                // |eta| <= 1 covers |dlon| <= 45 deg at the equator (eta' = asinh(1) = 0.88);
                // beyond it sinh/cosh of the series grow quickly and the point is refused anyway.
                if (xu / t.rect_radius_m).abs() > 1.0 || (yu / t.rect_radius_m).abs() > 4.0 {
                    return Err(outside(
                        "transverse Mercator",
                        format!("(x, y) = ({x}, {y}) m is too far from the central meridian"),
                    ));
                }
                let (lat_deg, dlon) = t.inverse(xu, yu);
                if dlon.is_nan() || dlon.abs() > TM_MAX_DLON_DEG || !lat_deg.is_finite() {
                    return Err(outside(
                        "transverse Mercator",
                        format!(
                            "(x, y) = ({x}, {y}) m maps to {dlon:.3} deg from the central meridian \
                             (limit {TM_MAX_DLON_DEG})"
                        ),
                    ));
                }
                Ok((lat_deg, wrap_lon_deg(p.lon0_deg + dlon)))
            }
        }
    }

    /// Grid convergence and point scale factor at a geographic point (see module docs for the
    /// sign convention). Errors for the geographic CRS.
    pub fn grid_factors(&self, lat_deg: f64, lon_deg: f64) -> Result<GridFactors, GeoError> {
        check_lat_deg(lat_deg)?;
        check_finite("lon_deg", lon_deg)?;
        match self {
            Crs::Geographic => Err(GeoError::NotProjected {
                operation: "grid convergence / scale factor",
            }),
            Crs::WebMercator => {
                if lat_deg.abs() > WEB_MERCATOR_MAX_LAT_DEG {
                    return Err(outside(
                        "web Mercator (EPSG:3857)",
                        format!("|lat| {lat_deg} deg > {WEB_MERCATOR_MAX_LAT_DEG}"),
                    ));
                }
                let (s, c) = sin_cos_deg(lat_deg);
                let n = A_M / (1.0 - E2 * s * s).sqrt();
                Ok(GridFactors {
                    convergence_deg: 0.0,
                    scale: A_M / (n * c),
                })
            }
            _ => {
                let p = self.tm_params_required()?;
                let dlon = wrap_lon_deg(lon_deg - p.lon0_deg);
                if dlon.abs() > TM_MAX_DLON_DEG {
                    return Err(outside(
                        "transverse Mercator",
                        format!(
                            "{dlon:.3} deg from the central meridian (limit {TM_MAX_DLON_DEG})"
                        ),
                    ));
                }
                let (_, _, gamma, k) = TmEllipsoid::wgs84().forward(lat_deg, dlon);
                Ok(GridFactors {
                    convergence_deg: gamma,
                    scale: p.k0 * k,
                })
            }
        }
    }

    /// Grid convergence gamma in degrees (bearing of grid north clockwise from true north).
    pub fn grid_convergence_deg(&self, lat_deg: f64, lon_deg: f64) -> Result<f64, GeoError> {
        Ok(self.grid_factors(lat_deg, lon_deg)?.convergence_deg)
    }

    /// Point scale factor k (grid length / ellipsoid length).
    pub fn point_scale_factor(&self, lat_deg: f64, lon_deg: f64) -> Result<f64, GeoError> {
        Ok(self.grid_factors(lat_deg, lon_deg)?.scale)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tm(lat0_deg: f64, lon0_deg: f64, k0: f64, fe: f64, fn_: f64) -> Crs {
        Crs::TransverseMercator {
            lat0_deg,
            lon0_deg,
            k0,
            false_easting_m: fe,
            false_northing_m: fn_,
        }
    }

    /// Lines of C. F. F. Karney, "Test data for the transverse Mercator projection" (2009),
    /// file TMcoords.dat (https://doi.org/10.5281/zenodo.32470; reproduced in PyGeodesy's
    /// test/testTMcoords.py): WGS84, central meridian 0, k0 = 0.9996, no false origin.
    /// Columns: lat (deg), lon (deg), easting (m), northing (m), convergence (deg), scale.
    /// Selected: every line of the first 258 within 8.3 deg of the central meridian.
    #[rustfmt::skip]
    #[allow(clippy::excessive_precision)] // published digits, kept verbatim
    const TMCOORDS: [[f64; 6]; 24] = [
        [19.376879758731, 0.344604702538, 36187.3424147238117, 2142565.3248023055831, 0.114334366652574163, 0.99961618629427946552],
        [33.028801664026, 0.765842683855, 71519.4504575306802, 3654740.4448518867014, 0.417448360256695198, 0.9996630662116279997],
        [84.986930137199, 2.067177857261, 20163.0752214330146, 9438635.9888499043815, 2.059277291707588222, 0.99960496589466017622],
        [40.552052236608, 3.10605643618, 263004.7709889716198, 4493669.7624508701848, 2.020523080004668331, 1.00045152537558245158],
        [20.166741997072, 3.143947731274, 328652.2771294843991, 2233043.9588736710395, 1.084863297347176706, 1.00093521803437134364],
        [9.916090592983, 2.895277339837, 317518.4555464869534, 1097517.5837454216348, 0.499003720919636014, 1.00084775964536943313],
        [38.617487254111, 4.099838486616, 356983.618539634654, 4282309.0489941972154, 2.561484750887838159, 1.00116967656345686077],
        [35.434073450488, 1.762794707137, 160012.1869587518858, 3922609.2532306700222, 1.022225124144958262, 0.99991553289064298164],
        [55.753535712331, 3.471798114123, 217855.5460780085389, 6184108.1225681774287, 2.870992737838008847, 1.00018219161553870971],
        [58.542492989325, 0.162592684741, 9464.9343875445955, 6489121.6249442771542, 0.138696123095078659, 0.9996010981636145684],
        [19.753508884702, 1.603846135125, 168047.3369803282036, 2185000.046530304967, 0.542186563040675395, 0.99994905785319155467],
        [69.499593633291, 1.928335626092, 75358.2619616238705, 7711258.6622510055509, 1.806297402204658786, 0.99966947406657274597],
        [3.58204121273, 1.137286307295, 126314.1916179008865, 396006.6879211498981, 0.071064512019013209, 0.99979750106848045799],
        [31.750313985725, 4.2481669819, 402511.3467124300447, 3520621.5619106356485, 2.238473873171145824, 1.0015987516192805961],
        [43.977935890852, 5.672541129169, 454986.2188972515956, 4885087.8878842827264, 3.945648021963556589, 1.00214702964307690511],
        [49.495348846691, 6.087551111735, 440696.5100700030027, 5500355.8262971466109, 4.636103927615996534, 1.00198639702101890472],
        [8.920166746304, 5.101512904759, 561561.4939374572189, 989910.2362210683617, 0.793118092514896753, 1.00350496287174529381],
        [29.526119573162, 6.49306920517, 629892.8222431609312, 3283914.9104510948801, 3.210482004553411381, 1.00449937658081974569],
        [27.203894742072, 7.440229319956, 738062.0477794809553, 3031007.0741158638797, 3.416801681625375868, 1.00633168074600267019],
        [42.701376407719, 7.572738186139, 620365.9050898417601, 4755542.0265620241836, 5.152021939103753522, 1.00433819291969569998],
        [19.427290417638, 7.268247299591, 764616.6650506681717, 2164299.3379453227242, 2.429300399613599967, 1.00683508317252458097],
        [43.570988154502, 7.46449391571, 602838.450710449767, 4851370.6372051615015, 5.160395241581517306, 1.00407312998832083041],
        [33.054056916574, 7.787458413753, 727939.4383912861907, 3684363.2368099898959, 4.266227267489998418, 1.00614020225651810072],
        [57.367533447896, 8.260865981663, 496148.2537306291007, 6388503.3650426645438, 6.970955082495557851, 1.00261965657610768433],
    ];

    #[test]
    fn karney_tmcoords_reference() {
        let crs = tm(0.0, 0.0, 0.9996, 0.0, 0.0);
        let mut worst_m: f64 = 0.0;
        for [lat, lon, x_ref, y_ref, gamma_ref, k_ref] in TMCOORDS {
            // Both hemispheres and both sides of the central meridian by symmetry:
            // (lat, lon) -> (x, y); (-lat, lon) -> (x, -y); (lat, -lon) -> (-x, y); gamma flips
            // with each sign change.
            for (sl, so) in [(1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)] {
                let (x, y) = crs.from_geodetic(sl * lat, so * lon).unwrap();
                let err = (x - so * x_ref).hypot(y - sl * y_ref);
                worst_m = worst_m.max(err);
                assert!(
                    err < 1e-3,
                    "({lat},{lon}) -> ({x},{y}), ref ({x_ref},{y_ref})"
                );
                let gf = crs.grid_factors(sl * lat, so * lon).unwrap();
                assert!(
                    (gf.convergence_deg - sl * so * gamma_ref).abs() < 1e-9,
                    "{gf:?}"
                );
                assert!((gf.scale - k_ref).abs() < 1e-12, "{gf:?} vs {k_ref}");
                let (lat_b, lon_b) = crs.to_geodetic(so * x_ref, sl * y_ref).unwrap();
                assert!(
                    (lat_b - sl * lat).abs() < 1e-10,
                    "inverse lat {lat_b} vs {lat}"
                );
                assert!(
                    (lon_b - so * lon).abs() < 1e-10,
                    "inverse lon {lon_b} vs {lon}"
                );
            }
        }
        eprintln!("worst TMcoords forward error: {worst_m:.3e} m");
    }

    /// EPSG Guidance Note 7-2 (IOGP Publication 373-7-2), Transverse Mercator (method 9807)
    /// worked example, OSGB 1936 / British National Grid on the Airy 1830 ellipsoid
    /// (a = 6377563.396, 1/f = 299.3249646): lat 50 deg 30' N, lon 0 deg 30' E (2.5 deg from the
    /// central meridian 2 W) -> E = 577274.99 m, N = 69740.50 m.
    #[test]
    fn epsg_guidance_note_osgb_example() {
        let airy = TmEllipsoid::new(6_377_563.396, 1.0 / 299.324_964_6);
        let (k0, fe, fn_) = (0.999_601_271_7, 400_000.0, -100_000.0);
        let (x, y, _, _) = airy.forward(50.5, 0.5 - (-2.0));
        let (_, y0, _, _) = airy.forward(49.0, 0.0);
        let (e, n) = (fe + k0 * x, fn_ + k0 * (y - y0));
        assert!((e - 577_274.99).abs() < 0.01, "E = {e}");
        assert!((n - 69_740.50).abs() < 0.01, "N = {n}");
        let (lat, dlon) = airy.inverse((577_274.99 - fe) / k0, (69_740.50 - fn_) / k0 + y0);
        assert!(
            (lat - 50.5).abs() < 1e-7 && (dlon - 2.5).abs() < 1e-7,
            "{lat} {dlon}"
        );
    }

    /// GeographicLib GeoConvert(1) manual page: "33.3 44.4" is given as equivalent to the UTM
    /// coordinates "38n 444140.54 3684706.36".
    #[test]
    fn geoconvert_utm_example() {
        let crs = Crs::Utm {
            zone: 38,
            north: true,
        };
        assert_eq!(Crs::utm_zone_for(33.3, 44.4).unwrap(), crs);
        let (x, y) = crs.from_geodetic(33.3, 44.4).unwrap();
        assert!(
            (x - 444_140.54).abs() < 0.006 && (y - 3_684_706.36).abs() < 0.006,
            "{x} {y}"
        );
        let (lat, lon) = crs.to_geodetic(444_140.54, 3_684_706.36).unwrap();
        assert!((lat - 33.3).abs() < 1e-7 && (lon - 44.4).abs() < 1e-7);
    }

    /// The NGI 3324C data set uses `+proj=tmerc +lat_0=0 +lon_0=25 +k=1 +x_0=0 +y_0=0`. The truth
    /// camera centre of frame 05_0182 at (x, y) = (-55094.50, -3727407.04) converts with PROJ 9.5.1
    /// (pyproj 3.7.2, whose tmerc uses the independent Poder/Engsager series) to
    /// lat -33.6717187561, lon 24.4059206832, meridian convergence +0.32938588 deg and scale
    /// 1.0000374050. Rough check by hand: dlon ~ x / (N cos lat) = -0.594 deg, gamma ~ dlon sin lat.
    #[test]
    fn ngi_truth_camera_position() {
        let crs = tm(0.0, 25.0, 1.0, 0.0, 0.0);
        let (lat, lon) = crs.to_geodetic(-55_094.50, -3_727_407.04).unwrap();
        assert!((lat + 33.671_718_756_1).abs() < 1e-8, "lat {lat}");
        assert!((lon - 24.405_920_683_2).abs() < 1e-8, "lon {lon}");
        let (x, y) = crs.from_geodetic(lat, lon).unwrap();
        assert!((x + 55_094.50).abs() < 1e-6 && (y + 3_727_407.04).abs() < 1e-6);
        let gf = crs.grid_factors(lat, lon).unwrap();
        assert!((gf.convergence_deg - 0.329_385_888).abs() < 1e-7, "{gf:?}");
        assert!((gf.scale - 1.000_037_405).abs() < 1e-9, "{gf:?}");
    }

    /// EPSG Guidance Note 7-2, Popular Visualisation Pseudo Mercator (method 1024) example:
    /// lat 24 deg 22' 54.433" N, lon 100 deg 20' W -> E = -11169055.58, N = 2800000.00, parallel
    /// scale k = 1.0972914; reverse of (-11169055.58, 2810000.00) -> lat 24 deg 27' 48.889" N.
    #[test]
    fn epsg_web_mercator_example() {
        let lat = 24.0 + 22.0 / 60.0 + 54.433 / 3600.0;
        let lon = -(100.0 + 20.0 / 60.0);
        let (x, y) = Crs::WebMercator.from_geodetic(lat, lon).unwrap();
        assert!(
            (x + 11_169_055.58).abs() < 0.006 && (y - 2_800_000.00).abs() < 0.01,
            "{x} {y}"
        );
        let gf = Crs::WebMercator.grid_factors(lat, lon).unwrap();
        assert_eq!(gf.convergence_deg, 0.0);
        assert!((gf.scale - 1.097_291_4).abs() < 1e-7, "{gf:?}");
        let (lat_b, lon_b) = Crs::WebMercator
            .to_geodetic(-11_169_055.58, 2_810_000.0)
            .unwrap();
        assert!(
            (lat_b - (24.0 + 27.0 / 60.0 + 48.889 / 3600.0)).abs() < 1e-6,
            "{lat_b}"
        );
        assert!((lon_b - lon).abs() < 1e-7);
    }

    #[test]
    fn utm_zones() {
        let z = |lat, lon| match Crs::utm_zone_for(lat, lon).unwrap() {
            Crs::Utm { zone, north } => (zone, north),
            other => panic!("{other:?}"),
        };
        assert_eq!(z(-33.67, 24.4), (35, false));
        assert_eq!(z(47.0, -97.0), (14, true));
        assert_eq!(z(44.05, -123.1), (10, true));
        assert_eq!(z(0.0, -180.0), (1, true));
        assert_eq!(z(0.0, 180.0), (1, true));
        assert_eq!(z(0.0, 179.999), (60, true));
        assert_eq!(z(60.0, 5.0), (32, true)); // Norway exception
        assert_eq!(z(60.0, 2.9), (31, true));
        assert_eq!(z(78.0, 8.0), (31, true)); // Svalbard exceptions
        assert_eq!(z(78.0, 10.0), (33, true));
        assert_eq!(z(78.0, 25.0), (35, true));
        assert_eq!(z(78.0, 40.0), (37, true));
        assert!(Crs::utm_zone_for(f64::NAN, 0.0).is_err());
        assert!(Crs::utm_zone_for(0.0, f64::INFINITY).is_err());
    }

    #[test]
    fn epsg_codes() {
        assert_eq!(Crs::from_epsg(4326), Some(Crs::Geographic));
        assert_eq!(Crs::from_epsg(3857), Some(Crs::WebMercator));
        assert_eq!(
            Crs::from_epsg(32610),
            Some(Crs::Utm {
                zone: 10,
                north: true
            })
        );
        assert_eq!(
            Crs::from_epsg(32735),
            Some(Crs::Utm {
                zone: 35,
                north: false
            })
        );
        assert_eq!(
            Crs::from_epsg(26914),
            Some(Crs::Utm {
                zone: 14,
                north: true
            })
        );
        for bad in [
            0, 32600, 32661, 32700, 32761, 26900, 26924, 26929, 2154, 27700,
        ] {
            assert_eq!(Crs::from_epsg(bad), None, "{bad}");
        }
        for code in (32601..=32660).chain(32701..=32760).chain([4326, 3857]) {
            assert_eq!(Crs::from_epsg(code).and_then(|c| c.epsg()), Some(code));
        }
        assert_eq!(tm(0.0, 25.0, 1.0, 0.0, 0.0).epsg(), None);
    }

    #[test]
    fn rejects_bad_input() {
        let utm = Crs::Utm {
            zone: 35,
            north: false,
        };
        assert!(matches!(
            utm.from_geodetic(91.0, 25.0),
            Err(GeoError::LatitudeOutOfRange { .. })
        ));
        assert!(utm.from_geodetic(f64::NAN, 25.0).is_err());
        assert!(utm.to_geodetic(f64::INFINITY, 0.0).is_err());
        assert!(matches!(
            utm.from_geodetic(0.0, 27.0 + 46.0),
            Err(GeoError::OutsideProjectionDomain { .. })
        ));
        assert!(utm.to_geodetic(9.0e6, 5.0e6).is_err());
        assert!(utm.to_geodetic(500_000.0, 1.0e9).is_err());
        for zone in [0, 61] {
            let c = Crs::Utm { zone, north: true };
            assert!(matches!(
                c.from_geodetic(0.0, 0.0),
                Err(GeoError::InvalidUtmZone { .. })
            ));
            assert!(c.to_geodetic(0.0, 0.0).is_err());
            assert_eq!(c.epsg(), None);
        }
        assert!(
            tm(0.0, 25.0, 0.0, 0.0, 0.0)
                .from_geodetic(0.0, 25.0)
                .is_err()
        );
        assert!(tm(0.0, 25.0, -1.0, 0.0, 0.0).to_geodetic(0.0, 0.0).is_err());
        assert!(tm(95.0, 25.0, 1.0, 0.0, 0.0).validate().is_err());
        assert!(tm(0.0, f64::NAN, 1.0, 0.0, 0.0).validate().is_err());
        assert!(Crs::WebMercator.from_geodetic(85.5, 0.0).is_err());
        assert!(Crs::WebMercator.to_geodetic(0.0, 3.0e7).is_err());
        assert!(Crs::Geographic.to_geodetic(0.0, 91.0).is_err());
        assert!(matches!(
            Crs::Geographic.grid_factors(0.0, 0.0),
            Err(GeoError::NotProjected { .. })
        ));
    }

    #[test]
    fn geographic_axis_order() {
        assert_eq!(
            Crs::Geographic.from_geodetic(47.0, -97.0).unwrap(),
            (-97.0, 47.0)
        );
        assert_eq!(
            Crs::Geographic.to_geodetic(-97.0, 47.0).unwrap(),
            (47.0, -97.0)
        );
        assert_eq!(
            Crs::Geographic.to_geodetic(190.0, 0.0).unwrap(),
            (0.0, -170.0)
        );
    }

    #[test]
    fn pole_is_handled() {
        let crs = tm(0.0, 25.0, 1.0, 0.0, 0.0);
        let (x, y) = crs.from_geodetic(90.0, 30.0).unwrap();
        assert!(x.abs() < 1e-6);
        let (lat, _) = crs.to_geodetic(x, y).unwrap();
        assert!((lat - 90.0).abs() < 1e-9);
        let (x_s, y_s) = crs.from_geodetic(-90.0, 30.0).unwrap();
        assert!(x_s.abs() < 1e-6 && (y_s + y).abs() < 1e-6);
    }

    /// Meridian distance to 90 deg (the quarter meridian of WGS84) is 10001965.729 m
    /// (GeographicLib documentation of the WGS84 ellipsoid, QuarterMeridian()).
    #[test]
    fn quarter_meridian() {
        let (_, y) = tm(0.0, 0.0, 1.0, 0.0, 0.0)
            .from_geodetic(90.0, 0.0)
            .unwrap();
        assert!((y - 10_001_965.729).abs() < 1e-3, "{y}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        /// Generic TM round trip within 4 deg of the central meridian, any origin: < 1 mm
        /// (measured: about 1e-8 m).
        #[test]
        fn tm_round_trip(lat0 in -60.0f64..60.0, lon0 in -180.0f64..180.0, k0 in 0.9f64..1.1,
                         fe in -1.0e6f64..1.0e6, fn_ in -1.0e7f64..1.0e7,
                         lat in -89.9f64..89.9, dlon in -4.0f64..4.0) {
            let crs = tm(lat0, lon0, k0, fe, fn_);
            let (x, y) = crs.from_geodetic(lat, lon0 + dlon).unwrap();
            let (lat_b, lon_b) = crs.to_geodetic(x, y).unwrap();
            let (x2, y2) = crs.from_geodetic(lat_b, lon_b).unwrap();
            prop_assert!((x2 - x).hypot(y2 - y) < 1e-3);
            prop_assert!((lat_b - lat).abs() < 1e-9, "{lat} -> {lat_b}");
            let dlon_b = wrap_lon_deg(lon_b - lon0 - dlon);
            prop_assert!((dlon_b * lat.to_radians().cos()).abs() < 1e-9, "{dlon} -> {dlon_b}");
        }

        /// UTM both hemispheres, whole zone width and beyond: grid -> geo -> grid < 1 mm, and the
        /// southern false northing is exactly 10 000 km below the northern one.
        #[test]
        fn utm_round_trip(zone in 1u8..=60, lat in -80.0f64..84.0, dlon in -3.5f64..3.5) {
            let north = lat >= 0.0;
            let crs = Crs::Utm { zone, north };
            let lon = wrap_lon_deg(6.0 * f64::from(zone) - 183.0 + dlon);
            let (x, y) = crs.from_geodetic(lat, lon).unwrap();
            let (lat_b, lon_b) = crs.to_geodetic(x, y).unwrap();
            let (x2, y2) = crs.from_geodetic(lat_b, lon_b).unwrap();
            prop_assert!((x2 - x).hypot(y2 - y) < 1e-3);
            prop_assert!((lat_b - lat).abs() < 1e-9);
            let (xs, ys) = Crs::Utm { zone, north: !north }.from_geodetic(lat, lon).unwrap();
            prop_assert!((xs - x).abs() < 1e-9);
            let expected_shift = if north { 1.0e7 } else { -1.0e7 };
            prop_assert!((ys - y - expected_shift).abs() < 1e-6);
        }

        /// Grid -> geo -> grid for web Mercator within +-85 deg: < 1 mm.
        #[test]
        fn web_mercator_round_trip(lat in -85.0f64..85.0, lon in -180.0f64..180.0) {
            let (x, y) = Crs::WebMercator.from_geodetic(lat, lon).unwrap();
            let (lat_b, lon_b) = Crs::WebMercator.to_geodetic(x, y).unwrap();
            let (x2, y2) = Crs::WebMercator.from_geodetic(lat_b, lon_b).unwrap();
            prop_assert!((x2 - x).hypot(y2 - y) < 1e-3);
            prop_assert!((lat_b - lat).abs() < 1e-10);
            prop_assert!((wrap_lon_deg(lon_b - lon)).abs() < 1e-10);
        }

        /// Convergence and scale agree with finite differences of the projection itself:
        /// grid north is rotated by gamma clockwise from true north, so a step due north moves on
        /// the grid at azimuth -gamma; a step due east of ellipsoidal length ds moves k ds.
        #[test]
        fn convergence_and_scale_match_finite_differences(lat in -80.0f64..80.0, dlon in -4.0f64..4.0) {
            let crs = tm(0.0, 25.0, 0.9996, 500_000.0, 0.0);
            let lon = 25.0 + dlon;
            let gf = crs.grid_factors(lat, lon).unwrap();
            let h = 1e-5;
            let (xn, yn) = crs.from_geodetic(lat + h, lon).unwrap();
            let (xs, ys) = crs.from_geodetic(lat - h, lon).unwrap();
            let az_grid_deg = (xn - xs).atan2(yn - ys).to_degrees();
            prop_assert!((az_grid_deg + gf.convergence_deg).abs() < 1e-6,
                         "{az_grid_deg} vs {}", gf.convergence_deg);
            let (xe, ye) = crs.from_geodetic(lat, lon + h).unwrap();
            let (xw, yw) = crs.from_geodetic(lat, lon - h).unwrap();
            let n = A_M / (1.0 - E2 * lat.to_radians().sin().powi(2)).sqrt();
            let ds = n * lat.to_radians().cos() * (2.0 * h).to_radians();
            let k_fd = (xe - xw).hypot(ye - yw) / ds;
            prop_assert!((k_fd - gf.scale).abs() < 1e-8, "{k_fd} vs {}", gf.scale);
        }
    }
}
