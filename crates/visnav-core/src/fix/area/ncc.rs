//! Masked normalised cross-correlation in the Fourier domain (Padfield, "Masked object
//! registration in the Fourier domain", IEEE TIP 21(5), 2012, eqs. 9-12): a window's spectra
//! computed once, then six correlations per template give, for every shift, the overlap count
//! and the sums the Pearson correlation over the overlap needs.

use std::sync::Arc;

use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

use super::*;

/// The FFTs' number type: single precision suffices for values normalised to zero mean and unit
/// variance (sums over at most a few 10^5 pixels; the correlations agree with a direct f64
/// computation to 1e-4, unit test) and halves the time of the placement.
type Real = f32;

/// Sizes FFTs are fast at: products of 2, 3 and 5, at least `n`.
pub(super) fn fast_size(n: usize) -> usize {
    let mut m = n.max(1);
    loop {
        let mut r = m;
        for p in [2, 3, 5] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return m;
        }
        m += 1;
    }
}

/// A 2-D FFT of `sw x sh` (row-major, `sh` rows); the spectrum is kept transposed (`sw` rows of
/// `sh`), which every use here is indifferent to.
struct Fft2 {
    sw: usize,
    sh: usize,
    fwd_w: Arc<dyn Fft<Real>>,
    fwd_h: Arc<dyn Fft<Real>>,
    inv_w: Arc<dyn Fft<Real>>,
    inv_h: Arc<dyn Fft<Real>>,
}

/// `src` (`h` rows of `w`) transposed, in tiles that stay in cache.
fn transpose(src: &[Complex<Real>], w: usize, h: usize) -> Vec<Complex<Real>> {
    const TILE: usize = 16;
    let mut out = vec![Complex::new(0.0, 0.0); w * h];
    for y0 in (0..h).step_by(TILE) {
        for x0 in (0..w).step_by(TILE) {
            for y in y0..(y0 + TILE).min(h) {
                for x in x0..(x0 + TILE).min(w) {
                    out[x * h + y] = src[y * w + x];
                }
            }
        }
    }
    out
}

impl Fft2 {
    fn new(sw: usize, sh: usize) -> Self {
        let mut p = FftPlanner::new();
        Self {
            sw,
            sh,
            fwd_w: p.plan_fft_forward(sw),
            fwd_h: p.plan_fft_forward(sh),
            inv_w: p.plan_fft_inverse(sw),
            inv_h: p.plan_fft_inverse(sh),
        }
    }

    /// Row-major `sh x sw` in, transposed spectrum out.
    fn forward(&self, mut buf: Vec<Complex<Real>>) -> Vec<Complex<Real>> {
        self.fwd_w.process(&mut buf);
        let mut t = transpose(&buf, self.sw, self.sh);
        self.fwd_h.process(&mut t);
        t
    }

    /// Transposed spectrum in, row-major `sh x sw` out (normalised).
    fn inverse(&self, mut t: Vec<Complex<Real>>) -> Vec<Complex<Real>> {
        self.inv_h.process(&mut t);
        let mut buf = transpose(&t, self.sh, self.sw);
        self.inv_w.process(&mut buf);
        let k = 1.0 / (self.sw * self.sh) as Real;
        buf.iter_mut().for_each(|v| *v *= k);
        buf
    }

    /// Spectra of two real signals packed as `a + i b`: `(A, B)` from `Z = F(a + i b)` by the
    /// Hermitian symmetry of real signals' spectra.
    fn forward_pair(&self, z: Vec<Complex<Real>>) -> (Vec<Complex<Real>>, Vec<Complex<Real>>) {
        let zf = self.forward(z);
        let (sw, sh) = (self.sw, self.sh);
        let mut a = vec![Complex::new(0.0, 0.0); zf.len()];
        let mut b = a.clone();
        for kx in 0..sw {
            let jx = if kx == 0 { 0 } else { sw - kx };
            for ky in 0..sh {
                let i = kx * sh + ky;
                let j = jx * sh + if ky == 0 { 0 } else { sh - ky };
                let (zk, zm) = (zf[i], zf[j].conj());
                a[i] = (zk + zm) * 0.5;
                b[i] = (zk - zm) * Complex::new(0.0, -0.5);
            }
        }
        (a, b)
    }

    /// Spectrum of one real signal.
    fn forward_real(&self, a: &[Real]) -> Vec<Complex<Real>> {
        self.forward(a.iter().map(|&x| Complex::new(x, 0.0)).collect())
    }
}

/// A plane normalised over its valid pixels (zero mean, unit variance) and padded into an
/// `sw x sh` grid, with its mask: `(values * mask, mask)`.
fn normalised_padded(p: &Plane, sw: usize, sh: usize) -> (Vec<Real>, Vec<Real>) {
    let (mut s, mut s2, mut n) = (0f64, 0f64, 0usize);
    for (v, ok) in p.data.iter().zip(&p.valid) {
        if *ok {
            s += f64::from(*v);
            s2 += f64::from(*v).powi(2);
            n += 1;
        }
    }
    let mean = if n > 0 { s / n as f64 } else { 0.0 };
    let sd = if n > 1 {
        (s2 / n as f64 - mean * mean).max(0.0).sqrt()
    } else {
        0.0
    };
    let inv = if sd > 1e-9 { 1.0 / sd } else { 1.0 };
    let mut vals = vec![0.0; sw * sh];
    let mut mask = vec![0.0; sw * sh];
    for y in 0..p.height {
        for x in 0..p.width {
            let i = p.idx(x, y);
            if p.valid[i] {
                vals[y * sw + x] = ((f64::from(p.data[i]) - mean) * inv) as Real;
                mask[y * sw + x] = 1.0;
            }
        }
    }
    (vals, mask)
}

