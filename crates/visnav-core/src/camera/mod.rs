//! Camera model: pinhole intrinsics, Brown-Conrady distortion, camera-to-body mount, and the frame
//! and rotation conventions that connect the camera to the vehicle and to the map.
//!
//! # Conventions (copied into `docs/conventions.md`)
//! * Camera frame `_cam`: computer-vision convention, x right, y down, z forward (optical axis).
//! * Pixels `(u, v)`: u right, v down; the CENTRE of the top-left pixel is (0, 0), the image centre is
//!   `((w-1)/2, (h-1)/2)`. `u = fx x + cx`, `v = fy y + cy` on distorted normalised coordinates.
//! * Photogrammetric camera frame `_pg` (PATB): x right, y up, z backwards;
//!   `R_pg_cam = diag(1, -1, -1)`.
//! * Body `_body_frd`: x forward, y right, z down. Mount `R_body_cam` + lever arm (camera centre in
//!   body FRD, metres). Nadir mount: image top towards the nose (`x_cam = y_body`,
//!   `y_cam = -x_body`, `z_cam = z_body`). Mount angles are a ZYX roll/pitch/yaw of a plate carrying
//!   the nadir camera: `R_body_cam = Rz(yaw) Ry(pitch) Rx(roll) R_body_cam_nadir`.
//! * World: local NED, and ENU / map grid (x east, y north, z up); `R_enu_ned = [[0,1,0],[1,0,0],[0,0,-1]]`.
//! * `R_a_b` maps vectors from frame b into frame a. Omega-phi-kappa:
//!   `R_world_pg = Rx(omega) Ry(phi) Rz(kappa)`, so `R_world_cam = Rx Ry Rz diag(1,-1,-1)`.
//!   Vehicle attitude: `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`.
//!
//! Details and equations live in the submodules: [`frames`], [`intrinsics`], [`distortion`],
//! [`mount`], [`config`].

pub mod config;
pub mod distortion;
pub mod frames;
pub mod intrinsics;
pub mod mount;

pub use config::{CameraConfig, DistortionConfig, MountConfig};
pub use distortion::Distortion;
pub use frames::{Attitude, Opk};
pub use intrinsics::Intrinsics;
pub use mount::Mount;

use crate::validate::Invalid;
use nalgebra::{Point2, Rotation3, Unit, Vector3};

/// Minimum depth (metres along the optical axis) for a point to be projected; also excludes points
/// behind the camera.
const MIN_DEPTH_M: f64 = 1e-9;

/// Errors building a camera model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// One parameter of a programmatic constructor is out of range.
    #[error("invalid camera parameter {name}: {reason}")]
    InvalidParameter {
        /// Name of the parameter.
        name: &'static str,
        /// Why it was refused, with the value.
        reason: String,
    },
    /// The configuration section failed validation (dotted keys relative to the camera section).
    #[error("invalid camera configuration: {}", list.iter().map(|i| i.to_string()).collect::<Vec<_>>().join("; "))]
    Config {
        /// Every problem found, each with its key, value and accepted range.
        list: Vec<Invalid>,
    },
}

/// A complete camera: intrinsics, lens distortion and mount on the vehicle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Pinhole intrinsics and image size.
    pub intrinsics: Intrinsics,
    /// Lens distortion on normalised coordinates.
    pub distortion: Distortion,
    /// Orientation and lever arm of the camera on the body.
    pub mount: Mount,
    /// Cached [`Distortion::max_radius`]: largest valid normalised (undistorted) radius.
    max_radius: f64,
}

