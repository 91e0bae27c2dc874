//! Reference frames and rotation conventions for the camera, the vehicle body and the world.
//!
//! # Frames
//! * `_cam`: computer-vision camera frame. x right, y down, z forward along the optical axis.
//! * `_pg`: photogrammetric camera frame (PATB, used by aerial triangulation and the NGI truth).
//!   x right, y up, z backwards (the camera looks along -z). `v_pg = R_pg_cam * v_cam` with
//!   `R_pg_cam = diag(1, -1, -1)` (a 180 deg rotation about x, its own inverse).
//! * `_body_frd`: vehicle body, x forward (nose), y right (starboard wing), z down.
//! * `_ned`: local-level north, east, down.
//! * `_enu` / world: local-level east, north, up. The photogrammetric "map grid" world (x = grid
//!   easting, y = grid northing, z = height up) has the same axis order; it differs from true ENU
//!   only by the meridian convergence (a rotation about z), which callers apply when it matters.
//!   `v_enu = R_enu_ned * v_ned` with `R_enu_ned = [[0,1,0],[1,0,0],[0,0,-1]]`.
//!
//! # Rotations
//! `R_a_b` maps coordinates of a vector expressed in frame `b` into frame `a`: `v_a = R_a_b * v_b`.
//! Its columns are the axes of `b` written in `a`. Elementary rotations are the usual right-handed
//! active ones: `Rx(a) = [[1,0,0],[0,c,-s],[0,s,c]]`, `Ry(a) = [[c,0,s],[0,1,0],[-s,0,c]]`,
//! `Rz(a) = [[c,-s,0],[s,c,0],[0,0,1]]`.
//!
//! * Omega-phi-kappa (PATB, as in `ngi_3324c/README.md`): `R_world_pg = Rx(omega) Ry(phi) Rz(kappa)`
//!   maps photogrammetric camera coordinates into the world (x east, y north, z up). Hence
//!   `R_world_cam = Rx(omega) Ry(phi) Rz(kappa) R_pg_cam`. With all angles zero the camera looks
//!   straight down and the image top (-y_cam = +y_pg) points north; kappa = 180 deg turns the
//!   image top south. Recovery: `phi = asin(R13)`, `omega = atan2(-R23, R33)`,
//!   `kappa = atan2(-R12, R11)` (1-based indices of `R_world_pg`), phi in [-90, 90] deg.
//! * Vehicle attitude: Tait-Bryan ZYX, `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)` (aerospace
//!   convention, same as nalgebra's `Rotation3::from_euler_angles(roll, pitch, yaw)`). Recovery:
//!   `pitch = asin(-R31)`, `roll = atan2(R32, R33)`, `yaw = atan2(R21, R11)`.

use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

/// Right-handed elementary rotation about x by `a_rad`.
pub fn rot_x(a_rad: f64) -> Rotation3<f64> {
    let (s, c) = a_rad.sin_cos();
    Rotation3::from_matrix_unchecked(Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c))
}

/// Right-handed elementary rotation about y by `a_rad`.
pub fn rot_y(a_rad: f64) -> Rotation3<f64> {
    let (s, c) = a_rad.sin_cos();
    Rotation3::from_matrix_unchecked(Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c))
}

/// Right-handed elementary rotation about z by `a_rad`.
pub fn rot_z(a_rad: f64) -> Rotation3<f64> {
    let (s, c) = a_rad.sin_cos();
    Rotation3::from_matrix_unchecked(Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
}

/// `R_pg_cam = diag(1, -1, -1)`: computer-vision camera frame to photogrammetric camera frame.
/// It is its own inverse, so it also serves as `R_cam_pg`.
pub fn r_pg_cam() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0)))
}

/// `R_enu_ned`: swaps north/east and flips down to up. It is its own inverse (`R_ned_enu`).
pub fn r_enu_ned() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0))
}

/// Wrap an angle to (-pi, pi].
pub fn wrap_pi(a_rad: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut w = a_rad % two_pi;
    if w <= -std::f64::consts::PI {
        w += two_pi;
    } else if w > std::f64::consts::PI {
        w -= two_pi;
    }
    w
}

