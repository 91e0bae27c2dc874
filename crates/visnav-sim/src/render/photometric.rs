//! Photometric effects of the simulated camera, applied to a rendered radiance frame (digital
//! numbers on the 8-bit scale, channel-interleaved, with a validity mask).
//!
//! Order (a simplified sensor/ISP chain; every step is optional and parameterised by
//! [`PhotometricSpec`]):
//!
//! 1. Exposure and vignetting: `v <- gain * V(r) * v + offset_dn`, with the radial falloff
//!    `V(r) = 1 - vignetting_corner * (r / r_corner)^2` (`r` distance from the principal point,
//!    `r_corner` its distance to the farthest image corner; `vignetting_corner` is the fraction of
//!    light lost in the corners).
//! 2. Gaussian blur (separable, kernel radius `ceil(3 sigma)`), then linear motion blur (a line
//!    kernel of `motion_length_px` along `motion_angle_deg`, measured from the image +u axis
//!    towards +v, i.e. clockwise on screen; sampled every <= 0.5 px with bilinear interpolation).
//!    Both are normalised convolutions over valid pixels: off-map pixels neither contribute nor
//!    change. Borders are clamped.
//! 3. Noise: shot noise (Gaussian approximation of Poisson, variance `v * conversion_gain_dn_per_e`
//!    DN^2, i.e. `v / g` photo-electrons) plus Gaussian read noise `read_noise_dn`, then clipping to
//!    the sensor range [0, 255].
//! 4. Response curve: `v <- 255 (v / 255)^gamma` (gamma > 1 darkens mid-tones).
//! 5. Optional quantisation to integers (8-bit output).
//!
//! Off-map pixels are set to `fill_dn` at the end and skipped by every step.
//!
//! Noise is deterministic: each image row draws from its own [`visnav_core::rng::Rng`] stream
//! (xoshiro256++, Ziggurat normals) seeded from `(seed, frame_index, row)`, so results do not
//! depend on the number of threads.

use rayon::prelude::*;
use visnav_core::rng::Rng;

/// Photometric parameters (see the module doc for the model). `Default` is the identity apart
/// from the clipping to [0, 255].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotometricSpec {
    /// Exposure gain on the radiance.
    pub gain: f64,
    /// Exposure offset added after the gain, DN.
    pub offset_dn: f64,
    /// Response curve exponent (> 1 darkens mid-tones).
    pub gamma: f64,
    /// Fraction of light lost in the image corners.
    pub vignetting_corner: f64,
    /// Gaussian blur sigma, px (0: none).
    pub blur_sigma_px: f64,
    /// Motion blur length, px (0: none).
    pub motion_length_px: f64,
    /// Motion blur direction, from image +u towards +v, deg.
    pub motion_angle_deg: f64,
    /// Gaussian read noise, DN (1 sigma).
    pub read_noise_dn: f64,
    /// Shot noise conversion gain, DN per photo-electron (0: none).
    pub conversion_gain_dn_per_e: f64,
    /// Round the output to integers.
    pub quantise: bool,
    /// Value of off-map pixels, DN.
    pub fill_dn: f64,
    /// Noise seed (each row of each frame draws from its own stream).
    pub seed: u64,
}

impl Default for PhotometricSpec {
    fn default() -> Self {
        Self {
            gain: 1.0,
            offset_dn: 0.0,
            gamma: 1.0,
            vignetting_corner: 0.0,
            blur_sigma_px: 0.0,
            motion_length_px: 0.0,
            motion_angle_deg: 0.0,
            read_noise_dn: 0.0,
            conversion_gain_dn_per_e: 0.0,
            quantise: false,
            fill_dn: 0.0,
            seed: 0,
        }
    }
}

/// Image buffer the effects work on.
pub(crate) struct Planes<'a> {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: &'a mut [f32],
    pub valid: &'a [bool],
    /// Principal point, pixels (vignetting centre).
    pub cx_px: f64,
    pub cy_px: f64,
}

