//! The solve stage: the resection of a fix's correspondences in a local east-north-up frame about
//! the footprint (exact geodesy), the attitude prior fused, each point weighted by the map's
//! height error at its viewing angle; the report in geodetic, map-grid and NED terms with the
//! map's registration and height errors added to the covariance, and the image-only pose beside
//! it.

use super::*;

impl FixEngine {
    /// The resection's attitude prior from an NED attitude prior.
    pub(super) fn solve_prior(&self, att: &AttitudePriorNed) -> Result<SolvePrior, Rejection> {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(att.sigma_rad) && ok(att.sigma_yaw_rad)) {
            return Err(Rejection::PriorSigmas);
        }
        Ok(SolvePrior {
            r_enu_cam: r_enu_ned() * self.camera.mount.r_ned_cam(&att.attitude),
            sigma_tilt_rad: att.sigma_rad,
            sigma_yaw_rad: att.sigma_yaw_rad,
        })
    }

    /// The resection of `pairs` in a local ENU frame about the footprint, with the prior fused.
    pub(super) fn solve_pairs(
        &self,
        v: &View,
        pairs: &[Pair],
        method: FixMethod,
        t_us: u64,
    ) -> FixReport {
        let g = v.g;
        let rej = |reason: Rejection| FixReport::rejected(reason, t_us, 0.0);
        if pairs.len() < self.params.min_matches {
            return rej(Rejection::FewMatches {
                n: pairs.len(),
                min: self.params.min_matches,
            });
        }
        let crs = self.reference.crs();
        let mid = pairs[pairs.len() / 2].map;
        let origin = match crs
            .to_geodetic(mid[0], mid[1])
            .and_then(|(lat, lon)| Geodetic::new(lat, lon, mid[2] + geoid_undulation_m(lat, lon)?))
        {
            Ok(o) => o,
            Err(e) => return rej(geodesy("map geodesy")(e)),
        };
        let local = match LocalFrame::new(origin) {
            Ok(l) => l,
            Err(e) => return rej(geodesy("map geodesy")(e)),
        };
        let c_enu = match map_to_enu(&crs, &local, g.c_map.x, g.c_map.y, g.c_map.z) {
            Ok(c) => c,
            Err(e) => return rej(geodesy("prior geodesy")(e)),
        };
        let heights = self.reference.height_errors();
        // Pixel thresholds are in frame pixels; a frame finer than the map level sees its
        // localisation errors magnified by 1/scale.
        let mag = (1.0 / v.scale).max(1.0);
        // An inlier's residual stays within the consensus threshold, so the part of its height
        // error the image shows cannot exceed it (the points whose heights are further off, the
        // roofs and trees a constant height leaves out, fail the consensus): at most a uniform
        // spread over +-threshold.
        let height_cap_px = self.params.pose.ransac.threshold_px * mag / 3f64.sqrt();
        let corrs: Vec<Correspondence> = pairs
            .iter()
            .filter_map(|p| {
                let r = self.camera.unproject(&p.frame_px)?.into_inner();
                if r.z <= 0.0 {
                    return None;
                }
                let p_enu = map_to_enu(&crs, &local, p.map[0], p.map[1], p.map[2]).ok()?;
                let sigma_height_px = height_error_px(
                    &p_enu,
                    &c_enu,
                    heights.point_sigma_m,
                    self.camera.intrinsics.fx_px,
                )
                .min(height_cap_px);
                Some(Correspondence {
                    point_world: p_enu,
                    obs_norm: Vector2::new(r.x / r.z, r.y / r.z),
                    sigma_px: p.sigma_px.hypot(sigma_height_px),
                })
            })
            .collect();
        let image = ImageGeometry::from(&self.camera.intrinsics);
        let priors = Priors {
            // World = local ENU: tilt about east/north, heading about up. A loose heading (after
            // a GPS loss, or unknown) keeps the tilt: gravity still fixes it.
            attitude: g
                .solve
                .filter(|s| s.sigma_tilt_rad < MAX_PRIOR_TILT_SIGMA_RAD)
                .map(|s| AttitudePrior {
                    r_world_cam: s.r_enu_cam,
                    cov_rad2: nalgebra::Matrix3::from_diagonal(&Vector3::new(
                        s.sigma_tilt_rad.powi(2),
                        s.sigma_tilt_rad.powi(2),
                        s.sigma_yaw_rad.min(MAX_PRIOR_YAW_SIGMA_RAD).powi(2),
                    )),
                }),
            position: Some(PositionPrior {
                c_world: c_enu,
                cov_m2: nalgebra::Matrix3::from_diagonal(&Vector3::new(
                    g.sigma_h_m.powi(2),
                    g.sigma_h_m.powi(2),
                    g.sigma_v_m.powi(2),
                )),
            }),
            map_tilt_sigma_rad: heights.slope_sigma.atan(),
        };
        let mut cfg = self.params.pose.clone();
        // The filter's own attitude is not an independent prior: weigh it as before this
        // weighting became the information-weighted one (docs/fix.md, "The attitude prior").
        if g.att_from_filter {
            cfg.refine = cfg.refine.for_unscaled_prior();
        }
        cfg.ransac.threshold_px *= mag;
        cfg.integrity.max_reprojection_rms_px *= mag;
        let outcome = resect(&corrs, &image, &priors, &cfg);
        let verdict = match &outcome.verdict {
            Verdict::Accepted => None,
            Verdict::Rejected(r) => Some(Rejection::Pose(r.clone())),
        };
        let Some(fix) = outcome.fix.as_ref() else {
            let mut r = rej(Rejection::or_unexplained(verdict));
            r.matches = pairs.len();
            r.method = method;
            return r;
        };
        let mut report = match self.report_from(&crs, &local, fix, t_us, verdict) {
            Ok(r) => r,
            Err(e) => return rej(e),
        };
        report.matches = pairs.len();
        report.inliers = fix.quality.inliers;
        report.method = method;
        report
    }

    pub(super) fn report_from(
        &self,
        crs: &Crs,
        local: &LocalFrame,
        fix: &crate::pose::Fix,
        t_us: u64,
        rejection: Option<Rejection>,
    ) -> Result<FixReport, Rejection> {
        let geo = local
            .enu_to_geodetic(&fix.pose.c_world)
            .map_err(geodesy("fix geodesy"))?;
        let n = geoid_undulation_m(geo.lat_deg, geo.lon_deg).map_err(geodesy("geoid"))?;
        let (x, y) = crs
            .from_geodetic(geo.lat_deg, geo.lon_deg)
            .map_err(geodesy("fix to map grid"))?;
        // Local ENU axes differ from the NED axes at the fix by the angle between the two
        // verticals (distance / Earth radius, < 0.01 deg over a footprint): ignored.
        let r_ned_enu = r_enu_ned().inverse();
        let r_ned_cam = r_ned_enu * fix.pose.r_world_cam;
        let att = self.camera.mount.attitude_from_r_ned_cam(&r_ned_cam);
        let mut cov = fix.covariance.position_ned_m2(&r_ned_enu);
        let reg_var = self.map_registration_var_m2();
        let height_var = self.map_height_var_m2();
        cov[(0, 0)] += reg_var;
        cov[(1, 1)] += reg_var;
        cov[(2, 2)] += height_var;
        let cov_att = fix.covariance.attitude_ned_rad2(&r_ned_enu);
        let to_arr = |m: &nalgebra::Matrix3<f64>| {
            [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ]
        };
        let r = FixReport {
            accepted: rejection.is_none(),
            rejection,
            t_capture_us: t_us,
            lat_deg: geo.lat_deg,
            lon_deg: geo.lon_deg,
            alt_amsl_m: geo.h_ellip_m - n,
            h_ellip_m: geo.h_ellip_m,
            x_m: x,
            y_m: y,
            z_m: geo.h_ellip_m - n,
            roll_deg: att.roll_rad.to_degrees(),
            pitch_deg: att.pitch_rad.to_degrees(),
            yaw_deg: att.yaw_rad.to_degrees(),
            cov_ned_m2: to_arr(&cov),
            cov_att_ned_rad2: to_arr(&cov_att),
            inliers: fix.quality.inliers,
            matches: 0,
            reproj_rms_px: fix.quality.reprojection_rms_px,
            sigma0: fix.quality.sigma0,
            cov_factor: fix.covariance.factor(),
            split_groups: fix.vision_covariance.split_groups,
            vision_only: self.vision_only_pose(local, fix, &r_ned_enu),
            // Position world = ENU, attitude errors as world rotation vectors: D_ned =
            // R_ned_enu G R_enu_ned (R_world_cam = R_enu_ned R_ned_body R_body_cam, so a body
            // error Exp(psi_ned) is the world error Exp(R_enu_ned psi_ned)).
            prior_dependence: fix
                .prior_dependence
                .map(|d| {
                    let r = r_ned_enu.matrix();
                    // The registration shift is part of the image's share (cov = image_cov +
                    // D P D^T holds with it).
                    let mut image_cov = r * d.image_position_cov_m2 * r.transpose();
                    image_cov[(0, 0)] += reg_var;
                    image_cov[(1, 1)] += reg_var;
                    image_cov[(2, 2)] += height_var;
                    crate::fix::PriorDependenceNed {
                        d_pos_d_att: to_arr(&(r * d.d_position_d_prior_att * r.transpose())),
                        image_cov_ned_m2: to_arr(&image_cov),
                    }
                })
                .filter(crate::fix::PriorDependenceNed::is_finite),
            prior_attitude_from_filter: false,
            level: 0,
            method: FixMethod::Features,
            ms: 0.0,
        };
        let finite = [
            r.lat_deg,
            r.lon_deg,
            r.alt_amsl_m,
            r.x_m,
            r.y_m,
            r.roll_deg,
            r.pitch_deg,
            r.yaw_deg,
        ]
        .iter()
        .chain(r.cov_ned_m2.iter().flatten())
        .all(|v| v.is_finite());
        if !finite {
            return Err(Rejection::NonFinite { what: "the fix" });
        }
        Ok(r)
    }

    /// Variance of the map's horizontal registration per axis, m^2
    /// (`FixParams::map_registration_sigma_px` in orthophoto pixels, whatever the map's upsampling).
    pub(super) fn map_registration_var_m2(&self) -> f64 {
        (self.params.map_registration_sigma_px * self.reference.ortho_pixel_m()).powi(2)
    }

    /// Vertical variance a height error shared by the whole footprint adds, m^2: every map point
    /// raised by `dh` raises the solved camera by exactly `dh` and moves nothing else, so the
    /// map's height sigma ([`Reference::height_sigma_m`]) goes into the vertical in full (the
    /// per-point weighting of [`height_error_px`] covers the part that varies across the
    /// footprint, which the points' scatter would otherwise average away).
    pub(super) fn map_height_var_m2(&self) -> f64 {
        self.reference.height_errors().offset_sigma_m.powi(2)
    }

    /// The image-only pose of `fix` in geodetic / NED terms, its 6x6 covariance reordered to
    /// `[position NED, attitude NED]` (the pose module orders `[phi, C]` in the local ENU frame
    /// and uses the same error signs as the filter: `crates/visnav-core/tests/integration/pose_resection.rs` checks them). None
    /// when a number is not finite.
    pub(super) fn vision_only_pose(
        &self,
        local: &LocalFrame,
        fix: &crate::pose::Fix,
        r_ned_enu: &nalgebra::Rotation3<f64>,
    ) -> Option<crate::fix::VisionOnlyPose> {
        let geo = local.enu_to_geodetic(&fix.vision_pose.c_world).ok()?;
        let att = self
            .camera
            .mount
            .attitude_from_r_ned_cam(&(r_ned_enu * fix.vision_pose.r_world_cam));
        let c = fix.vision_covariance.conservative();
        let r = r_ned_enu.matrix();
        // Rotate both 3-blocks into NED and swap them: [phi, C] -> [C, phi].
        let mut t = nalgebra::Matrix6::<f64>::zeros();
        t.fixed_view_mut::<3, 3>(0, 3).copy_from(r);
        t.fixed_view_mut::<3, 3>(3, 0).copy_from(r);
        let cov = t * c * t.transpose();
        let mut cov = (cov + cov.transpose()) * 0.5;
        let reg_var = self.map_registration_var_m2();
        cov[(0, 0)] += reg_var;
        cov[(1, 1)] += reg_var;
        cov[(2, 2)] += self.map_height_var_m2();
        let v = crate::fix::VisionOnlyPose {
            lat_deg: geo.lat_deg,
            lon_deg: geo.lon_deg,
            h_ellip_m: geo.h_ellip_m,
            roll_deg: att.roll_rad.to_degrees(),
            pitch_deg: att.pitch_rad.to_degrees(),
            yaw_deg: att.yaw_rad.to_degrees(),
            cov6_ned: std::array::from_fn(|i| std::array::from_fn(|j| cov[(i, j)])),
        };
        v.is_finite().then_some(v)
    }
}

