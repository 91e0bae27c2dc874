//! Rectification of a camera frame to a virtual nadir, north-up (map-grid) camera at a chosen scale.
//!
//! The virtual camera shares the real camera's projection centre; only its orientation and focal
//! length differ, so the warp is the infinite homography `H = K_v R_virt_cam K^-1` (plus the real
//! lens's distortion) and needs neither the position nor the terrain. Its axes, in the map grid
//! frame (x east, y north, z up): `x_virt` = east, `y_virt` = south (image down), `z_virt` = down
//! (optical axis), i.e. `R_map_virt = diag(1, -1, -1)`. With focal length `f_v = AGL / gsd` a pixel
//! of the virtual image covers `gsd` metres of flat ground at AGL below, the scale of a map level, so
//! upright SURF (no orientation) sees the same geometry in the frame and in the map.
//!
//! Every virtual pixel remembers the frame pixel it was sampled from ([`Rectification::to_frame_px`],
//! the same function used for sampling), so keypoints found in the rectified image map back to the
//! original (distorted) pixel coordinates exactly, whatever the error of the attitude used.
//!
//! Downsampling is antialiased: the frame is first halved (2x2 means) `k` times so the remaining
//! resampling factor lies in about [0.6, 1.25].

use nalgebra::{Matrix3, Point2, Rotation3, Vector3};
use rayon::prelude::*;

use super::reference::half_size;
use crate::camera::Camera;
use crate::vision::GrayImage;

/// `R_map_virt`: the virtual nadir camera's axes in the map grid frame.
pub fn r_map_virt() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(
        1.0, 0.0, 0.0, //
        0.0, -1.0, 0.0, //
        0.0, 0.0, -1.0,
    ))
}

/// A rectified frame.
#[derive(Debug, Clone)]
pub struct Rectification {
    /// The virtual image; pixels not covered by the frame hold the mean of the covered ones.
    pub image: GrayImage,
    /// `row * width + col`: true where the pixel was sampled from the frame.
    pub valid: Vec<bool>,
    /// Virtual focal length, pixels.
    pub f_px: f64,
    /// Virtual principal point, column, pixels.
    pub cx_px: f64,
    /// Virtual principal point, row, pixels.
    pub cy_px: f64,
    /// `R_cam_virt`: virtual-camera rays into the real camera frame.
    r_cam_virt: Rotation3<f64>,
    camera: Camera,
}

/// Virtual pixels between exact evaluations of the warp (it is smooth: the interpolation error is
/// far below a pixel at this spacing).
const STEP: usize = 4;

/// The resampling of one rectification: the exactly evaluated warp grid and the source level.
struct Warp<'a> {
    /// Frame pixel (full resolution) of virtual pixel `(gx STEP, gy STEP)`; NaN where none.
    grid: &'a [[f64; 2]],
    gw: usize,
    /// The frame, halved `log2 f` times for antialiasing.
    src: &'a GrayImage,
    f: f64,
    frame_wh: [f64; 2],
    centre: [f64; 2],
    f_px: f64,
    tan2_max: f64,
}

