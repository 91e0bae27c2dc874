//! Relocalisation: a fix without a position prior (docs/fix.md, "Relocalisation"). With the
//! altitude and the tilt known, the area search shortlists places and headings over the whole map
//! image and each candidate is verified by the prior pipeline and confirmed from its own pose;
//! otherwise (or when it cannot run) every level is tried coarse to fine by features voted in a
//! Hough space, over the heading hypotheses. The budget counts work, so the same frame gives the
//! same answer on any machine.

use super::*;

impl FixEngine {
    /// Global relocalisation: no position prior. The altitude is unknown, so every level is tried
    /// (coarse to fine), each with the frame rectified to that level's scale at an assumed height
    /// chosen to make the virtual image about the frame's size; SURF's scale invariance absorbs the
    /// remaining scale error. Matches are voted in (log scale, translation) space like Lowe's
    /// Hough transform, the winning cluster's 3-D points seed a resection whose pose then serves
    /// as the prior of the normal pipeline. With a loose heading (or none) the headings are
    /// searched ([`heading_hypotheses`], tilt kept from the prior, or nadir without one); the
    /// first level with an accepted fix decides, by [`select_unique`] over all its hypotheses.
    /// The budget counts work (pixels through SURF, descriptor comparisons), so the same
    /// frame gives the same answer on any machine; when it runs out before a level's hypotheses
    /// are all tried, the fix is rejected (a winner without its competitors is not unique).
    pub(super) fn relocalise(&self, frame: &GrayImage, prior: &FixPrior) -> (FixReport, Attempt) {
        let t_us = prior.t_capture_us;
        let budget = (self.params.reloc_budget_mwork * 1e6) as u64;
        if let (Some(alt), Some(att)) = (prior.altitude, prior.attitude)
            && self.params.area_matching != AreaMatching::Off
        {
            let mut work = 0u64;
            match self.relocalise_area(frame, &alt, &att, t_us, &mut work, None) {
                Ok(found) => return found,
                // The search ran and confirmed nothing: the frame does not match well enough
                // (the feature search would spend seconds to find little more).
                Err(AreaRelocError::NotFound(e)) => {
                    return (
                        FixReport::rejected(e.in_relocalisation(), t_us, 0.0),
                        Attempt::default(),
                    );
                }
                // It could not run (an old map, a budget too small, no ground in view): the
                // feature search below.
                Err(AreaRelocError::CannotRun(e)) => {
                    tracing::debug!("area relocalisation: {e}; the feature search instead");
                }
            }
        }
        let (hyps, solve) = match prior.attitude {
            Some(a) if a.sigma_yaw_rad <= YAW_SWEEP_ABOVE_DEG.to_radians() => (vec![a], Some(a)),
            Some(a) => (heading_hypotheses(&a), Some(a)),
            None => (heading_hypotheses(&self.nadir_any_heading()), None),
        };
        let mut work = 0u64;
        let mut last_reason = Rejection::NoLevelFix;
        // Each hypothesis' rectified view and features serve every level (rectified at the
        // frame's own scale); computed on first use.
        let mut views: Vec<Option<Result<RelocView, Rejection>>> =
            hyps.iter().map(|_| None).collect();
        for level in (0..self.levels_gsd_m.len()).rev() {
            let level_map = match self.reloc_level_map(level) {
                Ok(l) => l,
                Err(e) => {
                    last_reason = e;
                    continue;
                }
            };
            // The hypotheses are independent: each is tried on its own thread with its own
            // work count, then replayed in order against the budget. The replay stops where the
            // sequential search would have stopped, so the report is the same as trying them one
            // after another (what was computed past that point is discarded).
            let outcomes: Vec<HypothesisOutcome> = hyps
                .par_iter()
                .zip(views.par_iter_mut())
                .map(|(hyp, view)| {
                    let mut view_work = 0u64;
                    let view =
                        view.get_or_insert_with(|| self.reloc_view(frame, hyp, &mut view_work));
                    let mut level_work = 0u64;
                    let tried = match view {
                        Ok(v) => Some(self.reloc_level(
                            frame,
                            v,
                            &level_map,
                            solve.as_ref(),
                            t_us,
                            &mut level_work,
                        )),
                        Err(_) => None,
                    };
                    HypothesisOutcome {
                        view_work,
                        level_work,
                        tried,
                    }
                })
                .collect();
            let mut tries = Vec::new();
            for (outcome, view) in outcomes.into_iter().zip(&views) {
                if work >= budget {
                    let reason = Rejection::WorkBudget {
                        budget_mwork: self.params.reloc_budget_mwork,
                        level,
                        last: Box::new(last_reason),
                    };
                    let r = FixReport::rejected(reason.in_relocalisation(), t_us, 0.0);
                    return (r, Attempt::default());
                }
                work = work.saturating_add(outcome.view_work);
                let Some(tried) = outcome.tried else {
                    if let Some(Err(e)) = view {
                        last_reason = e.clone();
                    }
                    continue;
                };
                work = work.saturating_add(outcome.level_work);
                match tried {
                    Ok(h) => {
                        if let Some(r) = &h.report.rejection {
                            last_reason = r.clone().at_level(level);
                        }
                        tries.push(h);
                    }
                    Err(e) => last_reason = e,
                }
            }
            if tries.iter().any(|h| h.report.accepted) {
                let (mut r, a) = select_unique(tries, t_us);
                r.rejection = r
                    .rejection
                    .take()
                    .map(|why| why.at_level(level).in_relocalisation());
                return (r, a);
            }
        }
        let r = FixReport::rejected(last_reason.in_relocalisation(), t_us, 0.0);
        (r, Attempt::default())
    }