impl Camera {
    /// Assemble a camera. The intrinsics are re-checked (their fields are public), non-finite
    /// distortion coefficients or mount values are rejected.
    pub fn new(
        intrinsics: Intrinsics,
        distortion: Distortion,
        mount: Mount,
    ) -> Result<Self, CameraError> {
        let k = intrinsics;
        Intrinsics::new(k.fx_px, k.fy_px, k.cx_px, k.cy_px, k.width_px, k.height_px)?;
        if !distortion.is_finite() {
            return Err(CameraError::InvalidParameter {
                name: "distortion",
                reason: format!(
                    "coefficients must be finite, got k1, k2, k3, p1, p2 = {}",
                    crate::text::numbers(&distortion.coefficients())
                ),
            });
        }
        if !mount.lever_arm_body_frd_m.iter().all(|c| c.is_finite())
            || !mount.r_body_cam.matrix().iter().all(|c| c.is_finite())
        {
            return Err(CameraError::InvalidParameter {
                name: "mount",
                reason: format!(
                    "rotation and lever arm must be finite, got the rotation {} (row by row) \
                     and the lever arm {} m",
                    crate::text::numbers(mount.r_body_cam.matrix().transpose().as_slice()),
                    crate::text::numbers(mount.lever_arm_body_frd_m.as_slice())
                ),
            });
        }
        Ok(Self {
            intrinsics,
            distortion,
            mount,
            max_radius: distortion.max_radius(),
        })
    }

    /// Distortion-free camera on the nadir mount (checks the intrinsics like [`Self::new`]).
    pub fn pinhole(intrinsics: Intrinsics) -> Result<Self, CameraError> {
        Self::new(intrinsics, Distortion::none(), Mount::nadir())
    }

    /// Image width in pixels.
    pub fn width_px(&self) -> u32 {
        self.intrinsics.width_px
    }

    /// Image height in pixels.
    pub fn height_px(&self) -> u32 {
        self.intrinsics.height_px
    }

    /// Largest normalised ideal radius where the lens model is one-to-one (see [`Distortion::max_radius`]).
    pub fn max_radius(&self) -> f64 {
        self.max_radius
    }

    /// Project a point in the `_cam` frame to a (distorted) pixel. `None` when the point is not in
    /// front of the camera (z <= 1e-9 m), is not finite, or lies outside the radius where the
    /// distortion model is valid (it would fold back into the image). The pixel may lie outside the
    /// image; check with [`Intrinsics::contains`] or use [`Self::project_in_image`].
    pub fn project(&self, p_cam: &Vector3<f64>) -> Option<Point2<f64>> {
        if !p_cam.z.is_finite()
            || p_cam.z <= MIN_DEPTH_M
            || !p_cam.x.is_finite()
            || !p_cam.y.is_finite()
        {
            return None;
        }
        let n = p_cam.xy() / p_cam.z;
        let r = n.norm();
        if r.is_nan() || r > self.max_radius {
            return None;
        }
        let px = self.intrinsics.to_pixel(&self.distortion.distort(&n));
        (px.x.is_finite() && px.y.is_finite()).then_some(px)
    }

    /// [`Self::project`], keeping only pixels on the image area.
    pub fn project_in_image(&self, p_cam: &Vector3<f64>) -> Option<Point2<f64>> {
        self.project(p_cam)
            .filter(|px| self.intrinsics.contains(px))
    }

    /// Unit ray in the `_cam` frame through a (distorted) pixel; `None` if the pixel is not finite or
    /// the distortion cannot be inverted there. Pixels outside the image are accepted.
    pub fn unproject(&self, px: &Point2<f64>) -> Option<Unit<Vector3<f64>>> {
        let nd = self.intrinsics.to_normalised(px);
        let n = self.distortion.undistort_within(&nd, self.max_radius)?;
        let ray = Vector3::new(n.x, n.y, 1.0);
        ray.iter()
            .all(|c| c.is_finite())
            .then(|| Unit::new_normalize(ray))
    }
}

/// Exterior orientation of a camera in a world frame: `p_world = R_world_cam p_cam + centre_world`.
/// The world is whatever frame `r_world_cam` targets (ENU / map grid for [`Opk`], or NED).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// Camera (`_cam`, computer-vision axes) to world rotation.
    pub r_world_cam: Rotation3<f64>,
    /// Projection centre in world coordinates, metres.
    pub centre_world_m: Vector3<f64>,
}

