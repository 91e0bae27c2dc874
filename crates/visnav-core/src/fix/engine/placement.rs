//! The placement fix (docs/fix.md, "The placement fix"): when the area correlation placed the
//! rectified frame uniquely but too few tie points confirmed it (ground changed between the
//! map's date and the frame's, little texture), the refined placement itself gives the camera's
//! horizontal position and heading, with the attitude prior's tilt and the prior's height.
//!
//! The math: a grid of frame pixels is cast from the prior's pose onto the terrain (predicted
//! ground `P_i`); the placement says where that ground truly is (`T_i`). The least-squares
//! similarity from `P_i` to `T_i` (Umeyama) gives the turn about the vertical. Each pixel's ray,
//! turned so, drops `u_i` metres horizontally per metre of height and meets the terrain (height
//! `h_i`) at `T_i = c + (z - h_i) u_i`; with `z` the prior's height, the camera's horizontal
//! position is `c = mean(T_i + (h_i - z) u_i)` (relief under the footprint included). A tilt
//! error `psi` of the prior moves the solved position by `D psi`; `D` is computed by casting
//! the same pixels with the prior turned by small rotations (central to the covariance: at
//! 2 km above ground, 0.5 deg of tilt is 17 m). The report carries `D` and the image's own
//! covariance ([`crate::fix::PriorDependenceNed`]) like a resection's fused pose, and no
//! image-only pose: the frame does not measure the tilt here.

use nalgebra::{Matrix3, Point2, Rotation3, Vector3};

use super::area_stage::PlacementObs;
use super::{FixEngine, MAX_RAY_RANGE_AGL, PriorGeom, View};
use crate::camera::frames::{r_enu_ned, rot_z};
use crate::fix::Rejection;
use crate::fix::{FixMethod, FixReport, PriorDependenceNed};
use crate::geo::geoid::geoid_undulation_m;
use crate::pose::similarity::Sim2;

/// Rotation of the prior for the numerical derivative of the position with respect to its
/// attitude, rad (0.1 deg: the position moves by metres, far above the solve's rounding, while
/// the geometry stays linear).
const DIFF_RAD: f64 = 1.0e-3 * std::f64::consts::PI / 1.8;

/// The placement fix does not measure the height: the correlation's scale is its weakest
/// parameter (over Autzen's trees and roofs at 80 m above ground it chose 18 % off, the height
/// 18 m off). The report carries the prior's height with this many times its sigma, so that
/// fusing it tells a filter nothing about the height.
const HEIGHT_SIGMA_FACTOR: f64 = 10.0;

/// The camera as the placement puts it, map grid.
struct Placed3 {
    /// Position (the prior's height).
    c_map: Vector3<f64>,
    /// Turn about the vertical (map grid, counter-clockwise seen from above), rad.
    theta_rad: f64,
    /// Distance of the grid's ground points' centroid from the camera's nadir, metres.
    lever_m: f64,
    /// Variance of the relief displacement the placement averages, m^2 per axis.
    relief_var_m2: f64,
}

/// The image's share of the placement fix's covariance, map grid, m^2: the placement's own
/// localisation, the relief displacement it averages, its rotation and scale acting over the
/// lever from the ground points to the nadir; the height the prior's (`sigma_v_m`) times
/// [`HEIGHT_SIGMA_FACTOR`].
fn image_cov_map(p: &PlacementObs, est: &Placed3, sigma_v_m: f64) -> Matrix3<f64> {
    let var_h = est.relief_var_m2
        + (est.lever_m * p.sigma_rot_rad).powi(2)
        + (est.lever_m * p.sigma_log_scale).powi(2);
    let c = &p.cov_h_m2;
    Matrix3::new(
        c[0][0] + var_h,
        c[0][1],
        0.0,
        c[1][0],
        c[1][1] + var_h,
        0.0,
        0.0,
        0.0,
        (HEIGHT_SIGMA_FACTOR * sigma_v_m).powi(2),
    )
}