/// The resection fuses an attitude prior only when its tilt sigma is below this (rad, ~29 deg):
/// beyond, the prior carries nothing a linearised prior can use.
pub(super) const MAX_PRIOR_TILT_SIGMA_RAD: f64 = 0.5;

/// A heading sigma beyond this (rad) is treated as this: no heading information, and the prior's
/// information matrix stays finite.
pub(super) const MAX_PRIOR_YAW_SIGMA_RAD: f64 = std::f64::consts::PI;

/// Angle wrapped to (-pi, pi].
/// Image displacement (pixels, focal length `fx_px`) of a map point at `p` seen from `c` (same
/// local frame, z up) when its height is off by `height_sigma_m`: the component of a vertical
/// shift across the line of sight is `dh sin(alpha)` (alpha the ray's angle from the vertical),
/// seen at range `|p - c|`. 0 for a point straight below the camera, largest at the edge of a
/// tilted view: the same roof height misleads a point at the edge more than one at nadir.
pub(super) fn height_error_px(
    p: &Vector3<f64>,
    c: &Vector3<f64>,
    height_sigma_m: f64,
    fx_px: f64,
) -> f64 {
    if height_sigma_m <= 0.0 {
        return 0.0;
    }
    let d = p - c;
    let range_m = d.norm();
    if !(range_m.is_finite() && range_m > 1e-6) {
        return 0.0;
    }
    let sin_alpha = d.xy().norm() / range_m;
    fx_px * height_sigma_m * sin_alpha / range_m
}

