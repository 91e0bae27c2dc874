//! End-to-end check of the camera model and the omega-phi-kappa convention on real aerial frames.
//!
//! For each NGI frame (ngi_3324c, Intergraph DMC, 640 x 1152 px, f = 120 mm, no distortion), the
//! simulator's camera renderer (`sitl::render`) casts every pixel as a ray from the
//! aerial-triangulation pose (`frames_truth.csv`), intersects it with the 24 m DEM and samples the
//! NGI 5 m orthophoto (anti-aliased) at the ground point. If the
//! intrinsics, the pixel convention, the OPK rotation and the camera frame flip are right, the
//! re-rendered image matches the frame: the grey-level Pearson correlation must be at least 0.9.
//! With kappa + 180 deg (image turned upside down on the ground) it must collapse (< 0.3).
//! The data lives in `../shared/data/ngi_3324c`; the test is skipped with a message without it.

use nalgebra::{Point2, Vector3};
use std::path::{Path, PathBuf};
use visnav::camera::{Camera, CameraConfig, CameraPose, Opk};
use visnav::geo::geotiff::load_geotiff;
use visnav::sitl::render::{ColourMode, LUMA_REC601, RenderPose, RenderSpec, Renderer, Scene};

fn data_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/ngi_3324c");
    if dir.join("frames_truth.csv").is_file() {
        Some(dir)
    } else {
        eprintln!(
            "SKIP: {} not found (shared NGI test data absent)",
            dir.display()
        );
        None
    }
}

struct Truth {
    centre_m: Vector3<f64>,
    opk: Opk,
}

fn read_truth(dir: &Path, frame: &str) -> Truth {
    let text =
        std::fs::read_to_string(dir.join("frames_truth.csv")).expect("read frames_truth.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    assert_eq!(
        header,
        [
            "frame",
            "x_m",
            "y_m",
            "z_m",
            "omega_deg",
            "phi_deg",
            "kappa_deg"
        ]
    );
    for line in lines {
        let f: Vec<&str> = line.trim().split(',').collect();
        if f[0] == frame {
            let v: Vec<f64> = f[1..7].iter().map(|s| s.parse().expect("number")).collect();
            return Truth {
                centre_m: Vector3::new(v[0], v[1], v[2]),
                opk: Opk::from_deg(v[3], v[4], v[5]),
            };
        }
    }
    panic!("{frame} not in frames_truth.csv");
}

/// The NGI camera, built through the configuration path (focal length + sensor size form).
fn ngi_camera() -> Camera {
    let cfg: CameraConfig = toml::from_str(
        "width_px = 640\nheight_px = 1152\nfocal_length_mm = 120.0\n\
         sensor_width_mm = 92.16\nsensor_height_mm = 165.888\n",
    )
    .expect("camera toml");
    let cam = cfg.build().expect("valid camera");
    assert!((cam.intrinsics.fx_px - 833.333).abs() < 1e-2);
    assert_eq!((cam.intrinsics.cx_px, cam.intrinsics.cy_px), (319.5, 575.5));
    cam
}

/// Pearson correlation of the frame's grey levels with the ortho re-rendered through `pose` by the
/// simulator's camera renderer (`sitl::render`: per-pixel ray cast onto the DEM, anti-aliased
/// orthophoto sampling, no photometric effect), and the fraction of pixels that could be rendered.
fn render_correlation(
    renderer: &Renderer,
    scene: &Scene,
    pose: &CameraPose,
    frame_grey: &[f64],
) -> (f64, f64) {
    let rendered = renderer
        .render(scene, &RenderPose::from_camera_pose(pose), 0)
        .expect("render");
    let pairs: Vec<(f64, f64)> = rendered
        .data
        .iter()
        .zip(&rendered.valid)
        .zip(frame_grey)
        .filter(|((_, valid), _)| **valid)
        .map(|((r, _), f)| (*f, f64::from(*r)))
        .collect();
    let n = pairs.len() as f64;
    assert!(n > 1000.0, "only {n} pixels rendered");
    let (mf, mr) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), (f, r)| (a + f / n, b + r / n));
    let (mut sff, mut srr, mut sfr) = (0.0, 0.0, 0.0);
    for (f, r) in &pairs {
        sff += (f - mf) * (f - mf);
        srr += (r - mr) * (r - mr);
        sfr += (f - mf) * (r - mr);
    }
    (sfr / (sff * srr).sqrt(), n / frame_grey.len() as f64)
}

