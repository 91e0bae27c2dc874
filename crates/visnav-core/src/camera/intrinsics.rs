//! Pinhole intrinsics: focal lengths and principal point in pixels, image size.
//!
//! Pixel convention: `u` to the right, `v` down, and the CENTRE of the top-left pixel is (0, 0), so
//! the image spans `[-0.5, w - 0.5] x [-0.5, h - 0.5]` and its centre is `((w-1)/2, (h-1)/2)`.
//! A normalised image point `(x, y) = (X/Z, Y/Z)` of the `_cam` frame (x right, y down, z forward)
//! maps to `u = fx x + cx`, `v = fy y + cy` (Hartley & Zisserman, eq. 6.4, zero skew).
//!
//! Constructors: from pixels directly, from a focal length and sensor size in millimetres
//! (`fx = f_mm * w_px / sensor_w_mm`, `fy = f_mm * h_px / sensor_h_mm`), or from the horizontal field of
//! view across the full image width (`fx = fy = (w/2) / tan(hfov/2)`). The latter two put the
//! principal point at the image centre.

use super::CameraError;
use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};

/// Pinhole camera intrinsics (zero skew).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along u, pixels.
    pub fx_px: f64,
    /// Focal length along v, pixels.
    pub fy_px: f64,
    /// Principal point u, pixels (top-left pixel centre at 0).
    pub cx_px: f64,
    /// Principal point v, pixels.
    pub cy_px: f64,
    /// Image width, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
}

fn invalid(name: &'static str, reason: String) -> CameraError {
    CameraError::InvalidParameter { name, reason }
}

impl Intrinsics {
    /// From focal lengths and principal point in pixels. Focal lengths must be finite and positive,
    /// the image non-empty and the principal point finite and inside the image.
    pub fn new(
        fx_px: f64,
        fy_px: f64,
        cx_px: f64,
        cy_px: f64,
        width_px: u32,
        height_px: u32,
    ) -> Result<Self, CameraError> {
        if width_px == 0 || height_px == 0 {
            return Err(invalid(
                "width_px/height_px",
                format!("image size {width_px}x{height_px} must be at least 1x1"),
            ));
        }
        for (name, f) in [("fx_px", fx_px), ("fy_px", fy_px)] {
            if !f.is_finite() || f <= 0.0 {
                return Err(invalid(name, format!("{f} must be finite and > 0")));
            }
        }
        for (name, c, n) in [("cx_px", cx_px, width_px), ("cy_px", cy_px, height_px)] {
            let hi = f64::from(n) - 0.5;
            if !c.is_finite() || c < -0.5 || c > hi {
                return Err(invalid(
                    name,
                    format!("{c} must lie inside the image [-0.5, {hi}]"),
                ));
            }
        }
        Ok(Self {
            fx_px,
            fy_px,
            cx_px,
            cy_px,
            width_px,
            height_px,
        })
    }

    /// Principal point at the image centre `((w-1)/2, (h-1)/2)`.
    pub fn centred(
        fx_px: f64,
        fy_px: f64,
        width_px: u32,
        height_px: u32,
    ) -> Result<Self, CameraError> {
        Self::new(
            fx_px,
            fy_px,
            (f64::from(width_px) - 1.0) / 2.0,
            (f64::from(height_px) - 1.0) / 2.0,
            width_px,
            height_px,
        )
    }

