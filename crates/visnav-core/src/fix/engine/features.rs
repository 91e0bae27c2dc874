//! The feature stage of a fix with a position prior (module doc of `fix::engine`): the rectified
//! frame's SURF features on valid ground, each predicted on the map from the prior, gated, voted
//! into a similarity (the prior's shift, rotation and scale error), matched finely with the ratio
//! test, and counted against the matches chance gives with the predictions displaced (the
//! a-contrario check).

use super::*;

impl FixEngine {
    /// Feature correspondences: detect in the rectified frame, predict each keypoint's map
    /// position from the prior, gate, vote a similarity, match finely, and check the count
    /// against chance (module doc).
    pub(super) fn feature_pairs(&self, v: &View, a: &mut Attempt) -> Result<Vec<Pair>, Rejection> {
        let (rect, level) = (v.rect, v.level);
        let gsd = self.levels_gsd_m[level];
        // Query features on valid ground, strongest first, capped.
        let feats = self
            .features
            .detect_and_describe(self.detector.as_ref(), &rect.image);
        let keep = self.query_on_ground(v, &feats);
        a.query_features = keep.len();
        if keep.len() < self.params.min_matches {
            return Err(Rejection::FewFeatures { n: keep.len() });
        }
        // Selection: predicted footprint grown by the coarse gate.
        let gate_m = self.gate_m(v);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (_, p) in &keep {
            lo = [lo[0].min(p[0]), lo[1].min(p[1])];
            hi = [hi[0].max(p[0]), hi[1].max(p[1])];
        }
        let bounds = self.reference.bounds_m();
        if footprint_outside_map(lo, hi, gate_m, bounds) {
            return Err(Rejection::FootprintOutsideMap {
                footprint_m: [lo[0], hi[0], lo[1], hi[1]],
                map_m: [bounds[0], bounds[2], bounds[1], bounds[3]],
            });
        }
        let sel = self.reference.select(
            level,
            [
                lo[0] - gate_m,
                lo[1] - gate_m,
                hi[0] + gate_m,
                hi[1] + gate_m,
            ],
        );
        a.map_features = sel.features.len();
        if sel.features.len() < self.params.min_matches {
            return Err(Rejection::FewMapFeatures {
                n: sel.features.len(),
            });
        }
        // Level-pixel coordinates: origin at the selection's top-left, y down.
        let (ox, oy) = (lo[0] - gate_m, hi[1] + gate_m);
        let to_lp = |x: f64, y: f64| [((x - ox) / gsd) as f32, ((oy - y) / gsd) as f32];
        let train = train_features(&sel, gsd, to_lp)?;
        let query = subset(&feats, keep.iter().map(|(i, _)| *i))?;
        let pred: Vec<[f32; 2]> = keep.iter().map(|(_, p)| to_lp(p[0], p[1])).collect();

        // Coarse: gated nearest neighbours (no ratio test: the gate holds many look-alikes) and a
        // RANSAC 2-D similarity between predicted and map positions. The prior's position error
        // is a shift, its yaw error a rotation and its height error a scale of this map.
        let gate_px = (gate_m / gsd) as f32;
        let fine_r = self.params.fine_radius_px as f32;
        let sim = if gate_px > fine_r {
            self.coarse_similarity(v, [&query, &train], &pred, gate_px, a)?
        } else {
            Sim2::identity()
        };
        let pred_fine: Vec<[f32; 2]> = pred.iter().map(|p| sim.apply(*p)).collect();
        let wide = self.params.fine_wide_factor as f32 * fine_r;
        let matches = gated_match(&query, &train, &pred_fine, fine_r, wide, self.params.ratio);
        a.fine_matches = matches.len();
        for m in &matches {
            let (q, f) = (&query.keypoints[m.query], &sel.features[m.train]);
            if let Some(px) = rect.to_frame_px(f64::from(q.x), f64::from(q.y)) {
                a.pairs.push(([px.x, px.y], [f.x_m, f.y_m, f.z_amsl_m]));
            }
        }
        // A-contrario check (Moisan & Stival 2004 in spirit): the same gated matching with the
        // predictions displaced to unrelated map areas counts the matches chance alone produces
        // here (texture density, gate size, ratio test). A genuine view must beat that clearly.
        let null = self.chance_matches([&query, &train], &pred_fine, wide);
        a.null_matches = null;
        let needed =
            self.params.min_matches + (self.params.null_factor * null as f64).ceil() as usize;
        if matches.len() < needed {
            return Err(Rejection::BelowChance {
                matches: matches.len(),
                chance: null,
                needed,
            });
        }
        // SURF localises a keypoint to a fraction of its scale s (rectified pixels).
        let sigma_px = self.base_sigma_px(v);
        Ok(matches
            .iter()
            .filter_map(|m| {
                let (q, f) = (&query.keypoints[m.query], &sel.features[m.train]);
                let px = rect.to_frame_px(f64::from(q.x), f64::from(q.y))?;
                let s_rect = f64::from(q.scale.max(f.scale_m / gsd as f32));
                Some(Pair {
                    frame_px: px,
                    map: [f.x_m, f.y_m, f.z_amsl_m],
                    sigma_px: sigma_px * (s_rect / 2.0).max(1.0),
                })
            })
            .collect())
    }