fn check_frame(frame: &str, ortho_file: &str) {
    let Some(dir) = data_dir() else { return };
    let truth = read_truth(&dir, frame);
    let cam = ngi_camera();
    let dem = visnav::geo::dem::load_dem(&dir.join("dem.tif"), None).expect("load dem.tif");
    let ortho = load_geotiff(&dir.join(ortho_file), None).expect("load ortho");
    let img = image::open(dir.join(frame)).expect("open frame").to_rgb8();
    assert_eq!(
        (img.width(), img.height()),
        (cam.width_px(), cam.height_px())
    );
    let frame_grey: Vec<f64> = img
        .pixels()
        .map(|p| {
            (0..3)
                .map(|c| f64::from(LUMA_REC601[c]) * f64::from(p[c]))
                .sum::<f64>()
        })
        .collect();
    let scene = Scene::new(&ortho, dem.clone(), ColourMode::Grey).expect("scene");
    let renderer = Renderer::new(cam, RenderSpec::clean()).expect("renderer");

    let pose = CameraPose::from_opk(truth.centre_m, &truth.opk);
    // Ray -> terrain -> back through the camera returns to the same pixel.
    let origin = [
        pose.centre_world_m.x,
        pose.centre_world_m.y,
        pose.centre_world_m.z,
    ];
    let mut worst_px: f64 = 0.0;
    for v in (0..1152).step_by(64) {
        for u in (0..640).step_by(64) {
            let px = Point2::new(f64::from(u), f64::from(v));
            let ray = pose.ray_world(&cam, &px).expect("ray");
            assert!(
                ray.z < -0.75,
                "nadir camera (half diagonal FOV 38 deg) must look down, ray {ray:?}"
            );
            let hit = dem
                .intersect_ray(origin, [ray.x, ray.y, ray.z], 20_000.0)
                .expect("ray hits the DEM");
            let back = pose
                .project_world(&cam, &Vector3::from(hit))
                .expect("ground point projects");
            worst_px = worst_px.max((back - px).norm());
        }
    }
    assert!(
        worst_px < 1e-3,
        "{frame}: ray/project round trip {worst_px} px"
    );
    let (corr, covered) = render_correlation(&renderer, &scene, &pose, &frame_grey);
    eprintln!(
        "{frame}: grey correlation frame vs ortho through truth pose = {corr:.4} \
         ({:.1} % of pixels rendered)",
        100.0 * covered
    );

    // For a visual check next to the real frame.
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("target");
    if std::fs::create_dir_all(&out).is_ok() {
        let rendered = renderer
            .render(&scene, &RenderPose::from_camera_pose(&pose), 0)
            .expect("render");
        let name = format!("render_ngi_{}", frame);
        if let Err(e) = rendered.to_gray_image().save(out.join(&name)) {
            eprintln!("could not write target/{name}: {e}");
        }
    }

    let mut flipped = truth.opk;
    flipped.kappa_rad += std::f64::consts::PI;
    let pose_flipped = CameraPose::from_opk(truth.centre_m, &flipped);
    let (corr_flipped, covered_flipped) =
        render_correlation(&renderer, &scene, &pose_flipped, &frame_grey);
    eprintln!(
        "{frame}: with kappa + 180 deg = {corr_flipped:.4} ({:.1} % rendered)",
        100.0 * covered_flipped
    );

    assert!(
        covered > 0.8,
        "{frame}: only {:.1} % rendered",
        100.0 * covered
    );
    assert!(corr >= 0.9, "{frame}: correlation {corr} < 0.9");
    assert!(
        corr_flipped < 0.3 && corr - corr_flipped > 0.6,
        "{frame}: kappa + 180 deg still correlates ({corr_flipped} vs {corr})"
    );
}

#[test]
fn ngi_frame_0182_reprojects_onto_ortho() {
    check_frame("frame_05_0182.png", "ngi_ortho_5m_tile1.tif");
}

#[test]
fn ngi_frame_0184_reprojects_onto_ortho() {
    check_frame("frame_05_0184.png", "ngi_ortho_5m_tile2.tif");
}