    /// Relocalisation by area when the altitude and the tilt are known (docs/fix.md,
    /// "Relocalisation"): [`Self::area_search`] shortlists places and headings over the whole
    /// map image; each candidate, best first, is verified by the prior pipeline (a position
    /// prior of one coarse pixel at the candidate, rectified at its heading) and confirmed from
    /// its own pose ([`Self::confirm_from_own_pose`]). After the first confirmed candidate only
    /// its rivals (a correlation within [`RELOC_AREA_RIVAL_MARGIN`] of its own) are verified,
    /// and one of them confirmed at another place makes the answer ambiguous. Err: no candidate
    /// confirmed.
    pub(super) fn relocalise_area(
        &self,
        frame: &GrayImage,
        alt: &crate::fix::AltitudePrior,
        att: &AttitudePriorNed,
        t_us: u64,
        work: &mut u64,
        window: Option<&SearchWindow>,
    ) -> Result<(FixReport, Attempt), AreaRelocError> {
        let search = self
            .area_search(frame, alt, att, window, work)
            .map_err(AreaRelocError::CannotRun)?;
        let how = Single {
            att_from_filter: false,
            features: true,
            area: true,
            placement: false,
            corroborate: false,
        };
        // The best candidate may be confirmed by its placement alone when it leads every other
        // place searched by the placement fix's margin (there no tie point confirms it), also
        // the places a window's distance rule left out.
        let lead = match search.candidates.first() {
            Some(first) => first.ncc - search.runner_up_ncc,
            None => f64::INFINITY,
        };
        let mut confirmed: Option<(f64, Hypothesis)> = None;
        let mut best_refused: Option<(f64, Box<Rejection>)> = None;
        for (i, c) in search.candidates.iter().enumerate() {
            if let Some((ncc, _)) = &confirmed
                && c.ncc < ncc - RELOC_AREA_RIVAL_MARGIN
            {
                break;
            }
            let how = Single {
                placement: i == 0 && lead >= area_stage::PLACEMENT_FIX_MARGIN,
                ..how
            };
            *work = work.saturating_add((frame.width() * frame.height()) as u64);
            let plan = Plan::new(&c.rect_att, Some(att), how);
            let (r, a) = self.fix_single(frame, &c.position, plan, t_us);
            let h = if r.accepted {
                self.confirm_from_own_pose(frame, (r, a), plan, t_us, search.gsd_m, work)
            } else {
                Hypothesis::new(c.rect_att.attitude.yaw_rad, r, a)
            };
            if !h.report.accepted {
                if best_refused.is_none() {
                    best_refused = Some((
                        c.ncc,
                        Box::new(Rejection::or_unexplained(h.report.rejection)),
                    ));
                }
                continue;
            }
            match &confirmed {
                None => confirmed = Some((c.ncc, h)),
                Some((first_ncc, first)) => {
                    let d =
                        (h.report.x_m - first.report.x_m).hypot(h.report.y_m - first.report.y_m);
                    let same = SAME_PLACE_SIGMAS
                        * sigma_h_m(&first.report)
                            .hypot(sigma_h_m(&h.report))
                            .max(search.coarse_px_m);
                    if d > same {
                        let reason = Rejection::TwoPlaces {
                            distance_m: d,
                            ncc: [*first_ncc, c.ncc],
                        }
                        .in_relocalisation();
                        return Ok((FixReport::rejected(reason, t_us, 0.0), Attempt::default()));
                    }
                }
            }
        }
        match confirmed {
            Some((_, h)) => Ok((h.report, h.attempt)),
            None => Err(AreaRelocError::NotFound(Rejection::NoCandidateConfirmed {
                candidates: search.candidates.len(),
                best: best_refused,
            })),
        }
    }

