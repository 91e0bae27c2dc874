//! The uniqueness rule of a search over hypotheses (headings, places): the accepted hypothesis
//! with the most evidence wins only when it leads every competitor (an accepted fix elsewhere, a
//! hypothesis at a far heading) by [`UNIQUENESS_RATIO`]; a placement fix, which has no tie points
//! to weigh, by its correlation's margin. With none accepted, the hypothesis that got furthest
//! explains the rejection.

use super::*;

/// A hypothesis search accepts its best fix only when its evidence (fine matches above its own
/// chance level, [`Attempt::evidence`]) is at least this many times its best competitor's (an
/// accepted fix at another place, or any hypothesis two or more heading steps away from the
/// fix's heading). The same margin as the a-contrario test's default `null_factor`: a genuine
/// view beats the alternatives clearly, a look-alike does not.
pub(super) const UNIQUENESS_RATIO: f64 = 1.5;

/// Two accepted fixes are at the same place when their horizontal distance is within this many
/// of their combined horizontal sigmas.
pub(super) const SAME_PLACE_SIGMAS: f64 = 3.0;

/// One hypothesis of a search: the heading the frame was rectified at and its outcome.
pub(super) struct Hypothesis {
    pub(super) rect_yaw_rad: f64,
    pub(super) report: FixReport,
    pub(super) attempt: Attempt,
}

impl Hypothesis {
    pub(super) fn new(rect_yaw_rad: f64, report: FixReport, attempt: Attempt) -> Self {
        Self {
            rect_yaw_rad,
            report,
            attempt,
        }
    }
}

/// The strongest alternative to a search's best hypothesis.
pub(super) struct Competitor {
    /// Its [`Attempt::evidence`].
    pub(super) evidence: usize,
    /// Distance of its accepted fix from the best one, metres (None: not accepted).
    pub(super) elsewhere_m: Option<f64>,
    pub(super) rect_yaw_rad: f64,
}

/// Horizontal 1-sigma of a report, metres (the larger of north and east).
pub(super) fn sigma_h_m(r: &FixReport) -> f64 {
    r.cov_ned_m2[0][0].max(r.cov_ned_m2[1][1]).max(0.0).sqrt()
}

/// Horizontal distance between two fixes, metres (map grid).
pub(super) fn apart_m(a: &FixReport, b: &FixReport) -> f64 {
    (a.x_m - b.x_m).hypot(a.y_m - b.y_m)
}

/// Two accepted fixes within [`SAME_PLACE_SIGMAS`] of their combined horizontal sigmas (not
/// shown further apart: a distance that is not a number does not separate them).
pub(super) fn same_place(a: &FixReport, b: &FixReport) -> bool {
    let further = apart_m(a, b) > SAME_PLACE_SIGMAS * sigma_h_m(a).hypot(sigma_h_m(b));
    !further
}