/// Applies all effects in place (see the module doc). `frame_index` varies the noise per frame.
pub(crate) fn apply(p: &mut Planes<'_>, spec: &PhotometricSpec, frame_index: u64) {
    let (w, h, ch) = (p.width, p.height, p.channels);
    if w == 0 || h == 0 {
        return;
    }
    // 1. Exposure + vignetting.
    let r_corner2 = [
        (-0.5 - p.cx_px, -0.5 - p.cy_px),
        (w as f64 - 0.5 - p.cx_px, -0.5 - p.cy_px),
        (-0.5 - p.cx_px, h as f64 - 0.5 - p.cy_px),
        (w as f64 - 0.5 - p.cx_px, h as f64 - 0.5 - p.cy_px),
    ]
    .iter()
    .map(|(x, y)| x * x + y * y)
    .fold(0.0f64, f64::max)
    .max(1e-12);
    let (gain, offset, vig) = (spec.gain, spec.offset_dn, spec.vignetting_corner);
    let (cx, cy) = (p.cx_px, p.cy_px);
    let valid = p.valid;
    if gain != 1.0 || offset != 0.0 || vig != 0.0 {
        p.data
            .par_chunks_mut(w * ch)
            .enumerate()
            .for_each(|(row, line)| {
                let dy = row as f64 - cy;
                for col in 0..w {
                    if !valid[row * w + col] {
                        continue;
                    }
                    let dx = col as f64 - cx;
                    let f = gain * (1.0 - vig * (dx * dx + dy * dy) / r_corner2);
                    for v in &mut line[col * ch..(col + 1) * ch] {
                        *v = (f * f64::from(*v) + offset) as f32;
                    }
                }
            });
    }
    // 2. Blur.
    if spec.blur_sigma_px > 0.0 {
        gaussian_blur(p, spec.blur_sigma_px);
    }
    if spec.motion_length_px > 0.0 {
        motion_blur(p, spec.motion_length_px, spec.motion_angle_deg.to_radians());
    }
    // 3-5. Noise, clipping, response, quantisation, fill.
    let (read, conv, gamma) = (
        spec.read_noise_dn,
        spec.conversion_gain_dn_per_e,
        spec.gamma,
    );
    // Frame stream seed from (seed, frame index); rows seeded from it (Rng::new mixes its seed
    // through SplitMix64, so neighbouring seeds give unrelated streams).
    let seed = Rng::new(spec.seed ^ frame_index.wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64();
    let (quantise, fill) = (spec.quantise, spec.fill_dn as f32);
    p.data
        .par_chunks_mut(w * ch)
        .enumerate()
        .for_each(|(row, line)| {
            let mut rng =
                Rng::new(seed.wrapping_add((row as u64).wrapping_mul(0xD1B5_4A32_D192_ED03)));
            for col in 0..w {
                let px = &mut line[col * ch..(col + 1) * ch];
                if !valid[row * w + col] {
                    px.fill(fill);
                    continue;
                }
                for v in px {
                    let mut x = f64::from(*v);
                    if conv > 0.0 {
                        x += (x.max(0.0) * conv).sqrt() * rng.normal();
                    }
                    if read > 0.0 {
                        x += read * rng.normal();
                    }
                    x = x.clamp(0.0, 255.0);
                    if gamma != 1.0 {
                        x = 255.0 * (x / 255.0).powf(gamma);
                    }
                    if quantise {
                        x = x.round();
                    }
                    *v = x as f32;
                }
            }
        });
}

/// Normalised 1-D Gaussian kernel, radius `ceil(3 sigma)`.
fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as usize; // ok: sigma > 0 finite (validated)
    let mut k: Vec<f64> = (0..=2 * r)
        .map(|i| {
            let x = i as f64 - r as f64;
            (-0.5 * x * x / (sigma * sigma)).exp()
        })
        .collect();
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k.into_iter().map(|v| v as f32).collect()
}

/// Separable Gaussian, normalised over valid pixels, clamped borders.
fn gaussian_blur(p: &mut Planes<'_>, sigma: f64) {
    let k = gaussian_kernel(sigma);
    let r = (k.len() / 2) as i64;
    let (w, h, ch) = (p.width, p.height, p.channels);
    let valid = p.valid;
    // Horizontal pass: weighted sums and weights.
    let src = p.data.to_vec();
    let mut tmp = vec![0.0f32; w * h * ch];
    let mut wsum = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w * ch)
        .zip(wsum.par_chunks_mut(w))
        .enumerate()
        .for_each(|(row, (line, wline))| {
            for col in 0..w {
                let mut acc = [0.0f32; 3];
                let mut ws = 0.0f32;
                for (ki, kv) in k.iter().enumerate() {
                    let c = (col as i64 + ki as i64 - r).clamp(0, w as i64 - 1) as usize;
                    let idx = row * w + c;
                    if valid[idx] {
                        ws += kv;
                        for (a, s) in acc.iter_mut().zip(&src[idx * ch..(idx + 1) * ch]) {
                            *a += kv * s;
                        }
                    }
                }
                line[col * ch..(col + 1) * ch].copy_from_slice(&acc[..ch]);
                wline[col] = ws;
            }
        });
    // Vertical pass on both sums; divide.
    p.data
        .par_chunks_mut(w * ch)
        .enumerate()
        .for_each(|(row, line)| {
            for col in 0..w {
                if !valid[row * w + col] {
                    continue;
                }
                let mut acc = [0.0f32; 3];
                let mut ws = 0.0f32;
                for (ki, kv) in k.iter().enumerate() {
                    let rr = (row as i64 + ki as i64 - r).clamp(0, h as i64 - 1) as usize;
                    let idx = rr * w + col;
                    ws += kv * wsum[idx];
                    for (a, s) in acc.iter_mut().zip(&tmp[idx * ch..(idx + 1) * ch]) {
                        *a += kv * s;
                    }
                }
                if ws > 0.0 {
                    for (v, a) in line[col * ch..(col + 1) * ch].iter_mut().zip(acc) {
                        *v = a / ws;
                    }
                }
            }
        });
}

