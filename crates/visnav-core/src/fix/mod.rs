//! The vision position fix: one camera frame plus a prior (or none) to an absolute, integrity-checked
//! camera/vehicle pose.
//!
//! Data flow (Sheta 2012 ch. 4; Kong: predicted reference view):
//! 1. footprint: the image corners ray-cast onto the DEM from the prior pose, grown by the prior's
//!    uncertainty, select the reference-map features (`map`);
//! 2. rectification: the frame resampled with the prior attitude onto a north-up map-grid raster at the
//!    map level's ground sample distance, so upright SURF sees the same geometry as the map; every
//!    rectified pixel keeps the original frame pixel it came from, so matches go back to the original
//!    pixel coordinates for the solve;
//! 3. matching (`vision::match_features`) with the ratio test and the spatial gate around the position
//!    predicted from the prior;
//! 4. resection (`pose::resect`) in a local east-north-up frame about the footprint (exact geodesy:
//!    map grid -> geodetic -> ECEF -> ENU), integrity checks, covariance to NED;
//! 5. with no prior: global relocalisation, coarse to fine over the whole map within a time budget.
//!
//! Types here are the interface the daemon and the CLI use ([`FixPrior`] in, [`FixReport`] out).

use nalgebra::{Matrix3, Matrix6};
use serde::{Deserialize, Serialize};

use crate::camera::Attitude;

/// Prior position of the camera: geodetic latitude/longitude, altitude above mean sea level
/// (EGM96), and 1-sigma horizontal / vertical uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionPriorGeo {
    /// Geodetic latitude (WGS84), degrees.
    pub lat_deg: f64,
    /// Geodetic longitude (WGS84), degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level (EGM96), metres.
    pub alt_amsl_m: f64,
    /// 1-sigma horizontal uncertainty, metres (the same along each horizontal axis).
    pub sigma_h_m: f64,
    /// 1-sigma vertical uncertainty, metres.
    pub sigma_v_m: f64,
}

/// Prior vehicle attitude (body FRD relative to NED, aerospace ZYX Euler angles, see
/// `camera::frames`) with 1-sigma uncertainties: `sigma_rad` of the tilt (rotation-vector error
/// about the north and east axes) and `sigma_yaw_rad` of the heading (about down). An autopilot's
/// AHRS knows its tilt far better than its heading; a single isotropic sigma would either
/// overstate the heading or throw the tilt information away (position and tilt trade against
/// each other in a resection over flat ground).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AttitudePriorNed {
    /// The vehicle attitude, body FRD relative to NED.
    pub attitude: Attitude,
    /// 1-sigma of the tilt (rotation about the north and east axes), radians.
    pub sigma_rad: f64,
    /// 1-sigma of the heading (rotation about down), radians.
    pub sigma_yaw_rad: f64,
}

impl AttitudePriorNed {
    /// The same sigma about every axis.
    pub fn isotropic(attitude: Attitude, sigma_rad: f64) -> Self {
        Self {
            attitude,
            sigma_rad,
            sigma_yaw_rad: sigma_rad,
        }
    }
}

/// The camera's altitude alone: what a barometer still knows after the horizontal position is
/// lost (altitude above mean sea level, EGM96, and its 1-sigma).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AltitudePrior {
    /// Camera altitude above mean sea level (EGM96), metres.
    pub alt_amsl_m: f64,
    /// Its 1-sigma, metres.
    pub sigma_m: f64,
}

/// What the fix knows before looking at the frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FixPrior {
    /// Capture time of the frame in autopilot boot time, microseconds (0 when unknown).
    pub t_capture_us: u64,
    /// None: global relocalisation over the whole map.
    pub position: Option<PositionPriorGeo>,
    /// Without `position` only: the altitude alone. With it and a tilt, relocalisation knows the
    /// frame's scale and searches the map image by area correlation first (docs/fix.md).
    pub altitude: Option<AltitudePrior>,
    /// None: the attitude is solved for without a prior (rectification assumes a nadir view).
    pub attitude: Option<AttitudePriorNed>,
    /// The attitude prior is the navigation filter's own attitude (its errors are the filter's
    /// attitude error state): copied into [`FixReport::prior_attitude_from_filter`].
    pub attitude_from_filter: bool,
    /// When no fix is found at the prior's heading, search the heading again wider (`[fix]
    /// widen_heading_sigma_deg`) and then the area search over the prior's window before giving
    /// the frame up (docs/fix.md, "A heading that is wrong"). Each costs a heading sweep, so a
    /// stream of frames asks for it after repeated rejections (the daemon's policy), a single
    /// frame always (`visnav fix`).
    pub widen_heading: bool,
}

