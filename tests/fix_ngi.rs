//! The vision fix on real NGI aerial frames 0182 and 0184 (../shared/data/ngi_3324c)
//! against the Sentinel-2 10 m map + 24 m DEM (other sensor, other date) and against the
//! same-source NGI 5 m orthophoto, with a 500 m position prior and with no position prior (global
//! relocalisation). Truth: the aerial-triangulation camera poses. Skips when the data are absent.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Rotation3, Vector3};
use visnav::camera::frames::{r_enu_ned, rot_z};
use visnav::camera::{Attitude, Camera, CameraConfig, Opk};
use visnav::fix::{AttitudePriorNed, FixEngine, FixParams, FixPrior, FixReport};
use visnav::fix::{MapReference, PositionPriorGeo, Reference};
use visnav::geo::Crs;
use visnav::map::{BuildSpec, HeightSource, build_map};
use visnav::vision::{GrayImage, GrayImageFile};

fn data_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/ngi_3324c");
    if dir.join("frames_truth.csv").is_file() {
        Some(dir)
    } else {
        eprintln!("SKIP: {} not found (shared NGI data absent)", dir.display());
        None
    }
}

struct Truth {
    centre_m: Vector3<f64>,
    opk: Opk,
}

fn read_truth(dir: &Path, frame: &str) -> Option<Truth> {
    let text = std::fs::read_to_string(dir.join("frames_truth.csv")).ok()?;
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.trim().split(',').collect();
        if f.len() == 7 && f[0] == frame {
            let v: Vec<f64> = f[1..7].iter().filter_map(|s| s.parse().ok()).collect();
            if v.len() == 6 {
                return Some(Truth {
                    centre_m: Vector3::new(v[0], v[1], v[2]),
                    opk: Opk::from_deg(v[3], v[4], v[5]),
                });
            }
        }
    }
    None
}

fn ngi_camera() -> Camera {
    let cfg: CameraConfig = toml::from_str(
        "width_px = 640\nheight_px = 1152\nfocal_length_mm = 120.0\n\
         sensor_width_mm = 92.16\nsensor_height_mm = 165.888\n",
    )
    .expect("camera toml");
    cfg.build().expect("valid camera")
}

/// `R_ned_cam` of the truth (OPK is in the map grid; grid north is `gamma` east of true north).
fn truth_r_ned_cam(crs: &Crs, t: &Truth) -> (Rotation3<f64>, f64, f64) {
    let (lat, lon) = crs.to_geodetic(t.centre_m.x, t.centre_m.y).unwrap();
    let gamma = crs.grid_convergence_deg(lat, lon).unwrap().to_radians();
    let r_map_cam = t.opk.r_world_cam();
    let r_enu_cam = rot_z(-gamma) * r_map_cam;
    (r_enu_ned().inverse() * r_enu_cam, lat, lon)
}

struct Outcome {
    report: FixReport,
    err_h_m: f64,
    err_v_m: f64,
    err_att_deg: f64,
}

fn run(
    engine: &FixEngine,
    camera: &Camera,
    crs: &Crs,
    dir: &Path,
    frame: &str,
    prior_m: Option<f64>,
) -> Option<Outcome> {
    let truth = read_truth(dir, frame)?;
    let img = GrayImage::load(&dir.join(frame)).ok()?;
    let (r_ned_cam, lat, lon) = truth_r_ned_cam(crs, &truth);
    let att = camera.mount.attitude_from_r_ned_cam(&r_ned_cam);
    // Prior: attitude 0.3 deg off per axis (stated 0.5 deg); position 500 m off when given.
    let off = 0.3f64.to_radians();
    let prior_att = Attitude::new(att.roll_rad + off, att.pitch_rad - off, att.yaw_rad + off);
    let position = prior_m.map(|d| {
        let (plat, plon) = crs
            .to_geodetic(truth.centre_m.x + 0.6 * d, truth.centre_m.y - 0.8 * d)
            .unwrap();
        PositionPriorGeo {
            lat_deg: plat,
            lon_deg: plon,
            alt_amsl_m: truth.centre_m.z + 50.0,
            sigma_h_m: d,
            sigma_v_m: 100.0,
        }
    });
    let _ = (lat, lon);
    let prior = FixPrior {
        t_capture_us: 1,
        position,
        attitude: Some(AttitudePriorNed::isotropic(prior_att, 0.5f64.to_radians())),
        altitude: None,
        attitude_from_filter: false,
        widen_heading: true,
    };
    let (report, attempt) = engine.fix_with_attempt(&img, &prior);
    // Residuals of the fine matches at the truth pose (map grid taken as Cartesian).
    let tp = visnav::camera::CameraPose::from_opk(truth.centre_m, &truth.opk);
    let mut res: Vec<(f64, f64)> = Vec::new();
    for (px, p) in &attempt.pairs {
        if let Some(q) = tp.project_world(camera, &Vector3::new(p[0], p[1], p[2])) {
            let d = (px[0] - q.x, px[1] - q.y);
            if d.0.hypot(d.1) < 3.0 {
                res.push(d);
            }
        }
    }
    let n = res.len().max(1) as f64;
    let (mx, my) = (
        res.iter().map(|r| r.0).sum::<f64>() / n,
        res.iter().map(|r| r.1).sum::<f64>() / n,
    );
    let rms = (res.iter().map(|r| r.0 * r.0 + r.1 * r.1).sum::<f64>() / n).sqrt();
    eprintln!(
        "  truth residuals of {} / {} matches within 3 px: mean ({mx:.2}, {my:.2}) px, rms {rms:.2} px, level {}",
        res.len(),
        attempt.pairs.len(),
        attempt.level
    );
    let (eh, ev, ea) = if report.accepted {
        let fix_att = Attitude::from_deg(report.roll_deg, report.pitch_deg, report.yaw_deg);
        let r_fix = camera.mount.r_ned_cam(&fix_att);
        let d = (r_fix.inverse() * r_ned_cam).angle().to_degrees();
        (
            ((report.x_m - truth.centre_m.x).powi(2) + (report.y_m - truth.centre_m.y).powi(2))
                .sqrt(),
            (report.z_m - truth.centre_m.z).abs(),
            d,
        )
    } else {
        (f64::NAN, f64::NAN, f64::NAN)
    };
    eprintln!(
        "{frame} prior {:?}: accepted {} ({}), rms {:.2} px, inliers {} of {} matches, error h {eh:.1} m (dx {:.1} dy {:.1} dz {:.1}) v {ev:.1} m attitude {ea:.3} deg, sigma h {:.1} m (sigma0 {:.2}, covariance factor {:.1}), {:.0} ms",
        prior_m,
        report.accepted,
        report.reason(),
        report.reproj_rms_px,
        report.inliers,
        report.matches,
        report.x_m - truth.centre_m.x,
        report.y_m - truth.centre_m.y,
        report.z_m - truth.centre_m.z,
        report.cov_ned_m2[0][0].max(report.cov_ned_m2[1][1]).sqrt(),
        report.sigma0,
        report.cov_factor,
        report.ms
    );
    Some(Outcome {
        report,
        err_h_m: eh,
        err_v_m: ev,
        err_att_deg: ea,
    })
}

