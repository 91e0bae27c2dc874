//! Camera renderer: the simulated camera of the closed-loop simulator and the source of the
//! vision-fix test frames. It renders the perspective view of an orthophoto draped on a DEM from a
//! camera pose, through the lens model, then applies photometric effects (exposure, vignetting,
//! blur, noise, quantisation).
//!
//! Golden rule for tests: never render frames from the same orthophoto the matcher uses as its map;
//! render from another year of the same area (`sitl/maps/naip_nd_2014.tif` is the camera year,
//! `naip_nd_2009.tif` the map year).
//!
//! # Geometry (per output pixel)
//!
//! 1. Pixel centre `(u, v)` (top-left pixel centre at (0, 0), `docs/conventions.md`) -> ideal
//!    normalised point by inverting the Brown-Conrady model ([`Camera::unproject`]) -> unit ray
//!    `r_cam` (x right, y down, z forward). The rays are computed once per [`Renderer`].
//! 2. `r_map = R_map_cam r_cam`; the ray `c + t r_map` (`c` the projection centre; map grid frame:
//!    x grid east, y grid north, z up, heights in the DEM's datum) is intersected with the terrain:
//!    analytically for a flat DEM, exactly with empty-space skipping for a gridded one
//!    (`terrain` submodule). No hit within `max_range_m` -> off-map.
//! 3. The ground point is converted to orthophoto pixel coordinates; its **footprint** is the
//!    Jacobian of ground position over image position, estimated from the neighbouring pixels' hits
//!    (per axis, the one-sided difference with the smaller magnitude, so a depth discontinuity does
//!    not inflate it). The pixel value is the mean of `s x s` samples placed on the affine image of
//!    the pixel square (`s` = `supersample`), each a trilinear mipmap lookup with a footprint of
//!    `max(|J_u|, |J_v|) / s` orthophoto pixels (`pyramid` submodule). This approximates the box
//!    integral of the orthophoto over the pixel's ground footprint (anti-aliasing when one camera
//!    pixel covers several map pixels, e.g. 5 m NAIP pixels seen from 2500 m).
//! 4. Off-map pixels (no terrain hit, ground point outside the orthophoto, or missing data there) are
//!    marked invalid in [`RenderedFrame::valid`] and set to `fill_dn`.
//!
//! Values are digital numbers on the 8-bit scale (`pyramid::dn_scale`). The photometric chain is
//! described in the `photometric` submodule.
//!
//! # Pose
//!
//! [`RenderPose`] is the camera's projection centre `centre_map_m` and `R_map_cam` (maps `_cam`
//! vectors into the map grid frame). From a vehicle state ([`RenderPose::from_body`]):
//! `R_map_cam = Rz(gamma) R_enu_ned R_ned_body R_body_cam`, `c = p_body + R_map_body lever_arm`,
//! where `gamma` is the grid convergence (bearing of grid north clockwise from true north, as
//! `Crs::grid_convergence_deg` reports it) and `R_map_enu = Rz(gamma)` rotates true-north ENU
//! vectors into the grid frame (true north appears at grid bearing `-gamma`). Attitudes are
//! relative to true north (`R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`).

pub mod degrade;
pub mod photometric;
pub mod pyramid;
pub mod spec;
pub mod terrain;

pub use photometric::PhotometricSpec;
pub use pyramid::{ColourMode, LUMA_REC601, OrthoPyramid};
pub use spec::{BlurSpec, ExposureSpec, NoiseSpec, RenderSpec};
pub use terrain::Terrain;

use nalgebra::{Point2, Rotation3, Vector3};
use rayon::prelude::*;
use std::time::Instant;
use visnav_core::camera::frames::{r_enu_ned, rot_z};
use visnav_core::camera::{Attitude, Camera, CameraError, CameraPose, Intrinsics, Mount, Opk};
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::Raster;
use visnav_core::geo::{Crs, GeoError};
use visnav_core::validate::Invalid;
use visnav_io::geo::geotiff::crs_equivalent;