impl FixEngine {
    /// The placement fix's report (module doc); rejected when the grid's rays miss the terrain
    /// or a number is not finite.
    pub(super) fn placement_report(&self, v: &View, p: &PlacementObs, t_us: u64) -> FixReport {
        let rej = |why: Rejection| {
            FixReport::rejected(
                Rejection::NoPlacementFix {
                    ties: Box::new(p.ties_rejection.clone()),
                    placement: Box::new(why),
                },
                t_us,
                0.0,
            )
        };
        match self.placement_pose(v.g, v.agl_m, p) {
            Ok(mut r) => {
                r.t_capture_us = t_us;
                r.level = v.level;
                r
            }
            Err(e) => rej(e),
        }
    }

    /// The placement fix's pose from the prior `g` (`agl_m` above the ground) and `p`.
    fn placement_pose(
        &self,
        g: &PriorGeom,
        agl_m: f64,
        p: &PlacementObs,
    ) -> Result<FixReport, Rejection> {
        let est = self
            .camera_from_ground(g.c_map, agl_m, &g.r_map_cam, &p.obs)
            .ok_or(Rejection::RaysMissTerrain)?;
        let crs = self.reference.crs();
        let (lat0, lon0) = crs
            .to_geodetic(g.c_map.x, g.c_map.y)
            .map_err(super::geodesy("prior geodesy"))?;
        let gamma = crs
            .grid_convergence_deg(lat0, lon0)
            .map_err(super::geodesy("prior geodesy"))?
            .to_radians();
        // v_map = m v_ned (grid east-north-up, turned by the grid convergence).
        let m = rot_z(gamma) * r_enu_ned();
        let mut d_map = Matrix3::zeros();
        for k in 0..3 {
            let step = |sign: f64| {
                let psi = m * (Vector3::ith(k, sign * DIFF_RAD));
                let r = Rotation3::from_scaled_axis(psi) * g.r_map_cam;
                self.camera_from_ground(g.c_map, agl_m, &r, &p.obs)
                    .map(|e| e.c_map)
                    .ok_or(Rejection::RaysMissTerrain)
            };
            let (plus, minus) = (step(1.0)?, step(-1.0)?);
            d_map.set_column(k, &((plus - minus) / (2.0 * DIFF_RAD)));
        }
        // The height is the prior's, with a variance that leaves a filter's height alone.
        let z = g.c_map.z;
        let image_map = image_cov_map(p, &est, g.sigma_v_m);
        let ned_from_map = m.inverse();
        let rm = ned_from_map.matrix();
        let mut image_ned = rm * image_map * rm.transpose();
        let reg_var = self.map_registration_var_m2();
        image_ned[(0, 0)] += reg_var;
        image_ned[(1, 1)] += reg_var;
        image_ned[(2, 2)] += self.map_height_var_m2();
        let d_ned = rm * d_map;
        let prior_att = Matrix3::from_diagonal(&Vector3::new(
            g.sigma_tilt_rad.powi(2),
            g.sigma_tilt_rad.powi(2),
            g.sigma_yaw_rad.powi(2),
        ));
        let cov = image_ned + d_ned * prior_att * d_ned.transpose();
        let cov = (cov + cov.transpose()) * 0.5;
        // The attitude: the prior's, turned about the vertical as the placement says.
        let r_ned_cam = ned_from_map * rot_z(est.theta_rad) * g.r_map_cam;
        let att = self.camera.mount.attitude_from_r_ned_cam(&r_ned_cam);
        let (lat, lon) = crs
            .to_geodetic(est.c_map.x, est.c_map.y)
            .map_err(super::geodesy("fix geodesy"))?;
        let n = geoid_undulation_m(lat, lon).map_err(super::geodesy("geoid"))?;
        let arr = |a: &Matrix3<f64>| std::array::from_fn(|i| std::array::from_fn(|j| a[(i, j)]));
        let att_cov = Matrix3::from_diagonal(&Vector3::new(
            g.sigma_tilt_rad.powi(2),
            g.sigma_tilt_rad.powi(2),
            p.sigma_rot_rad.powi(2),
        ));
        let r = FixReport {
            accepted: true,
            rejection: None,
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: z,
            h_ellip_m: z + n,
            x_m: est.c_map.x,
            y_m: est.c_map.y,
            z_m: z,
            roll_deg: att.roll_rad.to_degrees(),
            pitch_deg: att.pitch_rad.to_degrees(),
            yaw_deg: att.yaw_rad.to_degrees(),
            cov_ned_m2: arr(&cov),
            cov_att_ned_rad2: arr(&att_cov),
            inliers: 0,
            matches: 0,
            reproj_rms_px: f64::NAN,
            sigma0: f64::NAN,
            cov_factor: 1.0,
            vision_only: None,
            prior_dependence: Some(PriorDependenceNed {
                d_pos_d_att: arr(&d_ned),
                image_cov_ned_m2: arr(&image_ned),
            })
            .filter(PriorDependenceNed::is_finite),
            method: FixMethod::Placement,
            ..FixReport::rejected(Rejection::NoHypothesis, 0, 0.0)
        };
        let finite = [
            r.lat_deg,
            r.lon_deg,
            r.alt_amsl_m,
            r.roll_deg,
            r.pitch_deg,
            r.yaw_deg,
        ]
        .iter()
        .chain(r.cov_ned_m2.iter().flatten())
        .all(|x| x.is_finite());
        if !finite || r.prior_dependence.is_none() {
            return Err(Rejection::NonFinite { what: "the pose" });
        }
        Ok(r)
    }