    /// The area search over the whole map image: the frame rectified at the prior's tilt (its
    /// heading as given, however wrong) and at the scale the altitude gives over the map's
    /// middle height, in two channels ([`crate::fix::area::grey_and_gradient`]) block-averaged to
    /// at most [`RELOC_AREA_TEMPLATE_PX`] per side, correlated with the map image at every
    /// heading and over the scales the altitude's +-3 sigma and the map's height range allow,
    /// steps moving the template's corner by [`RELOC_AREA_EDGE_STEP_PX`]; the
    /// [`RELOC_AREA_CANDIDATES`] best distinct places with the camera position and heading each
    /// implies.
    pub(super) fn area_search(
        &self,
        frame: &GrayImage,
        alt: &crate::fix::AltitudePrior,
        att: &AttitudePriorNed,
        window: Option<&SearchWindow>,
        work: &mut u64,
    ) -> Result<AreaSearch, Rejection> {
        use crate::fix::area::{candidates, grey_and_gradient};
        let (level, agl_m, held, budget) = self.area_level(alt, window, work)?;
        let img = held.image();
        let gsd = self.levels_gsd_m[level];
        let (lo, hi) = self.reference.dem().height_range_m();
        let (rect, tc, f) = self.area_template(frame, att, agl_m / gsd, work)?;
        let crop = window.map_or([0, 0, img.width, img.height], |w| w.pixels(&img));
        let map = img
            .crop(crop[0] as i64, crop[1] as i64, crop[2], crop[3])
            .and_then(|m| grey_and_gradient(&m, f))
            .ok_or(Rejection::MapImageTooSmall)?;
        // The frame may see beyond the map's edge: the map inside a border of no data as wide
        // as the largest overhang the overlap rule allows.
        let (tw, th) = (tc[0].width, tc[0].height);
        let over = 1.0 - RELOC_AREA_MIN_OVERLAP;
        let (mx, my) = (
            (tw as f64 * over).ceil() as usize,
            (th as f64 * over).ceil() as usize,
        );
        let map = [map[0].padded(mx, my), map[1].padded(mx, my)];
        // The headings of the prior's +-3 sigma (every heading when that reaches round); the
        // scales the altitude and the terrain allow.
        let radius = 0.5 * (tw as f64).hypot(th as f64);
        let step = RELOC_AREA_EDGE_STEP_PX / radius.max(1.0);
        let half_log = ((3.0 * alt.sigma_m + 0.5 * (hi - lo)) / agl_m).min(0.7);
        let hyps = similarity_hypotheses(att.sigma_yaw_rad, half_log, step);
        // The budget counts work: the search's transforms, estimated before it runs.
        let points = (map[0].width * map[0].height) as u64;
        let estimate =
            (hyps.len() as u64 * 2 * 5 + 2 * 3).saturating_mul(points) / AREA_FFT_POINTS_PER_UNIT;
        if work.saturating_add(estimate) > budget {
            return Err(Rejection::AreaSearchBudget {
                needed_mwork: estimate as f64 / 1e6,
                budget_mwork: self.params.reloc_budget_mwork,
            });
        }
        let mut fft_points = 0u64;
        let shortlist = candidates(
            &[(&map[0], &tc[0]), (&map[1], &tc[1])],
            &hyps,
            RELOC_AREA_MIN_OVERLAP,
            crate::fix::area::UNIQUE_RADIUS_COARSE_PX,
            RELOC_AREA_CANDIDATES,
            &mut fft_points,
        );
        *work = work.saturating_add(fft_points / AREA_FFT_POINTS_PER_UNIT);
        // A candidate's camera: the virtual principal point (straight below the camera)
        // carried from the template's centre by the candidate's similarity.
        let fine = |c: f64| c * f as f64 + (f as f64 - 1.0) / 2.0;
        let (tcx, tcy) = (fine((tw as f64 - 1.0) / 2.0), fine((th as f64 - 1.0) / 2.0));
        let (dx, dy) = (rect.cx_px - tcx, rect.cy_px - tcy);
        let crs = self.reference.crs();
        let mut out: Vec<AreaCandidate> = Vec::new();
        let mut runner_up_ncc = f64::NEG_INFINITY;
        for c in &shortlist {
            let (s, co) = c.theta_rad.sin_cos();
            let px = [
                crop[0] as f64 + fine(c.centre[0] - mx as f64) + c.scale * (co * dx - s * dy),
                crop[1] as f64 + fine(c.centre[1] - my as f64) + c.scale * (s * dx + co * dy),
            ];
            let xy = img.to_map(px);
            // The shortlist is best first: every place after the first kept one is a rival, and
            // so is every place the window's distance rule leaves out.
            let admitted = window.is_none_or(|w| w.admits(xy));
            if !admitted || !out.is_empty() {
                runner_up_ncc = runner_up_ncc.max(c.ncc);
            }
            if !admitted {
                continue;
            }
            let Ok((lat, lon)) = crs.to_geodetic(xy[0], xy[1]) else {
                continue;
            };
            out.push(AreaCandidate {
                ncc: c.ncc,
                position: PositionPriorGeo {
                    lat_deg: lat,
                    lon_deg: lon,
                    alt_amsl_m: alt.alt_amsl_m,
                    sigma_h_m: f as f64 * gsd,
                    sigma_v_m: alt.sigma_m,
                },
                rect_att: AttitudePriorNed {
                    attitude: Attitude::new(
                        att.attitude.roll_rad,
                        att.attitude.pitch_rad,
                        wrap_pi(att.attitude.yaw_rad + c.theta_rad),
                    ),
                    sigma_rad: att.sigma_rad,
                    sigma_yaw_rad: (0.5 * step).max(MIN_HYPOTHESIS_YAW_SIGMA_RAD),
                },
            });
        }
        Ok(AreaSearch {
            candidates: out,
            runner_up_ncc,
            gsd_m: gsd,
            coarse_px_m: f as f64 * gsd,
        })
    }

