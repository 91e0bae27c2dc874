//! Corroboration of a weak feature fix by the area method (docs/fix.md, "Corroboration").
//!
//! A resection's covariance is checked for errors its inliers share by the split-sample factor
//! (`pose::split_variance_factor`: the pose re-solved from the image's quadrants). With too few
//! inliers to re-solve from two quadrants that check cannot run, and a shared error (one changed,
//! shadowed or re-planted structure matched a few map pixels off, the rest of the frame without
//! features) moves the fix by several of its sigmas while every residual stays small. The area
//! method (tie points across the whole footprint, or the placement) is an independent
//! measurement of the same frame. When it would run after features anyway
//! (`[fix] area_matching = "fallback"`), it is asked for such a fix too:
//!
//! * it finds nothing: the feature fix stands as it is (no evidence either way);
//! * its horizontal position lies outside the feature fix's own 3-sigma ellipse: the feature fix
//!   claims what the frame does not support, and the frame is refused
//!   ([`Rejection::MethodsDisagree`]). Which of the two is wrong is not known, so neither is
//!   injected;
//! * inside: the feature fix stands with the disagreement added to its horizontal covariance,
//!   `P_h + d d^T` (`d` the area fix's offset, north and east). Two independent measurements of
//!   one position differ by both errors; their difference is the one sample of the feature fix's
//!   error the unchecked covariance can be held against, and adding it covers a fix whose error
//!   is shared by all its inliers (a feature fix 3.5 sigma off with the area fix near the truth
//!   lies about 1 sigma off after it). Vertical and attitude are left alone: the area fix's
//!   height is the weaker of the two at high altitude and a placement has none.
//!
//! The gate is `d^T P_h^-1 d <= chi2_2(0.9973)` with `P_h` the feature fix's horizontal
//! covariance: when the area fix is near the truth, the integrity criterion of the feature fix.

use nalgebra::{Matrix2, Vector2};

use super::{Attempt, FixEngine, Single, View};
use crate::fix::{FixMethod, FixReport, Rejection};
use crate::geo::{Geodetic, LocalFrame};

/// Probability inside a 3-sigma interval of one normal variable: the ellipse the test uses
/// holds the same probability in two dimensions.
const THREE_SIGMA_PROBABILITY: f64 = 0.997_300_203_936_74;

/// The chi-square(2) quantile of [`THREE_SIGMA_PROBABILITY`]: `-2 ln(1 - p)`.
pub(super) fn three_sigma_gate_2d() -> f64 {
    -2.0 * (1.0 - THREE_SIGMA_PROBABILITY).ln()
}

/// A feature fix whose covariance the split-sample factor did not check.
pub(super) fn unchecked(r: &FixReport) -> bool {
    r.accepted && r.method == FixMethod::Features && r.split_groups == 0
}

/// The area fix's horizontal offset from the feature fix (north, east, metres) and its squared
/// Mahalanobis distance in the feature fix's horizontal covariance; `None` when either is not
/// finite.
pub(super) fn offset_d2(feature: &FixReport, area: &FixReport) -> Option<(Vector2<f64>, f64)> {
    let at = |r: &FixReport| Geodetic::new(r.lat_deg, r.lon_deg, r.h_ellip_m).ok();
    let local = LocalFrame::new(at(feature)?).ok()?;
    let ned = local.geodetic_to_ned(&at(area)?).ok()?;
    let d = Vector2::new(ned.x, ned.y);
    let c = feature.cov_ned_m2;
    let p = Matrix2::new(c[0][0], c[0][1], c[1][0], c[1][1]);
    let d2 = (d.transpose() * p.try_inverse()? * d)[0];
    (d2.is_finite() && d2 >= 0.0).then_some((d, d2))
}

/// `d d^T` added to the north-east block of every position covariance the report carries (the
/// fused one, the image-only pose's and the image's share of a fused position).
fn add_horizontal(r: &mut FixReport, d: &Vector2<f64>) {
    let dd = d * d.transpose();
    add_ne(&mut r.cov_ned_m2, &dd);
    if let Some(p) = r.prior_dependence.as_mut() {
        add_ne(&mut p.image_cov_ned_m2, &dd);
    }
    if let Some(v) = r.vision_only.as_mut() {
        add_ne(&mut v.cov6_ned, &dd);
    }
}