/// Photogrammetric exterior-orientation angles (PATB omega-phi-kappa), see the module docs:
/// `R_world_pg = Rx(omega) Ry(phi) Rz(kappa)`, world = (x east/grid east, y north/grid north, z up).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Opk {
    /// Rotation about the world x axis (applied last), radians.
    pub omega_rad: f64,
    /// Rotation about the y axis, radians, in [-pi/2, pi/2] when recovered from a matrix.
    pub phi_rad: f64,
    /// Rotation about the photogrammetric camera's z axis (applied first), radians; the image
    /// top's azimuth is -kappa.
    pub kappa_rad: f64,
}

impl Opk {
    /// From angles in radians.
    pub fn new(omega_rad: f64, phi_rad: f64, kappa_rad: f64) -> Self {
        Self {
            omega_rad,
            phi_rad,
            kappa_rad,
        }
    }

    /// From angles in degrees (as in `frames_truth.csv`).
    pub fn from_deg(omega_deg: f64, phi_deg: f64, kappa_deg: f64) -> Self {
        Self::new(
            omega_deg.to_radians(),
            phi_deg.to_radians(),
            kappa_deg.to_radians(),
        )
    }

    /// `[omega, phi, kappa]` in degrees.
    pub fn to_deg(&self) -> [f64; 3] {
        [
            self.omega_rad.to_degrees(),
            self.phi_rad.to_degrees(),
            self.kappa_rad.to_degrees(),
        ]
    }

    /// `R_world_pg = Rx(omega) Ry(phi) Rz(kappa)` (photogrammetric camera -> world ENU/grid).
    pub fn r_world_pg(&self) -> Rotation3<f64> {
        rot_x(self.omega_rad) * rot_y(self.phi_rad) * rot_z(self.kappa_rad)
    }

    /// `R_world_cam = R_world_pg R_pg_cam` (computer-vision camera -> world ENU/grid).
    pub fn r_world_cam(&self) -> Rotation3<f64> {
        self.r_world_pg() * r_pg_cam()
    }

    /// Angles of a photogrammetric-camera-to-world rotation. phi in [-pi/2, pi/2], omega and kappa
    /// in (-pi, pi]. At phi = +-90 deg (never the case for a mapping camera) omega and kappa are not
    /// separable: omega is set to 0 and kappa takes the whole rotation; the matrix is reproduced.
    pub fn from_r_world_pg(r_world_pg: &Rotation3<f64>) -> Self {
        let m = r_world_pg.matrix();
        let phi = m[(0, 2)].clamp(-1.0, 1.0).asin();
        let cos_phi = (m[(0, 0)].powi(2) + m[(0, 1)].powi(2)).sqrt();
        if cos_phi < 1e-9 {
            // Gimbal lock: set omega = 0; then R = Ry(phi) Rz(kappa) gives R21 = sin(kappa), R22 = cos(kappa).
            let kappa = m[(1, 0)].atan2(m[(1, 1)]);
            return Self::new(0.0, phi, kappa);
        }
        let omega = (-m[(1, 2)]).atan2(m[(2, 2)]);
        let kappa = (-m[(0, 1)]).atan2(m[(0, 0)]);
        Self::new(omega, phi, kappa)
    }

    /// Angles of a computer-vision-camera-to-world rotation (`R_world_cam`).
    pub fn from_r_world_cam(r_world_cam: &Rotation3<f64>) -> Self {
        // R_world_pg = R_world_cam R_cam_pg, and R_cam_pg = R_pg_cam.
        Self::from_r_world_pg(&(r_world_cam * r_pg_cam()))
    }
}

/// Vehicle attitude as Tait-Bryan ZYX angles: `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`.
/// Yaw is the heading of the nose from north, positive towards east; pitch positive nose up;
/// roll positive right wing down.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Attitude {
    /// Roll about the body x axis, radians, positive right wing down.
    pub roll_rad: f64,
    /// Pitch about the body y axis, radians, positive nose up.
    pub pitch_rad: f64,
    /// Heading of the nose from true north, radians, positive towards east.
    pub yaw_rad: f64,
}