/// Line-kernel motion blur of `length_px` along angle `angle_rad` (from +u towards +v).
fn motion_blur(p: &mut Planes<'_>, length_px: f64, angle_rad: f64) {
    let n = ((2.0 * length_px).ceil() as usize).max(1) + 1; // ok: length validated finite > 0
    let (du, dv) = (angle_rad.cos(), angle_rad.sin());
    let offsets: Vec<(f64, f64)> = (0..n)
        .map(|i| {
            let s = length_px * (i as f64 / (n - 1) as f64 - 0.5);
            (s * du, s * dv)
        })
        .collect();
    let (w, h, ch) = (p.width, p.height, p.channels);
    let valid = p.valid;
    let src = p.data.to_vec();
    p.data
        .par_chunks_mut(w * ch)
        .enumerate()
        .for_each(|(row, line)| {
            for col in 0..w {
                if !valid[row * w + col] {
                    continue;
                }
                let mut acc = [0.0f32; 3];
                let mut ws = 0.0f32;
                for &(ou, ov) in &offsets {
                    let u = (col as f64 + ou).clamp(0.0, (w - 1) as f64);
                    let v = (row as f64 + ov).clamp(0.0, (h - 1) as f64);
                    let (i0, j0) = (u.floor() as usize, v.floor() as usize); // ok: clamped >= 0
                    let (i1, j1) = ((i0 + 1).min(w - 1), (j0 + 1).min(h - 1));
                    let (a, b) = ((u - i0 as f64) as f32, (v - j0 as f64) as f32);
                    for (i, j, wt) in [
                        (i0, j0, (1.0 - a) * (1.0 - b)),
                        (i1, j0, a * (1.0 - b)),
                        (i0, j1, (1.0 - a) * b),
                        (i1, j1, a * b),
                    ] {
                        let idx = j * w + i;
                        if wt > 0.0 && valid[idx] {
                            ws += wt;
                            for (acc_c, s) in acc.iter_mut().zip(&src[idx * ch..(idx + 1) * ch]) {
                                *acc_c += wt * s;
                            }
                        }
                    }
                }
                if ws > 0.0 {
                    for (v, a) in line[col * ch..(col + 1) * ch].iter_mut().zip(acc) {
                        *v = a / ws;
                    }
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(w: usize, h: usize, data: &mut [f32], valid: &[bool], spec: &PhotometricSpec, k: u64) {
        let mut p = Planes {
            width: w,
            height: h,
            channels: 1,
            data,
            valid,
            cx_px: (w as f64 - 1.0) / 2.0,
            cy_px: (h as f64 - 1.0) / 2.0,
        };
        apply(&mut p, spec, k);
    }

    #[test]
    fn exposure_gamma_vignetting() {
        let (w, h) = (5, 3);
        let valid = vec![true; w * h];
        let mut d = vec![100.0f32; w * h];
        let spec = PhotometricSpec {
            gain: 1.5,
            offset_dn: 10.0,
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        assert!(d.iter().all(|v| (*v - 160.0).abs() < 1e-4));
        // Gamma 2 on 127.5: 255 * 0.25.
        let mut d = vec![127.5f32; w * h];
        let spec = PhotometricSpec {
            gamma: 2.0,
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        assert!((d[0] - 63.75).abs() < 1e-3);
        // Vignetting: centre untouched, corners lose about the fraction given (pixel centres are
        // half a pixel inside the outer corners).
        let mut d = vec![200.0f32; w * h];
        let spec = PhotometricSpec {
            vignetting_corner: 0.4,
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        assert_eq!(d[w + 2], 200.0);
        let corner = 1.0 - 0.4 * (4.0 + 1.0) / (2.5 * 2.5 + 1.5 * 1.5);
        assert!((d[0] - 200.0 * corner as f32).abs() < 1e-3, "{}", d[0]);
        // Saturation and quantisation.
        let mut d = vec![300.0f32, -5.0, 10.4, 10.6, 0.0, 0.0];
        let spec = PhotometricSpec {
            quantise: true,
            ..Default::default()
        };
        run(3, 2, &mut d, &[true; 6], &spec, 0);
        assert_eq!(&d[..4], &[255.0, 0.0, 10.0, 11.0]);
    }

    #[test]
    fn blur_preserves_constants_and_respects_mask() {
        let (w, h) = (20, 10);
        // Left half valid at 100, right half invalid (contents 0 must not bleed in).
        let valid: Vec<bool> = (0..w * h).map(|i| i % w < 10).collect();
        let mut d: Vec<f32> = (0..w * h)
            .map(|i| if i % w < 10 { 100.0 } else { 0.0 })
            .collect();
        let spec = PhotometricSpec {
            blur_sigma_px: 2.0,
            motion_length_px: 5.0,
            motion_angle_deg: 30.0,
            fill_dn: 7.0,
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        for (i, v) in d.iter().enumerate() {
            let expect = if i % w < 10 { 100.0 } else { 7.0 };
            assert!((v - expect).abs() < 1e-3, "{i}: {v}");
        }
    }

    #[test]
    fn gaussian_blur_of_an_impulse_has_the_right_width() {
        let (w, h) = (41, 41);
        let valid = vec![true; w * h];
        let mut d = vec![0.0f32; w * h];
        d[20 * w + 20] = 1000.0;
        let spec = PhotometricSpec {
            blur_sigma_px: 2.5,
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        let total: f64 = d.iter().map(|v| f64::from(*v)).sum();
        let var_x: f64 = d
            .iter()
            .enumerate()
            .map(|(i, v)| f64::from(*v) * ((i % w) as f64 - 20.0).powi(2))
            .sum::<f64>()
            / total;
        assert!((total - 1000.0).abs() < 1.0, "{total}");
        assert!((var_x.sqrt() - 2.5).abs() < 0.05, "{}", var_x.sqrt());
    }

    #[test]
    fn motion_blur_spreads_along_its_direction() {
        let (w, h) = (41, 41);
        let valid = vec![true; w * h];
        let mut d = vec![0.0f32; w * h];
        d[20 * w + 20] = 1000.0;
        let spec = PhotometricSpec {
            motion_length_px: 10.0,
            motion_angle_deg: 90.0, // along +v
            ..Default::default()
        };
        run(w, h, &mut d, &valid, &spec, 0);
        let (mut sv, mut su, mut tot) = (0.0, 0.0, 0.0);
        for (i, v) in d.iter().enumerate() {
            let (u, vv) = ((i % w) as f64 - 20.0, (i / w) as f64 - 20.0);
            tot += f64::from(*v);
            su += f64::from(*v) * u * u;
            sv += f64::from(*v) * vv * vv;
        }
        // Uniform over 10 px: variance 100/12.
        assert!(su / tot < 0.1, "{}", su / tot);
        assert!(((sv / tot) - 100.0 / 12.0).abs() < 1.0, "{}", sv / tot);
    }

    #[test]
    fn noise_is_seeded_and_has_the_right_level() {
        let (w, h) = (200, 100);
        let valid = vec![true; w * h];
        let spec = PhotometricSpec {
            read_noise_dn: 2.0,
            conversion_gain_dn_per_e: 0.25, // at 100 DN: shot sigma 5
            ..Default::default()
        };
        let go = |seed: u64, frame: u64| {
            let mut d = vec![100.0f32; w * h];
            run(
                w,
                h,
                &mut d,
                &valid,
                &PhotometricSpec { seed, ..spec },
                frame,
            );
            d
        };
        let a = go(1, 0);
        assert_eq!(a, go(1, 0));
        assert_ne!(a, go(2, 0));
        assert_ne!(a, go(1, 1));
        let n = a.len() as f64;
        let mean = a.iter().map(|v| f64::from(*v)).sum::<f64>() / n;
        let sd = (a
            .iter()
            .map(|v| (f64::from(*v) - mean).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        let expect = (4.0f64 + 25.0).sqrt();
        assert!((mean - 100.0).abs() < 0.1, "{mean}");
        assert!((sd - expect).abs() < 0.1, "{sd} vs {expect}");
    }
}