fn engine_for(dir: &Path, ortho: &str, levels: usize) -> Option<(FixEngine, Camera, Crs)> {
    // The product path: a .vnm map built from the orthophoto and the DEM.
    let mut spec = BuildSpec::new(
        vec![dir.join(ortho)],
        HeightSource::Dem(dir.join("dem.tif")),
    );
    spec.levels = Some(levels);
    let tmp = tempfile::tempdir().ok()?;
    let path = tmp.path().join("map.vnm");
    let summary = build_map(&spec, &path, &mut |_| {}).ok()?;
    eprintln!(
        "{ortho}: features per level {:?}",
        summary
            .header
            .levels
            .iter()
            .map(|l| l.n_features)
            .collect::<Vec<_>>()
    );
    let reference = MapReference::open(&path, None).ok()?;
    let crs = reference.crs();
    let camera = ngi_camera();
    let engine = FixEngine::new(Arc::new(reference), camera, FixParams::default()).ok()?;
    Some((engine, camera, crs))
}

/// An accepted fix lies within 3 sigma of the truth on each NED axis.
fn within_3_sigma(o: &Outcome, dx: f64, dy: f64, dz: f64) -> bool {
    let c = &o.report.cov_ned_m2;
    // Grid and NED axes differ by the convergence (0.3 deg here): the per-axis test uses the
    // larger horizontal sigma for both horizontal axes.
    let sh = c[0][0].max(c[1][1]).sqrt();
    dx.abs() <= 3.0 * sh && dy.abs() <= 3.0 * sh && dz.abs() <= 3.0 * c[2][2].sqrt()
}

/// Both priors (500 m, none) for `frame` against `engine`: accepted, within its own 3 sigma, and
/// within the horizontal / vertical / attitude guards.
fn check_frame(
    dir: &Path,
    (engine, camera, crs): &(FixEngine, Camera, Crs),
    frame: &str,
    max_h_m: f64,
) {
    let truth = read_truth(dir, frame).expect("truth");
    for prior in [Some(500.0), None] {
        let o = run(engine, camera, crs, dir, frame, prior).expect("run");
        assert!(
            o.report.accepted,
            "{frame} prior {prior:?}: {}",
            o.report.reason()
        );
        let (dx, dy, dz) = (
            o.report.x_m - truth.centre_m.x,
            o.report.y_m - truth.centre_m.y,
            o.report.z_m - truth.centre_m.z,
        );
        assert!(within_3_sigma(&o, dx, dy, dz), "{frame}: beyond 3 sigma");
        assert!(o.err_h_m <= max_h_m, "{frame}: horizontal {} m", o.err_h_m);
        assert!(o.err_v_m <= 15.0, "{frame}: vertical {} m", o.err_v_m);
        assert!(
            o.err_att_deg <= 0.2,
            "{frame}: attitude {} deg",
            o.err_att_deg
        );
    }
}

#[test]
fn ngi_frames_against_sentinel2() {
    let Some(dir) = data_dir() else { return };
    let e = engine_for(&dir, "sentinel2_b432_byte.tif", 3).expect("engine");
    // Measured 6.1-12.8 m / 0.6-1.6 m / 0.03-0.14 deg (targets 10 m / 15 m / 0.2 deg); the
    // horizontal guard has a margin (docs/fix.md).
    for frame in ["frame_05_0182.png", "frame_05_0184.png"] {
        check_frame(&dir, &e, frame, 15.0);
    }
}

#[test]
fn ngi_frames_against_ngi_ortho() {
    let Some(dir) = data_dir() else { return };
    // Target 5 m; measured 5.4-16.4 m (docs/fix.md): guard at 20 m.
    for (frame, tile) in [
        ("frame_05_0182.png", "ngi_ortho_5m_tile1.tif"),
        ("frame_05_0184.png", "ngi_ortho_5m_tile2.tif"),
    ] {
        let e = engine_for(&dir, tile, 3).expect("engine");
        check_frame(&dir, &e, frame, 20.0);
    }
}
