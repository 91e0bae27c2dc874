//! How much noisier the visual odometry's displacements are than they claim, learned from the
//! filter's own innovations (covariance matching on a sliding window: Mehra 1972; Mohamed and
//! Schwarz 1999, "Adaptive Kalman filtering for INS/GPS").
//!
//! A motion's covariance comes from its resection: the tracks' pixel noise, the previous pose's
//! height and tilt, the terrain model. What it leaves out depends on the platform and the scene:
//! tree crowns that the surface model draws as one blurred dome, a multirotor's attitude-loop
//! oscillation between two gyro samples, a rolling shutter, a clock. Measured in ArduCopter SITL
//! at 100 m over Autzen with a 2 Hz camera: the motions' errors were 0.05 / 0.17 m (median / p90)
//! where they claimed 0.048 m, and the filter's VO innovations had a mean NIS of 8.3 for 4 degrees
//! of freedom. Taken at their word, they pulled the gyro-bias states and with them the tilt 1 deg
//! off in a minute; the fixes were then refused as inconsistent and the position drifted
//! (docs/vo.md, "Fusion").
//!
//! Each displacement innovation `dz` is kept with the two parts of its covariance, the filter's
//! own `H P H^T` and the motion's `R`. The scale `k >= 1` is the one for which the median over the
//! window of `dz^T (H P H^T + k R)^-1 dz` is the chi-square median (3 dof): what a consistent
//! measurement gives. The next motion is fused with `k R`. The median makes one gross motion
//! (which the gate refuses anyway) no evidence; `H P H^T` keeps the filter's own uncertainty
//! (after a long time without fixes, when VO matters most) from being blamed on the motions, and
//! innovations where the motion's variance is under a tenth of the whole are left out (they say
//! nothing about it); `k`
//! never goes below 1, so the motions are never believed more than they claim. A motion's own
//! innovation does not set the scale it is fused with. The window lives in the filter's state, so
//! a late measurement's replay of the history sees the scale each motion saw.

use nalgebra::Matrix3;
use nalgebra::Vector3;

use crate::stats::chi2_quantile;

/// Motions in the window: at 2 Hz ten seconds, at 10 Hz two. Enough for the median to be known to
/// about +-30 %, short enough to follow the scene (a wood, then fields).
const WINDOW: usize = 20;
/// Fewest motions before the window says anything (below: scale 1, the motions as claimed).
const MIN_ENTRIES: usize = 8;
/// Largest scale, in variance: 100 is ten times the claimed sigma. A window that asks for more
/// holds motions the gate refuses at any scale the filter would still call VO.
pub(super) const MAX_SCALE: f64 = 100.0;
/// Smallest share of a motion's own variance in its innovation's (traces) for the innovation to
/// say something about it: where the filter's uncertainty is ten times the motion's, any scale
/// of the motion's covariance leaves the NIS nearly as it is, and the filter's own error would be
/// read as the motion's.
const MIN_R_SHARE: f64 = 0.1;
/// Bisection steps on `ln k` over `[0, ln MAX_SCALE]`: 2^-30 of 4.6, far below the median's own
/// uncertainty.
const BISECTION_STEPS: usize = 30;

/// One displacement innovation and the two parts of its covariance.
#[derive(Debug, Clone, Copy)]
struct Entry {
    dz: Vector3<f64>,
    hph: Matrix3<f64>,
    r: Matrix3<f64>,
}

impl Entry {
    /// `dz^T (H P H^T + k R)^-1 dz`; `None` where that covariance is singular.
    fn nis(&self, k: f64) -> Option<f64> {
        let s = self.hph + self.r * k;
        s.try_inverse().map(|inv| self.dz.dot(&(inv * self.dz)))
    }
}

/// The sliding window of displacement innovations (module doc).
#[derive(Debug, Clone, Copy)]
pub(super) struct VoNoise {
    entries: [Option<Entry>; WINDOW],
    next: usize,
}

impl Default for VoNoise {
    fn default() -> Self {
        Self {
            entries: [None; WINDOW],
            next: 0,
        }
    }
}

impl VoNoise {
    /// Keep one motion's innovation `dz` with `H P H^T` and its `R` (as claimed, unscaled).
    /// Non-finite numbers are not kept.
    pub(super) fn push(&mut self, dz: Vector3<f64>, hph: Matrix3<f64>, r: Matrix3<f64>) {
        let finite = dz
            .iter()
            .chain(hph.iter())
            .chain(r.iter())
            .all(|v| v.is_finite());
        if !finite {
            return;
        }
        self.entries[self.next] = Some(Entry { dz, hph, r });
        self.next = (self.next + 1) % WINDOW;
    }