/// The result of one fix attempt. Angles and positions are finite whenever `accepted` is true.
///
/// Serialised (`visnav fix --json`, the bench's per-frame records), a number that is not
/// finite is left out rather than written as `null`: a rejected report has no position, angles
/// or covariance fields; a placement fix (no resection) no `reproj_rms_px` or `sigma0`. Every
/// number present is a number.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FixReport {
    /// The fix passed every check: the pose below is valid.
    pub accepted: bool,
    /// Why the fix was rejected (or could not be computed); None when accepted. Serialised as
    /// `reason`: "ok" when accepted, otherwise the rejection in words.
    #[serde(rename = "reason", serialize_with = "reason_text")]
    pub rejection: Option<Rejection>,
    /// Capture time copied from the prior, microseconds.
    pub t_capture_us: u64,
    /// Camera projection centre: geodetic latitude (WGS84), degrees.
    #[serde(skip_serializing_if = "not_finite")]
    pub lat_deg: f64,
    /// Camera projection centre: geodetic longitude (WGS84), degrees.
    #[serde(skip_serializing_if = "not_finite")]
    pub lon_deg: f64,
    /// Camera projection centre: altitude above mean sea level (EGM96), metres.
    #[serde(skip_serializing_if = "not_finite")]
    pub alt_amsl_m: f64,
    /// Height above the WGS84 ellipsoid, metres.
    #[serde(skip_serializing_if = "not_finite")]
    pub h_ellip_m: f64,
    /// Camera projection centre in the map's CRS: grid easting, metres.
    #[serde(skip_serializing_if = "not_finite")]
    pub x_m: f64,
    /// Camera projection centre in the map's CRS: grid northing, metres.
    #[serde(skip_serializing_if = "not_finite")]
    pub y_m: f64,
    /// Camera projection centre: height above mean sea level, metres.
    #[serde(skip_serializing_if = "not_finite")]
    pub z_m: f64,
    /// Vehicle roll (body FRD to NED, aerospace ZYX), degrees.
    #[serde(skip_serializing_if = "not_finite")]
    pub roll_deg: f64,
    /// Vehicle pitch (body FRD to NED, aerospace ZYX), degrees.
    #[serde(skip_serializing_if = "not_finite")]
    pub pitch_deg: f64,
    /// Vehicle yaw, the heading (body FRD to NED, aerospace ZYX), degrees.
    #[serde(skip_serializing_if = "not_finite")]
    pub yaw_deg: f64,
    /// Position covariance in NED, m^2 (row-major 3x3).
    #[serde(skip_serializing_if = "not_all_finite")]
    pub cov_ned_m2: [[f64; 3]; 3],
    /// Attitude covariance as an NED rotation vector, rad^2.
    #[serde(skip_serializing_if = "not_all_finite")]
    pub cov_att_ned_rad2: [[f64; 3]; 3],
    /// Correspondences the resection kept as inliers.
    pub inliers: usize,
    /// Correspondences (feature matches or tie points) given to the resection.
    pub matches: usize,
    /// RMS reprojection error of the inliers, pixels.
    #[serde(skip_serializing_if = "not_finite")]
    pub reproj_rms_px: f64,
    /// A-posteriori standard deviation of unit weight of the image-only adjustment (the RMS of
    /// the whitened residuals: 1 when the keypoint sigmas the engine assumes are right).
    #[serde(skip_serializing_if = "not_finite")]
    pub sigma0: f64,
    /// The factor on the a-priori covariance behind the reported one (see
    /// `pose::PoseCovariance::factor`).
    #[serde(skip_serializing_if = "not_finite")]
    pub cov_factor: f64,
    /// How many image quadrants' own poses measured the covariance's split-sample factor
    /// (`pose::split_variance_factor`): 0 when the resection had too few inliers to measure it
    /// (its covariance unchecked for errors the inliers share) and for a placement fix.
    pub split_groups: usize,
    /// The image-only pose and its full covariance (no attitude prior in it); `None` when no
    /// pose was computed. The pose above fuses the attitude prior when `[fix.pose.refine]
    /// use_attitude_prior` is on; a filter that supplied that prior fuses this one instead.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vision_only: Option<VisionOnlyPose>,
    /// How the position above depends on the attitude prior it fused (None when no prior was
    /// fused): see [`PriorDependenceNed`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub prior_dependence: Option<PriorDependenceNed>,
    /// Whether the attitude prior was the navigation filter's own attitude
    /// ([`FixPrior::attitude_from_filter`]).
    pub prior_attitude_from_filter: bool,
    /// Map pyramid level used.
    pub level: usize,
    /// How the frame was matched to the map.
    pub method: FixMethod,
    /// Wall time from frame to fix, milliseconds: filled by the caller that timed the call (the
    /// daemon's fix worker, the bench, `visnav fix`); the engine reads no clock and leaves 0.
    pub ms: f64,
}