    /// The area search's template: the frame rectified at `att` with `agl_px` (height above
    /// ground in map-level pixels) as its scale, in the two channels block-averaged by the factor
    /// `f` that brings its longer side to at most [`RELOC_AREA_TEMPLATE_PX`]; the rectification's
    /// pixels are counted as work.
    pub(super) fn area_template(
        &self,
        frame: &GrayImage,
        att: &AttitudePriorNed,
        agl_px: f64,
        work: &mut u64,
    ) -> Result<(Rectification, [crate::fix::area::Plane; 2], usize), Rejection> {
        let r_map_cam = r_enu_ned() * self.camera.mount.r_ned_cam(&att.attitude);
        let rect = Rectification::new(
            frame,
            &self.camera,
            &r_map_cam,
            agl_px / self.camera.intrinsics.fx_px,
            self.params.max_rect_side_px,
            self.params.max_off_nadir_deg.to_radians(),
        )
        .ok_or(Rejection::NoGround)?;
        *work = work.saturating_add((rect.width() * rect.height()) as u64);
        let plane = rect.plane().ok_or(Rejection::NoGround)?;
        let f = rect
            .width()
            .max(rect.height())
            .div_ceil(RELOC_AREA_TEMPLATE_PX)
            .max(1);
        let tc = crate::fix::area::grey_and_gradient(&plane, f).ok_or(Rejection::ImagesTooSmall)?;
        Ok((rect, tc, f))
    }

    /// The area search's map level (the one whose ground sample matches the frame's at the
    /// altitude prior over the terrain's middle height), that height above ground, the level's
    /// image and the work budget; the image's pixels are counted as work (a map too large for the
    /// budget is left to the feature search before any is read).
    pub(super) fn area_level(
        &self,
        alt: &crate::fix::AltitudePrior,
        window: Option<&SearchWindow>,
        work: &mut u64,
    ) -> Result<(usize, f64, crate::fix::reference::LevelWindow<'_>, u64), Rejection> {
        if !(alt.alt_amsl_m.is_finite() && alt.sigma_m.is_finite() && alt.sigma_m > 0.0) {
            return Err(Rejection::AltitudePrior);
        }
        let (lo, hi) = self.reference.dem().height_range_m();
        let agl_m = alt.alt_amsl_m - 0.5 * (lo + hi);
        if agl_m.is_nan() || agl_m <= 1.0 {
            return Err(Rejection::AltitudeBelowMap {
                alt_amsl_m: alt.alt_amsl_m,
            });
        }
        let level = self.pick_level(agl_m / self.camera.intrinsics.fx_px);
        let held = self
            .reference
            .level_window(
                level,
                window.map_or(self.reference.bounds_m(), |w| w.rect_m),
            )
            .ok_or(Rejection::NoLevelImages)?;
        let img = held.image();
        // Each pixel of the level image read (and held in the working planes) counts one unit:
        // a map too large for the budget is left to the feature search before any is read.
        let budget = (self.params.reloc_budget_mwork * 1e6) as u64;
        let [_, _, w, h] = window.map_or([0, 0, img.width, img.height], |w| w.pixels(&img));
        let map_px = (w * h) as u64;
        if work.saturating_add(map_px) > budget {
            return Err(Rejection::MapLevelBudget {
                mpixels: map_px as f64 / 1e6,
                budget_mwork: self.params.reloc_budget_mwork,
            });
        }
        *work = work.saturating_add(map_px);
        Ok((level, agl_m, held, budget))
    }