    /// The scale on the motions' covariance, in `[1, MAX_SCALE]` (module doc).
    pub(super) fn scale(&self) -> f64 {
        let entries: Vec<&Entry> = self
            .entries
            .iter()
            .flatten()
            .filter(|e| e.r.trace() >= MIN_R_SHARE * (e.hph.trace() + e.r.trace()))
            .collect();
        if entries.len() < MIN_ENTRIES {
            return 1.0;
        }
        let target = chi2_quantile(3.0, 0.5);
        let median_at = |k: f64| {
            let mut v: Vec<f64> = entries.iter().map(|e| e.nis(k).unwrap_or(0.0)).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let at_claim = median_at(1.0);
        if at_claim.is_nan() || at_claim <= target {
            return 1.0;
        }
        if median_at(MAX_SCALE) > target {
            return MAX_SCALE;
        }
        // The median falls as `k` grows (every term does): bisect on `ln k`.
        let (mut lo, mut hi) = (0.0, MAX_SCALE.ln());
        for _ in 0..BISECTION_STEPS {
            let mid = 0.5 * (lo + hi);
            if median_at(mid.exp()) > target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        hi.exp()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Innovations of motions whose true noise is `true_sigma` where they claim `claimed_sigma`,
    /// with the filter's own velocity uncertainty `filter_sigma` (all metres, isotropic).
    fn window(seed: u64, claimed: f64, truth: f64, filter: f64) -> VoNoise {
        let mut rng = Rng::new(seed);
        let mut w = VoNoise::default();
        for _ in 0..WINDOW {
            let sd = (truth * truth + filter * filter).sqrt();
            let dz = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sd;
            let r = Matrix3::identity() * claimed * claimed;
            w.push(dz, Matrix3::identity() * filter * filter, r);
        }
        w
    }

    #[test]
    fn honest_motions_keep_their_covariance_and_noisier_ones_get_theirs() {
        let (mut honest, mut three) = (Vec::new(), Vec::new());
        for seed in 0..40 {
            honest.push(window(seed, 0.05, 0.05, 0.02).scale());
            three.push(window(seed, 0.05, 0.15, 0.02).scale());
        }
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let (h, t) = (median(&mut honest), median(&mut three));
        // Honest: 1 in about half the windows (the median below the chi-square median), a
        // little above in the others.
        assert!(h < 1.3, "honest motions: median scale {h}");
        assert!(honest.iter().all(|k| *k >= 1.0));
        // Three times noisier than claimed: about 9 in variance (the filter's part is known).
        assert!((6.0..13.0).contains(&t), "3x noisier: median scale {t}");
    }

    #[test]
    fn the_filters_own_uncertainty_is_not_blamed_on_the_motions() {
        // Honest motions (0.05 m) while the filter's velocity is uncertain to 1 m (a long time
        // without fixes): the innovations are large, and all of it is the filter's.
        for s in 0..20 {
            assert_eq!(window(100 + s, 0.05, 0.05, 1.0).scale(), 1.0);
        }
        // Half the filter's variance: the motions still tell, and are found honest.
        let k: Vec<f64> = (0..20)
            .map(|s| window(200 + s, 0.05, 0.05, 0.05).scale())
            .collect();
        assert!(k.iter().all(|k| *k < 3.0), "{k:?}");
    }

    #[test]
    fn few_motions_or_bad_numbers_say_nothing() {
        let mut w = VoNoise::default();
        for _ in 0..MIN_ENTRIES - 1 {
            w.push(
                Vector3::new(10.0, 10.0, 10.0),
                Matrix3::zeros(),
                Matrix3::identity() * 1e-4,
            );
        }
        assert_eq!(w.scale(), 1.0);
        w.push(
            Vector3::new(f64::NAN, 0.0, 0.0),
            Matrix3::zeros(),
            Matrix3::identity(),
        );
        assert_eq!(w.scale(), 1.0, "a NaN is not kept");
        w.push(
            Vector3::new(10.0, 10.0, 10.0),
            Matrix3::zeros(),
            Matrix3::identity() * 1e-4,
        );
        // 10 m where 1 cm is claimed: the largest scale, which the gate then refuses.
        assert_eq!(w.scale(), MAX_SCALE);
    }
}
