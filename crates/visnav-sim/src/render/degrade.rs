//! Photometric degradation of a whole orthophoto: a copy that differs from the original the way
//! two flights' imagery of the same ground differs, for areas of which only one date exists
//! (Autzen). The map is built from one such copy and the camera renders another, so a frame is
//! never matched against the image it was rendered from.
//!
//! Effects, in this order (each optional, [`DegradeSpec`]):
//!
//! 1. **Cast shadows** of the surface model for a sun at `shadow.azimuth_deg` /
//!    `shadow.elevation_deg`: a surface cell is in shadow when the surface rises above the ray
//!    towards the sun within `SHADOW_MAX_REACH_M`; the mask is computed on the surface model's grid
//!    (one sample per cell along the ray), interpolated bilinearly (soft edges one cell wide) and
//!    darkens by `shadow.darkening` (the fraction of light lost: skylight remains). The original
//!    photo keeps its own shadows: another time of day adds shadows where it had none.
//! 2. **White balance and exposure** per channel: `v <- gain_rgb[c] v + offset_dn`.
//! 3. **Low-frequency brightness field** (haze, thin cloud shadows, sun-angle BRDF): a smooth
//!    random field `F` (standard normal values on a grid of `field_wavelength_m`, interpolated
//!    with smoothstep weights) multiplies the brightness by `exp(field_amplitude F)`.
//! 4. **Blur, noise, response curve** (`photometric::apply`: Gaussian blur of `blur_sigma_px`
//!    normalised over valid pixels, Gaussian noise `noise_dn`, `gamma`).
//! 5. **JPEG** at `jpeg_quality` (1-100; 0: none), re-decoded: block artefacts and lost fine
//!    detail, as a map tile server or a camera delivers them.
//!
//! Nodata pixels (all bands equal to the raster's nodata value) stay nodata; valid pixels are
//! kept off the nodata value so that none becomes a hole. Noise streams are seeded per row from
//! `seed` ([`visnav_core::rng::Rng`]): the same spec gives the same bytes on any number of threads.

use image::ImageEncoder;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use visnav_core::geo::dem::Dem;
use visnav_core::geo::raster::{Raster, RasterData};
use visnav_core::rng::Rng;
use visnav_core::validate::{Problems, Validate};

use super::photometric::{self, PhotometricSpec, Planes};

/// Longest distance searched towards the sun for an occluding surface, m (Autzen's tallest
/// structures cast about 90 m at 35 deg; further occluders are not expected at drone scale).
const SHADOW_MAX_REACH_M: f64 = 300.0;

/// Cast shadows of the surface model (step 1 of the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SunShadow {
    /// Sun azimuth, degrees clockwise from grid north.
    pub azimuth_deg: f64,
    /// Sun elevation above the horizon, degrees.
    pub elevation_deg: f64,
    /// Fraction of the light a shadow takes (0-0.95).
    pub darkening: f64,
}

/// How a degraded copy differs from the original (module doc). `Default` is the identity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DegradeSpec {
    /// Noise and field seed.
    pub seed: u64,
    /// Per-channel gain (white balance and exposure); grey rasters use the first.
    pub gain_rgb: [f64; 3],
    /// Offset after the gain, DN.
    pub offset_dn: f64,
    /// Response curve `255 (v / 255)^gamma`.
    pub gamma: f64,
    /// Amplitude of the low-frequency brightness field (log scale, 1 sigma).
    pub field_amplitude: f64,
    /// Its wavelength (grid spacing), metres.
    pub field_wavelength_m: f64,
    /// Gaussian blur, pixels (1 sigma).
    pub blur_sigma_px: f64,
    /// Gaussian noise, DN (1 sigma).
    pub noise_dn: f64,
    /// JPEG quality 1-100 (0: no JPEG).
    pub jpeg_quality: u8,
    /// Cast shadows of the surface model (needs one).
    pub shadow: Option<SunShadow>,
}

impl Default for DegradeSpec {
    fn default() -> Self {
        Self {
            seed: 0,
            gain_rgb: [1.0; 3],
            offset_dn: 0.0,
            gamma: 1.0,
            field_amplitude: 0.0,
            field_wavelength_m: 50.0,
            blur_sigma_px: 0.0,
            noise_dn: 0.0,
            jpeg_quality: 0,
            shadow: None,
        }
    }
}