/// `serde` helper: a report's outcome in words ([`FixReport::reason`]).
fn reason_text<S: serde::Serializer>(r: &Option<Rejection>, s: S) -> Result<S::Ok, S::Error> {
    match r {
        None => s.serialize_str("ok"),
        Some(r) => s.collect_str(r),
    }
}

/// `serde` helper: a number that is not finite is left out of a serialised report.
fn not_finite(v: &f64) -> bool {
    !v.is_finite()
}

/// `serde` helper: a matrix with a number that is not finite is left out of a serialised report.
fn not_all_finite(m: &[[f64; 3]; 3]) -> bool {
    !m.iter().flatten().all(|v| v.is_finite())
}

/// How a fix's correspondences were found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FixMethod {
    /// SURF features matched to the map's features (`fix::engine`).
    #[default]
    Features,
    /// Area correlation of the rectified frame with the map's image (`fix::area`): tie
    /// points and the resection.
    Area,
    /// The area correlation's placement alone, with the attitude prior's tilt (the placement
    /// fix, docs/fix.md): position and heading, no image-derived tilt.
    Placement,
}

impl std::fmt::Display for FixMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FixMethod::Features => "features",
            FixMethod::Area => "area",
            FixMethod::Placement => "placement",
        })
    }
}

/// The fused position's dependence on the attitude prior: to first order the reported position is
/// `p_true + D psi_prior + e` with `psi_prior` the prior's attitude error (NED rotation vector,
/// `R_prior = Exp(psi) R_true`) and `e` the image's error with covariance `image_cov_ned_m2`;
/// `cov_ned_m2 = image_cov_ned_m2 + D P D^T` with `P` the prior's covariance. A filter whose own
/// attitude was the prior fuses the position with `D` in its attitude Jacobian and the image's
/// covariance, instead of treating `D psi` as independent noise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PriorDependenceNed {
    /// `D`, metres per radian, row-major (rows N, E, D position; columns N, E, D rotation).
    pub d_pos_d_att: [[f64; 3]; 3],
    /// Position covariance from the image alone, NED, m^2.
    pub image_cov_ned_m2: [[f64; 3]; 3],
}

impl PriorDependenceNed {
    /// All numbers finite.
    pub fn is_finite(&self) -> bool {
        self.d_pos_d_att
            .iter()
            .chain(self.image_cov_ned_m2.iter())
            .flatten()
            .all(|v| v.is_finite())
    }
}

/// The camera pose from the image alone, with the covariance of all six degrees of freedom.
///
/// Over flat ground seen by a narrow or near-nadir camera, a small tilt and a horizontal shift of
/// the camera move the image almost alike: the position and the tilt of this pose are each
/// uncertain along that direction but tightly correlated (|rho| above 0.99 is common). Fusing
/// both with their correlation lets a navigation filter use its own tilt knowledge once.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VisionOnlyPose {
    /// Camera projection centre: geodetic latitude (WGS84), degrees.
    pub lat_deg: f64,
    /// Camera projection centre: geodetic longitude (WGS84), degrees.
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, m.
    pub h_ellip_m: f64,
    /// Vehicle roll (body FRD to NED, aerospace ZYX) from the camera attitude through the
    /// camera mount, degrees.
    pub roll_deg: f64,
    /// Vehicle pitch, as `roll_deg`, degrees.
    pub pitch_deg: f64,
    /// Vehicle yaw (heading), as `roll_deg`, degrees.
    pub yaw_deg: f64,
    /// Covariance of `[position error NED (m, 3), attitude error (rad, 3)]`, row-major 6x6. The
    /// attitude error is the NED rotation vector `psi` with `R_estimate = Exp(psi) R_true`, the
    /// position error `estimate - true`: the navigation filter's error convention.
    pub cov6_ned: [[f64; 6]; 6],
}

impl VisionOnlyPose {
    /// The covariance as a matrix.
    pub fn cov6(&self) -> Matrix6<f64> {
        Matrix6::from_fn(|r, c| self.cov6_ned[r][c])
    }

    /// All numbers finite.
    pub fn is_finite(&self) -> bool {
        [
            self.lat_deg,
            self.lon_deg,
            self.h_ellip_m,
            self.roll_deg,
            self.pitch_deg,
            self.yaw_deg,
        ]
        .iter()
        .chain(self.cov6_ned.iter().flatten())
        .all(|v| v.is_finite())
    }
}