impl CameraPose {
    /// From a projection centre (x east/grid, y north/grid, z up) and omega-phi-kappa.
    pub fn from_opk(centre_world_m: Vector3<f64>, opk: &Opk) -> Self {
        Self {
            r_world_cam: opk.r_world_cam(),
            centre_world_m,
        }
    }

    /// World point to `_cam` coordinates: `R_world_cam^T (p - c)`.
    pub fn cam_from_world(&self, p_world_m: &Vector3<f64>) -> Vector3<f64> {
        self.r_world_cam.inverse() * (p_world_m - self.centre_world_m)
    }

    /// `_cam` point to world coordinates.
    pub fn world_from_cam(&self, p_cam_m: &Vector3<f64>) -> Vector3<f64> {
        self.r_world_cam * p_cam_m + self.centre_world_m
    }

    /// World-frame unit direction of the ray through a pixel (starts at `centre_world_m`).
    pub fn ray_world(&self, camera: &Camera, px: &Point2<f64>) -> Option<Unit<Vector3<f64>>> {
        camera
            .unproject(px)
            .map(|r| Unit::new_unchecked(self.r_world_cam * r.into_inner()))
    }

    /// Pixel of a world point, `None` as for [`Camera::project`].
    pub fn project_world(&self, camera: &Camera, p_world_m: &Vector3<f64>) -> Option<Point2<f64>> {
        camera.project(&self.cam_from_world(p_world_m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn ngi() -> Camera {
        Camera::pinhole(Intrinsics::from_focal_length_mm(120.0, 92.16, 165.888, 640, 1152).unwrap())
            .unwrap()
    }

    fn wide() -> Camera {
        Camera::new(
            Intrinsics::new(900.0, 905.0, 645.0, 470.0, 1280, 960).unwrap(),
            Distortion {
                k1: -0.28,
                k2: 0.07,
                k3: 0.0,
                p1: 0.0012,
                p2: -0.0008,
            },
            Mount::nadir(),
        )
        .unwrap()
    }

    #[test]
    fn optical_axis_hits_principal_point() {
        let c = ngi();
        let px = c.project(&Vector3::new(0.0, 0.0, 5.0)).unwrap();
        assert_eq!(px, Point2::new(319.5, 575.5));
        let ray = c.unproject(&Point2::new(319.5, 575.5)).unwrap();
        assert!((ray.into_inner() - Vector3::z()).norm() < 1e-15);
        // A point to the right and below lands right of and below the centre.
        let px = c.project(&Vector3::new(1.0, 2.0, 10.0)).unwrap();
        assert!((px.x - (319.5 + 83.333_333)).abs() < 1e-4);
        assert!((px.y - (575.5 + 166.666_667)).abs() < 1e-4);
    }

    #[test]
    fn behind_camera_and_non_finite_are_none() {
        let c = wide();
        assert!(c.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
        assert!(c.project(&Vector3::new(1.0, 0.0, 0.0)).is_none());
        assert!(c.project(&Vector3::new(f64::NAN, 0.0, 1.0)).is_none());
        assert!(c.project(&Vector3::new(0.0, 0.0, f64::NAN)).is_none());
        assert!(c.unproject(&Point2::new(f64::INFINITY, 0.0)).is_none());
        // This lens never folds over (1 - 0.84 s + 0.35 s^2 > 0 for all s = r^2).
        assert_eq!(c.max_radius(), f64::INFINITY);
        // Pure k1 = -0.3 folds at r = 1.054: a point at r = 1.5 would distort to r_d = 0.49 (inside
        // the image) and must be refused rather than folded back.
        let folding = Camera::new(
            c.intrinsics,
            Distortion {
                k1: -0.3,
                ..Distortion::none()
            },
            Mount::nadir(),
        )
        .unwrap();
        assert!((folding.max_radius() - 1.0 / 0.9f64.sqrt()).abs() < 1e-9);
        assert!(folding.project(&Vector3::new(1.5, 0.0, 1.0)).is_none());
        assert!(folding.project(&Vector3::new(1.0, 0.0, 1.0)).is_some());
        assert!(c.project_in_image(&Vector3::new(0.0, 0.0, 1.0)).is_some());
        assert!(c.project_in_image(&Vector3::new(5.0, 0.0, 1.0)).is_none());
    }

    #[test]
    fn invalid_parts_rejected() {
        let mut k = ngi().intrinsics;
        k.fx_px = 0.0;
        assert!(Camera::new(k, Distortion::none(), Mount::nadir()).is_err());
        assert!(Camera::pinhole(k).is_err());
        let mut m = Mount::nadir();
        m.lever_arm_body_frd_m.x = f64::NAN;
        assert!(Camera::new(ngi().intrinsics, Distortion::none(), m).is_err());
    }

    #[test]
    fn nonfinite_distortion_rejected() {
        let d = Distortion {
            k1: f64::NAN,
            ..Distortion::none()
        };
        assert!(Camera::new(ngi().intrinsics, d, Mount::nadir()).is_err());
    }

    #[test]
    fn pose_round_trip_and_nadir_footprint() {
        // Nadir camera 1000 m above ground heading north (OPK zero): a ground point 100 m north of the
        // nadir point appears above the image centre (smaller v), one 100 m east to the right.
        let c = ngi();
        let pose =
            CameraPose::from_opk(Vector3::new(500.0, 800.0, 1000.0), &Opk::new(0.0, 0.0, 0.0));
        let north = pose
            .project_world(&c, &Vector3::new(500.0, 900.0, 0.0))
            .unwrap();
        let east = pose
            .project_world(&c, &Vector3::new(600.0, 800.0, 0.0))
            .unwrap();
        assert!((north.x - 319.5).abs() < 1e-9 && (north.y - (575.5 - 83.333_333)).abs() < 1e-4);
        assert!((east.y - 575.5).abs() < 1e-9 && (east.x - (319.5 + 83.333_333)).abs() < 1e-4);
        let ray = pose.ray_world(&c, &north).unwrap();
        let hit = pose.centre_world_m + ray.into_inner() * (1000.0 / -ray.z);
        assert!((hit - Vector3::new(500.0, 900.0, 0.0)).norm() < 1e-6);
        // Kappa 180: the same point north now appears below the centre (image top south).
        let pose = CameraPose::from_opk(pose.centre_world_m, &Opk::from_deg(0.0, 0.0, 180.0));
        let north = pose
            .project_world(&c, &Vector3::new(500.0, 900.0, 0.0))
            .unwrap();
        assert!(north.y > 575.5 + 80.0);
    }

    proptest! {
        #[test]
        fn unproject_project_round_trip(u in -0.5f64..1279.5, v in -0.5f64..959.5) {
            let c = wide();
            let px = Point2::new(u, v);
            let ray = c.unproject(&px);
            prop_assert!(ray.is_some());
            let ray = ray.unwrap();
            prop_assert!((ray.norm() - 1.0).abs() < 1e-12);
            let back = c.project(&(ray.into_inner() * 7.5)).unwrap();
            prop_assert!((back - px).norm() < 1e-6, "{} -> {}", px, back);
        }

        #[test]
        fn project_unproject_round_trip(x in -0.6f64..0.6, y in -0.45f64..0.45, z in 0.1f64..1e4) {
            let c = wide();
            let p = Vector3::new(x * z, y * z, z);
            let px = c.project(&p).unwrap();
            let ray = c.unproject(&px).unwrap();
            prop_assert!((ray.into_inner() - p.normalize()).norm() < 1e-9);
        }
    }
}