impl Validate for DegradeSpec {
    fn validate(&self, p: &mut Problems) {
        for (i, g) in self.gain_rgb.iter().enumerate() {
            p.range(&format!("gain_rgb[{i}]"), *g, 0.05, 20.0);
        }
        p.range("offset_dn", self.offset_dn, -255.0, 255.0);
        p.range("gamma", self.gamma, 0.1, 10.0);
        p.range("field_amplitude", self.field_amplitude, 0.0, 2.0);
        p.range("field_wavelength_m", self.field_wavelength_m, 0.1, 1.0e5);
        p.range("blur_sigma_px", self.blur_sigma_px, 0.0, 50.0);
        p.range("noise_dn", self.noise_dn, 0.0, 100.0);
        p.range("jpeg_quality", f64::from(self.jpeg_quality), 0.0, 100.0);
        if let Some(s) = &self.shadow {
            p.section("shadow", |p| {
                p.range("azimuth_deg", s.azimuth_deg, -360.0, 360.0);
                p.range("elevation_deg", s.elevation_deg, 5.0, 90.0);
                p.range("darkening", s.darkening, 0.0, 0.95);
            });
        }
    }
}

/// Why a copy could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DegradeError {
    /// The spec is invalid, or asks for what the inputs cannot give (shadows without a surface
    /// model); the problems in words.
    #[error("degrade: {0}")]
    Spec(String),
    /// The raster cannot be degraded (not 8-bit, not grey or RGB) or its copy cannot be built.
    #[error("degrade: {0}")]
    Raster(String),
}

impl DegradeSpec {
    /// The problems of this spec as one error, keys relative to its section.
    pub fn check(&self) -> Result<(), DegradeError> {
        let mut p = Problems::default();
        self.validate(&mut p);
        if p.list.is_empty() {
            Ok(())
        } else {
            let list: Vec<String> = p.list.iter().map(ToString::to_string).collect();
            Err(DegradeError::Spec(list.join("; ")))
        }
    }
}

/// The degraded copy of an 8-bit `raster` (1 or 3 bands); `surface` (the surface model, heights
/// in metres, the raster's CRS) is needed for `spec.shadow`.
pub fn degrade(
    raster: &Raster,
    surface: Option<&Dem>,
    spec: &DegradeSpec,
) -> Result<Raster, DegradeError> {
    spec.check()?;
    let RasterData::U8(src) = raster.data() else {
        return Err(DegradeError::Raster(
            "only 8-bit orthophotos are degraded".into(),
        ));
    };
    let (w, h, ch) = (raster.width(), raster.height(), raster.bands());
    if !(ch == 1 || ch == 3) {
        return Err(DegradeError::Raster(format!(
            "{ch} bands: only grey or RGB orthophotos are degraded"
        )));
    }
    let nodata = raster
        .nodata()
        .and_then(|v| (v.fract() == 0.0 && (0.0..=255.0).contains(&v)).then_some(v as u8));
    let valid: Vec<bool> = src
        .chunks_exact(ch)
        .map(|px| nodata.is_none_or(|n| px.iter().any(|&v| v != n)))
        .collect();
    let mut data: Vec<f32> = src.iter().map(|&v| f32::from(v)).collect();
    let light = light_field(raster, surface, spec)?;
    let gains: Vec<f32> = (0..ch).map(|c| spec.gain_rgb[c] as f32).collect();
    let offset = spec.offset_dn as f32;
    data.par_chunks_mut(w * ch)
        .zip(light.par_chunks(w))
        .for_each(|(line, l)| {
            for (px, &f) in line.chunks_exact_mut(ch).zip(l) {
                for (v, g) in px.iter_mut().zip(&gains) {
                    *v = g * f * *v + offset;
                }
            }
        });
    let (cx, cy) = (0.5 * w as f64, 0.5 * h as f64);
    photometric::apply(
        &mut Planes {
            width: w,
            height: h,
            channels: ch,
            data: &mut data,
            valid: &valid,
            cx_px: cx,
            cy_px: cy,
        },
        &PhotometricSpec {
            gamma: spec.gamma,
            blur_sigma_px: spec.blur_sigma_px,
            read_noise_dn: spec.noise_dn,
            quantise: true,
            fill_dn: f64::from(nodata.unwrap_or(0)),
            seed: spec.seed,
            ..PhotometricSpec::default()
        },
        0,
    );
    let mut out: Vec<u8> = data.iter().map(|&v| v.clamp(0.0, 255.0) as u8).collect();
    if spec.jpeg_quality > 0 {
        out = jpeg_round_trip(&out, w, h, ch, spec.jpeg_quality)?;
    }
    // Nodata stays nodata; nothing valid becomes nodata.
    if let Some(n) = nodata {
        let bump = if n == 255 { 254 } else { n.saturating_add(1) };
        for (px, &ok) in out.chunks_exact_mut(ch).zip(&valid) {
            if !ok {
                px.fill(n);
            } else if px.iter().all(|&v| v == n) {
                px[0] = bump;
            }
        }
    }
    Raster::new(
        w,
        h,
        ch,
        RasterData::U8(out),
        *raster.transform(),
        raster.crs(),
        raster.nodata(),
    )
    .map_err(|e| DegradeError::Raster(e.to_string()))
}