    /// The confirmation of a search's accepted fix `r`: the frame matched again from that fix's
    /// own pose (a tight position, rectified at the fix's attitude), the resection fusing the
    /// caller's `solve` prior again (not the first fix's attitude: the reported fix must not be
    /// checked against itself). A true view is confirmed (its matches come back with
    /// predictions accurate to a few pixels); a chance alignment found among many hypotheses
    /// is not (its matches came from the loose coarse gate), which the a-contrario count of one
    /// attempt cannot see after a search of dozens. The refined pass is kept only with more
    /// inliers.
    pub(super) fn confirm_from_own_pose(
        &self,
        frame: &GrayImage,
        (r, a): (FixReport, Attempt),
        plan: Plan,
        t_us: u64,
        gsd: f64,
        work: &mut u64,
    ) -> Hypothesis {
        let att = plan.rect;
        let refined_pos = PositionPriorGeo {
            lat_deg: r.lat_deg,
            lon_deg: r.lon_deg,
            alt_amsl_m: r.alt_amsl_m,
            sigma_h_m: 3.0 * r.cov_ned_m2[0][0].max(r.cov_ned_m2[1][1]).sqrt().max(gsd),
            sigma_v_m: 3.0 * r.cov_ned_m2[2][2].sqrt().max(gsd),
        };
        let refined_rect = AttitudePriorNed::isotropic(
            Attitude::from_deg(r.roll_deg, r.pitch_deg, r.yaw_deg),
            1f64.to_radians(),
        );
        *work = work.saturating_add((frame.width() * frame.height()) as u64);
        let (r2, a2) = self.fix_single(frame, &refined_pos, plan.at(&refined_rect), t_us);
        if !r2.accepted {
            let mut rejected = FixReport::rejected(
                Rejection::NotConfirmed(Box::new(Rejection::or_unexplained(r2.rejection))),
                t_us,
                0.0,
            );
            rejected.matches = r.matches;
            rejected.level = r.level;
            return Hypothesis::new(att.attitude.yaw_rad, rejected, a);
        }
        if r2.inliers >= r.inliers {
            Hypothesis::new(att.attitude.yaw_rad, r2, a2)
        } else {
            Hypothesis::new(att.attitude.yaw_rad, r, a)
        }
    }

    /// Near nadir at an unknown heading: what relocalisation assumes without an attitude prior.
    pub(super) fn nadir_any_heading(&self) -> AttitudePriorNed {
        AttitudePriorNed {
            attitude: Attitude::new(0.0, 0.0, 0.0),
            sigma_rad: self.params.reloc_tilt_sigma_deg.to_radians(),
            sigma_yaw_rad: std::f64::consts::PI,
        }
    }

    /// The frame rectified at `att` at its own scale (level-independent) with its query features;
    /// adds the pixels to `work`.
    pub(super) fn reloc_view(
        &self,
        frame: &GrayImage,
        att: &AttitudePriorNed,
        work: &mut u64,
    ) -> Result<RelocView, Rejection> {
        let r_ned_cam = self.camera.mount.r_ned_cam(&att.attitude);
        let r_map_cam = r_enu_ned() * r_ned_cam; // grid convergence unknown yet: < 3 deg in a zone
        let Some(rect) = Rectification::new(
            frame,
            &self.camera,
            &r_map_cam,
            1.0,
            self.params.max_rect_side_px,
            self.params.max_off_nadir_deg.to_radians(),
        ) else {
            return Err(Rejection::NoGround);
        };
        *work = work.saturating_add((rect.width() * rect.height()) as u64);
        let feats = self
            .features
            .detect_and_describe(self.detector.as_ref(), &rect.image);
        let idx: Vec<usize> = feats
            .keypoints
            .iter()
            .enumerate()
            .filter(|(_, k)| {
                rect.window_valid(f64::from(k.x), f64::from(k.y), 10.0 * f64::from(k.scale))
            })
            .map(|(i, _)| i)
            .take(self.params.max_query_features)
            .collect();
        if idx.len() < self.params.min_matches {
            return Err(Rejection::FewFeatures { n: idx.len() });
        }
        let query = subset(&feats, idx.iter().copied())?;
        Ok(RelocView {
            rect,
            query,
            att: *att,
        })
    }

