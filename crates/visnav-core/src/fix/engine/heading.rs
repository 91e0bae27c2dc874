//! The heading search of a fix with a position prior (docs/fix.md, "A heading that is wrong"):
//! one rectification at the prior's heading, or a sweep of heading hypotheses when its sigma is
//! too large for one; when nothing is found and the caller asks, the heading widened and then the
//! area search over the prior's window, each fix beating a chance bar raised for the headings
//! asked.

use super::*;

impl FixEngine {
    /// A position prior without attitude: near-nadir views at [`HEADINGS`] headings (upright
    /// SURF degrades quickly beyond about +-10 deg), no attitude prior in the resection; the
    /// unique best hypothesis wins ([`select_unique`]).
    pub(super) fn fix_any_heading(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        t_us: u64,
    ) -> (FixReport, Attempt) {
        self.fix_heading_sweep(frame, pos, &self.nadir_any_heading(), None, t_us, false)
    }

    /// A heading sigma too large for one rectification ([`YAW_SWEEP_ABOVE_DEG`]): the frame is
    /// rectified at heading hypotheses [`HEADING_STEP_DEG`] apart over the prior's +-3 sigma
    /// (tilt kept: roll and pitch come from gravity), each matched and solved with the caller's
    /// prior (its loose heading; `solve`, None for no attitude prior), and the unique best
    /// hypothesis wins ([`select_unique`]). With none accepted, the same by area correlation
    /// alone (unless `[fix] area_matching = "off"`). The winner is redone at its own heading
    /// ([`Self::refine_sweep_fix`]).
    pub(super) fn fix_heading_sweep(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        att_from_filter: bool,
    ) -> (FixReport, Attempt) {
        let hyps = heading_hypotheses(att);
        let sweep = |how: Single| -> Vec<Hypothesis> {
            hyps.iter()
                .map(|hyp| {
                    let (r, a) = self.fix_single(frame, pos, Plan::new(hyp, solve, how), t_us);
                    Hypothesis::new(hyp.attitude.yaw_rad, r, a)
                })
                .collect()
        };
        let features = Single {
            att_from_filter,
            features: true,
            area: false,
            placement: false,
            corroborate: false,
        };
        let (r, a) = select_unique(sweep(features), t_us);
        if r.accepted {
            return self.refine_sweep_fix(
                frame,
                pos,
                Plan::new(att, solve, features),
                t_us,
                (r, a),
            );
        }
        // Without an attitude prior an area fix has the features' position-tilt ambiguity and
        // fails the sigma limit as theirs do (NAIP: 0 of 3 frames, 1.7 s each): not tried.
        if self.params.area_matching == AreaMatching::Off || solve.is_none() {
            return (r, a);
        }
        // No heading matched by features: the area correlation at every heading (its placement
        // covers +-3 hypothesis sigmas of rotation, more than half a step), with the same
        // uniqueness rule.
        let area = Single {
            att_from_filter,
            features: false,
            area: true,
            placement: true,
            corroborate: false,
        };
        let (r2, a2) = select_unique(sweep(area), t_us);
        if !r2.accepted {
            let mut r = r;
            r.rejection = Some(Rejection::Methods(vec![
                (
                    FixMethod::Features,
                    Rejection::or_unexplained(r.rejection.take()),
                ),
                (FixMethod::Area, Rejection::or_unexplained(r2.rejection)),
            ]));
            return (r, a);
        }
        self.refine_sweep_fix(frame, pos, Plan::new(att, solve, area), t_us, (r2, a2))
    }

    /// The sweep's fix `r` again, rectified at its own heading: a hypothesis is up to half a
    /// [`HEADING_STEP_DEG`] from the true heading, which costs upright SURF matches and lets a
    /// few chance matches into a weak consensus. The caller's attitude prior is kept for the
    /// resection (the heading found is the image's, not a prior). The second fix replaces the
    /// first when it is at the same place; at another place the answer is ambiguous; when it
    /// is rejected the first stands (the sweep's uniqueness test passed). NAIP cross-date with
    /// a 25 deg heading error: the one fix 54 m off (tilt 1.3 deg) becomes 48 m max, p90 30.7 ->
    /// 27.8 m, same acceptance (docs/fix.md).
    pub(super) fn refine_sweep_fix(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        plan: Plan,
        t_us: u64,
        (r, a): (FixReport, Attempt),
    ) -> (FixReport, Attempt) {
        let rect = at_own_heading(plan.rect, &r);
        let (r2, a2) = self.fix_single(frame, pos, plan.at(&rect), t_us);
        if !r2.accepted {
            return (r, a);
        }
        if !same_place(&r2, &r) {
            let moved_m = apart_m(&r2, &r);
            let mut rej = FixReport::rejected(Rejection::MovesAtOwnHeading { moved_m }, t_us, 0.0);
            rej.matches = r.matches;
            rej.level = r.level;
            return (rej, a);
        }
        (r2, a2)
    }