/// Errors of the renderer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// The DEM and the orthophoto are in different CRSs.
    #[error("DEM CRS {dem} differs from the orthophoto CRS {ortho}")]
    CrsMismatch {
        /// The DEM's CRS.
        dem: Crs,
        /// The orthophoto's CRS.
        ortho: Crs,
    },
    /// Rays need metres in x, y and z.
    #[error("orthophoto CRS {0} is not projected (x, y must be metres)")]
    NotProjected(Crs),
    /// The render specification failed validation (keys relative to the spec).
    #[error("invalid render spec: {}", list.iter().map(|i| i.to_string()).collect::<Vec<_>>().join("; "))]
    Spec {
        /// Every problem found.
        list: Vec<Invalid>,
    },
    /// The scene's pyramid was built for another colour mode than the spec asks for.
    #[error("scene has {scene} channels but the render spec asks for {spec}")]
    ColourMismatch {
        /// The scene pyramid's colour mode.
        scene: ColourMode,
        /// The colour mode the spec asks for.
        spec: ColourMode,
    },
    /// The camera model could not be built.
    #[error("camera: {0}")]
    Camera(CameraError),
    /// Non-finite pose.
    #[error(
        "camera pose is not finite: centre {}",
        visnav_core::text::numbers(centre_map_m)
    )]
    BadPose {
        /// The pose's projection centre, map grid, m.
        centre_map_m: [f64; 3],
    },
}

// Not `#[from]`: that would also make the error its `source()`, and the message already has its
// text (an error chain printed with `{:#}` would say it twice).
impl From<CameraError> for RenderError {
    fn from(e: CameraError) -> Self {
        Self::Camera(e)
    }
}

/// What the camera looks at: an orthophoto pyramid and the terrain, in one projected CRS.
#[derive(Debug, Clone)]
pub struct Scene {
    ortho: OrthoPyramid,
    terrain: Terrain,
}

impl Scene {
    /// Builds the orthophoto pyramid (`colour` channels) and prepares the DEM. The DEM, unless
    /// flat, must be in the orthophoto's CRS, which must be projected.
    pub fn new(ortho: &Raster, dem: Dem, colour: ColourMode) -> Result<Self, RenderError> {
        let crs = ortho.crs();
        if crs == Crs::Geographic {
            return Err(RenderError::NotProjected(crs));
        }
        if let Some(d) = dem.crs()
            && !crs_equivalent(&d, &crs)
        {
            return Err(RenderError::CrsMismatch { dem: d, ortho: crs });
        }
        Ok(Self {
            ortho: OrthoPyramid::new(ortho, colour),
            terrain: Terrain::new(dem),
        })
    }

    /// The scene of a mosaic: the orthophoto repeated `cols x rows` times east and south of its
    /// place, every other copy mirrored ([`OrthoPyramid::mirror_tiled`]); the terrain is kept.
    pub fn mirror_tiled(mut self, cols: usize, rows: usize) -> Self {
        self.ortho = self.ortho.mirror_tiled(cols, rows);
        self
    }

    /// The orthophoto pyramid.
    pub fn ortho(&self) -> &OrthoPyramid {
        &self.ortho
    }
    /// The terrain.
    pub fn dem(&self) -> &Dem {
        self.terrain.dem()
    }
    /// The terrain prepared for ray casting.
    pub fn terrain(&self) -> &Terrain {
        &self.terrain
    }
}

/// Grid convergence at map point `(x_m, y_m)` of `crs`, radians: the bearing of grid north
/// clockwise from true north (`Crs::grid_convergence_deg` at the point's geodetic position), the
/// `grid_convergence_rad` argument of [`RenderPose::from_body`].
pub fn grid_convergence_rad(crs: &Crs, x_m: f64, y_m: f64) -> Result<f64, GeoError> {
    let (lat_deg, lon_deg) = crs.to_geodetic(x_m, y_m)?;
    Ok(crs.grid_convergence_deg(lat_deg, lon_deg)?.to_radians())
}

/// Camera pose in the map grid frame (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderPose {
    /// Projection centre: x grid east, y grid north, z up (DEM vertical datum), metres.
    pub centre_map_m: Vector3<f64>,
    /// `_cam` (x right, y down, z forward) to map grid rotation.
    pub r_map_cam: Rotation3<f64>,
}

impl RenderPose {
    /// From the projection centre and `R_map_cam`.
    pub fn new(centre_map_m: Vector3<f64>, r_map_cam: Rotation3<f64>) -> Self {
        Self {
            centre_map_m,
            r_map_cam,
        }
    }

    /// From photogrammetric omega-phi-kappa in the map grid frame (`docs/conventions.md`).
    pub fn from_opk(centre_map_m: Vector3<f64>, opk: &Opk) -> Self {
        Self::new(centre_map_m, opk.r_world_cam())
    }

