//! Why the filter's health is what it is: each cause with its numbers as fields. People read
//! the `Display` (logs, STATUSTEXT, `visnav sim`'s final health); a consumer that must tell news
//! from a changed number (the link sends its health STATUSTEXT on real changes only) compares
//! the kinds ([`HealthReason::same_kind`]), never the words.

use super::super::divergence::Inconsistent;

/// Why the filter was reset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ResetCause {
    /// The IMU stream stopped for longer than the filter can bridge.
    ImuGap {
        /// The gap, s.
        dt_s: f64,
    },
    /// The state stopped being finite after a propagation.
    NonFinite,
    /// Consecutive position fixes were rejected and the filter's position was reset onto them.
    Divergence {
        /// The fixes rejected in a row.
        rejected: u32,
    },
    /// The covariance lost positive definiteness and was re-initialised.
    CovarianceNotPositiveDefinite,
}

impl std::fmt::Display for ResetCause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::ImuGap { dt_s } => write!(f, "IMU gap of {dt_s:.3} s"),
            Self::NonFinite => write!(f, "non-finite state after propagation"),
            Self::Divergence { rejected } => write!(
                f,
                "{rejected} consecutive position fixes rejected: position reset onto the fix"
            ),
            Self::CovarianceNotPositiveDefinite => write!(f, "covariance not positive definite"),
        }
    }
}

/// One reason the health is not ok.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HealthCause {
    /// Not initialised yet (the last reset's cause when it was reset).
    NotInitialised {
        /// Why it was reset, when it was.
        after_reset: Option<ResetCause>,
    },
    /// The horizontal 1-sigma is over a health limit.
    SigmaOver {
        /// The horizontal 1-sigma, m.
        sigma_m: f64,
        /// The limit, m.
        limit_m: f64,
    },
    /// No position fix has been accepted for a while.
    NoFixFor {
        /// Since the last accepted position fix, s.
        s: f64,
    },
    /// A reset not long ago.
    RecentReset(ResetCause),
    /// Position fixes rejected in a row.
    FixesRejected {
        /// How many.
        n: u32,
    },
    /// The rejected fixes do not agree enough to reset onto.
    NoResetOnto(Inconsistent),
    /// The autopilot's IMU stream fell silent (the service's watchdog: nothing is propagated).
    ImuSilent,
    /// The autopilot rebooted: its clock starts again and the navigation restarts.
    AutopilotRebooted,
}

impl std::fmt::Display for HealthCause {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::NotInitialised { after_reset: None } => {
                write!(
                    f,
                    "not initialised: waiting for a position fix and autopilot attitude"
                )
            }
            Self::NotInitialised {
                after_reset: Some(r),
            } => write!(f, "not initialised (after reset: {r})"),
            Self::SigmaOver { sigma_m, limit_m } => {
                write!(f, "horizontal sigma {sigma_m:.1} m > {limit_m} m")
            }
            Self::NoFixFor { s } => write!(f, "no accepted position fix for {s:.1} s"),
            Self::RecentReset(r) => write!(f, "recent reset: {r}"),
            Self::FixesRejected { n } => write!(f, "{n} consecutive position fixes rejected"),
            Self::NoResetOnto(why) => write!(f, "no reset onto them: {why}"),
            Self::ImuSilent => write!(f, "no IMU data from the autopilot"),
            Self::AutopilotRebooted => write!(f, "autopilot rebooted; navigation restarting"),
        }
    }
}

impl HealthCause {
    /// The same cause whatever its numbers (a nested reset cause or refusal counts by its kind).
    pub fn same_kind(&self, other: &Self) -> bool {
        use std::mem::discriminant as d;
        match (self, other) {
            (Self::NotInitialised { after_reset: a }, Self::NotInitialised { after_reset: b }) => {
                a.map(|a| d(&a)) == b.map(|b| d(&b))
            }
            (Self::RecentReset(a), Self::RecentReset(b)) => d(a) == d(b),
            (Self::NoResetOnto(a), Self::NoResetOnto(b)) => d(a) == d(b),
            _ => d(self) == d(other),
        }
    }
}

/// Why the health is not ok: its causes, in the order they were found (empty when ok).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct HealthReason(pub Vec<HealthCause>);

impl HealthReason {
    /// One cause.
    pub fn of(cause: HealthCause) -> Self {
        Self(vec![cause])
    }
    /// No cause: the health is ok.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    /// The same causes in the same order, whatever their numbers: the same news.
    pub fn same_kind(&self, other: &Self) -> bool {
        self.0.len() == other.0.len() && self.0.iter().zip(&other.0).all(|(a, b)| a.same_kind(b))
    }
}

/// The causes joined by "; " (empty when ok).
impl std::fmt::Display for HealthReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, c) in self.0.iter().enumerate() {
            if i > 0 {
                write!(f, "; ")?;
            }
            write!(f, "{c}")?;
        }
        Ok(())
    }
}

/// Serialised as its words (the output record's `reason`).
impl serde::Serialize for HealthReason {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_news_is_the_same_kind_whatever_its_numbers() {
        let a = HealthReason(vec![
            HealthCause::SigmaOver {
                sigma_m: 31.0,
                limit_m: 30.0,
            },
            HealthCause::NoFixFor { s: 12.5 },
        ]);
        let b = HealthReason(vec![
            HealthCause::SigmaOver {
                sigma_m: 47.2,
                limit_m: 30.0,
            },
            HealthCause::NoFixFor { s: 40.1 },
        ]);
        assert!(a.same_kind(&b));
        assert_eq!(
            a.to_string(),
            "horizontal sigma 31.0 m > 30 m; no accepted position fix for 12.5 s"
        );
        // Another cause, or one cause more, is news.
        let c = HealthReason::of(HealthCause::NoFixFor { s: 12.5 });
        assert!(!a.same_kind(&c));
        let r1 = HealthReason::of(HealthCause::RecentReset(ResetCause::ImuGap { dt_s: 1.0 }));
        let r2 = HealthReason::of(HealthCause::RecentReset(ResetCause::ImuGap { dt_s: 3.0 }));
        let r3 = HealthReason::of(HealthCause::RecentReset(ResetCause::NonFinite));
        assert!(r1.same_kind(&r2) && !r1.same_kind(&r3));
        assert_eq!(HealthReason::default().to_string(), "");
    }
}