    /// The prior-driven fix: one rectification at the prior attitude, or a heading sweep when
    /// the prior's heading sigma is larger than one rectification tolerates. When that finds no
    /// fix and the caller asks for it (`widen`, [`FixPrior::widen_heading`]), the heading is
    /// searched wider ([`Self::widened_heading`]) and then the area search runs over the prior's
    /// window ([`Self::area_search_near`]) before the frame is given up.
    pub(super) fn fix_prior(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
        att_from_filter: bool,
        widen: bool,
    ) -> (FixReport, Attempt) {
        let (r, a) = self.fix_prior_as_stated(frame, pos, att, t_us, att_from_filter);
        if r.accepted && a.uncorroborated {
            return self.confirm_uncorroborated(frame, pos, att, (t_us, att_from_filter), (r, a));
        }
        // Two methods that matched the frame at the stated heading and disagree do not ask for
        // another heading: the frame was found, its fix is what is in doubt.
        let disagree = matches!(r.rejection, Some(Rejection::MethodsDisagree { .. }));
        if r.accepted || !widen || disagree {
            return (r, a);
        }
        let mut why = WidenedWhy {
            stated: Rejection::or_unexplained(r.rejection),
            heading: None,
            near: None,
        };
        let wide = self.widened_heading(att);
        if let Some(wide) = &wide {
            let (r2, a2) =
                self.fix_heading_sweep(frame, pos, wide, Some(wide), t_us, att_from_filter);
            let verdict = if r2.accepted {
                self.confirm_widened(wide, (&r2, &a2))
            } else {
                Err(Rejection::or_unexplained(r2.rejection.clone()))
            };
            match verdict {
                Ok(()) => return (r2, a2),
                Err(e) => why.heading = Some((3.0 * wide.sigma_yaw_rad.to_degrees(), e)),
            }
        }
        let searched = wide.as_ref().unwrap_or(att);
        let near = self.area_search_near(frame, pos, searched, t_us);
        match near {
            // Its candidates are confirmed by features over many places and headings: the
            // widened chance bar applies to them too.
            Ok((r3, a3)) if r3.accepted => {
                match (r3.method == FixMethod::Features)
                    .then(|| self.widened_chance_bar(searched, &a3))
                {
                    None | Some(Ok(())) => return (r3, a3),
                    Some(Err(e)) => why.near = Some(e),
                }
            }
            Ok((r3, _)) => why.near = Some(Rejection::or_unexplained(r3.rejection)),
            Err(AreaRelocError::NotFound(e)) => why.near = Some(e),
            // It could not run (an old map, no level images, the budget): nothing to add.
            Err(AreaRelocError::CannotRun(e)) => {
                tracing::debug!("area search of the prior's window: {e}");
            }
        }
        let mut r = FixReport::rejected(why.into_rejection(), t_us, 0.0);
        r.prior_attitude_from_filter = att_from_filter;
        (r, a)
    }

    /// A feature fix nothing checked (`Attempt::uncorroborated`): too few inliers for the
    /// split-sample factor and no area fix to hold it against. Its inliers can be chance matches
    /// that agree on one wrong pose, and with the heading wrong as stated such a fix passes every
    /// check at that heading (NAIP cross-date, the heading 30 deg off at a claimed 2 deg: 12
    /// inliers of 37-41 matches, none correct, 136 m and 479 m off at 5.6 and 20.7 sigma). So
    /// its heading is put to the widened search (its uniqueness rule over the headings, its
    /// raised chance bar), which also tries the stated heading:
    /// * its fix at the same place confirms the stated fix, which stands: no other heading
    ///   outweighed the stated one (the chance bar raised for the headings is for a fix the
    ///   search adopts, and the stated heading was not searched for);
    /// * its fix at another place outweighed the stated heading's hypothesis: it is the answer
    ///   when it passes what any widened fix must ([`Self::confirm_widened`]), otherwise the
    ///   frame is refused;
    /// * no fix (nothing unique): the frame is refused ([`Rejection::Unconfirmed`]).
    ///
    /// This runs whether or not the caller asked for widening (the daemon widens a failed frame
    /// only after refusals in a row, to bound the cost when every frame fails): here a fix is
    /// in hand and a few frames in a hundred need it (the demo flight at 1500 m: refusing them
    /// instead cost 18 of 599 fixes). With `widen_heading_sigma_deg = 0` the fix is refused.
    fn confirm_uncorroborated(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        (t_us, att_from_filter): (u64, bool),
        (r, a): (FixReport, Attempt),
    ) -> (FixReport, Attempt) {
        let refuse = |search: Option<Rejection>, a: Attempt| {
            let why = Rejection::Unconfirmed {
                inliers: r.inliers,
                matches: a.fine_matches,
                chance: a.null_matches,
                search: search.map(Box::new),
            };
            let mut rej = FixReport::rejected(why, t_us, 0.0);
            rej.matches = r.matches;
            rej.level = r.level;
            rej.prior_attitude_from_filter = att_from_filter;
            (rej, a)
        };
        let Some(wide) = self.widened_heading(att) else {
            return refuse(None, a);
        };
        let (r2, a2) =
            self.fix_heading_sweep(frame, pos, &wide, Some(&wide), t_us, att_from_filter);
        if !r2.accepted {
            return refuse(Some(Rejection::or_unexplained(r2.rejection)), a);
        }
        if same_place(&r2, &r) {
            return (r, a);
        }
        match self.confirm_widened(&wide, (&r2, &a2)) {
            Ok(()) => (r2, a2),
            Err(e) => refuse(Some(e), a),
        }
    }