    /// From a camera exterior orientation whose world frame is the map grid.
    pub fn from_camera_pose(pose: &CameraPose) -> Self {
        Self::new(pose.centre_world_m, pose.r_world_cam)
    }

    /// The same pose as a `camera::CameraPose` (world = map grid), for projecting points.
    pub fn to_camera_pose(&self) -> CameraPose {
        CameraPose {
            r_world_cam: self.r_map_cam,
            centre_world_m: self.centre_map_m,
        }
    }

    /// From the vehicle state: body origin `body_map_m` (x grid east, y grid north, z up), attitude
    /// relative to TRUE north (`R_ned_body`), the camera mount, and the grid convergence
    /// `grid_convergence_rad` at the vehicle (bearing of grid north clockwise from true north; 0 for
    /// a local ENU map). `R_map_cam = Rz(gamma) R_enu_ned R_ned_body R_body_cam`, centre =
    /// `body + R_map_body lever_arm`.
    pub fn from_body(
        body_map_m: Vector3<f64>,
        attitude: &Attitude,
        mount: &Mount,
        grid_convergence_rad: f64,
    ) -> Self {
        let r_map_body = rot_z(grid_convergence_rad) * r_enu_ned() * attitude.r_ned_body();
        Self::new(
            body_map_m + r_map_body * mount.lever_arm_body_frd_m,
            r_map_body * mount.r_body_cam,
        )
    }

    /// Pixel where a map point appears (distorted; may lie outside the image), `None` behind the
    /// camera or outside the lens model's valid radius.
    pub fn project(&self, camera: &Camera, p_map_m: &Vector3<f64>) -> Option<Point2<f64>> {
        self.to_camera_pose().project_world(camera, p_map_m)
    }

    fn is_finite(&self) -> bool {
        self.centre_map_m.iter().all(|v| v.is_finite())
            && self.r_map_cam.matrix().iter().all(|v| v.is_finite())
    }
}

/// A rendered frame: channel-interleaved values (8-bit digital numbers, possibly fractional) and a
/// validity mask (false = off-map, value = `fill_dn`).
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedFrame {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// 1 (grey) or 3 (RGB).
    pub channels: usize,
    /// `(row * width + col) * channels + channel`.
    pub data: Vec<f32>,
    /// `row * width + col`.
    pub valid: Vec<bool>,
}

impl RenderedFrame {
    /// Value of one channel at pixel `(col, row)`, `None` out of range.
    pub fn value(&self, col: usize, row: usize, channel: usize) -> Option<f32> {
        (col < self.width && row < self.height && channel < self.channels)
            .then(|| self.data[(row * self.width + col) * self.channels + channel])
    }

    /// Fraction of valid pixels.
    pub fn valid_fraction(&self) -> f64 {
        let n = self.valid.iter().filter(|v| **v).count();
        n as f64 / self.valid.len().max(1) as f64
    }

    /// Grey level per pixel (the channel itself, or Rec. 601 luma of RGB).
    pub fn grey(&self) -> Vec<f32> {
        match self.channels {
            3 => self
                .data
                .chunks_exact(3)
                .map(|p| LUMA_REC601[0] * p[0] + LUMA_REC601[1] * p[1] + LUMA_REC601[2] * p[2])
                .collect(),
            _ => self.data.clone(),
        }
    }

    /// 8-bit grey image (rounded and clamped).
    pub fn to_gray_image(&self) -> image::GrayImage {
        let px: Vec<u8> = self.grey().iter().map(|v| to_u8(*v)).collect();
        gray_from(self.width, px)
    }

    /// 8-bit RGB image (grey replicated for one channel).
    pub fn to_rgb_image(&self) -> image::RgbImage {
        let px: Vec<u8> = if self.channels == 3 {
            self.data.iter().map(|v| to_u8(*v)).collect()
        } else {
            self.data.iter().flat_map(|v| [to_u8(*v); 3]).collect()
        };
        let w = self.width.max(1);
        image::RgbImage::from_fn(w as u32, (px.len() / (3 * w)) as u32, |x, y| {
            let i = 3 * (y as usize * w + x as usize);
            image::Rgb([px[i], px[i + 1], px[i + 2]])
        })
    }

    /// Validity mask as an 8-bit image (255 valid, 0 off-map).
    pub fn mask_image(&self) -> image::GrayImage {
        let px: Vec<u8> = self
            .valid
            .iter()
            .map(|v| if *v { 255 } else { 0 })
            .collect();
        gray_from(self.width, px)
    }
}

