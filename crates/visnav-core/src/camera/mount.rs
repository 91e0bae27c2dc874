//! Camera mount on the vehicle: rotation `R_body_cam` and lever arm, plus the pose compositions
//! between vehicle attitude (NED) and camera orientation (NED, ENU/grid world, omega-phi-kappa).
//!
//! * `R_body_cam` maps `_cam` (x right, y down, z forward) coordinates into `_body_frd`.
//! * The lever arm is the camera's projection centre in `_body_frd`, metres, from the body origin
//!   (the point the navigation solution refers to).
//! * Nadir mount ([`Mount::nadir`]): camera looks straight down with the image top towards the nose:
//!   `x_cam = +y_body`, `y_cam = -x_body`, `z_cam = +z_body`, i.e. `R_body_cam = Rz(+90 deg) =
//!   [[0,-1,0],[1,0,0],[0,0,1]]`.
//! * Mount angles ([`Mount::from_angles`]): the camera sits nadir-mounted on a plate whose attitude
//!   relative to the body is the ZYX rotation `R_body_plate = Rz(yaw) Ry(pitch) Rx(roll)` (same
//!   convention and sign sense as the vehicle attitude), so
//!   `R_body_cam = Rz(yaw) Ry(pitch) Rx(roll) R_body_cam_nadir`. Positive pitch tilts the view
//!   forward (pitch = 90 deg: forward-looking camera, image top up); positive roll tilts it to the
//!   left (the plate's right side goes down); positive yaw turns the image top to the right.
//! * Compositions: `R_ned_cam = R_ned_body R_body_cam`, `R_enu_cam = R_enu_ned R_ned_cam`,
//!   camera centre `p_cam_ned = p_body_ned + R_ned_body * lever_arm_body_frd_m`.

use super::frames::{Attitude, Opk, r_enu_ned, rot_x, rot_y, rot_z};
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

/// Rigid mount of the camera on the vehicle body.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Mount {
    /// Camera (`_cam`) to body (`_body_frd`) rotation.
    pub r_body_cam: Rotation3<f64>,
    /// Camera projection centre in the body frame, metres.
    pub lever_arm_body_frd_m: Vector3<f64>,
}

impl Default for Mount {
    fn default() -> Self {
        Self::nadir()
    }
}

impl Mount {
    /// `R_body_cam` of the nadir mount with the image top towards the nose.
    pub fn nadir_r_body_cam() -> Rotation3<f64> {
        Rotation3::from_matrix_unchecked(Matrix3::new(
            0.0, -1.0, 0.0, //
            1.0, 0.0, 0.0, //
            0.0, 0.0, 1.0,
        ))
    }

    /// Nadir mount, no lever arm.
    pub fn nadir() -> Self {
        Self {
            r_body_cam: Self::nadir_r_body_cam(),
            lever_arm_body_frd_m: Vector3::zeros(),
        }
    }

    /// Mount tilted from nadir by ZYX angles (see module docs), with a lever arm.
    pub fn from_angles(
        roll_rad: f64,
        pitch_rad: f64,
        yaw_rad: f64,
        lever_arm_body_frd_m: Vector3<f64>,
    ) -> Self {
        Self {
            r_body_cam: rot_z(yaw_rad)
                * rot_y(pitch_rad)
                * rot_x(roll_rad)
                * Self::nadir_r_body_cam(),
            lever_arm_body_frd_m,
        }
    }

    /// The mount angles `(roll, pitch, yaw)` in radians that reproduce `r_body_cam` via
    /// [`Self::from_angles`] (pitch in [-pi/2, pi/2]).
    pub fn angles_rad(&self) -> (f64, f64, f64) {
        let plate = self.r_body_cam * Self::nadir_r_body_cam().inverse();
        let a = Attitude::from_r_ned_body(&plate);
        (a.roll_rad, a.pitch_rad, a.yaw_rad)
    }

    /// `R_ned_cam = R_ned_body R_body_cam`.
    pub fn r_ned_cam(&self, attitude: &Attitude) -> Rotation3<f64> {
        attitude.r_ned_body() * self.r_body_cam
    }