/// `dd` added to the leading 2x2 block (north, east) of a covariance whose first rows are the
/// NED position.
fn add_ne<const N: usize>(m: &mut [[f64; N]; N], dd: &Matrix2<f64>) {
    for (i, row) in m.iter_mut().take(2).enumerate() {
        for (j, v) in row.iter_mut().take(2).enumerate() {
            *v += dd[(i, j)];
        }
    }
}

/// What the corroboration decides for `feature` given the area method's report.
pub(super) fn decide(feature: FixReport, area: &FixReport) -> FixReport {
    if !area.accepted {
        return feature;
    }
    let gate = three_sigma_gate_2d();
    match offset_d2(&feature, area) {
        Some((d, d2)) if d2 <= gate => {
            let mut r = feature;
            add_horizontal(&mut r, &d);
            r
        }
        Some((d, d2)) => FixReport::rejected(
            Rejection::MethodsDisagree {
                distance_m: d.norm(),
                d2,
                gate,
            },
            feature.t_capture_us,
            feature.ms,
        ),
        // Not comparable (a non-finite number slipped through): no evidence either way.
        None => feature,
    }
}

impl FixEngine {
    /// Ask the area method about an unchecked feature fix ([`unchecked`]) and [`decide`]. The
    /// attempt keeps the feature pass's figures unless the area fix refused it, and says when
    /// there was no area fix to compare with (`Attempt::uncorroborated`: the caller then asks
    /// the heading, `FixEngine::confirm_uncorroborated`).
    pub(super) fn corroborate(
        &self,
        view: &View,
        a: &mut Attempt,
        feature: FixReport,
        how: Single,
        t_us: u64,
    ) -> FixReport {
        let before = a.clone();
        let area = self.run_method(view, a, FixMethod::Area, how, t_us);
        let r = decide(feature, &area);
        if r.accepted {
            *a = before;
            a.uncorroborated = !area.accepted;
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fix_at(lat_deg: f64, lon_deg: f64, sigma_n_m: f64, sigma_e_m: f64) -> FixReport {
        let mut r = FixReport::rejected(Rejection::NoHypothesis, 1_000_000, 5.0);
        r.accepted = true;
        r.rejection = None;
        r.lat_deg = lat_deg;
        r.lon_deg = lon_deg;
        r.h_ellip_m = 900.0;
        r.cov_ned_m2 = [
            [sigma_n_m * sigma_n_m, 0.0, 0.0],
            [0.0, sigma_e_m * sigma_e_m, 0.0],
            [0.0, 0.0, 400.0],
        ];
        r
    }

    /// Metres north as latitude degrees near 47 deg (WGS84 meridian radius of curvature).
    const M_PER_DEG_LAT: f64 = 111_180.0;

    #[test]
    fn the_gate_is_the_3_sigma_chi2_quantile() {
        assert!((three_sigma_gate_2d() - 11.829).abs() < 1e-3);
    }

    #[test]
    fn only_a_feature_fix_without_a_split_check_is_unchecked() {
        let mut r = fix_at(47.0, -99.0, 6.0, 6.0);
        assert!(unchecked(&r));
        r.split_groups = 2;
        assert!(!unchecked(&r), "a split-checked covariance");
        r.split_groups = 0;
        r.method = FixMethod::Area;
        assert!(!unchecked(&r), "an area fix");
        r.method = FixMethod::Features;
        r.accepted = false;
        assert!(!unchecked(&r), "a rejection");
    }

    /// An area fix 25 m north of a feature fix claiming 6 m (4.2 sigma) refuses the frame; 15 m
    /// (2.5 sigma) corroborates it; 25 m east of a fix claiming 10 m east corroborates it too.
    #[test]
    fn an_area_fix_outside_the_3_sigma_ellipse_refuses_the_frame() {
        let feature = fix_at(47.0, -99.0, 6.0, 10.0);
        let north = |m: f64| fix_at(47.0 + m / M_PER_DEG_LAT, -99.0, 15.0, 15.0);
        let r = decide(feature.clone(), &north(25.0));
        assert!(!r.accepted);
        let Some(Rejection::MethodsDisagree {
            distance_m,
            d2,
            gate,
        }) = r.rejection
        else {
            panic!("{:?}", r.rejection)
        };
        assert!((distance_m - 25.0).abs() < 0.1, "{distance_m}");
        assert!((d2 - (25.0f64 / 6.0).powi(2)).abs() < 0.1, "{d2}");
        assert!((gate - 11.83).abs() < 0.01);
        assert_eq!(r.class(), "methods_disagree");
        let c = decide(feature.clone(), &north(15.0));
        assert!(
            c.accepted && c.lat_deg == feature.lat_deg,
            "the feature fix stands"
        );
        assert!(
            (c.cov_ned_m2[0][0] - (36.0 + 225.0)).abs() < 0.5,
            "{:?}",
            c.cov_ned_m2
        );
        assert!(c.cov_ned_m2[0][1].abs() < 0.1 && c.cov_ned_m2[1][1] == 100.0);
        assert_eq!(c.cov_ned_m2[2][2], 400.0, "vertical untouched");
        let east = fix_at(
            47.0,
            -99.0 + 25.0 / (M_PER_DEG_LAT * 47f64.to_radians().cos()),
            1.0,
            1.0,
        );
        let c = decide(feature.clone(), &east);
        // Longitude degrees are a little longer than this sphere says (the prime vertical radius).
        assert!(
            c.accepted && (c.cov_ned_m2[1][1] - 725.0).abs() < 7.0,
            "{:?}",
            c.cov_ned_m2
        );
    }

    /// Every position covariance the report carries gets the disagreement.
    #[test]
    fn the_disagreement_reaches_the_image_only_and_image_shares() {
        let mut feature = fix_at(47.0, -99.0, 6.0, 6.0);
        feature.vision_only = Some(crate::fix::VisionOnlyPose {
            lat_deg: 47.0,
            lon_deg: -99.0,
            h_ellip_m: 900.0,
            roll_deg: 0.0,
            pitch_deg: 0.0,
            yaw_deg: 0.0,
            cov6_ned: [[1.0; 6]; 6],
        });
        feature.prior_dependence = Some(crate::fix::PriorDependenceNed {
            d_pos_d_att: [[0.0; 3]; 3],
            image_cov_ned_m2: [[2.0; 3]; 3],
        });
        let area = fix_at(47.0 + 10.0 / M_PER_DEG_LAT, -99.0, 15.0, 15.0);
        let c = decide(feature, &area);
        let v = c.vision_only.unwrap().cov6_ned;
        assert!((v[0][0] - 101.0).abs() < 0.5 && v[1][1] < 1.01 && v[2][2] == 1.0);
        assert!(v[3][3] == 1.0 && v[0][3] == 1.0, "attitude rows untouched");
        let p = c.prior_dependence.unwrap().image_cov_ned_m2;
        assert!((p[0][0] - 102.0).abs() < 0.5 && p[2][2] == 2.0);
    }

    #[test]
    fn without_an_area_fix_the_feature_fix_stands() {
        let feature = fix_at(47.0, -99.0, 6.0, 6.0);
        let none = FixReport::rejected(Rejection::NoHypothesis, 1_000_000, 5.0);
        let same = |r: &FixReport| {
            r.accepted && r.lat_deg == feature.lat_deg && r.cov_ned_m2 == feature.cov_ned_m2
        };
        assert!(same(&decide(feature.clone(), &none)));
        let mut odd = fix_at(47.001, -99.0, 6.0, 6.0);
        odd.lat_deg = f64::NAN;
        assert!(same(&decide(feature.clone(), &odd)), "not comparable");
    }
}

/// The corroboration inside the engine: a map whose features all err by the same 25 m while its
/// images do not. The frame sees a smoothed-noise ground from 400 m; the map keeps about 25
/// features spread over the footprint, too few for the split-sample check (fewer than two
/// quadrants of 8 inliers), so the feature fix is unchecked and the area method is asked.
#[cfg(test)]
mod engine_level {
    use std::sync::Arc;

    use crate::camera::{Attitude, Camera, Intrinsics};
    use crate::fix::reference::MemoryReference;
    use crate::fix::{
        AreaMatching, AttitudePriorNed, FixEngine, FixParams, FixPrior, FixReport, PositionPriorGeo,
    };
    use crate::geo::Crs;
    use crate::geo::dem::Dem;
    use crate::geo::raster::{GeoTransform, Raster, RasterData};
    use crate::vision::{GrayImage, SurfParams};
    use nalgebra::{Point2, Vector3};

    const GSD_M: f64 = 2.0;
    const SIDE_PX: usize = 640;
    const ORIGIN_M: [f64; 2] = [500_000.0, 5_200_000.0];
    const GROUND_M: f64 = 300.0;
    const TRUTH_M: [f64; 2] = [500_640.0, 5_199_360.0];
    const ALT_AMSL_M: f64 = 700.0;
    const CRS: Crs = Crs::Utm {
        zone: 14,
        north: true,
    };
    /// The error every kept map feature shares, metres east.
    const SHIFT_EAST_M: f64 = 25.0;

    /// Separable box blur of radius `r`, edges clamped.
    fn blur(v: &[f32], r: usize) -> Vec<f32> {
        let n = SIDE_PX;
        let pass = |src: &[f32], along_x: bool| -> Vec<f32> {
            let mut out = vec![0f32; src.len()];
            for a in 0..n {
                for b in 0..n {
                    let mut s = 0f32;
                    for k in 0..=2 * r {
                        let c = (b + k).saturating_sub(r).min(n - 1);
                        s += if along_x {
                            src[a * n + c]
                        } else {
                            src[c * n + a]
                        };
                    }
                    let i = if along_x { a * n + b } else { b * n + a };
                    out[i] = s / (2 * r + 1) as f32;
                }
            }
            out
        };
        pass(&pass(v, true), false)
    }

    /// Smoothed noise at two scales, 20-235: blobs for SURF and texture for the correlation.
    fn texture() -> Vec<f32> {
        let mut rng = crate::rng::Rng::new(7);
        let noise: Vec<f32> = (0..SIDE_PX * SIDE_PX)
            .map(|_| rng.uniform() as f32)
            .collect();
        let (fine, coarse) = (blur(&blur(&noise, 2), 2), blur(&blur(&noise, 6), 6));
        let v: Vec<f32> = fine.iter().zip(&coarse).map(|(a, b)| a + 2.0 * b).collect();
        let (lo, hi) = v
            .iter()
            .fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
        v.iter()
            .map(|x| 20.0 + 215.0 * (x - lo) / (hi - lo))
            .collect()
    }

    /// Bilinear sample of the texture at a map-grid position (pixel centres at +0.5).
    fn sample(tex: &[f32], x_m: f64, y_m: f64) -> f32 {
        let c = (x_m - ORIGIN_M[0]) / GSD_M - 0.5;
        let r = (ORIGIN_M[1] - y_m) / GSD_M - 0.5;
        let max = (SIDE_PX - 2) as f64;
        let (c, r) = (c.clamp(0.0, max), r.clamp(0.0, max));
        let (c0, r0) = (c.floor() as usize, r.floor() as usize);
        let (fc, fr) = ((c - c0 as f64) as f32, (r - r0 as f64) as f32);
        let at = |cc: usize, rr: usize| tex[rr * SIDE_PX + cc];
        (at(c0, r0) * (1.0 - fc) + at(c0 + 1, r0) * fc) * (1.0 - fr)
            + (at(c0, r0 + 1) * (1.0 - fc) + at(c0 + 1, r0 + 1) * fc) * fr
    }

    fn camera() -> Camera {
        Camera::pinhole(Intrinsics::from_hfov(60f64.to_radians(), 320, 240).unwrap()).unwrap()
    }

    /// The frame at the truth, level, heading north, each ray met with the flat ground; its
    /// grey levels another exposure of the ground (gain, offset) than the map's.
    fn frame(tex: &[f32]) -> GrayImage {
        let cam = camera();
        let r = cam.mount.r_enu_cam(&Attitude::new(0.0, 0.0, 0.0));
        GrayImage::from_fn(320, 240, |u, v| {
            let ray = r * cam
                .unproject(&Point2::new(u as f64, v as f64))
                .unwrap()
                .into_inner();
            let t = (GROUND_M - ALT_AMSL_M) / ray.z;
            let p = Vector3::new(TRUTH_M[0], TRUTH_M[1], ALT_AMSL_M) + ray * t;
            0.8 * sample(tex, p.x, p.y) + 25.0
        })
    }

    /// An engine whose map keeps the first feature of each cell of a 5 x 5 grid over the
    /// frame's footprint, each moved `shift_m` east.
    fn engine(tex: &[f32], shift_m: f64, area: AreaMatching) -> FixEngine {
        engine_with(tex, shift_m, area, false)
    }

    /// [`engine`], its map images blank when `blank` (nothing for the area method to find).
    fn engine_with(tex: &[f32], shift_m: f64, area: AreaMatching, blank: bool) -> FixEngine {
        let data = tex.iter().map(|v| v.round() as u8).collect();
        let gt = GeoTransform::north_up(ORIGIN_M[0], ORIGIN_M[1], GSD_M, GSD_M).unwrap();
        let raster = Raster::new(SIDE_PX, SIDE_PX, 1, RasterData::U8(data), gt, CRS, None).unwrap();
        let surf = SurfParams {
            upright: true,
            ..Default::default()
        };
        let mut map =
            MemoryReference::from_raster(&raster, Dem::flat(GROUND_M).unwrap(), surf, 2).unwrap();
        // The footprint from 400 m is about 460 x 350 m; the grid stays inside it.
        let (half_x, half_y) = (200.0, 150.0);
        let mut taken = std::collections::HashSet::new();
        map.edit_features(
            |level, f| {
                let (dx, dy) = (f.x_m - TRUTH_M[0], f.y_m - TRUTH_M[1]);
                if dx.abs() >= half_x || dy.abs() >= half_y {
                    return false;
                }
                let cell = (
                    level,
                    ((dx + half_x) / (0.4 * half_x)) as usize,
                    ((dy + half_y) / (0.4 * half_y)) as usize,
                );
                taken.insert(cell)
            },
            [shift_m, 0.0],
        );
        if blank {
            map.blank_images();
        }
        let params = FixParams {
            area_matching: area,
            ..FixParams::default()
        };
        FixEngine::new(Arc::new(map), camera(), params).unwrap()
    }

    fn fix(engine: &FixEngine, frame: &GrayImage) -> FixReport {
        fix_widened(engine, frame, false)
    }

    /// [`fix`], the widened heading search allowed when `widen`.
    fn fix_widened(engine: &FixEngine, frame: &GrayImage, widen: bool) -> FixReport {
        let (lat_deg, lon_deg) = CRS.to_geodetic(TRUTH_M[0], TRUTH_M[1]).unwrap();
        engine.fix(
            frame,
            &FixPrior {
                t_capture_us: 1,
                position: Some(PositionPriorGeo {
                    lat_deg,
                    lon_deg,
                    alt_amsl_m: ALT_AMSL_M,
                    sigma_h_m: 30.0,
                    sigma_v_m: 10.0,
                }),
                attitude: Some(AttitudePriorNed::isotropic(
                    Attitude::new(0.0, 0.0, 0.0),
                    0.5f64.to_radians(),
                )),
                altitude: None,
                attitude_from_filter: false,
                widen_heading: widen,
            },
        )
    }

    /// Squared horizontal Mahalanobis distance of the fix from the truth in its own covariance
    /// (the map grid is north-aligned on the zone's central meridian).
    fn d2_from_truth(r: &FixReport) -> f64 {
        let (n, e) = (r.y_m - TRUTH_M[1], r.x_m - TRUTH_M[0]);
        let c = r.cov_ned_m2;
        let det = c[0][0] * c[1][1] - c[0][1] * c[1][0];
        (c[1][1] * n * n - 2.0 * c[0][1] * n * e + c[0][0] * e * e) / det
    }

    fn ne_trace(r: &FixReport) -> f64 {
        r.cov_ned_m2[0][0] + r.cov_ned_m2[1][1]
    }

    #[test]
    fn a_shared_feature_error_is_refused_and_an_agreeing_area_fix_widens_the_covariance() {
        let tex = texture();
        let frame = frame(&tex);
        let gate = super::three_sigma_gate_2d();

        // The map as it is: an unchecked feature fix near the truth...
        let alone = fix(&engine(&tex, 0.0, AreaMatching::Off), &frame);
        assert!(alone.accepted, "{}", alone.reason());
        assert_eq!(alone.split_groups, 0, "{} inliers", alone.inliers);
        assert!(d2_from_truth(&alone) < gate, "d2 {}", d2_from_truth(&alone));
        // ...which the area method agrees with: the same place, the covariance grown by d d^T
        // (d the area fix's offset from it).
        let area = fix(&engine(&tex, 0.0, AreaMatching::Only), &frame);
        assert!(area.accepted, "{}", area.reason());
        let (d, d2) = super::offset_d2(&alone, &area).unwrap();
        assert!(d2 < gate, "d2 {d2}");
        let both = fix(&engine(&tex, 0.0, AreaMatching::Fallback), &frame);
        assert!(both.accepted, "{}", both.reason());
        assert_eq!((both.x_m, both.y_m), (alone.x_m, alone.y_m));
        let grown = ne_trace(&both) - ne_trace(&alone);
        assert!(
            (grown - d.norm_squared()).abs() < 1e-6,
            "{grown} {}",
            d.norm_squared()
        );
        assert_eq!(
            both.cov_ned_m2[2], alone.cov_ned_m2[2],
            "the vertical stays"
        );

        // Every feature 25 m off: features alone accept a fix far beyond its own 3 sigma...
        let wrong = fix(&engine(&tex, SHIFT_EAST_M, AreaMatching::Off), &frame);
        assert!(wrong.accepted, "{}", wrong.reason());
        assert_eq!(wrong.split_groups, 0, "{} inliers", wrong.inliers);
        assert!(
            (wrong.x_m - TRUTH_M[0] - SHIFT_EAST_M).abs() < 5.0,
            "{}",
            wrong.x_m
        );
        assert!(d2_from_truth(&wrong) > gate, "d2 {}", d2_from_truth(&wrong));
        // ...which the area method, from the map's images, refuses.
        let refused = fix(&engine(&tex, SHIFT_EAST_M, AreaMatching::Fallback), &frame);
        assert!(!refused.accepted);
        assert_eq!(refused.class(), "methods_disagree", "{}", refused.reason());
    }

    /// With no area fix to hold it against, the unchecked feature fix is put to the widened
    /// heading search, asked for or not: kept when the search finds it again, refused when the
    /// heading search is off.
    #[test]
    fn an_uncorroborated_feature_fix_is_put_to_the_heading_search() {
        let tex = texture();
        let frame = frame(&tex);
        let engine = engine_with(&tex, 0.0, AreaMatching::Fallback, true);
        let alone = fix(&engine_with(&tex, 0.0, AreaMatching::Off, true), &frame);
        assert!(alone.accepted, "{}", alone.reason());
        assert_eq!(alone.split_groups, 0, "{} inliers", alone.inliers);

        for widen in [false, true] {
            let searched = fix_widened(&engine, &frame, widen);
            assert!(searched.accepted, "{}", searched.reason());
            assert_eq!((searched.x_m, searched.y_m), (alone.x_m, alone.y_m));
            assert_eq!(searched.cov_ned_m2, alone.cov_ned_m2);
        }

        let mut off = engine_with(&tex, 0.0, AreaMatching::Fallback, true);
        off.params.widen_heading_sigma_deg = 0.0;
        let refused = fix(&off, &frame);
        assert!(!refused.accepted);
        assert_eq!(refused.class(), "unconfirmed", "{}", refused.reason());
        assert!(
            refused.reason().contains("heading search is off"),
            "{}",
            refused.reason()
        );
    }
}