impl Warp<'_> {
    /// Resample virtual row `v` into `row` (valid pixels flagged in `ok`); returns the sum and
    /// the count of the valid values.
    fn row(&self, v: usize, row: &mut [f32], ok: &mut [bool]) -> (f64, usize) {
        let (gy, fy) = (v / STEP, (v % STEP) as f64 / STEP as f64);
        let ny = (v as f64 - self.centre[1]) / self.f_px;
        let (sw, sh) = (self.src.width(), self.src.height());
        let data = self.src.data();
        let [w, h] = self.frame_wh;
        // The grid's columns interpolated to this row, then along it.
        let col: Vec<[f64; 2]> = (0..self.gw)
            .map(|gx| {
                let (a, c) = (
                    self.grid[gy * self.gw + gx],
                    self.grid[(gy + 1) * self.gw + gx],
                );
                [(1.0 - fy) * a[0] + fy * c[0], (1.0 - fy) * a[1] + fy * c[1]]
            })
            .collect();
        let inv_f = 1.0 / self.f;
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (u, (out, flag)) in row.iter_mut().zip(ok.iter_mut()).enumerate() {
            let (gx, fx) = (u / STEP, (u % STEP) as f64 / STEP as f64);
            let (l, r) = (col[gx], col[gx + 1]);
            let px = (1.0 - fx) * l[0] + fx * r[0];
            let py = (1.0 - fx) * l[1] + fx * r[1];
            if !(px.is_finite() && py.is_finite()) {
                continue;
            }
            // Virtual pixels beyond the off-nadir limit stay invalid.
            let nx = (u as f64 - self.centre[0]) / self.f_px;
            if nx * nx + ny * ny > self.tan2_max {
                continue;
            }
            if px < -0.5 || py < -0.5 || px > w - 0.5 || py > h - 0.5 {
                continue;
            }
            let sx = ((px + 0.5) * inv_f - 0.5).clamp(0.0, (sw - 1) as f64);
            let sy = ((py + 0.5) * inv_f - 0.5).clamp(0.0, (sh - 1) as f64);
            // Bilinear (GrayImage::sample_bilinear without its checks: sx, sy are clamped).
            let (x0, y0) = (sx as usize, sy as usize);
            let (x1, y1) = ((x0 + 1).min(sw - 1), (y0 + 1).min(sh - 1));
            let (tx, ty) = ((sx - x0 as f64) as f32, (sy - y0 as f64) as f32);
            let top = data[y0 * sw + x0] * (1.0 - tx) + data[y0 * sw + x1] * tx;
            let bottom = data[y1 * sw + x0] * (1.0 - tx) + data[y1 * sw + x1] * tx;
            let val = top * (1.0 - ty) + bottom * ty;
            if val.is_finite() {
                *out = val;
                *flag = true;
                sum += f64::from(val);
                n += 1;
            }
        }
        (sum, n)
    }
}