    /// A fix the widened heading search found by features must beat the features' chance bar
    /// raised for the number of headings asked: the widened search runs the chance test at a
    /// dozen headings after the stated one failed, so chance gets that many tries. The most
    /// matches chance gives at any of H headings, each about Poisson with the mean `null` the
    /// a-contrario count measured, lies near `null + sqrt(2 null ln H)` (the maximum of H such
    /// draws), so that margin is added to the bar a single rectification uses (NAIP at
    /// 1200-1600 m: a fix 52 m off with 34 matches where chance gives 14 and the bar is 33).
    /// Area and placement fixes carry their own uniqueness rule and pass as they are.
    ///
    /// No area correlation is asked on top: over 400 NAIP cross-date frames with the heading
    /// 30 deg off it refused 15 correct fixes (its peak stays under 0.3 where the fields
    /// changed between the years) and not one wrong fix the raised bar let through; frames of
    /// other ground are refused by the bar alone (`tests/fix_naip.rs`).
    pub(super) fn confirm_widened(
        &self,
        wide: &AttitudePriorNed,
        (r, a): (&FixReport, &Attempt),
    ) -> Result<(), Rejection> {
        if r.method != FixMethod::Features {
            return Ok(());
        }
        self.widened_chance_bar(wide, a)
    }

    /// The features' chance bar raised for a search over the widened heading's hypotheses
    /// ([`Self::confirm_widened`]): `Err` names the count when `a`'s matches fall short of it.
    pub(super) fn widened_chance_bar(
        &self,
        wide: &AttitudePriorNed,
        a: &Attempt,
    ) -> Result<(), Rejection> {
        let headings = heading_hypotheses(wide).len().max(1);
        let null = a.null_matches as f64;
        let needed = self.params.min_matches
            + (self.params.null_factor * null).ceil() as usize
            + (2.0 * null * (headings as f64).ln()).sqrt().ceil() as usize;
        if a.fine_matches < needed {
            return Err(Rejection::BelowWidenedChance {
                matches: a.fine_matches,
                chance: a.null_matches,
                headings,
                needed,
            });
        }
        Ok(())
    }