    /// The camera near `c` (`agl_m` above the ground) that sees the ground `obs` (frame pixel,
    /// map x y) with attitude `r_map_cam`
    /// at the prior's height (module doc); `None` when a ray misses the terrain or the fit is
    /// degenerate.
    fn camera_from_ground(
        &self,
        c: Vector3<f64>,
        agl_m: f64,
        r_map_cam: &Rotation3<f64>,
        obs: &[(Point2<f64>, [f64; 2])],
    ) -> Option<Placed3> {
        let dem = self.reference.dem();
        let range = MAX_RAY_RANGE_AGL * agl_m.max(100.0);
        let (mut pred, mut truth, mut rays) = (Vec::new(), Vec::new(), Vec::new());
        let mut z_pred = 0.0;
        for (px, t) in obs {
            let d = r_map_cam * self.camera.unproject(px)?.into_inner();
            let p = dem.intersect_ray([c.x, c.y, c.z], [d.x, d.y, d.z], range)?;
            z_pred += p[2];
            let h = self.reference.height_amsl_m(t[0], t[1])?;
            pred.push([(p[0] - c.x) as f32, (p[1] - c.y) as f32]);
            truth.push([(t[0] - c.x) as f32, (t[1] - c.y) as f32]);
            (d.z < 0.0).then_some(())?;
            rays.push(([d.x / -d.z, d.y / -d.z], [t[0] - c.x, t[1] - c.y], h));
        }
        let n = obs.len().max(1) as f64;
        let theta = f64::from(Sim2::fit(&pred, &truth)?.theta_rad);
        // The rays turned by theta; at the prior's height z, c = mean(T_i + (h_i - z) u_i).
        let (sn, cs) = theta.sin_cos();
        let turned: Vec<[f64; 2]> = rays
            .iter()
            .map(|(u, _, _)| [cs * u[0] - sn * u[1], sn * u[0] + cs * u[1]])
            .collect();
        let z = c.z;
        let (mut xy, mut u_mean) = ([0.0; 2], [0.0; 2]);
        for (u, (_, t, h)) in turned.iter().zip(&rays) {
            for k in 0..2 {
                xy[k] += (t[k] + (h - z) * u[k]) / n;
                u_mean[k] += u[k] / n;
            }
        }
        // The rectified frame is a nadir perspective view: ground `dh` above the footprint's
        // mean is displaced by `dh u` from where the orthophoto has it (and by `sigma u` for
        // the map's own height error). The placement averages these displacements with
        // unknown weights; their mean square bounds the bias.
        let h_mean = rays.iter().map(|r| r.2).sum::<f64>() / n;
        let sigma_h2 = self.reference.height_sigma_m().powi(2);
        let relief_var_m2 = turned
            .iter()
            .zip(&rays)
            .map(|(u, r)| ((r.2 - h_mean).powi(2) + sigma_h2) * (u[0] * u[0] + u[1] * u[1]))
            .sum::<f64>()
            / n;
        Some(Placed3 {
            relief_var_m2,
            c_map: Vector3::new(c.x + xy[0], c.y + xy[1], z),
            theta_rad: theta,
            lever_m: (c.z - z_pred / n) * u_mean[0].hypot(u_mean[1]),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::checkerboard_engine;
    use super::*;
    use crate::camera::Attitude;
    use crate::fix::{AttitudePriorNed, PositionPriorGeo};

    /// The ground each pixel of a 5 x 5 grid sees from the camera at map `(x, y, z)` with
    /// attitude `att` (flat ground at 300 m).
    fn ground_seen(
        engine: &FixEngine,
        crs: &crate::geo::Crs,
        x: f64,
        y: f64,
        z: f64,
        att: Attitude,
    ) -> Vec<(Point2<f64>, [f64; 2])> {
        let g = prior(engine, crs, x, y, z, att);
        let mut obs = Vec::new();
        for i in 0..5 {
            for j in 0..5 {
                let px = Point2::new(32.0 + 64.0 * i as f64, 24.0 + 48.0 * j as f64);
                let d = g.r_map_cam * engine.camera.unproject(&px).unwrap().into_inner();
                let t = (z - 300.0) / -d.z;
                obs.push((px, [x + t * d.x, y + t * d.y]));
            }
        }
        obs
    }

    fn prior(
        engine: &FixEngine,
        crs: &crate::geo::Crs,
        x: f64,
        y: f64,
        z: f64,
        att: Attitude,
    ) -> PriorGeom {
        let (lat, lon) = crs.to_geodetic(x, y).unwrap();
        let pos = PositionPriorGeo {
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: z,
            sigma_h_m: 50.0,
            sigma_v_m: 10.0,
        };
        engine
            .prior_geom(&pos, &AttitudePriorNed::isotropic(att, 0.3f64.to_radians()))
            .unwrap()
    }

    fn obs(o: Vec<(Point2<f64>, [f64; 2])>) -> PlacementObs {
        PlacementObs {
            obs: o,
            cov_h_m2: [[1.0, 0.0], [0.0, 1.0]],
            sigma_rot_rad: 0.01,
            sigma_log_scale: 0.01,
            ties_rejection: Rejection::NoHypothesis,
        }
    }

    /// With the prior's tilt right, the fix is the true camera (position and heading) whatever
    /// the prior's position and heading errors; a tilt error moves it by `D psi` with the
    /// reported `D`, and the reported covariance holds that term.
    #[test]
    fn the_placement_fix_recovers_position_and_heading_and_its_tilt_dependence() {
        let (engine, crs) = checkerboard_engine();
        let truth = Attitude::new(3f64.to_radians(), -8f64.to_radians(), 40f64.to_radians());
        let (x, y, z) = (500_640.0, 5_199_360.0, 1300.0);
        let seen = ground_seen(&engine, &crs, x, y, z, truth);
        // Prior 60 m and 4 deg of heading off, tilt right.
        let off = Attitude::new(
            truth.roll_rad,
            truth.pitch_rad,
            truth.yaw_rad + 4f64.to_radians(),
        );
        let g = prior(&engine, &crs, x - 40.0, y + 45.0, z, off);
        let r = engine
            .placement_pose(&g, 1000.0, &obs(seen.clone()))
            .unwrap();
        assert!(
            (r.x_m - x).abs() < 0.05 && (r.y_m - y).abs() < 0.05,
            "{} {}",
            r.x_m - x,
            r.y_m - y
        );
        assert!((r.yaw_deg - 40.0).abs() < 0.01, "yaw {}", r.yaw_deg);
        assert!((r.roll_deg - 3.0).abs() < 0.01 && (r.pitch_deg + 8.0).abs() < 0.01);
        assert_eq!(r.z_m, z, "the height is the prior's");
        assert_eq!(r.method, FixMethod::Placement);
        // Tilt error psi (NED rotation vector: R_prior = Exp(psi) R_true) about north.
        let psi = Vector3::new(0.3f64.to_radians(), -0.2f64.to_radians(), 0.0);
        let r_ned_cam = Rotation3::from_scaled_axis(psi) * engine.camera.mount.r_ned_cam(&truth);
        let tilted = engine.camera.mount.attitude_from_r_ned_cam(&r_ned_cam);
        let g = prior(&engine, &crs, x - 40.0, y + 45.0, z, tilted);
        let r2 = engine.placement_pose(&g, 1000.0, &obs(seen)).unwrap();
        let d = r2.prior_dependence.unwrap().d_pos_d_att;
        let (lat, lon) = crs.to_geodetic(x, y).unwrap();
        let gamma = crs.grid_convergence_deg(lat, lon).unwrap().to_radians();
        // Map grid error to NED: v_map = Rz(gamma) v_enu.
        let (dx, dy) = (r2.x_m - x, r2.y_m - y);
        let (sg, cg) = gamma.sin_cos();
        let err_ned = [-dx * sg + dy * cg, dx * cg + dy * sg];
        for k in 0..2 {
            let pred = d[k][0] * psi.x + d[k][1] * psi.y + d[k][2] * psi.z;
            assert!(
                (pred - err_ned[k]).abs() < 0.05 * err_ned[k].abs().max(1.0),
                "axis {k}: D psi {pred} vs {}",
                err_ned[k]
            );
        }
        assert!(
            err_ned[0].hypot(err_ned[1]) > 4.0,
            "a tilt error of 0.36 deg at 1 km moves it"
        );
        // The covariance holds the tilt term: >= (1000 m x 0.3 deg)^2 per axis.
        let floor = (1000.0 * 0.3f64.to_radians()).powi(2);
        assert!(r2.cov_ned_m2[0][0] > 0.9 * floor && r2.cov_ned_m2[1][1] > 0.9 * floor);
        assert!(
            r2.cov_ned_m2[2][2] >= (10.0 * 10.0f64).powi(2),
            "height not measured"
        );
    }

    /// The placement's own covariance (map grid x east, y north) reaches the report's image
    /// covariance in NED as it is: a plateau along grid north (an east-west edge seen) is
    /// uncertain in north, not in east, beside the fixed terms.
    #[test]
    fn the_placement_covariance_enters_the_fix_along_its_axes() {
        let (engine, crs) = checkerboard_engine();
        let truth = Attitude::new(0.0, 0.0, 0.0);
        let (x, y, z) = (500_640.0, 5_199_360.0, 1300.0);
        let seen = ground_seen(&engine, &crs, x, y, z, truth);
        let g = prior(&engine, &crs, x, y, z, truth);
        let image = |cov_h_m2: [[f64; 2]; 2]| {
            let o = PlacementObs {
                cov_h_m2,
                ..obs(seen.clone())
            };
            let r = engine.placement_pose(&g, 1000.0, &o).unwrap();
            r.prior_dependence.unwrap().image_cov_ned_m2
        };
        let round = image([[1.0, 0.0], [0.0, 1.0]]);
        let north = image([[1.0, 0.0], [0.0, 401.0]]);
        // NED: index 0 north, 1 east; the grid convergence here turns by well under a degree.
        assert!((north[0][0] - round[0][0] - 400.0).abs() < 1.0, "{north:?}");
        assert!((north[1][1] - round[1][1]).abs() < 1.0, "{north:?}");
        let skew = image([[101.0, 100.0], [100.0, 101.0]]);
        assert!(skew[0][1] > 90.0 && skew[1][0] > 90.0, "{skew:?}");
    }
}