    /// All of `level`'s features in level pixels (origin at the map's top-left corner).
    pub(super) fn reloc_level_map(&self, level: usize) -> Result<RelocLevel, Rejection> {
        let gsd = self.levels_gsd_m[level];
        let sel = self.reference.select(level, self.reference.bounds_m());
        if sel.features.len() < self.params.min_matches {
            return Err(Rejection::FewLevelFeatures {
                level,
                n: sel.features.len(),
            });
        }
        let b = self.reference.bounds_m();
        let (ox, oy) = (b[0], b[3]);
        let to_lp = |x: f64, y: f64| [((x - ox) / gsd) as f32, ((oy - y) / gsd) as f32];
        let train = train_features(&sel, gsd, to_lp)?;
        Ok(RelocLevel {
            level,
            gsd,
            origin: (ox, oy),
            train,
        })
    }

    /// One relocalisation try at `level`, the frame rectified at `att` (one heading hypothesis),
    /// the resection fusing the caller's `solve` prior: the Hough cluster's position through the
    /// prior pipeline, refined once from its own fix. Err when no cluster was found; a rejected
    /// hypothesis is Ok (its evidence counts as a competitor in [`select_unique`]). Adds its work
    /// (pixels rectified and searched by SURF, descriptor comparisons / 16; each prior-pipeline
    /// pass counted as one frame's pixels) to `work`.
    pub(super) fn reloc_level(
        &self,
        frame: &GrayImage,
        view: &RelocView,
        level_map: &RelocLevel,
        solve: Option<&AttitudePriorNed>,
        t_us: u64,
        work: &mut u64,
    ) -> Result<Hypothesis, Rejection> {
        let RelocView { rect, query, att } = view;
        let RelocLevel {
            level,
            gsd,
            origin: (ox, oy),
            train,
        } = level_map;
        let (level, gsd, ox, oy) = (*level, *gsd, *ox, *oy);
        *work = work.saturating_add(
            (query.len() as u64).saturating_mul(train.len() as u64) / RELOC_COMPARISONS_PER_UNIT,
        );
        let m = self
            .features
            .match_features(
                query,
                train,
                &MatchParams {
                    ratio: self.params.ratio,
                    laplacian_gate: true,
                    mutual: false,
                    spatial_radius_px: None,
                },
                None,
            )
            .map_err(internal("matching"))?;
        let at_level = |r: Rejection| r.at_level(level);
        if m.len() < self.params.min_matches {
            return Err(at_level(Rejection::FewMatches {
                n: m.len(),
                min: self.params.min_matches,
            }));
        }
        let size_px = rect.width().max(rect.height()) as f32;
        let centre_px = [rect.cx_px as f32, rect.cy_px as f32];
        let Some(cluster) = hough_cluster(&m, query, train, size_px, centre_px) else {
            return Err(at_level(Rejection::NoHoughCluster));
        };
        if cluster.len() < MIN_HOUGH_CLUSTER {
            return Err(at_level(Rejection::SmallHoughCluster {
                n: cluster.len(),
                min: MIN_HOUGH_CLUSTER,
            }));
        }
        // Scale and translation of the cluster: camera height and nadir point.
        let mut ss: Vec<f32> = cluster
            .iter()
            .map(|&j| train.keypoints[m[j].train].scale / query.keypoints[m[j].query].scale)
            .collect();
        ss.sort_by(f32::total_cmp);
        let s = f64::from(ss[ss.len() / 2]);
        let mut txs: Vec<f64> = Vec::new();
        let mut tys: Vec<f64> = Vec::new();
        for &j in &cluster {
            let q = &query.keypoints[m[j].query];
            let t = &train.keypoints[m[j].train];
            txs.push(f64::from(t.x) - s * (f64::from(q.x) - rect.cx_px));
            tys.push(f64::from(t.y) - s * (f64::from(q.y) - rect.cy_px));
        }
        txs.sort_by(f64::total_cmp);
        tys.sort_by(f64::total_cmp);
        let (nx, ny) = (txs[txs.len() / 2], tys[tys.len() / 2]);
        let x = ox + nx * gsd;
        let y = oy - ny * gsd;
        // One virtual pixel covers s level pixels: height above ground = f_v * s * gsd.
        let agl = rect.f_px * s * gsd;
        let ground = self.reference.height_amsl_m(x, y).unwrap_or_else(|| {
            let (lo, hi) = self.reference.dem().height_range_m();
            0.5 * (lo + hi)
        });
        let crs = self.reference.crs();
        let (lat, lon) = crs.to_geodetic(x, y).map_err(geodesy("map geodesy"))?;
        let pos = PositionPriorGeo {
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: ground + agl,
            // The cluster locates the nadir point to a few bins and the height to a scale bin.
            sigma_h_m: (0.2 * agl).max(3.0 * gsd),
            sigma_v_m: (0.3 * agl).max(3.0 * gsd),
        };
        let frame_px = (frame.width() * frame.height()) as u64;
        *work = work.saturating_add(frame_px);
        let plan = Plan::new(att, solve, Single::FEATURES);
        let (r, a) = self.fix_single(frame, &pos, plan, t_us);
        if !r.accepted {
            return Ok(Hypothesis::new(att.attitude.yaw_rad, r, a));
        }
        Ok(self.confirm_from_own_pose(frame, (r, a), plan, t_us, gsd, work))
    }
}