/// Per-pixel light factor: shadows times the low-frequency field (1 without either).
fn light_field(
    raster: &Raster,
    surface: Option<&Dem>,
    spec: &DegradeSpec,
) -> Result<Vec<f32>, DegradeError> {
    let (w, h) = (raster.width(), raster.height());
    let t = raster.transform();
    let shadow = match (&spec.shadow, surface) {
        (None, _) => None,
        (Some(s), Some(d)) => Some((ShadowMask::new(raster, d, s), s.darkening)),
        (Some(_), None) => {
            return Err(DegradeError::Spec(
                "shadow needs the surface model the orthophoto lies on".into(),
            ));
        }
    };
    let field = (spec.field_amplitude > 0.0).then(|| {
        let b = raster.bounds();
        SmoothField::new(
            [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m],
            spec.field_wavelength_m,
            spec.seed,
        )
    });
    let mut out = vec![1.0f32; w * h];
    if shadow.is_none() && field.is_none() {
        return Ok(out);
    }
    out.par_chunks_mut(w).enumerate().for_each(|(row, line)| {
        for (col, v) in line.iter_mut().enumerate() {
            let (x, y) = t.pixel_to_map(col as f64 + 0.5, row as f64 + 0.5);
            let mut f = 1.0;
            if let Some((m, dark)) = &shadow {
                f *= 1.0 - dark * m.at(x, y);
            }
            if let Some(field) = &field {
                f *= (spec.field_amplitude * field.at(x, y)).exp();
            }
            *v = f as f32;
        }
    });
    Ok(out)
}

/// The shadow mask on the surface model's grid over the raster's bounds (1 in shadow).
struct ShadowMask {
    x0_m: f64,
    y0_m: f64,
    step_m: f64,
    w: usize,
    h: usize,
    mask: Vec<f32>,
}

impl ShadowMask {
    fn new(raster: &Raster, surface: &Dem, sun: &SunShadow) -> Self {
        let b = raster.bounds();
        let step_m = match surface {
            Dem::Grid(g) => {
                let (a, c) = g.transform().pixel_size();
                a.min(c).max(0.1)
            }
            Dem::Flat { .. } => 1.0,
        };
        let w = ((b.max_x_m - b.min_x_m) / step_m).ceil() as usize + 1;
        let h = ((b.max_y_m - b.min_y_m) / step_m).ceil() as usize + 1;
        // Samples at cell centres of a grid aligned with the raster's corner.
        let (x0_m, y0_m) = (b.min_x_m + 0.5 * step_m, b.max_y_m - 0.5 * step_m);
        let az = sun.azimuth_deg.to_radians();
        let (dx, dy) = (az.sin() * step_m, az.cos() * step_m);
        let rise = sun.elevation_deg.to_radians().tan() * step_m;
        let (_, top) = surface.height_range_m();
        let reach = (SHADOW_MAX_REACH_M / step_m) as usize;
        let mut mask = vec![0.0f32; w * h];
        mask.par_chunks_mut(w).enumerate().for_each(|(r, line)| {
            let y = y0_m - r as f64 * step_m;
            for (c, m) in line.iter_mut().enumerate() {
                let x = x0_m + c as f64 * step_m;
                let Some(z0) = surface.height_at(x, y) else {
                    continue;
                };
                for k in 1..=reach {
                    let z_ray = z0 + rise * k as f64;
                    if z_ray > top {
                        break;
                    }
                    let kf = k as f64;
                    if surface
                        .height_at(x + dx * kf, y + dy * kf)
                        .is_some_and(|z| z > z_ray)
                    {
                        *m = 1.0;
                        break;
                    }
                }
            }
        });
        Self {
            x0_m,
            y0_m,
            step_m,
            w,
            h,
            mask: soften(&mask, w, h),
        }
    }