/// The search's answer: the accepted hypothesis with the most inliers, if it is unique (its
/// evidence at least [`UNIQUENESS_RATIO`] times its best competitor's: an accepted fix at
/// another place, or any hypothesis rectified two or more heading steps from the fix's heading);
/// otherwise a rejection that says what competed. With none accepted, the hypothesis that got
/// furthest (most evidence) explains the rejection.
pub(super) fn select_unique(tries: Vec<Hypothesis>, t_us: u64) -> (FixReport, Attempt) {
    let n = tries.len();
    let best = tries
        .iter()
        .enumerate()
        .filter(|(_, h)| h.report.accepted)
        .max_by(|(ia, a), (ib, b)| {
            (a.report.inliers, a.attempt.fine_matches)
                .cmp(&(b.report.inliers, b.attempt.fine_matches))
                .then(a.attempt.area_ncc.total_cmp(&b.attempt.area_ncc))
                .then(ib.cmp(ia))
        })
        .map(|(i, _)| i);
    let Some(bi) = best else {
        let furthest = tries.into_iter().rev().max_by_key(|h| h.attempt.evidence());
        return match furthest {
            Some(h) => {
                let mut r = h.report;
                if n > 1 {
                    r.rejection = Some(Rejection::Headings {
                        tried: n,
                        best: Box::new(Rejection::or_unexplained(r.rejection.take())),
                    });
                }
                (r, h.attempt)
            }
            None => (
                FixReport::rejected(Rejection::NoHypothesis, t_us, 0.0),
                Attempt::default(),
            ),
        };
    };
    let b = &tries[bi];
    let far_heading = 1.5 * HEADING_STEP_DEG.to_radians();
    let best_yaw = b.report.yaw_deg.to_radians();
    if b.report.method == FixMethod::Placement {
        return placement_unique(tries, bi, far_heading, t_us);
    }
    let competitor = tries
        .iter()
        .enumerate()
        .filter(|(j, _)| *j != bi)
        .filter(|(_, h)| {
            if h.report.accepted {
                !same_place(&h.report, &b.report)
            } else {
                wrap_pi(h.rect_yaw_rad - best_yaw).abs() > far_heading
            }
        })
        .max_by_key(|(_, h)| h.attempt.evidence())
        .map(|(_, h)| Competitor {
            evidence: h.attempt.evidence(),
            elsewhere_m: h
                .report
                .accepted
                .then(|| (h.report.x_m - b.report.x_m).hypot(h.report.y_m - b.report.y_m)),
            rect_yaw_rad: h.rect_yaw_rad,
        });
    let mut tries = tries;
    let Hypothesis {
        report, attempt, ..
    } = tries.swap_remove(bi);
    if let Some(c) = competitor
        && (attempt.evidence() as f64) < UNIQUENESS_RATIO * c.evidence as f64
    {
        let reason = Rejection::Ambiguous {
            evidence: attempt.evidence(),
            heading_deg: report.yaw_deg,
            rival_evidence: c.evidence,
            rival: match c.elsewhere_m {
                Some(distance_m) => Rival::Elsewhere { distance_m },
                None => Rival::Heading {
                    heading_deg: c.rect_yaw_rad.to_degrees(),
                },
            },
            ratio: UNIQUENESS_RATIO,
        };
        let mut r = FixReport::rejected(reason, t_us, 0.0);
        r.matches = report.matches;
        r.level = report.level;
        return (r, attempt);
    }
    (report, attempt)
}