/// An 8-bit grey image of rows of `width` pixels (the rows `px` holds).
fn gray_from(width: usize, px: Vec<u8>) -> image::GrayImage {
    let w = width.max(1);
    image::GrayImage::from_fn(w as u32, (px.len() / w) as u32, |x, y| {
        image::Luma([px[y as usize * w + x as usize]])
    })
}

#[inline]
fn to_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8 // ok: clamped, NaN maps to 0
}

/// The simulated camera: lens model, cached pixel rays and rendering parameters.
#[derive(Debug, Clone)]
pub struct Renderer {
    camera: Camera,
    spec: RenderSpec,
    /// Unit `_cam` ray per pixel centre, NaN where the lens model cannot be inverted.
    rays_cam: Vec<[f64; 3]>,
}

impl Renderer {
    /// Validates `spec` and precomputes the ray of every pixel centre through `camera`'s lens.
    pub fn new(camera: Camera, spec: RenderSpec) -> Result<Self, RenderError> {
        spec.check()?;
        let (w, h) = (camera.width_px() as usize, camera.height_px() as usize);
        let mut rays_cam = vec![[f64::NAN; 3]; w * h];
        rays_cam
            .par_chunks_mut(w)
            .enumerate()
            .for_each(|(row, line)| {
                for (col, r) in line.iter_mut().enumerate() {
                    if let Some(ray) = camera.unproject(&Point2::new(col as f64, row as f64)) {
                        *r = [ray.x, ray.y, ray.z];
                    }
                }
            });
        Ok(Self {
            camera,
            spec,
            rays_cam,
        })
    }

    /// The camera model.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }
    /// The rendering parameters.
    pub fn spec(&self) -> &RenderSpec {
        &self.spec
    }

    /// Renders a frame with all photometric effects of the spec; `frame_index` selects the noise
    /// stream (same spec seed + same index = identical frame).
    pub fn render(
        &self,
        scene: &Scene,
        pose: &RenderPose,
        frame_index: u64,
    ) -> Result<RenderedFrame, RenderError> {
        let mut f = self.render_radiance(scene, pose)?;
        self.apply_photometric(&mut f, frame_index);
        Ok(f)
    }

    /// Applies the spec's photometric effects to a radiance frame of this camera's size.
    pub fn apply_photometric(&self, frame: &mut RenderedFrame, frame_index: u64) {
        let k: &Intrinsics = &self.camera.intrinsics;
        let mut planes = photometric::Planes {
            width: frame.width,
            height: frame.height,
            channels: frame.channels,
            data: &mut frame.data,
            valid: &frame.valid,
            cx_px: k.cx_px,
            cy_px: k.cy_px,
        };
        photometric::apply(&mut planes, &self.spec.photometric(), frame_index);
    }