/// The frame border's footprint in virtual normalised coordinates (16 steps along each edge),
/// rays above `tan_max` from the vertical clipped to it (the image continues to the horizon):
/// the bounding box (lo, hi), `None` when no border ray sees the ground.
fn footprint(
    camera: &Camera,
    [w, h]: [f64; 2],
    r_cam_virt: &Rotation3<f64>,
    tan_max: f64,
) -> Option<([f64; 2], [f64; 2])> {
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    let n_edge = 16;
    for i in 0..=n_edge {
        let t = i as f64 / n_edge as f64;
        for (px, py) in [
            (t * (w - 1.0), 0.0),
            (t * (w - 1.0), h - 1.0),
            (0.0, t * (h - 1.0)),
            (w - 1.0, t * (h - 1.0)),
        ] {
            let Some(ray_cam) = camera.unproject(&Point2::new(px, py)) else {
                continue;
            };
            let rv = r_cam_virt.inverse() * ray_cam.into_inner();
            // Rays above the limit are clipped to it (the image continues to the horizon).
            let z = rv.z.max((rv.x * rv.x + rv.y * rv.y).sqrt() / tan_max);
            if z <= 0.0 {
                continue;
            }
            let (x, y) = (rv.x / z, rv.y / z);
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
    }
    (lo[0].is_finite() && hi[0] > lo[0] && hi[1] > lo[1]).then_some((lo, hi))
}

/// The antialiasing pyramid level for a resample by `scale`: the frame halved k times so that
/// scale * 2^k lies in about [0.6, 1.25] (stopping at 64 px), with the factor 2^k.
fn antialiased(frame: &GrayImage, scale: f64) -> (GrayImage, f64) {
    let mut k = 0u32;
    let mut src = frame.clone();
    while scale * f64::from(1u32 << (k + 1)) <= 1.25 && src.width() >= 64 && src.height() >= 64 {
        src = half_size(&src);
        k += 1;
    }
    (src, f64::from(1u32 << k))
}

impl Rectification {
    /// Rectify `frame` (taken by `camera` with attitude `r_map_cam`) to a virtual nadir camera whose
    /// focal length is `scale` times the real `fx`. The virtual image covers the frame's footprint up
    /// to `max_off_nadir_rad` from the vertical and at most `max_side_px` per side (cropped about the
    /// nadir point's image). `None` when the frame does not see the ground below the horizon limit.
    pub fn new(
        frame: &GrayImage,
        camera: &Camera,
        r_map_cam: &Rotation3<f64>,
        scale: f64,
        max_side_px: usize,
        max_off_nadir_rad: f64,
    ) -> Option<Self> {
        if !(scale.is_finite() && scale > 0.0) || frame.width() < 2 || frame.height() < 2 {
            return None;
        }
        let f_px = camera.intrinsics.fx_px * scale;
        let r_cam_virt = r_map_cam.inverse() * r_map_virt();
        // Footprint of the frame border in virtual normalised coordinates.
        let (w, h) = (frame.width() as f64, frame.height() as f64);
        let tan_max = max_off_nadir_rad.tan();
        let (lo, hi) = footprint(camera, [w, h], &r_cam_virt, tan_max)?;
        let max_side = max_side_px as f64;
        let span = |a: f64, b: f64| -> (f64, f64) {
            // Pixels from the nadir point (0 normalised) to the edges, cropped symmetrically.
            let (mut a, mut b) = (a * f_px, b * f_px);
            if b - a > max_side {
                let c = (0f64).clamp(a + max_side / 2.0, b - max_side / 2.0);
                a = c - max_side / 2.0;
                b = c + max_side / 2.0;
            }
            (a.floor(), b.ceil())
        };
        let (x0, x1) = span(lo[0], hi[0]);
        let (y0, y1) = span(lo[1], hi[1]);
        let width = (x1 - x0) as usize + 1;
        let height = (y1 - y0) as usize + 1;
        if width < 32 || height < 32 {
            return None;
        }
        let (cx_px, cy_px) = (-x0, -y0);

        let (src, f) = antialiased(frame, scale);

        let mut rect = Self {
            image: GrayImage::from_fn(1, 1, |_, _| 0.0),
            valid: vec![false; width * height],
            f_px,
            cx_px,
            cy_px,
            r_cam_virt,
            camera: *camera,
        };
        // The warp is smooth: evaluate it exactly on a grid every STEP pixels and interpolate.
        let gw = width.div_ceil(STEP) + 1;
        let gh = height.div_ceil(STEP) + 1;
        let mut grid = vec![[f64::NAN; 2]; gw * gh];
        grid.par_chunks_mut(gw).enumerate().for_each(|(gy, row)| {
            for (gx, cell) in row.iter_mut().enumerate() {
                if let Some(p) = rect.to_frame_px((gx * STEP) as f64, (gy * STEP) as f64) {
                    *cell = [p.x, p.y];
                }
            }
        });
        let warp = Warp {
            grid: &grid,
            gw,
            src: &src,
            f,
            frame_wh: [w, h],
            centre: [cx_px, cy_px],
            f_px,
            tan2_max: tan_max * tan_max,
        };
        let mut data = vec![f32::NAN; width * height];
        // Rows in parallel; each row's sum is kept, and the rows' sums are added in order, so
        // the mean (and the image) does not depend on the thread count.
        let row_sums: Vec<(f64, usize)> = data
            .par_chunks_mut(width)
            .zip(rect.valid.par_chunks_mut(width))
            .enumerate()
            .map(|(v, (row, ok))| warp.row(v, row, ok))
            .collect();
        let (sum, n) = row_sums
            .iter()
            .fold((0.0f64, 0usize), |(s, n), (rs, rn)| (s + rs, n + rn));
        if n == 0 {
            return None;
        }
        let mean = (sum / n as f64) as f32;
        for v in data.iter_mut().filter(|v| !v.is_finite()) {
            *v = mean;
        }
        rect.image = GrayImage::new(width, height, data).ok()?;
        Some(rect)
    }

    /// The virtual image with its validity mask, as the area stages take it (`None` when empty).
    pub fn plane(&self) -> Option<super::area::Plane> {
        super::area::Plane::new(
            self.width(),
            self.height(),
            self.image.data().to_vec(),
            self.valid.clone(),
        )
    }

    /// Width of the virtual image.
    pub fn width(&self) -> usize {
        self.image.width()
    }
    /// Height of the virtual image.
    pub fn height(&self) -> usize {
        self.image.height()
    }

    /// Ray of virtual pixel `(u, v)` in the map grid frame (not normalised; `z < 0`, pointing down).
    pub fn ray_map(&self, u: f64, v: f64) -> Vector3<f64> {
        r_map_virt()
            * Vector3::new(
                (u - self.cx_px) / self.f_px,
                (v - self.cy_px) / self.f_px,
                1.0,
            )
    }

    /// The (distorted) frame pixel that virtual pixel `(u, v)` was sampled from; `None` when that
    /// ray is behind the real camera or outside its lens model.
    pub fn to_frame_px(&self, u: f64, v: f64) -> Option<Point2<f64>> {
        let rv = Vector3::new(
            (u - self.cx_px) / self.f_px,
            (v - self.cy_px) / self.f_px,
            1.0,
        );
        self.camera.project(&(self.r_cam_virt * rv))
    }

    /// True when the square of half-side `r` pixels about `(u, v)` lies on valid pixels (checked at
    /// its corners, edge midpoints and centre).
    pub fn window_valid(&self, u: f64, v: f64, r: f64) -> bool {
        let (w, h) = (self.width() as f64, self.height() as f64);
        [-1.0, 0.0, 1.0].iter().all(|&i| {
            [-1.0, 0.0, 1.0].iter().all(|&j| {
                let (x, y) = ((u + i * r).round(), (v + j * r).round());
                x >= 0.0
                    && y >= 0.0
                    && x < w
                    && y < h
                    && self.valid[y as usize * self.width() + x as usize]
            })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::frames::{r_enu_ned, rot_z};
    use crate::camera::{Attitude, Intrinsics, Mount};

    fn cam() -> Camera {
        Camera::pinhole(Intrinsics::from_hfov(60f64.to_radians(), 640, 480).unwrap()).unwrap()
    }

    #[test]
    fn the_footprint_of_a_nadir_frame_is_its_field_of_view() {
        let c = cam();
        // Camera looking straight down: the virtual camera is the real one.
        let r_cam_virt = Rotation3::identity();
        let (lo, hi) = footprint(&c, [640.0, 480.0], &r_cam_virt, 80f64.to_radians()).unwrap();
        let half_w = 319.5 / c.intrinsics.fx_px;
        let half_h = 239.5 / c.intrinsics.fy_px;
        assert!(
            (hi[0] - half_w).abs() < 1e-6 && (lo[0] + half_w).abs() < 1e-6,
            "{lo:?} {hi:?}"
        );
        assert!(
            (hi[1] - half_h).abs() < 1e-6 && (lo[1] + half_h).abs() < 1e-6,
            "{lo:?} {hi:?}"
        );
        // Looking at the horizon: the rays are clipped to the off-nadir limit.
        let up = Rotation3::from_axis_angle(&Vector3::x_axis(), 90f64.to_radians());
        if let Some((lo, hi)) = footprint(&c, [640.0, 480.0], &up, 60f64.to_radians()) {
            let tan = 60f64.to_radians().tan() + 1e-9;
            assert!(
                lo.iter().chain(hi.iter()).all(|v| v.abs() <= tan),
                "{lo:?} {hi:?}"
            );
        }
    }

    #[test]
    fn the_antialiasing_level_halves_until_the_resample_is_near_one() {
        let frame = GrayImage::from_fn(640, 480, |x, y| ((x + y) % 7) as f32);
        let (src, f) = antialiased(&frame, 1.0);
        assert_eq!((src.width(), f), (640, 1.0));
        let (src, f) = antialiased(&frame, 0.3);
        // 0.3 * 2 = 0.6 <= 1.25, 0.3 * 4 = 1.2 <= 1.25: two halvings.
        assert_eq!((src.width(), src.height(), f), (160, 120, 4.0));
    }

    #[test]
    fn nadir_north_up_frame_is_a_pure_scaling() {
        let c = cam();
        let att = Attitude::from_deg(0.0, 0.0, 0.0);
        let r_map_cam = rot_z(0.0) * r_enu_ned() * Mount::nadir().r_ned_cam(&att);
        let frame = GrayImage::from_fn(640, 480, |x, y| ((x * 7 + y * 13) % 255) as f32);
        let r = Rectification::new(&frame, &c, &r_map_cam, 1.0, 2048, 1.4).unwrap();
        // Scale 1: the virtual image is the frame, possibly rotated by a multiple of 90 deg.
        for (u, v) in [(10.0, 20.0), (320.0, 240.0), (600.0, 400.0)] {
            let p = r.to_frame_px(u, v).unwrap();
            let back = c.project(
                &(r.r_cam_virt * Vector3::new((u - r.cx_px) / r.f_px, (v - r.cy_px) / r.f_px, 1.0)),
            );
            assert!((back.unwrap() - p).norm() < 1e-9);
        }
        // Nadir mount has the image top towards the nose = north: virtual up (north) = frame up.
        let top = r.to_frame_px(r.cx_px, r.cy_px - 100.0).unwrap();
        let centre = r.to_frame_px(r.cx_px, r.cy_px).unwrap();
        assert!((centre.x - c.intrinsics.cx_px).abs() < 1e-9, "{centre:?}");
        assert!(
            (top.y - (centre.y - 100.0)).abs() < 1e-6,
            "{top:?} {centre:?}"
        );
        assert!((top.x - centre.x).abs() < 1e-6);
        assert_eq!((r.width(), r.height()), (641, 481));
    }

    proptest::proptest! {
        /// Keypoints map back exactly: the frame pixel of a virtual pixel, unprojected through the
        /// distorted lens and rotated into the virtual camera, lands on the same virtual pixel.
        #[test]
        fn back_mapping_round_trips_through_distortion(
            roll in -15.0f64..15.0, pitch in -15.0f64..15.0, yaw in -180.0f64..180.0,
            scale in 0.3f64..1.5, fu in 0.1f64..0.9, fv in 0.1f64..0.9,
        ) {
            let k = Intrinsics::from_hfov(60f64.to_radians(), 640, 480).unwrap();
            let d = crate::camera::Distortion { k1: -0.12, k2: 0.03, k3: 0.0, p1: 1e-4, p2: -2e-4 };
            let c = Camera::new(k, d, Mount::nadir()).unwrap();
            let att = Attitude::from_deg(roll, pitch, yaw);
            let r_map_cam = r_enu_ned() * Mount::nadir().r_ned_cam(&att);
            let frame = GrayImage::from_fn(640, 480, |x, y| ((x * 3 + y * 5) % 200) as f32);
            let r = Rectification::new(&frame, &c, &r_map_cam, scale, 4096, 1.2).unwrap();
            let (u, v) = (fu * r.width() as f64, fv * r.height() as f64);
            if let Some(px) = r.to_frame_px(u, v) {
                let ray = c.unproject(&px).unwrap().into_inner();
                let rv = r.r_cam_virt.inverse() * ray;
                let (bu, bv) = (r.cx_px + r.f_px * rv.x / rv.z, r.cy_px + r.f_px * rv.y / rv.z);
                proptest::prop_assert!((bu - u).abs() < 1e-3 && (bv - v).abs() < 1e-3,
                    "{u},{v} -> {px:?} -> {bu},{bv}");
            }
        }
    }

    #[test]
    fn heading_east_rotates_the_virtual_image() {
        let c = cam();
        // Yaw 90 deg: nose (image top) east. Virtual east (+u) is then the frame's up (-v).
        let att = Attitude::from_deg(0.0, 0.0, 90.0);
        let r_map_cam = r_enu_ned() * Mount::nadir().r_ned_cam(&att);
        let frame = GrayImage::from_fn(640, 480, |x, _| x as f32);
        let r = Rectification::new(&frame, &c, &r_map_cam, 0.5, 2048, 1.4).unwrap();
        let centre = r.to_frame_px(r.cx_px, r.cy_px).unwrap();
        let east = r.to_frame_px(r.cx_px + 50.0, r.cy_px).unwrap();
        assert!(
            (east.y - (centre.y - 100.0)).abs() < 1e-6,
            "{east:?} {centre:?}"
        );
        // Scale 0.5: the virtual image is half the size, rotated.
        assert!((r.width() as i64 - 241).abs() <= 2 && (r.height() as i64 - 321).abs() <= 2);
        // Interpolated sampling reproduces the ramp (frame x) at a virtual pixel.
        let (u, v) = (100usize, 150usize);
        let p = r.to_frame_px(u as f64, v as f64).unwrap();
        let got = r.image.get(u, v);
        // The 2x2 antialiasing mean of a ramp x is x at the block centre.
        assert!((f64::from(got) - p.x).abs() < 0.6, "{got} vs {}", p.x);
    }
}