impl FixReport {
    /// A rejected report with the given reason and no pose (its numbers that are not finite
    /// are left out when serialised).
    pub fn rejected(rejection: Rejection, t_capture_us: u64, ms: f64) -> Self {
        Self {
            accepted: false,
            rejection: Some(rejection),
            t_capture_us,
            lat_deg: f64::NAN,
            lon_deg: f64::NAN,
            alt_amsl_m: f64::NAN,
            h_ellip_m: f64::NAN,
            x_m: f64::NAN,
            y_m: f64::NAN,
            z_m: f64::NAN,
            roll_deg: f64::NAN,
            pitch_deg: f64::NAN,
            yaw_deg: f64::NAN,
            cov_ned_m2: [[f64::NAN; 3]; 3],
            cov_att_ned_rad2: [[f64::NAN; 3]; 3],
            inliers: 0,
            matches: 0,
            reproj_rms_px: f64::NAN,
            sigma0: f64::NAN,
            cov_factor: f64::NAN,
            split_groups: 0,
            vision_only: None,
            prior_dependence: None,
            prior_attitude_from_filter: false,
            level: 0,
            method: FixMethod::Features,
            ms,
        }
    }

    /// The outcome in words: "ok" when accepted, otherwise the rejection (what people read).
    pub fn reason(&self) -> String {
        match &self.rejection {
            None => "ok".into(),
            Some(r) => r.to_string(),
        }
    }

    /// The outcome's class for counting: "ok" when accepted, otherwise
    /// [`Rejection::class`].
    pub fn class(&self) -> &'static str {
        self.rejection.as_ref().map_or("ok", Rejection::class)
    }

    /// The position covariance as a matrix.
    pub fn cov_ned(&self) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.cov_ned_m2[r][c])
    }
}

pub mod area;
pub mod engine;
pub mod rectify;
pub mod reference;
pub mod rejection;

pub use engine::{AreaMatching, FixEngine, FixError, FixParams};
pub use reference::{MemoryReference, RefFeature, RefSelection, Reference};
pub use rejection::{Rejection, Rival};

#[cfg(test)]
mod tests {
    use super::*;

    fn nulls(v: &serde_json::Value) -> usize {
        match v {
            serde_json::Value::Null => 1,
            serde_json::Value::Array(a) => a.iter().map(nulls).sum(),
            serde_json::Value::Object(o) => o.values().map(nulls).sum(),
            _ => 0,
        }
    }

    /// A serialised report holds numbers only: a rejected one leaves its position, angles and
    /// covariances out, a placement fix its resection's residual figures; what is finite stays.
    #[test]
    fn a_serialised_report_has_no_null_numbers() {
        let rejected = FixReport::rejected(Rejection::FewFeatures { n: 3 }, 7, 0.0);
        let v = serde_json::to_value(&rejected).unwrap();
        assert_eq!(nulls(&v), 0, "{v}");
        for gone in [
            "lat_deg",
            "x_m",
            "yaw_deg",
            "cov_ned_m2",
            "reproj_rms_px",
            "sigma0",
        ] {
            assert!(v.get(gone).is_none(), "{gone}: {v}");
        }
        assert_eq!(v["accepted"], false);
        assert_eq!(v["reason"], "only 3 features in the frame");
        assert_eq!(v["t_capture_us"], 7);
        let placement = FixReport {
            accepted: true,
            rejection: None,
            lat_deg: 47.0,
            lon_deg: -99.0,
            alt_amsl_m: 900.0,
            h_ellip_m: 878.0,
            x_m: 1.0,
            y_m: 2.0,
            z_m: 900.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            yaw_deg: 90.0,
            cov_ned_m2: [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 9e4]],
            cov_att_ned_rad2: [[1e-5, 0.0, 0.0], [0.0, 1e-5, 0.0], [0.0, 0.0, 1e-4]],
            method: FixMethod::Placement,
            ..rejected
        };
        let v = serde_json::to_value(&placement).unwrap();
        assert_eq!(nulls(&v), 0, "{v}");
        assert!(
            v.get("reproj_rms_px").is_none() && v.get("sigma0").is_none(),
            "{v}"
        );
        assert_eq!(v["lat_deg"], 47.0);
        assert_eq!(v["cov_ned_m2"][2][2], 9e4);
        assert_eq!(v["method"], "placement");
        assert_eq!(v["reason"], "ok");
        assert_eq!(v["inliers"], 0);
    }
}