    /// `R_enu_cam = R_enu_ned R_ned_body R_body_cam` (camera to ENU / map-grid world).
    pub fn r_enu_cam(&self, attitude: &Attitude) -> Rotation3<f64> {
        r_enu_ned() * self.r_ned_cam(attitude)
    }

    /// Omega-phi-kappa of the camera for a vehicle attitude (world = ENU / map grid).
    pub fn opk(&self, attitude: &Attitude) -> Opk {
        Opk::from_r_world_cam(&self.r_enu_cam(attitude))
    }

    /// Vehicle attitude from the camera orientation in NED: `R_ned_body = R_ned_cam R_body_cam^T`.
    pub fn attitude_from_r_ned_cam(&self, r_ned_cam: &Rotation3<f64>) -> Attitude {
        Attitude::from_r_ned_body(&(r_ned_cam * self.r_body_cam.inverse()))
    }

    /// Vehicle attitude from the camera orientation in ENU / map grid (`R_enu_cam`).
    pub fn attitude_from_r_enu_cam(&self, r_enu_cam: &Rotation3<f64>) -> Attitude {
        // R_ned_enu = R_enu_ned (involution).
        self.attitude_from_r_ned_cam(&(r_enu_ned() * r_enu_cam))
    }

    /// Vehicle attitude from camera omega-phi-kappa (world = ENU / map grid).
    pub fn attitude_from_opk(&self, opk: &Opk) -> Attitude {
        self.attitude_from_r_enu_cam(&opk.r_world_cam())
    }

    /// Camera projection centre in NED from the body origin position and attitude.
    pub fn camera_position_ned(
        &self,
        body_ned_m: &Vector3<f64>,
        attitude: &Attitude,
    ) -> Vector3<f64> {
        body_ned_m + attitude.r_ned_body() * self.lever_arm_body_frd_m
    }

    /// Body origin position in NED from the camera projection centre and attitude.
    pub fn body_position_ned(
        &self,
        camera_ned_m: &Vector3<f64>,
        attitude: &Attitude,
    ) -> Vector3<f64> {
        camera_ned_m - attitude.r_ned_body() * self.lever_arm_body_frd_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn vclose(a: Vector3<f64>, b: Vector3<f64>) -> bool {
        (a - b).norm() < 1e-12
    }

    #[test]
    fn nadir_axes() {
        let r = Mount::nadir().r_body_cam;
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-15);
        assert!(vclose(r * Vector3::x(), Vector3::y()));
        assert!(vclose(r * Vector3::y(), -Vector3::x()));
        assert!(vclose(r * Vector3::z(), Vector3::z()));
        assert_eq!(Mount::nadir().angles_rad(), (0.0, 0.0, 0.0));
    }

    #[test]
    fn nadir_heading_north_image_top_north() {
        // Level vehicle heading north, nadir camera: OPK must be zero (image top north, looking down).
        let opk = Mount::nadir().opk(&Attitude::from_deg(0.0, 0.0, 0.0));
        for a in opk.to_deg() {
            assert!(a.abs() < 1e-12, "{opk:?}");
        }
        let r = Mount::nadir().r_enu_cam(&Attitude::from_deg(0.0, 0.0, 0.0));
        assert!(vclose(r * -Vector3::y(), Vector3::new(0.0, 1.0, 0.0))); // image top north
        assert!(vclose(r * Vector3::z(), Vector3::new(0.0, 0.0, -1.0))); // looks down
        assert!(vclose(r * Vector3::x(), Vector3::new(1.0, 0.0, 0.0))); // image right east
    }

    #[test]
    fn heading_east_and_south() {
        // Heading east: image top east, kappa = -90 deg (image top azimuth = -kappa).
        let opk = Mount::nadir().opk(&Attitude::from_deg(0.0, 0.0, 90.0));
        assert!((opk.kappa_rad.to_degrees() + 90.0).abs() < 1e-9, "{opk:?}");
        // Heading south: kappa = +-180 deg, like the NGI strip.
        let opk = Mount::nadir().opk(&Attitude::from_deg(0.0, 0.0, 180.0));
        assert!(
            (opk.kappa_rad.to_degrees().abs() - 180.0).abs() < 1e-9,
            "{opk:?}"
        );
    }