    /// Geometry only: the anti-aliased radiance (orthophoto DN) seen through the lens, no
    /// photometric effect, no quantisation; off-map pixels are `fill_dn`.
    pub fn render_radiance(
        &self,
        scene: &Scene,
        pose: &RenderPose,
    ) -> Result<RenderedFrame, RenderError> {
        if scene.ortho.mode() != self.spec.colour {
            return Err(RenderError::ColourMismatch {
                scene: scene.ortho.mode(),
                spec: self.spec.colour,
            });
        }
        if !pose.is_finite() {
            let c = pose.centre_map_m;
            return Err(RenderError::BadPose {
                centre_map_m: [c.x, c.y, c.z],
            });
        }
        let (w, h) = (
            self.camera.width_px() as usize,
            self.camera.height_px() as usize,
        );
        let hits = self.cast(scene, pose);
        let ch = scene.ortho.channels();
        let mut data = vec![self.spec.fill_dn as f32; w * h * ch];
        let mut valid = vec![false; w * h];
        let s = self.spec.supersample.clamp(1, 4) as usize;
        let offsets: Vec<f64> = (0..s).map(|k| (k as f64 + 0.5) / s as f64 - 0.5).collect();
        // Fallback footprint (isolated pixels): range / f in metres over the ortho pixel size.
        let (gsx, gsy) = scene.ortho.transform().pixel_size();
        let fallback_scale = 1.0 / (self.camera.intrinsics.fx_px * gsx.min(gsy));
        data.par_chunks_mut(w * ch)
            .zip(valid.par_chunks_mut(w))
            .enumerate()
            .for_each(|(row, (line, vline))| {
                let mut acc = [0.0f32; 3];
                let mut smp = [0.0f32; 3];
                for col in 0..w {
                    let hit = hits[row * w + col];
                    if hit.col.is_nan() {
                        continue;
                    }
                    let at = |c: usize, r: usize| {
                        let x = hits[r * w + c];
                        (!x.col.is_nan()).then_some((x.col, x.row))
                    };
                    let du = derivative(
                        (hit.col, hit.row),
                        (col > 0).then(|| at(col - 1, row)).flatten(),
                        (col + 1 < w).then(|| at(col + 1, row)).flatten(),
                    );
                    let dv = derivative(
                        (hit.col, hit.row),
                        (row > 0).then(|| at(col, row - 1)).flatten(),
                        (row + 1 < h).then(|| at(col, row + 1)).flatten(),
                    );
                    let fallback = f64::from(hit.range_m) * fallback_scale;
                    let (du, dv) = match (du, dv) {
                        (Some(a), Some(b)) => (a, b),
                        (Some(a), None) => (a, (-a.1, a.0)),
                        (None, Some(b)) => ((b.1, -b.0), b),
                        (None, None) => ((fallback, 0.0), (0.0, fallback)),
                    };
                    let size = norm2(du).max(norm2(dv)).sqrt();
                    let lod = scene.ortho.lod(size / s as f64);
                    let out = &mut line[col * ch..(col + 1) * ch];
                    // Centre sample decides validity.
                    if !scene.ortho.sample_lod(lod, hit.col, hit.row, &mut smp) {
                        continue;
                    }
                    vline[col] = true;
                    if s == 1 {
                        out.copy_from_slice(&smp[..ch]);
                        continue;
                    }
                    acc.fill(0.0);
                    let mut n = 0u32;
                    for &ov in &offsets {
                        for &ou in &offsets {
                            let c = hit.col + du.0 * ou + dv.0 * ov;
                            let r = hit.row + du.1 * ou + dv.1 * ov;
                            if scene.ortho.sample_lod(lod, c, r, &mut smp) {
                                for (a, v) in acc.iter_mut().zip(&smp).take(ch) {
                                    *a += v;
                                }
                                n += 1;
                            }
                        }
                    }
                    if n == 0 {
                        scene.ortho.sample_lod(lod, hit.col, hit.row, &mut acc);
                        n = 1;
                    }
                    for (o, a) in out.iter_mut().zip(&acc) {
                        *o = a / n as f32;
                    }
                }
            });
        Ok(RenderedFrame {
            width: w,
            height: h,
            channels: ch,
            data,
            valid,
        })
    }

    /// Ground point (map x, y, z) seen at pixel `px` (distorted pixel coordinates), by the same ray
    /// cast as the renderer; `None` when the ray misses the terrain within `max_range_m`.
    pub fn ground_point(
        &self,
        scene: &Scene,
        pose: &RenderPose,
        px: &Point2<f64>,
    ) -> Option<Vector3<f64>> {
        let r = self.camera.unproject(px)?;
        let d = pose.r_map_cam * r.into_inner();
        let c = pose.centre_map_m;
        let (p, _) =
            scene
                .terrain
                .intersect([c.x, c.y, c.z], [d.x, d.y, d.z], self.spec.max_range_m)?;
        Some(Vector3::from(p))
    }

    /// Pass 1: ray cast of every pixel centre to orthophoto pixel coordinates (NaN = no hit).
    fn cast(&self, scene: &Scene, pose: &RenderPose) -> Vec<Hit> {
        let (w, h) = (
            self.camera.width_px() as usize,
            self.camera.height_px() as usize,
        );
        let m = pose.r_map_cam.matrix();
        let c = [
            pose.centre_map_m.x,
            pose.centre_map_m.y,
            pose.centre_map_m.z,
        ];
        let tf = scene.ortho.transform();
        let max_range = self.spec.max_range_m;
        let mut hits = vec![Hit::NONE; w * h];
        hits.par_chunks_mut(w).enumerate().for_each(|(row, line)| {
            for (col, out) in line.iter_mut().enumerate() {
                let r = self.rays_cam[row * w + col];
                if r[0].is_nan() {
                    continue;
                }
                let d = [
                    m[(0, 0)] * r[0] + m[(0, 1)] * r[1] + m[(0, 2)] * r[2],
                    m[(1, 0)] * r[0] + m[(1, 1)] * r[1] + m[(1, 2)] * r[2],
                    m[(2, 0)] * r[0] + m[(2, 1)] * r[1] + m[(2, 2)] * r[2],
                ];
                if let Some((p, t)) = scene.terrain.intersect(c, d, max_range) {
                    let (oc, or) = tf.map_to_pixel(p[0], p[1]);
                    *out = Hit {
                        col: oc,
                        row: or,
                        range_m: t as f32,
                    };
                }
            }
        });
        hits
    }
}