/// Descriptor comparisons per relocalisation work unit: 16 comparisons of 64-float descriptors
/// took about as long as one pixel through rectification and SURF detection (release build,
/// one core; docs/fix.md), so the budget bounds both kinds of work alike.
pub const RELOC_COMPARISONS_PER_UNIT: u64 = 16;

/// Largest side of the coarse template of the area search over the whole map (coarse pixels).
/// The search's cost grows with its cube (pixels times headings); at 48 (about 1 700 valid
/// template pixels) fields and roads still span several coarse pixels and a search of a map of
/// a few km takes about 0.3 s on one core (docs/fix.md).
pub(super) const RELOC_AREA_TEMPLATE_PX: usize = 48;

/// Heading and log-scale step of the area search: the template's corner moves by this many
/// coarse pixels per step (half of it at worst between steps, inside the correlation peak of
/// block-averaged images).
pub(super) const RELOC_AREA_EDGE_STEP_PX: f64 = 1.5;

/// Share of the template's valid pixels that must lie on the map: a frame at 2 km above
/// ground sees 2-3 km, and near the map's edge much of it lies outside; below this the overlap
/// is too small for a correlation to mean anything.
pub(super) const RELOC_AREA_MIN_OVERLAP: f64 = 0.45;

/// Distinct places of the area search shortlisted for verification (the true place is first
/// for most frames, and among the first four for nearly all).
pub(super) const RELOC_AREA_CANDIDATES: usize = 4;

/// After a candidate is confirmed, the others whose correlation is within this of its own are
/// its rivals and verified too (lower ones are not alternatives to it).
pub(super) const RELOC_AREA_RIVAL_MARGIN: f64 = 0.1;

/// FFT points per relocalisation work unit: a 2-D transform of 16 points took about as long as
/// one pixel through rectification and SURF detection (release build, one core), so the budget
/// bounds the area search and the feature search alike.
pub const AREA_FFT_POINTS_PER_UNIT: u64 = 16;

/// Smallest heading sigma of a verified candidate's rectification.
pub(super) const MIN_HYPOTHESIS_YAW_SIGMA_RAD: f64 = 0.5 * std::f64::consts::PI / 180.0;

/// Why the area relocalisation gave no answer.
pub(super) enum AreaRelocError {
    /// It could not run (no level images, budget, geometry).
    CannotRun(Rejection),
    /// It ran and confirmed no candidate.
    NotFound(Rejection),
}

/// Where the area search looks when a position prior bounds it ([`FixEngine::area_search_near`]):
/// the map rectangle searched (metres) and the largest distance of a candidate's camera from the
/// prior's centre.
pub(super) struct SearchWindow {
    pub(super) rect_m: [f64; 4],
    pub(super) centre_m: [f64; 2],
    pub(super) max_distance_m: f64,
}

impl SearchWindow {
    /// The rectangle in `img`'s pixels, clipped to the image: `[x0, y0, width, height]` (at
    /// least one pixel a side).
    fn pixels(&self, img: &crate::fix::reference::MapImage<'_>) -> [usize; 4] {
        let a = img.to_px(self.rect_m[0], self.rect_m[3]);
        let b = img.to_px(self.rect_m[2], self.rect_m[1]);
        let clip = |v: f64, n: usize| (v.max(0.0) as usize).min(n.saturating_sub(1));
        let (x0, y0) = (
            clip(a[0].floor(), img.width),
            clip(a[1].floor(), img.height),
        );
        let (x1, y1) = (clip(b[0].ceil(), img.width), clip(b[1].ceil(), img.height));
        [x0, y0, x1 - x0 + 1, y1 - y0 + 1]
    }