    #[test]
    fn mount_angle_senses() {
        let z = Vector3::zeros();
        // Pitch 90: forward-looking, image top up.
        let m = Mount::from_angles(0.0, 90f64.to_radians(), 0.0, z);
        assert!(vclose(m.r_body_cam * Vector3::z(), Vector3::x()));
        assert!(vclose(m.r_body_cam * -Vector3::y(), -Vector3::z()));
        // Small positive pitch: optical axis gets a forward component.
        let m = Mount::from_angles(0.0, 0.2, 0.0, z);
        assert!((m.r_body_cam * Vector3::z()).x > 0.0);
        // Positive roll: optical axis goes left (negative body y).
        let m = Mount::from_angles(0.2, 0.0, 0.0, z);
        assert!((m.r_body_cam * Vector3::z()).y < 0.0);
        // Positive yaw: image top turns right (positive body y).
        let m = Mount::from_angles(0.0, 0.0, 0.2, z);
        assert!((m.r_body_cam * -Vector3::y()).y > 0.0);
    }

    #[test]
    fn lever_arm_rotates_with_body() {
        let m = Mount::from_angles(0.0, 0.0, 0.0, Vector3::new(0.5, 0.0, 0.1));
        let att = Attitude::from_deg(0.0, 0.0, 90.0); // nose east
        let p = m.camera_position_ned(&Vector3::new(10.0, 20.0, -100.0), &att);
        assert!(vclose(p, Vector3::new(10.0, 20.5, -99.9)));
        assert!(vclose(
            m.body_position_ned(&p, &att),
            Vector3::new(10.0, 20.0, -100.0)
        ));
    }

    proptest! {
        #[test]
        fn mount_angles_round_trip(r in -3.1f64..3.1, p in -1.5f64..1.5, y in -3.1f64..3.1) {
            let m = Mount::from_angles(r, p, y, Vector3::zeros());
            let (r2, p2, y2) = m.angles_rad();
            prop_assert!((r - r2).abs() < 1e-9 && (p - p2).abs() < 1e-9 && (y - y2).abs() < 1e-9);
        }

        #[test]
        fn attitude_opk_round_trip(
            r in -0.5f64..0.5, p in -0.5f64..0.5, y in -3.1f64..3.1,
            mr in -0.3f64..0.3, mp in -1.2f64..1.2, my in -3.1f64..3.1,
        ) {
            let m = Mount::from_angles(mr, mp, my, Vector3::zeros());
            let att = Attitude::new(r, p, y);
            let back = m.attitude_from_opk(&m.opk(&att));
            prop_assert!((back.roll_rad - r).abs() < 1e-9);
            prop_assert!((back.pitch_rad - p).abs() < 1e-9);
            prop_assert!((back.yaw_rad - y).abs() < 1e-9);
        }

        #[test]
        fn composition_is_associative_with_mount(
            r in -0.5f64..0.5, p in -0.5f64..0.5, y in -3.1f64..3.1,
            vx in -1.0f64..1.0, vy in -1.0f64..1.0, vz in 0.1f64..1.0,
        ) {
            // A camera ray mapped to NED via the composed rotation equals mapping it to the body first.
            let m = Mount::from_angles(0.1, 0.3, -0.2, Vector3::zeros());
            let att = Attitude::new(r, p, y);
            let v_cam = Vector3::new(vx, vy, vz);
            let direct = m.r_ned_cam(&att) * v_cam;
            let stepwise = att.r_ned_body() * (m.r_body_cam * v_cam);
            prop_assert!((direct - stepwise).norm() < 1e-12);
            // And ENU is the NED vector with x/y swapped and z negated.
            let enu = m.r_enu_cam(&att) * v_cam;
            prop_assert!((enu - Vector3::new(direct.y, direct.x, -direct.z)).norm() < 1e-12);
        }
    }
}