    /// The frame's features (indices into `feats`, strongest first, at most `max_query_features`)
    /// on valid rectified ground, with the map position the prior puts each at.
    pub(super) fn query_on_ground(&self, v: &View, feats: &Features) -> Vec<(usize, [f64; 2])> {
        let mut keep: Vec<(usize, [f64; 2])> = Vec::new();
        for (i, k) in feats.keypoints.iter().enumerate() {
            if keep.len() >= self.params.max_query_features {
                break;
            }
            if !v
                .rect
                .window_valid(f64::from(k.x), f64::from(k.y), 10.0 * f64::from(k.scale))
            {
                continue;
            }
            let Some(p) = self.ground_of(v, f64::from(k.x), f64::from(k.y)) else {
                continue;
            };
            keep.push((i, p));
        }
        keep
    }

    /// The coarse stage: gated nearest neighbours (no ratio test: the gate holds many
    /// look-alikes) and a RANSAC 2-D similarity from the predicted to the map positions (level
    /// pixels). `qt` = [query, train].
    pub(super) fn coarse_similarity(
        &self,
        v: &View,
        qt: [&Features; 2],
        pred: &[[f32; 2]],
        gate_px: f32,
        a: &mut Attempt,
    ) -> Result<Sim2, Rejection> {
        let [query, train] = qt;
        let coarse = MatchParams {
            ratio: 1.0,
            laplacian_gate: true,
            mutual: false,
            spatial_radius_px: Some(gate_px),
        };
        let m = self
            .features
            .match_features(query, train, &coarse, Some(pred))
            .map_err(internal("matching"))?;
        a.coarse_matches = m.len();
        let src: Vec<[f32; 2]> = m.iter().map(|mm| pred[mm.query]).collect();
        let dst: Vec<[f32; 2]> = m
            .iter()
            .map(|mm| [train.keypoints[mm.train].x, train.keypoints[mm.train].y])
            .collect();
        let (max_rot, max_log_scale) = self.similarity_bounds(v);
        let fine_r = self.params.fine_radius_px as f32;
        let (sim, n) = ransac_similarity(&src, &dst, fine_r, max_rot, max_log_scale, 0x5EED)
            .ok_or(Rejection::NoCoarseConsensus { matches: m.len() })?;
        a.vote_peak = n;
        Ok(sim)
    }

    /// The a-contrario count: the most matches the fine gated matching finds with the
    /// predictions displaced by three wide gates to unrelated map areas (what chance alone gives
    /// here). `qt` = [query, train].
    pub(super) fn chance_matches(
        &self,
        qt: [&Features; 2],
        pred_fine: &[[f32; 2]],
        wide: f32,
    ) -> usize {
        let [query, train] = qt;
        let fine_r = self.params.fine_radius_px as f32;
        let d = 3.0 * wide;
        [[d, 0.0], [-d, 0.0], [0.0, d], [0.0, -d]]
            .par_iter()
            .map(|o| {
                let shifted: Vec<[f32; 2]> = pred_fine
                    .iter()
                    .map(|p| [p[0] + o[0], p[1] + o[1]])
                    .collect();
                gated_match(query, train, &shifted, fine_r, wide, self.params.ratio).len()
            })
            .max()
            .unwrap_or(0)
    }