    /// The area search (as relocalisation runs it without a position prior) restricted to the
    /// window the position prior allows: its +-3 sigma gate grown by the footprint's reach, the
    /// candidates' camera positions within the gate. So a position prior never makes a frame fail
    /// that the search without one would fix there; the search is also far cheaper than over the
    /// whole map. The altitude is the prior's.
    pub(super) fn area_search_near(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
    ) -> Result<(FixReport, Attempt), AreaRelocError> {
        if self.params.area_matching == AreaMatching::Off {
            return Err(AreaRelocError::CannotRun(Rejection::AreaOff));
        }
        let g = self
            .prior_geom(pos, att)
            .map_err(AreaRelocError::CannotRun)?;
        let agl_m = g.c_map.z - self.ground_below(&g);
        if !(agl_m.is_finite() && agl_m > 1.0) {
            return Err(AreaRelocError::CannotRun(Rejection::PriorBelowTerrain {
                alt_amsl_m: g.c_map.z,
            }));
        }
        let k = &self.camera.intrinsics;
        let half_diag_rad = (0.5 * f64::from(k.width_px))
            .hypot(0.5 * f64::from(k.height_px))
            .atan2(k.fx_px.min(k.fy_px));
        let off_nadir = (half_diag_rad + 3.0 * att.sigma_rad + tilt_of(&att.attitude))
            .min(self.params.max_off_nadir_deg.to_radians());
        let gate_m = self.params.gate_sigmas * pos.sigma_h_m;
        let reach_m = gate_m + agl_m * off_nadir.tan();
        let window = SearchWindow {
            rect_m: [
                g.c_map.x - reach_m,
                g.c_map.y - reach_m,
                g.c_map.x + reach_m,
                g.c_map.y + reach_m,
            ],
            centre_m: [g.c_map.x, g.c_map.y],
            max_distance_m: gate_m,
        };
        let alt = crate::fix::AltitudePrior {
            alt_amsl_m: pos.alt_amsl_m,
            sigma_m: pos.sigma_v_m,
        };
        let mut work = 0u64;
        let (r, a) = self.relocalise_area(frame, &alt, att, t_us, &mut work, Some(&window))?;
        if !r.accepted {
            return Ok((r, a));
        }
        // The window bounds the candidates; the verified fix must still agree with the prior.
        let d = (r.x_m - g.c_map.x).hypot(r.y_m - g.c_map.y);
        let limit = self.params.gate_sigmas * pos.sigma_h_m.hypot(sigma_h_m(&r));
        if d > limit {
            return Err(AreaRelocError::NotFound(Rejection::FarFromPrior {
                distance_m: d,
                limit_m: limit,
            }));
        }
        Ok((r, a))
    }

    /// [`Self::fix_prior`] at the prior's heading sigma as stated.
    pub(super) fn fix_prior_as_stated(
        &self,
        frame: &GrayImage,
        pos: &PositionPriorGeo,
        att: &AttitudePriorNed,
        t_us: u64,
        att_from_filter: bool,
    ) -> (FixReport, Attempt) {
        if att.sigma_yaw_rad > YAW_SWEEP_ABOVE_DEG.to_radians() {
            self.fix_heading_sweep(frame, pos, att, Some(att), t_us, att_from_filter)
        } else {
            let how = Single {
                att_from_filter,
                features: true,
                area: true,
                placement: true,
                corroborate: true,
            };
            self.fix_single(frame, pos, Plan::new(att, Some(att), how), t_us)
        }
    }

    /// The prior with its heading sigma widened to `[fix] widen_heading_sigma_deg` (tilt kept:
    /// gravity fixes it), or None when that is not wider than the prior's own. The widened
    /// heading also enters the resection: the heading a fix reports then comes from the image,
    /// not from the prior that failed.
    pub(super) fn widened_heading(&self, att: &AttitudePriorNed) -> Option<AttitudePriorNed> {
        let wide = self.params.widen_heading_sigma_deg.to_radians();
        (wide > att.sigma_yaw_rad).then_some(AttitudePriorNed {
            sigma_yaw_rad: wide,
            ..*att
        })
    }
}

/// Above this heading sigma (degrees) one rectification is not enough: upright SURF matches a
/// frame rotated by up to about 10 deg against the map (docs/surf.md) and the coarse similarity
/// searches +-3 sigma, so 3 x 3.5 deg is about the most one rectification covers.
pub(super) const YAW_SWEEP_ABOVE_DEG: f64 = 3.5;

/// Number of heading hypotheses over a full turn.
pub(super) const HEADINGS: u32 = 24;

/// Their spacing, degrees: every heading is within 7.5 deg of one, inside upright SURF's
/// tolerance.
pub(super) const HEADING_STEP_DEG: f64 = 360.0 / HEADINGS as f64;

/// Heading sigma of one hypothesis for its rectification and coarse gate, degrees: the true
/// heading is within half a step of the nearest hypothesis, which 3 sigma covers.
pub(super) const HYPOTHESIS_YAW_SIGMA_DEG: f64 = HEADING_STEP_DEG / 6.0;

/// Heading hypotheses covering `att`'s heading +-3 sigma (all of them when that reaches round):
/// the prior heading first, then alternating outwards, [`HEADING_STEP_DEG`] apart, each with
/// the prior's roll, pitch and tilt sigma and [`HYPOTHESIS_YAW_SIGMA_DEG`].
pub(super) fn heading_hypotheses(att: &AttitudePriorNed) -> Vec<AttitudePriorNed> {
    let step = HEADING_STEP_DEG.to_radians();
    let half_range = 3.0 * att.sigma_yaw_rad + 0.5 * step;
    let n_side = (half_range / step).floor() as i64;
    let full = 2 * n_side + 1 >= i64::from(HEADINGS);
    let mut ks = vec![0i64];
    let last = if full {
        i64::from(HEADINGS) / 2
    } else {
        n_side
    };
    for k in 1..=last {
        ks.push(k);
        if !(full && 2 * k == i64::from(HEADINGS)) {
            ks.push(-k);
        }
    }
    ks.into_iter()
        .map(|k| AttitudePriorNed {
            attitude: Attitude::new(
                att.attitude.roll_rad,
                att.attitude.pitch_rad,
                wrap_pi(att.attitude.yaw_rad + k as f64 * step),
            ),
            sigma_rad: att.sigma_rad,
            sigma_yaw_rad: HYPOTHESIS_YAW_SIGMA_DEG.to_radians(),
        })
        .collect()
}