    /// A candidate camera at map `xy` is within the distance allowed.
    fn admits(&self, xy: [f64; 2]) -> bool {
        (xy[0] - self.centre_m[0]).hypot(xy[1] - self.centre_m[1]) <= self.max_distance_m
    }
}

/// The area search's shortlist ([`FixEngine::area_search`]).
pub(super) struct AreaSearch {
    candidates: Vec<AreaCandidate>,
    /// The best correlation of any other place searched (a candidate or one the window's
    /// distance rule left out; -inf when there is none).
    runner_up_ncc: f64,
    /// Ground sample distance of the level searched and of its coarse grid, metres.
    gsd_m: f64,
    coarse_px_m: f64,
}

/// A place and heading of the area search, as the prior pipeline takes it.
pub(super) struct AreaCandidate {
    /// The channels' mean correlation.
    ncc: f64,
    position: PositionPriorGeo,
    /// The attitude to rectify at: the prior's tilt and the candidate's heading.
    rect_att: AttitudePriorNed,
}

/// Fewest matches in the winning Hough bin of a relocalisation try (a similarity needs 2; 6
/// keeps chance clusters out, as the resection's own minimum then decides).
pub(super) const MIN_HOUGH_CLUSTER: usize = 6;

/// One relocalisation hypothesis tried at one level, with the work it took (the view's only the
/// first time the view was made).
pub(super) struct HypothesisOutcome {
    view_work: u64,
    level_work: u64,
    /// None when the hypothesis' view could not be made.
    tried: Option<Result<Hypothesis, Rejection>>,
}

/// A relocalisation hypothesis' rectified view (frame scale) and its query features.
pub(super) struct RelocView {
    rect: Rectification,
    query: Features,
    /// The hypothesis it was rectified at.
    att: AttitudePriorNed,
}

/// One map level prepared for relocalisation: every feature, in level pixels from `origin`
/// (the map's top-left corner, grid metres).
pub(super) struct RelocLevel {
    level: usize,
    gsd: f64,
    origin: (f64, f64),
    train: Features,
}

/// The (scale, rotation) hypotheses of the area search, `step` apart (radians; a step moves the
/// template's corner by the edge step): the headings of +-3 `sigma_yaw_rad` (every heading when
/// that reaches round) at every log-scale step within +-`half_log`.
pub(super) fn similarity_hypotheses(
    sigma_yaw_rad: f64,
    half_log: f64,
    step: f64,
) -> Vec<(f64, f64)> {
    let n_full = (std::f64::consts::TAU / step).ceil() as usize;
    let half_rot = 3.0 * sigma_yaw_rad + 0.5 * step;
    let rotations: Vec<f64> = if 2.0 * half_rot >= std::f64::consts::TAU {
        (0..n_full)
            .map(|r| r as f64 * std::f64::consts::TAU / n_full as f64)
            .collect()
    } else {
        let n = (half_rot / step).ceil() as i64;
        (-n..=n).map(|r| r as f64 * step).collect()
    };
    let n_scale = (half_log / step - 0.5).ceil().max(0.0) as i64;
    let mut hyps = Vec::new();
    for k in -n_scale..=n_scale {
        for &r in &rotations {
            hyps.push(((k as f64 * step).exp(), r));
        }
    }
    hyps
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_area_hypotheses_cover_the_heading_and_scale_bands() {
        let step = 0.05;
        // A tight heading: rotations within +-(3 sigma + a step), scales within the log band.
        let h = similarity_hypotheses(0.02, 0.12, step);
        let max_rot = h.iter().map(|(_, r)| r.abs()).fold(0.0, f64::max);
        assert!((0.06..=0.06 + 1.5 * step).contains(&max_rot), "{max_rot}");
        assert!(h.iter().any(|&(s, r)| s == 1.0 && r == 0.0));
        let max_log = h.iter().map(|(s, _)| s.ln().abs()).fold(0.0, f64::max);
        assert!((0.12 - step..=0.12 + step).contains(&max_log), "{max_log}");
        // An unknown heading: every heading, evenly.
        let h = similarity_hypotheses(2.0, 0.0, step);
        let n = (std::f64::consts::TAU / step).ceil() as usize;
        assert_eq!(h.len(), n);
        assert!(h.iter().all(|&(s, _)| s == 1.0));
        assert!((h[1].1 - h[0].1 - std::f64::consts::TAU / n as f64).abs() < 1e-12);
    }
}