    /// Bilinear mask value at a map point (0 outside).
    fn at(&self, x_m: f64, y_m: f64) -> f64 {
        let u = (x_m - self.x0_m) / self.step_m;
        let v = (self.y0_m - y_m) / self.step_m;
        if !(u >= 0.0 && v >= 0.0) {
            return 0.0;
        }
        let (c, r) = (u.floor() as usize, v.floor() as usize);
        if c + 1 >= self.w || r + 1 >= self.h {
            return 0.0;
        }
        let (fu, fv) = (u - c as f64, v - r as f64);
        let m = |cc: usize, rr: usize| f64::from(self.mask[rr * self.w + cc]);
        (1.0 - fv) * ((1.0 - fu) * m(c, r) + fu * m(c + 1, r))
            + fv * ((1.0 - fu) * m(c, r + 1) + fu * m(c + 1, r + 1))
    }
}

/// `mask` smoothed once by the separable `[1 2 1] / 4` kernel (edge cells repeated): shadow
/// edges about a cell wide, as a penumbra and the surface model's own smoothing give, instead
/// of the cells' staircase.
fn soften(mask: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut a = mask.to_vec();
    let mut b = vec![0.0f32; w * h];
    for _ in 0..1 {
        for r in 0..h {
            for c in 0..w {
                let (l, rr) = (c.saturating_sub(1), (c + 1).min(w - 1));
                b[r * w + c] = 0.25 * (a[r * w + l] + 2.0 * a[r * w + c] + a[r * w + rr]);
            }
        }
        for r in 0..h {
            let (u, d) = (r.saturating_sub(1), (r + 1).min(h - 1));
            for c in 0..w {
                a[r * w + c] = 0.25 * (b[u * w + c] + 2.0 * b[r * w + c] + b[d * w + c]);
            }
        }
    }
    a
}

/// Standard normal values on a square grid over a box, interpolated with smoothstep weights.
struct SmoothField {
    x0_m: f64,
    y0_m: f64,
    step_m: f64,
    w: usize,
    values: Vec<f64>,
}

impl SmoothField {
    fn new(bounds: [f64; 4], step_m: f64, seed: u64) -> Self {
        let w = ((bounds[2] - bounds[0]) / step_m).ceil() as usize + 2;
        let h = ((bounds[3] - bounds[1]) / step_m).ceil() as usize + 2;
        let mut rng = Rng::new(seed ^ 0x5EED_F1E1_D000_0001);
        let values = (0..w * h).map(|_| rng.normal()).collect();
        Self {
            x0_m: bounds[0],
            y0_m: bounds[1],
            step_m,
            w,
            values,
        }
    }

    fn at(&self, x_m: f64, y_m: f64) -> f64 {
        let u = ((x_m - self.x0_m) / self.step_m).max(0.0);
        let v = ((y_m - self.y0_m) / self.step_m).max(0.0);
        let h = self.values.len() / self.w;
        let (c, r) = (
            (u.floor() as usize).min(self.w - 2),
            (v.floor() as usize).min(h - 2),
        );
        let s = |t: f64| {
            let t = t.clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        };
        let (fu, fv) = (s(u - c as f64), s(v - r as f64));
        let m = |cc: usize, rr: usize| self.values[rr * self.w + cc];
        (1.0 - fv) * ((1.0 - fu) * m(c, r) + fu * m(c + 1, r))
            + fv * ((1.0 - fu) * m(c, r + 1) + fu * m(c + 1, r + 1))
    }
}