/// Ground hit of one pixel in level-0 orthophoto pixel coordinates.
#[derive(Debug, Clone, Copy)]
struct Hit {
    col: f64,
    row: f64,
    range_m: f32,
}

impl Hit {
    const NONE: Hit = Hit {
        col: f64::NAN,
        row: f64::NAN,
        range_m: f32::NAN,
    };
}

/// Derivative of the hit position along one image axis from the previous/next neighbours: the
/// one-sided difference with the smaller magnitude.
#[inline]
fn derivative(
    here: (f64, f64),
    prev: Option<(f64, f64)>,
    next: Option<(f64, f64)>,
) -> Option<(f64, f64)> {
    let back = prev.map(|p| (here.0 - p.0, here.1 - p.1));
    let fwd = next.map(|n| (n.0 - here.0, n.1 - here.1));
    match (back, fwd) {
        (Some(b), Some(f)) => Some(if norm2(b) <= norm2(f) { b } else { f }),
        (b, f) => b.or(f),
    }
}

/// Squared length of a pixel-space vector (compared and rooted instead of `hypot`, a libm call
/// per use: a pixel's hits are a few pixels apart, far from overflow or underflow).
#[inline]
fn norm2(v: (f64, f64)) -> f64 {
    v.0 * v.0 + v.1 * v.1
}

/// Timing of one render configuration (milliseconds, wall clock, best and median of the runs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderTiming {
    /// Frame width, px.
    pub width: usize,
    /// Frame height, px.
    pub height: usize,
    /// Renders timed.
    pub iterations: usize,
    /// Geometry + anti-aliased sampling ([`Renderer::render_radiance`]): the best run.
    pub radiance_min_ms: f64,
    /// The same, the median run.
    pub radiance_median_ms: f64,
    /// Photometric effects of the spec ([`Renderer::apply_photometric`]): the best run.
    pub photometric_min_ms: f64,
    /// The same, the median run.
    pub photometric_median_ms: f64,
    /// Fraction of valid pixels of the frame.
    pub valid_fraction: f64,
}

/// Times `iterations` renders (at least 1) of `scene` through `pose` (for `visnav bench`; no
/// assertion on the numbers anywhere).
pub fn time_render(
    renderer: &Renderer,
    scene: &Scene,
    pose: &RenderPose,
    iterations: usize,
) -> Result<RenderTiming, RenderError> {
    let n = iterations.max(1);
    let mut rad = Vec::with_capacity(n);
    let mut pho = Vec::with_capacity(n);
    let mut valid_fraction = 0.0;
    for k in 0..n {
        let t0 = Instant::now();
        let mut f = renderer.render_radiance(scene, pose)?;
        let t1 = Instant::now();
        renderer.apply_photometric(&mut f, k as u64);
        let t2 = Instant::now();
        rad.push((t1 - t0).as_secs_f64() * 1e3);
        pho.push((t2 - t1).as_secs_f64() * 1e3);
        valid_fraction = f.valid_fraction();
    }
    let stats = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (v[0], v[v.len() / 2])
    };
    let (radiance_min_ms, radiance_median_ms) = stats(&mut rad);
    let (photometric_min_ms, photometric_median_ms) = stats(&mut pho);
    Ok(RenderTiming {
        width: renderer.camera.width_px() as usize,
        height: renderer.camera.height_px() as usize,
        iterations: n,
        radiance_min_ms,
        radiance_median_ms,
        photometric_min_ms,
        photometric_median_ms,
        valid_fraction,
    })
}

/// The acceptance-test camera: 640 x 480 px, 60 deg horizontal field of view, no distortion,
/// nadir mount.
pub fn vga_camera() -> Result<Camera, CameraError> {
    Camera::pinhole(Intrinsics::from_hfov(60f64.to_radians(), 640, 480)?)
}

/// A drone's camera: 1280 x 960 px, 80 deg horizontal field of view (a multirotor's mapping or
/// FPV camera at 4:3), no distortion, nadir mount.
pub fn drone_camera() -> Result<Camera, CameraError> {
    Camera::pinhole(Intrinsics::from_hfov(80f64.to_radians(), 1280, 960)?)
}