/// Map grid point (height AMSL) to the local ENU frame.
pub(super) fn map_to_enu(
    crs: &Crs,
    local: &LocalFrame,
    x_m: f64,
    y_m: f64,
    z_amsl_m: f64,
) -> Result<Vector3<f64>, crate::geo::GeoError> {
    let (lat, lon) = crs.to_geodetic(x_m, y_m)?;
    let h = z_amsl_m + geoid_undulation_m(lat, lon)?;
    local.geodetic_to_enu(&Geodetic::new(lat, lon, h)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_height_error_moves_a_point_in_the_image_by_its_viewing_angle() {
        let c = Vector3::new(0.0, 0.0, 100.0);
        let fx = 500.0;
        // Straight below: a height error moves the point along the ray, not across it.
        assert_eq!(height_error_px(&Vector3::zeros(), &c, 10.0, fx), 0.0);
        // 45 deg off the vertical at range 100 sqrt(2): 500 * 10 * sin 45 / 141.4 = 25 px.
        let p = Vector3::new(100.0, 0.0, 0.0);
        let px = height_error_px(&p, &c, 10.0, fx);
        assert!((px - 25.0).abs() < 1e-9, "{px}");
        // Proportional to the sigma; none without one; a degenerate geometry gives 0, not NaN.
        assert!((height_error_px(&p, &c, 5.0, fx) - 12.5).abs() < 1e-9);
        assert_eq!(height_error_px(&p, &c, 0.0, fx), 0.0);
        assert_eq!(height_error_px(&c, &c, 10.0, fx), 0.0);
    }
}