/// Encodes `data` as JPEG at `quality` and decodes it again.
fn jpeg_round_trip(
    data: &[u8],
    w: usize,
    h: usize,
    ch: usize,
    quality: u8,
) -> Result<Vec<u8>, DegradeError> {
    let err = |e: &dyn std::fmt::Display| DegradeError::Raster(format!("JPEG: {e}"));
    let (w32, h32) = (
        u32::try_from(w).map_err(|e| err(&e))?,
        u32::try_from(h).map_err(|e| err(&e))?,
    );
    let colour = if ch == 3 {
        image::ExtendedColorType::Rgb8
    } else {
        image::ExtendedColorType::L8
    };
    let mut buf = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut buf, quality.clamp(1, 100))
        .write_image(data, w32, h32, colour)
        .map_err(|e| err(&e))?;
    let img =
        image::load_from_memory_with_format(&buf, image::ImageFormat::Jpeg).map_err(|e| err(&e))?;
    Ok(if ch == 3 {
        img.into_rgb8().into_raw()
    } else {
        img.into_luma8().into_raw()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use visnav_core::geo::Crs;
    use visnav_core::geo::raster::GeoTransform;

    fn raster(w: usize, h: usize, f: impl Fn(usize, usize) -> [u8; 3]) -> Raster {
        let mut d = Vec::with_capacity(w * h * 3);
        for r in 0..h {
            for c in 0..w {
                d.extend_from_slice(&f(c, r));
            }
        }
        Raster::new(
            w,
            h,
            3,
            RasterData::U8(d),
            GeoTransform::north_up(1000.0, 2000.0, 1.0, 1.0).unwrap(),
            Crs::Utm {
                zone: 10,
                north: true,
            },
            Some(0.0),
        )
        .unwrap()
    }

    #[test]
    fn the_identity_spec_copies_and_nodata_stays() {
        let r = raster(
            40,
            30,
            |c, _| if c < 5 { [0, 0, 0] } else { [100, 120, 90] },
        );
        let d = degrade(&r, None, &DegradeSpec::default()).unwrap();
        assert_eq!(d.data(), r.data());
        let spec = DegradeSpec {
            gain_rgb: [0.05, 0.05, 0.05],
            noise_dn: 5.0,
            blur_sigma_px: 1.0,
            jpeg_quality: 50,
            field_amplitude: 0.3,
            field_wavelength_m: 10.0,
            seed: 3,
            ..DegradeSpec::default()
        };
        let d = degrade(&r, None, &spec).unwrap();
        let RasterData::U8(v) = d.data() else {
            panic!()
        };
        for r in 0..30 {
            for c in 0..40 {
                let px = &v[(r * 40 + c) * 3..(r * 40 + c) * 3 + 3];
                if c < 5 {
                    assert_eq!(px, [0, 0, 0], "nodata at {c},{r}");
                } else {
                    assert!(px.iter().any(|&x| x != 0), "valid at {c},{r} became nodata");
                }
            }
        }
        // Same spec, same bytes.
        assert_eq!(degrade(&r, None, &spec).unwrap().data(), d.data());
    }

    #[test]
    fn a_wall_casts_its_shadow_away_from_the_sun() {
        // 60 x 60 m, 1 m cells, a 10 m wall over x = 1030-1032 m; sun from the east at 45 deg: the
        // ground west of the wall is in shadow for 10 m, east of it lit.
        let r = raster(60, 60, |_, _| [200, 200, 200]);
        let mut dem = vec![100.0f32; 60 * 60];
        for row in 0..60 {
            dem[row * 60 + 30] = 110.0;
            dem[row * 60 + 31] = 110.0;
        }
        let dem = Dem::from_raster(
            &Raster::new(
                60,
                60,
                1,
                RasterData::F32(dem),
                GeoTransform::north_up(1000.0, 2000.0, 1.0, 1.0).unwrap(),
                Crs::Utm {
                    zone: 10,
                    north: true,
                },
                None,
            )
            .unwrap(),
        )
        .unwrap();
        let spec = DegradeSpec {
            shadow: Some(SunShadow {
                azimuth_deg: 90.0,
                elevation_deg: 45.0,
                darkening: 0.5,
            }),
            ..DegradeSpec::default()
        };
        let d = degrade(&r, Some(&dem), &spec).unwrap();
        let at = |c: usize| d.sample(c, 30, 0).unwrap();
        assert!(at(24) < 110.0, "west of the wall in shadow: {}", at(24));
        assert!(at(12) > 190.0, "beyond the shadow lit: {}", at(12));
        assert!(at(40) > 190.0, "east of the wall lit: {}", at(40));
        assert!(
            degrade(&r, None, &spec).is_err(),
            "shadows need the surface"
        );
    }

    #[test]
    fn bad_specs_name_their_key() {
        let spec = DegradeSpec {
            gamma: 0.0,
            ..DegradeSpec::default()
        };
        let e = spec.check().unwrap_err().to_string();
        assert!(e.contains("gamma"), "{e}");
    }
}