    /// From the focal length and the sensor's active area in millimetres, principal point centred.
    /// NGI DMC example: 120 mm, 92.16 x 165.888 mm, 640 x 1152 px gives fx = fy = 833.33 px.
    pub fn from_focal_length_mm(
        focal_length_mm: f64,
        sensor_width_mm: f64,
        sensor_height_mm: f64,
        width_px: u32,
        height_px: u32,
    ) -> Result<Self, CameraError> {
        for (name, v) in [
            ("focal_length_mm", focal_length_mm),
            ("sensor_width_mm", sensor_width_mm),
            ("sensor_height_mm", sensor_height_mm),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err(invalid(name, format!("{v} must be finite and > 0")));
            }
        }
        Self::centred(
            focal_length_mm * f64::from(width_px) / sensor_width_mm,
            focal_length_mm * f64::from(height_px) / sensor_height_mm,
            width_px,
            height_px,
        )
    }

    /// From the horizontal field of view across the full image width (pixel edges), square pixels,
    /// principal point centred. `hfov_rad` must be in (0, pi).
    pub fn from_hfov(hfov_rad: f64, width_px: u32, height_px: u32) -> Result<Self, CameraError> {
        if !hfov_rad.is_finite() || hfov_rad <= 0.0 || hfov_rad >= std::f64::consts::PI {
            return Err(invalid(
                "hfov",
                format!(
                    "{} deg must be inside (0, 180) deg for a pinhole camera",
                    hfov_rad.to_degrees()
                ),
            ));
        }
        let f = 0.5 * f64::from(width_px) / (0.5 * hfov_rad).tan();
        Self::centred(f, f, width_px, height_px)
    }

    /// Horizontal field of view across the full image width, radians.
    pub fn hfov_rad(&self) -> f64 {
        let w = f64::from(self.width_px);
        ((self.cx_px + 0.5) / self.fx_px).atan() + ((w - 0.5 - self.cx_px) / self.fx_px).atan()
    }

    /// Vertical field of view across the full image height, radians.
    pub fn vfov_rad(&self) -> f64 {
        let h = f64::from(self.height_px);
        ((self.cy_px + 0.5) / self.fy_px).atan() + ((h - 0.5 - self.cy_px) / self.fy_px).atan()
    }

    /// Normalised image point -> pixel (no distortion).
    pub fn to_pixel(&self, n: &Vector2<f64>) -> Point2<f64> {
        Point2::new(self.fx_px * n.x + self.cx_px, self.fy_px * n.y + self.cy_px)
    }

    /// Pixel -> normalised image point (no distortion).
    pub fn to_normalised(&self, px: &Point2<f64>) -> Vector2<f64> {
        Vector2::new(
            (px.x - self.cx_px) / self.fx_px,
            (px.y - self.cy_px) / self.fy_px,
        )
    }

    /// True when the pixel position lies on the image area `[-0.5, w-0.5) x [-0.5, h-0.5)`.
    pub fn contains(&self, px: &Point2<f64>) -> bool {
        px.x >= -0.5
            && px.y >= -0.5
            && px.x < f64::from(self.width_px) - 0.5
            && px.y < f64::from(self.height_px) - 0.5
    }

    /// The four outer image corners (pixel edges), clockwise from top-left.
    pub fn corners(&self) -> [Point2<f64>; 4] {
        let (r, b) = (
            f64::from(self.width_px) - 0.5,
            f64::from(self.height_px) - 0.5,
        );
        [
            Point2::new(-0.5, -0.5),
            Point2::new(r, -0.5),
            Point2::new(r, b),
            Point2::new(-0.5, b),
        ]
    }

    /// The same camera at a different resolution (scales focal lengths and keeps the pixel-centre
    /// convention: `c' = (c + 0.5) s - 0.5`).
    pub fn scaled(&self, width_px: u32, height_px: u32) -> Result<Self, CameraError> {
        let sx = f64::from(width_px) / f64::from(self.width_px);
        let sy = f64::from(height_px) / f64::from(self.height_px);
        Self::new(
            self.fx_px * sx,
            self.fy_px * sy,
            (self.cx_px + 0.5) * sx - 0.5,
            (self.cy_px + 0.5) * sy - 0.5,
            width_px,
            height_px,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ngi_focal_length_form() {
        let k = Intrinsics::from_focal_length_mm(120.0, 92.16, 165.888, 640, 1152).unwrap();
        assert!((k.fx_px - 833.333_333).abs() < 1e-5);
        assert!((k.fy_px - 833.333_333).abs() < 1e-5);
        assert_eq!((k.cx_px, k.cy_px), (319.5, 575.5));
    }

    #[test]
    fn hfov_round_trip() {
        let k = Intrinsics::from_hfov(60f64.to_radians(), 640, 480).unwrap();
        assert!((k.fx_px - 320.0 / 30f64.to_radians().tan()).abs() < 1e-9);
        assert!((k.hfov_rad().to_degrees() - 60.0).abs() < 1e-9);
        assert_eq!(k.fx_px, k.fy_px);
    }

    #[test]
    fn rejects_bad_values() {
        assert!(Intrinsics::new(0.0, 1.0, 1.0, 1.0, 10, 10).is_err());
        assert!(Intrinsics::new(1.0, f64::NAN, 1.0, 1.0, 10, 10).is_err());
        assert!(Intrinsics::new(1.0, 1.0, 9.6, 1.0, 10, 10).is_err());
        assert!(Intrinsics::new(1.0, 1.0, 1.0, -0.6, 10, 10).is_err());
        assert!(Intrinsics::new(1.0, 1.0, 0.0, 0.0, 0, 10).is_err());
        assert!(Intrinsics::from_hfov(std::f64::consts::PI, 10, 10).is_err());
        assert!(Intrinsics::from_focal_length_mm(10.0, -1.0, 1.0, 10, 10).is_err());
    }

    #[test]
    fn pixel_centre_convention() {
        let k = Intrinsics::centred(100.0, 100.0, 4, 2).unwrap();
        assert_eq!((k.cx_px, k.cy_px), (1.5, 0.5));
        // The optical axis hits the image centre; the top-left pixel centre is (0, 0).
        assert_eq!(k.to_pixel(&Vector2::zeros()), Point2::new(1.5, 0.5));
        assert!(k.contains(&Point2::new(-0.5, -0.5)));
        assert!(!k.contains(&Point2::new(3.5, 0.0)));
        let half = k.scaled(2, 1).unwrap();
        assert_eq!((half.cx_px, half.cy_px, half.fx_px), (0.5, 0.0, 50.0));
        let p = Point2::new(0.3, 1.7);
        assert!((k.to_pixel(&k.to_normalised(&p)) - p).norm() < 1e-12);
    }
}