/// `att` turned to the heading a sweep's fix `r` found (tilt kept), at a hypothesis's heading
/// sigma: the rectification that fix is checked or redone at.
pub(super) fn at_own_heading(att: &AttitudePriorNed, r: &FixReport) -> AttitudePriorNed {
    AttitudePriorNed {
        attitude: Attitude::new(
            att.attitude.roll_rad,
            att.attitude.pitch_rad,
            r.yaw_deg.to_radians(),
        ),
        sigma_rad: att.sigma_rad,
        sigma_yaw_rad: HYPOTHESIS_YAW_SIGMA_DEG.to_radians(),
    }
}

/// The rejections of [`FixEngine::fix_prior`]'s searches, gathered as they fail.
pub(super) struct WidenedWhy {
    stated: Rejection,
    /// The widened heading's +-3 sigma (degrees) and why it found nothing.
    heading: Option<(f64, Rejection)>,
    near: Option<Rejection>,
}

impl WidenedWhy {
    fn into_rejection(self) -> Rejection {
        if self.heading.is_none() && self.near.is_none() {
            return self.stated;
        }
        Rejection::Widened {
            stated: Box::new(self.stated),
            heading: self.heading.map(|(deg, r)| (deg, Box::new(r))),
            near: self.near.map(Box::new),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn prior_with_yaw_sigma(yaw_deg: f64, sigma_yaw_deg: f64) -> AttitudePriorNed {
        AttitudePriorNed {
            attitude: Attitude::from_deg(3.0, -4.0, yaw_deg),
            sigma_rad: 1f64.to_radians(),
            sigma_yaw_rad: sigma_yaw_deg.to_radians(),
        }
    }

    #[test]
    fn heading_hypotheses_cover_three_sigma_and_keep_the_tilt() {
        let step = HEADING_STEP_DEG;
        for (sigma, yaw0) in [
            (4.0, 10.0),
            (10.0, 170.0),
            (30.0, -120.0),
            (60.0, 0.0),
            (180.0, 45.0),
        ] {
            let h = heading_hypotheses(&prior_with_yaw_sigma(yaw0, sigma));
            // The prior heading first; roll, pitch and tilt sigma kept; unique headings.
            assert!((h[0].attitude.yaw_rad.to_degrees() - yaw0).abs() < 1e-9);
            let mut yaws: Vec<f64> = h.iter().map(|a| a.attitude.yaw_rad.to_degrees()).collect();
            for a in &h {
                assert_eq!(a.attitude.roll_rad, 3f64.to_radians());
                assert_eq!(a.attitude.pitch_rad, (-4f64).to_radians());
                assert_eq!(a.sigma_rad, 1f64.to_radians());
                assert!(a.attitude.yaw_rad.abs() <= std::f64::consts::PI + 1e-12);
            }
            yaws.sort_by(f64::total_cmp);
            yaws.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
            assert_eq!(yaws.len(), h.len(), "sigma {sigma}: duplicate headings");
            assert!(h.len() <= HEADINGS as usize);
            // Every heading within 3 sigma of the prior is within half a step of a hypothesis.
            let mut d = -3.0 * sigma.min(60.0);
            while d <= 3.0 * sigma.min(60.0) {
                let t = (yaw0 + d).to_radians();
                let near = h
                    .iter()
                    .map(|a| wrap_pi(a.attitude.yaw_rad - t).abs().to_degrees())
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    near <= 0.5 * step + 1e-9,
                    "sigma {sigma}: {d} deg off is {near} from a hypothesis"
                );
                d += 0.5;
            }
        }
        assert_eq!(
            heading_hypotheses(&prior_with_yaw_sigma(0.0, 180.0)).len(),
            HEADINGS as usize
        );
        assert_eq!(heading_hypotheses(&prior_with_yaw_sigma(0.0, 4.0)).len(), 3);
        assert!((wrap_pi(3.5 * std::f64::consts::PI) + 0.5 * std::f64::consts::PI).abs() < 1e-12);
    }
}