fn pack(a: &[Real], b: &[Real]) -> Vec<Complex<Real>> {
    a.iter().zip(b).map(|(x, y)| Complex::new(*x, *y)).collect()
}

/// The window side of a masked NCC: its spectra, computed once for many templates.
pub struct NccWindow {
    fft: Fft2,
    width: usize,
    height: usize,
    /// Spectra of the mask and the normalised masked values (packed as one transform) and of
    /// their squares.
    f_mi: Vec<Complex<Real>>,
    f_i: Vec<Complex<Real>>,
    f_i2: Vec<Complex<Real>>,
}

impl NccWindow {
    /// Spectra of `window` on FFT sizes of at least its own.
    pub fn new(window: &Plane) -> Self {
        let (sw, sh) = (fast_size(window.width), fast_size(window.height));
        let fft = Fft2::new(sw, sh);
        let (i, mi) = normalised_padded(window, sw, sh);
        let i2: Vec<Real> = i.iter().map(|v| v * v).collect();
        let (f_mi, f_i) = fft.forward_pair(pack(&mi, &i));
        let f_i2 = fft.forward_real(&i2);
        Self {
            fft,
            width: window.width,
            height: window.height,
            f_mi,
            f_i,
            f_i2,
        }
    }

    /// Points of one 2-D transform (the work unit of a correlation: each costs five transforms).
    pub fn transform_points(&self) -> u64 {
        (self.fft.sw * self.fft.sh) as u64
    }

    /// Masked NCC of `template` at every shift inside the window (Padfield 2012): entry
    /// `(dx, dy)` is the Pearson correlation over the pixels valid in both when the template's
    /// top-left pixel lies on window pixel `(dx, dy)`; `dx in 0..=Ww-Tw`, `dy in 0..=Wh-Th`.
    /// `NaN` where the overlap is under `min_overlap` of the template's valid pixels or either
    /// side is flat. `None` when the template does not fit or has no valid pixel.
    pub fn correlate(&self, template: &Plane, min_overlap: f64) -> Option<Surface> {
        if template.width > self.width || template.height > self.height {
            return None;
        }
        let n_t = template.valid_count();
        if n_t == 0 {
            return None;
        }
        let (sw, sh) = (self.fft.sw, self.fft.sh);
        let (t, mt) = normalised_padded(template, sw, sh);
        let t2: Vec<Real> = t.iter().map(|v| v * v).collect();
        let (f_mt, f_t) = self.fft.forward_pair(pack(&mt, &t));
        let f_t2 = self.fft.forward_real(&t2);
        // Correlation c(s) = sum_x a(x) b(x + s)  <->  conj(A) B; two real results per inverse.
        let corr2 = |a1: &[Complex<Real>],
                     b1: &[Complex<Real>],
                     a2: &[Complex<Real>],
                     b2: &[Complex<Real>]| {
            let z: Vec<Complex<Real>> = (0..a1.len())
                .map(|k| a1[k].conj() * b1[k] + Complex::new(0.0, 1.0) * (a2[k].conj() * b2[k]))
                .collect();
            self.fft.inverse(z)
        };
        let n_si = corr2(&f_mt, &self.f_mi, &f_mt, &self.f_i);
        let sii_st = corr2(&f_mt, &self.f_i2, &f_t, &self.f_mi);
        let stt_sit = corr2(&f_t2, &self.f_mi, &f_t, &self.f_i);
        let (w, h) = (
            self.width - template.width + 1,
            self.height - template.height + 1,
        );
        let mut data = vec![f64::NAN; w * h];
        let mut unjudged = Vec::new();
        let need = (min_overlap * n_t as f64).max(2.0);
        for dy in 0..h {
            for dx in 0..w {
                let k = dy * sw + dx;
                let n = f64::from(n_si[k].re).round();
                if n < need {
                    unjudged.push(dy * w + dx);
                    continue;
                }
                let (si, sii, st, stt, sit) = (
                    f64::from(n_si[k].im),
                    f64::from(sii_st[k].re),
                    f64::from(sii_st[k].im),
                    f64::from(stt_sit[k].re),
                    f64::from(stt_sit[k].im),
                );
                let vi = sii - si * si / n;
                let vt = stt - st * st / n;
                if vi < MIN_VARIANCE * n || vt < MIN_VARIANCE * n {
                    continue;
                }
                data[dy * w + dx] = ((sit - si * st / n) / (vi * vt).sqrt()).clamp(-1.0, 1.0);
            }
        }
        Some(Surface {
            width: w,
            height: h,
            data,
            unjudged,
        })
    }
}