    /// The coarse gate: the prior's position and tilt uncertainty on the ground, metres.
    pub(super) fn gate_m(&self, v: &View) -> f64 {
        let g = v.g;
        (self.params.gate_sigmas
            * (g.sigma_h_m.powi(2) + (v.agl_m * g.sigma_tilt_rad.min(0.5)).powi(2)).sqrt())
        .max(self.params.min_gate_m)
    }

    /// Largest rotation (rad) and log scale between the predicted and the true map positions the
    /// prior allows.
    pub(super) fn similarity_bounds(&self, v: &View) -> (f64, f64) {
        let g = v.g;
        let max_rot =
            (self.params.gate_sigmas * g.sigma_yaw_rad.max(g.sigma_tilt_rad)).min(0.5) + 0.02;
        let max_log_scale = (self.params.gate_sigmas * g.sigma_v_m / v.agl_m).min(0.7) + 0.05;
        (max_rot, max_log_scale)
    }
}

/// Train features in level-pixel coordinates.
pub(super) fn train_features(
    sel: &RefSelection,
    gsd_m: f64,
    to_lp: impl Fn(f64, f64) -> [f32; 2],
) -> Result<Features, Rejection> {
    let kps = sel
        .features
        .iter()
        .map(|f| {
            let p = to_lp(f.x_m, f.y_m);
            KeyPoint {
                x: p[0],
                y: p[1],
                size: f.scale_m / gsd_m as f32 * 9.0 / 1.2,
                scale: f.scale_m / gsd_m as f32,
                response: 0.0,
                orientation_rad: 0.0,
                laplacian: f.laplacian,
                octave: 0,
            }
        })
        .collect();
    Features::new(kps, sel.descriptors.clone(), sel.kind).map_err(internal("map features"))
}

/// The features at `idx` (in that order).
pub(super) fn subset(
    f: &Features,
    idx: impl Iterator<Item = usize>,
) -> Result<Features, Rejection> {
    let st = f.kind().stride();
    let mut kps = Vec::new();
    let mut desc = Vec::new();
    for i in idx {
        kps.push(f.keypoints[i]);
        desc.extend_from_slice(&f.descriptors_padded()[i * st..(i + 1) * st]);
    }
    Features::new(kps, desc, f.kind()).map_err(internal("query features"))
}

/// Whether a footprint `[lo, hi]` (map metres), grown by the search gate, misses the map's
/// `bounds` `[min_x, min_y, max_x, max_y]` entirely: nothing there can match.
pub(super) fn footprint_outside_map(
    lo: [f64; 2],
    hi: [f64; 2],
    gate_m: f64,
    bounds: [f64; 4],
) -> bool {
    hi[0] + gate_m < bounds[0]
        || lo[0] - gate_m > bounds[2]
        || hi[1] + gate_m < bounds[1]
        || lo[1] - gate_m > bounds[3]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_footprint_beyond_the_map_is_outside_it() {
        let b = [1000.0, 2000.0, 3000.0, 4000.0];
        // Inside, overlapping an edge, and within the gate of it: not outside.
        assert!(!footprint_outside_map(
            [1500.0, 2500.0],
            [1800.0, 2800.0],
            50.0,
            b
        ));
        assert!(!footprint_outside_map(
            [2900.0, 3900.0],
            [3200.0, 4200.0],
            50.0,
            b
        ));
        assert!(!footprint_outside_map(
            [3020.0, 2500.0],
            [3300.0, 2800.0],
            50.0,
            b
        ));
        // Beyond each side.
        assert!(footprint_outside_map(
            [3100.0, 2500.0],
            [3300.0, 2800.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [500.0, 2500.0],
            [900.0, 2800.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [1500.0, 4100.0],
            [1800.0, 4300.0],
            50.0,
            b
        ));
        assert!(footprint_outside_map(
            [1500.0, 1000.0],
            [1800.0, 1900.0],
            50.0,
            b
        ));
    }
}
