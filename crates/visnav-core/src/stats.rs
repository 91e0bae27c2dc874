//! Statistics shared by the pose integrity checks, the navigation filter and the evaluations: the
//! chi-square distribution's CDF and quantiles (innovation gates, prior-consistency gates, NEES
//! bands) and sample quantiles ([`percentile`], nearest rank).
//!
//! CDF `P(k/2, x/2)` via the regularized lower incomplete gamma function (series for
//! `x < a + 1`, Lentz continued fraction otherwise; Numerical Recipes 6.2), `ln Gamma` by the
//! Lanczos approximation (g = 7, n = 9). Quantiles by bisection on the CDF (monotone).

/// The `p` quantile (nearest rank), NaN for an empty sample.
pub fn percentile(v: &[f64], p: f64) -> f64 {
    let mut v: Vec<f64> = v.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularized lower incomplete gamma function P(a, x).
fn gamma_p(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        let mut ap = a;
        let mut sum = 1.0 / a;
        let mut del = sum;
        for _ in 0..10_000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        sum * (-x + a * x.ln() - gln).exp()
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        1.0 - (-x + a * x.ln() - gln).exp() * h
    }
}

/// Chi-square CDF with `dof` degrees of freedom at `x`.
pub fn chi2_cdf(dof: f64, x: f64) -> f64 {
    gamma_p(0.5 * dof, 0.5 * x)
}

/// Chi-square quantile: the `x` with `chi2_cdf(dof, x) = p`. NaN unless `0 < p < 1` and `dof > 0`
/// (a gate computed from a bad probability must not silently pass everything).
pub fn chi2_quantile(dof: f64, p: f64) -> f64 {
    if !(p > 0.0 && p < 1.0 && dof > 0.0 && dof.is_finite()) {
        return f64::NAN;
    }
    let p = p.clamp(1e-12, 1.0 - 1e-12);
    let mut lo = 0.0;
    let mut hi = dof.max(1.0);
    while chi2_cdf(dof, hi) < p {
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if chi2_cdf(dof, mid) < p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo < 1e-12 * hi.max(1.0) {
            break;
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn quantile_inverts_chi2_cdf(dof in 1u32..400, p in 0.001f64..0.999) {
            let x = chi2_quantile(dof as f64, p);
            prop_assert!((chi2_cdf(dof as f64, x) - p).abs() < 1e-9);
        }
    }

    #[test]
    fn known_quantiles() {
        // Tabulated chi-square quantiles.
        assert!((chi2_quantile(1.0, 0.95) - 3.841_458_8).abs() < 1e-5);
        assert!((chi2_quantile(3.0, 0.95) - 7.814_727_9).abs() < 1e-5);
        assert!((chi2_quantile(3.0, 0.999) - 16.266_236).abs() < 1e-4);
        // Large dof: the Wilson-Hilferty approximation is accurate to ~0.01 here
        // (k = 150: 117.98 and 185.80).
        let wh =
            |k: f64, z: f64| k * (1.0 - 2.0 / (9.0 * k) + z * (2.0 / (9.0 * k)).sqrt()).powi(3);
        assert!((chi2_quantile(150.0, 0.025) - wh(150.0, -1.959_964)).abs() < 0.05);
        assert!((chi2_quantile(150.0, 0.975) - wh(150.0, 1.959_964)).abs() < 0.05);
        assert!((chi2_quantile(150.0, 0.975) - 185.80).abs() < 0.05);
        assert!((chi2_cdf(2.0, 2.0) - (1.0 - (-1.0f64).exp())).abs() < 1e-12);
        // More table values (p, dof, x).
        for (p, k, x) in [
            (0.95, 2.0, 5.991_465),
            (0.99, 6.0, 16.811_89),
            (0.5, 3.0, 2.365_974),
        ] {
            assert!((chi2_quantile(k, p) - x).abs() < 1e-4, "chi2({k}) at {p}");
        }
        assert!(chi2_quantile(3.0, f64::NAN).is_nan());
        assert!(chi2_quantile(3.0, 1.0).is_nan());
        assert!(chi2_quantile(0.0, 0.5).is_nan());
    }
}