/// A pose over the centre of the scene's orthophoto: `agl_m` above the terrain there (or above
/// the middle of the DEM's height range where the DEM has no height), optical axis tilted
/// `tilt_deg` from nadir towards the image top, image top towards grid bearing `heading_deg`.
pub fn pose_over_centre(scene: &Scene, agl_m: f64, tilt_deg: f64, heading_deg: f64) -> RenderPose {
    let tf = scene.ortho.transform();
    let (w, h) = scene.ortho.level_size(0).unwrap_or((0, 0)); // ok: level 0 always exists
    let (x, y) = tf.pixel_to_map(w as f64 / 2.0, h as f64 / 2.0);
    let (lo, hi) = scene.dem().height_range_m();
    let ground = scene.dem().height_at(x, y).unwrap_or(0.5 * (lo + hi));
    // Nadir camera heading north has OPK zero; heading = image-top bearing = -kappa; tilting the
    // axis towards the image top is a rotation about cam x.
    let r = Opk::new(0.0, 0.0, -heading_deg.to_radians()).r_world_cam()
        * visnav_core::camera::frames::rot_x(tilt_deg.to_radians());
    RenderPose::new(Vector3::new(x, y, ground + agl_m), r)
}

/// Benchmark of the acceptance configuration: VGA camera ([`vga_camera`]) `agl_m` above the
/// centre of `scene`, 10 deg tilt, with `spec`'s effects (its colour must match the scene).
pub fn bench_vga(
    scene: &Scene,
    spec: RenderSpec,
    agl_m: f64,
    iterations: usize,
) -> Result<RenderTiming, RenderError> {
    let renderer = Renderer::new(vga_camera()?, spec)?;
    let pose = pose_over_centre(scene, agl_m, 10.0, 30.0);
    time_render(&renderer, scene, &pose, iterations)
}

/// Height above the ground of the drone benchmark, metres: the drone scenario's cruise height.
pub const DRONE_BENCH_AGL_M: f64 = 60.0;
/// Tilt of the drone benchmark's body-fixed camera, degrees: a multirotor's lean at 10 m/s under
/// the drone scenario's drag law.
pub const DRONE_BENCH_TILT_DEG: f64 = 26.0;