impl Attitude {
    /// From angles in radians.
    pub fn new(roll_rad: f64, pitch_rad: f64, yaw_rad: f64) -> Self {
        Self {
            roll_rad,
            pitch_rad,
            yaw_rad,
        }
    }

    /// From angles in degrees.
    pub fn from_deg(roll_deg: f64, pitch_deg: f64, yaw_deg: f64) -> Self {
        Self::new(
            roll_deg.to_radians(),
            pitch_deg.to_radians(),
            yaw_deg.to_radians(),
        )
    }

    /// `R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`.
    pub fn r_ned_body(&self) -> Rotation3<f64> {
        rot_z(self.yaw_rad) * rot_y(self.pitch_rad) * rot_x(self.roll_rad)
    }

    /// Angles of a body-to-NED rotation: pitch in [-pi/2, pi/2], roll and yaw in (-pi, pi].
    /// At pitch = +-90 deg roll is set to 0 and the whole rotation about the vertical goes to yaw.
    pub fn from_r_ned_body(r_ned_body: &Rotation3<f64>) -> Self {
        let m = r_ned_body.matrix();
        let pitch = (-m[(2, 0)]).clamp(-1.0, 1.0).asin();
        let cos_pitch = (m[(2, 1)].powi(2) + m[(2, 2)].powi(2)).sqrt();
        if cos_pitch < 1e-9 {
            // R = Rz(yaw) Ry(+-90): R12 = -sin(yaw), R22 = cos(yaw).
            let yaw = (-m[(0, 1)]).atan2(m[(1, 1)]);
            return Self::new(0.0, pitch, yaw);
        }
        let roll = m[(2, 1)].atan2(m[(2, 2)]);
        let yaw = m[(1, 0)].atan2(m[(0, 0)]);
        Self::new(roll, pitch, yaw)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    fn close(a: &Rotation3<f64>, b: &Rotation3<f64>, tol: f64) -> bool {
        (a.matrix() - b.matrix()).amax() < tol
    }

    #[test]
    fn elementary_rotations_match_nalgebra() {
        for a in [-2.0, -0.3, 0.0, 0.7, 3.0] {
            assert!(close(
                &rot_x(a),
                &Rotation3::from_axis_angle(&Vector3::x_axis(), a),
                1e-15
            ));
            assert!(close(
                &rot_y(a),
                &Rotation3::from_axis_angle(&Vector3::y_axis(), a),
                1e-15
            ));
            assert!(close(
                &rot_z(a),
                &Rotation3::from_axis_angle(&Vector3::z_axis(), a),
                1e-15
            ));
        }
    }

    #[test]
    fn fixed_frame_changes_are_proper_involutions() {
        for r in [r_pg_cam(), r_enu_ned()] {
            assert!((r.matrix().determinant() - 1.0).abs() < 1e-15);
            assert!(close(&(r * r), &Rotation3::identity(), 1e-15));
        }
        // North in NED is y (north) in ENU; down is -z.
        let v = r_enu_ned() * Vector3::new(1.0, 2.0, 3.0);
        assert_eq!(v, Vector3::new(2.0, 1.0, -3.0));
    }

    #[test]
    fn opk_zero_is_nadir_with_image_top_north() {
        let r = Opk::new(0.0, 0.0, 0.0).r_world_cam();
        // Optical axis (+z_cam) points down, image top (-y_cam) north, image right (+x_cam) east.
        assert!((r * Vector3::z() - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-15);
        assert!((r * -Vector3::y() - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-15);
        assert!((r * Vector3::x() - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-15);
    }

    #[test]
    fn ngi_kappa_minus_179_points_image_top_south() {
        // frame_05_0182 truth.
        let opk = Opk::from_deg(-0.349216, 0.298484, -179.086702);
        let r = opk.r_world_cam();
        let top = r * -Vector3::y();
        let axis = r * Vector3::z();
        assert!(axis.z < -0.999, "camera must look down, axis {axis:?}");
        // Image top is within 1 deg of south (horizontal component).
        let az_deg = top.x.atan2(top.y).to_degrees(); // azimuth from north towards east
        assert!(
            (az_deg.abs() - 180.0).abs() < 1.0,
            "image top azimuth {az_deg} deg"
        );
        // Rz(kappa) turns +y_pg (image top) to azimuth -kappa (clockwise from north): 179.09 deg.
        assert!((wrap_pi((-opk.kappa_rad) - az_deg.to_radians())).abs() < 0.02);
    }

    #[test]
    fn attitude_matches_nalgebra_euler() {
        let a = Attitude::new(0.1, -0.2, 2.5);
        let n = Rotation3::from_euler_angles(0.1, -0.2, 2.5);
        assert!(close(&a.r_ned_body(), &n, 1e-14));
        // Yaw 90 deg: nose points east.
        let nose = Attitude::from_deg(0.0, 0.0, 90.0).r_ned_body() * Vector3::x();
        assert!((nose - Vector3::new(0.0, 1.0, 0.0)).norm() < 1e-15);
        // Pitch up: nose gets a negative down component.
        let nose = Attitude::from_deg(0.0, 10.0, 0.0).r_ned_body() * Vector3::x();
        assert!(nose.z < 0.0);
        // Roll right: right wing gets a positive down component.
        let wing = Attitude::from_deg(10.0, 0.0, 0.0).r_ned_body() * Vector3::y();
        assert!(wing.z > 0.0);
    }

    #[test]
    fn gimbal_lock_still_reproduces_matrix() {
        let r = Opk::new(0.4, FRAC_PI_2, -1.0).r_world_pg();
        assert!(close(&Opk::from_r_world_pg(&r).r_world_pg(), &r, 1e-9));
        let r = Attitude::new(0.4, -FRAC_PI_2, 1.0).r_ned_body();
        assert!(close(&Attitude::from_r_ned_body(&r).r_ned_body(), &r, 1e-9));
    }

    #[test]
    fn wrap_pi_range() {
        assert!((wrap_pi(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_pi(-PI) - PI).abs() < 1e-12);
        assert!((wrap_pi(0.5 + 4.0 * PI) - 0.5).abs() < 1e-12);
    }

    proptest! {
        #[test]
        fn opk_round_trip(o in -3.1f64..3.1, p in -1.55f64..1.55, k in -3.1f64..3.1) {
            let opk = Opk::new(o, p, k);
            let back = Opk::from_r_world_cam(&opk.r_world_cam());
            prop_assert!((back.omega_rad - o).abs() < 1e-9);
            prop_assert!((back.phi_rad - p).abs() < 1e-9);
            prop_assert!((back.kappa_rad - k).abs() < 1e-9);
        }

        #[test]
        fn matrix_opk_round_trip(ax in -1.0f64..1.0, ay in -1.0f64..1.0, az in -1.0f64..1.0, ang in 0.0f64..3.1) {
            let axis = Vector3::new(ax, ay, az);
            prop_assume!(axis.norm() > 1e-3);
            let r = Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), ang);
            prop_assert!(close(&Opk::from_r_world_cam(&r).r_world_cam(), &r, 1e-9));
            prop_assert!(close(&Attitude::from_r_ned_body(&r).r_ned_body(), &r, 1e-9));
        }

        #[test]
        fn attitude_round_trip(r in -3.1f64..3.1, p in -1.55f64..1.55, y in -3.1f64..3.1) {
            let a = Attitude::new(r, p, y);
            let back = Attitude::from_r_ned_body(&a.r_ned_body());
            prop_assert!((back.roll_rad - r).abs() < 1e-9);
            prop_assert!((back.pitch_rad - p).abs() < 1e-9);
            prop_assert!((back.yaw_rad - y).abs() < 1e-9);
        }
    }
}