/// [`select_unique`] for a placement fix (no tie points to weigh): every other hypothesis must
/// either be accepted at the same place, or (not accepted) correlate less than the winner: by
/// the placement fix's margin ([`area_stage::PLACEMENT_FIX_MARGIN`]) when it lies beyond
/// `far_heading` of the fix's heading, at all when within it. The place and the heading are
/// then unique over the sweep as the placement is within its own gate. A nearby heading that
/// saw the same ground correlate more and still refused it (no unique place, a plateau, a
/// refinement that moved) says that ground settles no place; a weaker view of it cannot be more
/// certain. NAIP cross-date at 300-600 m with the drone camera (seed 2, 60 frames): the widened
/// sweep's placements 68 m (6.2 sigma) and 169 m (7.1 sigma) off had such a neighbour (0.44
/// against 0.41; 0.575 against 0.573).
pub(super) fn placement_unique(
    mut tries: Vec<Hypothesis>,
    bi: usize,
    far_heading: f64,
    t_us: u64,
) -> (FixReport, Attempt) {
    let b = &tries[bi];
    let best_yaw = b.report.yaw_deg.to_radians();
    let rival_margin = |h: &Hypothesis| {
        if wrap_pi(h.rect_yaw_rad - best_yaw).abs() > far_heading {
            area_stage::PLACEMENT_FIX_MARGIN
        } else {
            0.0
        }
    };
    let rival = tries.iter().enumerate().find(|&(j, h)| {
        if j == bi {
            return false;
        }
        if h.report.accepted {
            return !same_place(&h.report, &b.report);
        }
        h.attempt.area_ncc > b.attempt.area_ncc - rival_margin(h)
    });
    if let Some((_, h)) = rival {
        let reason = Rejection::AmbiguousPlacement {
            ncc: b.attempt.area_ncc,
            heading_deg: b.report.yaw_deg,
            rival_ncc: h.attempt.area_ncc,
            rival_heading_deg: h.rect_yaw_rad.to_degrees(),
            margin: rival_margin(h),
        };
        let mut r = FixReport::rejected(reason, t_us, 0.0);
        r.level = b.report.level;
        return (r, tries.swap_remove(bi).attempt);
    }
    let h = tries.swap_remove(bi);
    (h.report, h.attempt)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hypothesis(
        rect_yaw_deg: f64,
        accepted: bool,
        at: (f64, f64),
        fine: usize,
        null: usize,
    ) -> Hypothesis {
        let mut r = FixReport::rejected(Rejection::FewFeatures { n: 0 }, 7, 0.0);
        if accepted {
            r.accepted = true;
            r.rejection = None;
            r.x_m = at.0;
            r.y_m = at.1;
            r.yaw_deg = rect_yaw_deg + 2.0;
            r.cov_ned_m2 = [[100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0]];
            r.inliers = fine / 2;
        }
        let a = Attempt {
            fine_matches: fine,
            null_matches: null,
            ..Attempt::default()
        };
        Hypothesis::new(rect_yaw_deg.to_radians(), r, a)
    }

    #[test]
    fn select_unique_accepts_a_clear_winner_only() {
        // A clear winner: its neighbours in heading and a far heading at chance level.
        let (r, _) = select_unique(
            vec![
                hypothesis(0.0, false, (0.0, 0.0), 14, 10),
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(30.0, true, (104.0, 52.0), 40, 10),
                hypothesis(90.0, false, (0.0, 0.0), 20, 10),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        assert_eq!((r.x_m, r.y_m), (100.0, 50.0));
        // A far heading with nearly as much evidence: ambiguous, rejected, saying so.
        let (r, a) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(120.0, false, (0.0, 0.0), 45, 10),
            ],
            7,
        );
        assert!(!r.accepted);
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::Ambiguous {
                    evidence: 50,
                    rival_evidence: 35,
                    rival: Rival::Heading { heading_deg },
                    ..
                }) if (heading_deg - 120.0).abs() < 1e-9
            ),
            "{}",
            r.reason()
        );
        assert_eq!(r.class(), "ambiguous");
        assert_eq!(a.fine_matches, 60);
        // An accepted fix at another place with nearly as much evidence: rejected.
        let (r, _) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(30.0, true, (900.0, 50.0), 44, 10),
            ],
            7,
        );
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::Ambiguous {
                    rival: Rival::Elsewhere { distance_m: 800.0 },
                    ..
                })
            ),
            "{}",
            r.reason()
        );
        assert!(!r.accepted && r.reason().contains("another place 800 m away"));
        // The same place twice is one answer, not a competitor.
        let (r, _) = select_unique(
            vec![
                hypothesis(15.0, true, (100.0, 50.0), 60, 10),
                hypothesis(90.0, true, (110.0, 45.0), 58, 10),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        // Nothing accepted: the rejection of the hypothesis that got furthest, with the count.
        let mut best = hypothesis(45.0, false, (0.0, 0.0), 30, 10);
        best.report.rejection = Some(Rejection::BelowChance {
            matches: 30,
            chance: 10,
            needed: 27,
        });
        let (r, _) = select_unique(vec![hypothesis(0.0, false, (0.0, 0.0), 12, 10), best], 7);
        assert!(!r.accepted);
        assert_eq!(
            r.reason(),
            "2 headings tried, best: only 30 matches where chance gives 10 (need 27)"
        );
        assert_eq!(r.class(), "below_chance");
    }

    /// An area-correlation hypothesis: no feature matches, `ties` tie points.
    fn area_hypothesis(
        rect_yaw_deg: f64,
        accepted: bool,
        at: (f64, f64),
        ties: usize,
    ) -> Hypothesis {
        let mut h = hypothesis(rect_yaw_deg, accepted, at, 0, 0);
        h.attempt.area_ties = ties;
        h.report.inliers = ties;
        h
    }

    #[test]
    fn select_unique_weighs_area_hypotheses_by_their_tie_points() {
        // Two area fixes at places 800 m apart with about the same tie points: ambiguous.
        let (r, _) = select_unique(
            vec![
                area_hypothesis(15.0, true, (100.0, 50.0), 40),
                area_hypothesis(60.0, true, (900.0, 50.0), 35),
            ],
            7,
        );
        assert!(
            !r.accepted && r.reason().contains("another place 800 m away"),
            "{}",
            r.reason()
        );
        // A clear winner against a far heading with a few ties.
        let (r, _) = select_unique(
            vec![
                area_hypothesis(15.0, true, (100.0, 50.0), 40),
                area_hypothesis(90.0, false, (0.0, 0.0), 12),
            ],
            7,
        );
        assert!(r.accepted, "{}", r.reason());
        // Features and area in one attempt: the larger evidence counts.
        let mut both = hypothesis(0.0, false, (0.0, 0.0), 30, 10).attempt;
        both.area_ties = 25;
        assert_eq!(both.evidence(), 25);
        both.area_ties = 5;
        assert_eq!(both.evidence(), 20);
        // Tie points count above their own chance level, as matches do.
        both.area_ties = 40;
        both.area_null_ties = 15;
        assert_eq!(both.evidence(), 25);
    }

    /// A hypothesis placed with correlation `ncc`; accepted as a placement fix at `at` or not.
    fn placement_hypothesis(rect_yaw_deg: f64, fix_at: Option<(f64, f64)>, ncc: f64) -> Hypothesis {
        let mut h = hypothesis(
            rect_yaw_deg,
            fix_at.is_some(),
            fix_at.unwrap_or_default(),
            0,
            0,
        );
        h.report.inliers = 0;
        if fix_at.is_some() {
            h.report.method = FixMethod::Placement;
        }
        h.attempt.area_ncc = ncc;
        h
    }

    #[test]
    fn select_unique_takes_a_placement_fix_only_when_its_correlation_leads() {
        // Headings within 1.5 steps (22.5 deg) of the fix's may correlate as well; farther ones
        // correlate 0.1 less or accept at the same place.
        let tries = || {
            vec![
                placement_hypothesis(0.0, None, 0.40),
                placement_hypothesis(15.0, Some((0.0, 0.0)), 0.45),
                placement_hypothesis(30.0, Some((5.0, 0.0)), 0.42),
                placement_hypothesis(45.0, None, 0.33),
                placement_hypothesis(180.0, None, 0.34),
            ]
        };
        let (r, a) = select_unique(tries(), 7);
        assert!(r.accepted, "{}", r.reason());
        assert_eq!(a.area_ncc, 0.45, "the best correlation wins");
        // A far heading within 0.1 of it: ambiguous.
        let mut t = tries();
        t[4].attempt.area_ncc = 0.36;
        let (r, _) = select_unique(t, 7);
        assert!(
            matches!(r.rejection, Some(Rejection::AmbiguousPlacement { .. })),
            "{}",
            r.reason()
        );
        // Another accepted placement fix at another place: ambiguous.
        let mut t = tries();
        t[4] = placement_hypothesis(180.0, Some((900.0, 0.0)), 0.30);
        let (r, _) = select_unique(t, 7);
        assert!(!r.accepted, "{}", r.reason());
        // A nearby heading that correlated more and refused the place: ambiguous; one that
        // correlated less, or as much, does not stand against it.
        let mut t = tries();
        t[0].attempt.area_ncc = 0.46;
        let (r, _) = select_unique(t, 7);
        assert!(
            matches!(
                r.rejection,
                Some(Rejection::AmbiguousPlacement { margin: 0.0, .. })
            ),
            "{}",
            r.reason()
        );
        let mut t = tries();
        t[0].attempt.area_ncc = 0.45;
        let (r, _) = select_unique(t, 7);
        assert!(r.accepted, "{}", r.reason());
        // A tie-point fix outranks a placement fix.
        let mut t = tries();
        t.push(area_hypothesis(90.0, true, (0.0, 3.0), 30));
        let (r, _) = select_unique(t, 7);
        assert!(r.accepted && r.inliers == 30, "{}", r.reason());
    }
}