/// Benchmark of the drone scenario's camera ([`drone_camera`], 1280 x 960, 80 deg) leaning
/// [`DRONE_BENCH_TILT_DEG`] [`DRONE_BENCH_AGL_M`] above the centre of `scene`, with `spec`'s
/// effects: the ray cast over a surface model at drone scale.
pub fn bench_drone(
    scene: &Scene,
    spec: RenderSpec,
    iterations: usize,
) -> Result<RenderTiming, RenderError> {
    let renderer = Renderer::new(drone_camera()?, spec)?;
    let pose = pose_over_centre(scene, DRONE_BENCH_AGL_M, DRONE_BENCH_TILT_DEG, 30.0);
    time_render(&renderer, scene, &pose, iterations)
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::geo::raster::{GeoTransform, RasterData};

    fn utm() -> Crs {
        Crs::Utm {
            zone: 14,
            north: true,
        }
    }

    #[test]
    fn from_body_matches_opk_and_convergence() {
        let mount = Mount::nadir();
        let p = Vector3::new(500_000.0, 5_000_000.0, 2000.0);
        // Level, heading true north, no convergence: OPK zero.
        let a = RenderPose::from_body(p, &Attitude::from_deg(0.0, 0.0, 0.0), &mount, 0.0);
        let b = RenderPose::from_opk(p, &Opk::new(0.0, 0.0, 0.0));
        assert!((a.r_map_cam.matrix() - b.r_map_cam.matrix()).norm() < 1e-12);
        // Grid north 1.5 deg east of true north: heading 1.5 deg true = grid north.
        let g = 1.5f64.to_radians();
        let a = RenderPose::from_body(p, &Attitude::new(0.0, 0.0, g), &mount, g);
        assert!((a.r_map_cam.matrix() - b.r_map_cam.matrix()).norm() < 1e-12);
        // Heading true north then appears at grid bearing -1.5 deg (image top turned west).
        let a = RenderPose::from_body(p, &Attitude::new(0.0, 0.0, 0.0), &mount, g);
        let top = a.r_map_cam * -Vector3::y();
        assert!((top.x.atan2(top.y) + g).abs() < 1e-12);
        // Lever arm 1 m forward, heading east: camera 1 m grid east of the body.
        let m = Mount::from_angles(0.0, 0.0, 0.0, Vector3::new(1.0, 0.0, 0.0));
        let a = RenderPose::from_body(p, &Attitude::from_deg(0.0, 0.0, 90.0), &m, 0.0);
        assert!((a.centre_map_m - (p + Vector3::x())).norm() < 1e-12);
    }

    #[test]
    fn grid_convergence_sign_and_size() {
        // UTM 14N (central meridian 99 W) at about 47 N: zero on the central meridian, about
        // dlon * sin(lat) = +0.73 deg one degree (~76 km) east of it, negative west of it.
        let c = utm();
        let (x_cm, y) = (500_000.0, 5_206_000.0);
        assert!(grid_convergence_rad(&c, x_cm, y).unwrap().abs() < 1e-9);
        let g_east = grid_convergence_rad(&c, x_cm + 76_000.0, y)
            .unwrap()
            .to_degrees();
        let g_west = grid_convergence_rad(&c, x_cm - 76_000.0, y)
            .unwrap()
            .to_degrees();
        assert!((g_east - 0.73).abs() < 0.02, "{g_east}");
        assert!((g_east + g_west).abs() < 1e-9);
        assert!(grid_convergence_rad(&Crs::Geographic, 0.0, 0.0).is_err());
    }

    #[test]
    fn errors_are_reported_not_panics() {
        let gt = GeoTransform::north_up(0.0, 100.0, 1.0, 1.0).unwrap();
        let r = Raster::new(10, 10, 1, RasterData::U8(vec![9; 100]), gt, utm(), None).unwrap();
        let geo = Raster::new(
            10,
            10,
            1,
            RasterData::U8(vec![9; 100]),
            gt,
            Crs::Geographic,
            None,
        )
        .unwrap();
        assert!(matches!(
            Scene::new(&geo, Dem::flat(0.0).unwrap(), ColourMode::Grey),
            Err(RenderError::NotProjected(_))
        ));
        let dem_r = Raster::new(
            10,
            10,
            1,
            RasterData::F32(vec![0.0; 100]),
            gt,
            Crs::WebMercator,
            None,
        )
        .unwrap();
        assert!(matches!(
            Scene::new(&r, Dem::from_raster(&dem_r).unwrap(), ColourMode::Grey),
            Err(RenderError::CrsMismatch { .. })
        ));
        let scene = Scene::new(&r, Dem::flat(0.0).unwrap(), ColourMode::Grey).unwrap();
        let cam = Camera::pinhole(Intrinsics::from_hfov(1.0, 8, 6).unwrap()).unwrap();
        let rgb = RenderSpec {
            colour: ColourMode::Rgb,
            ..RenderSpec::default()
        };
        let ren = Renderer::new(cam, rgb).unwrap();
        let pose = RenderPose::from_opk(Vector3::new(5.0, 95.0, 5.0), &Opk::new(0.0, 0.0, 0.0));
        assert!(matches!(
            ren.render(&scene, &pose, 0),
            Err(RenderError::ColourMismatch { .. })
        ));
        let ren = Renderer::new(cam, RenderSpec::default()).unwrap();
        let bad = RenderPose::from_opk(Vector3::new(f64::NAN, 0.0, 0.0), &Opk::new(0.0, 0.0, 0.0));
        assert!(matches!(
            ren.render(&scene, &bad, 0),
            Err(RenderError::BadPose { .. })
        ));
        let f = ren.render(&scene, &pose, 0).unwrap();
        assert_eq!(f.valid_fraction(), 1.0);
        assert!(f.data.iter().all(|v| *v == 9.0));
        let bad_spec = RenderSpec {
            supersample: 0,
            ..RenderSpec::default()
        };
        assert!(matches!(
            Renderer::new(cam, bad_spec),
            Err(RenderError::Spec { .. })
        ));
    }

    #[test]
    fn derivative_prefers_the_smaller_side() {
        assert_eq!(
            derivative((1.0, 1.0), Some((0.0, 1.0)), Some((11.0, 1.0))),
            Some((1.0, 0.0))
        );
        assert_eq!(
            derivative((1.0, 1.0), None, Some((1.0, 3.0))),
            Some((0.0, 2.0))
        );
        assert_eq!(derivative((1.0, 1.0), None, None), None);
    }
}
