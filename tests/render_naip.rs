//! The camera renderer on the bundled NAIP 2014 orthophoto (the camera year; the map year is 2009
//! and is never rendered from).
//!
//! * A nadir, north-up VGA frame whose ground sample distance equals the orthophoto's 5 m pixels,
//!   centred on the benchmark crop `../shared/data/bench/naip2014_640x480.png` (ortho pixels
//!   100..740 x 100..580), must reproduce that crop pixel for pixel (grey correlation >= 0.98, mean
//!   absolute difference small). Skipped without the shared data.
//! * The acceptance configuration (640 x 480, 60 deg HFOV, 1500 m above ground, 15 deg tilt, heading
//!   40 deg, with exposure change, vignetting, blur and noise) is rendered to
//!   `target/render_naip2014_1500m.png` (+ `_mask.png`) for a visual check.

use nalgebra::Vector3;
use std::path::{Path, PathBuf};
use visnav::camera::Opk;
use visnav::camera::frames::rot_x;
use visnav::geo::dem::Dem;
use visnav::geo::geotiff::load_geotiff;
use visnav::sitl::render::{
    BlurSpec, ColourMode, ExposureSpec, LUMA_REC601, NoiseSpec, RenderPose, RenderSpec, Renderer,
    Scene, vga_camera,
};

/// NAIP North Dakota is flat; the bundled README gives about 580 m AMSL.
const GROUND_M: f64 = 580.0;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn naip_2014() -> visnav::geo::raster::Raster {
    load_geotiff(&root().join("sitl/maps/naip_nd_2014.tif"), None).expect("bundled NAIP 2014")
}

fn out_dir() -> PathBuf {
    let d = root().join("target");
    std::fs::create_dir_all(&d).expect("create target/");
    d
}

#[test]
fn nadir_render_at_map_gsd_reproduces_the_bench_crop() {
    let crop_path = root().join("../shared/data/bench/naip2014_640x480.png");
    if !crop_path.is_file() {
        eprintln!(
            "SKIP: {} not found (shared data absent)",
            crop_path.display()
        );
        return;
    }
    let crop = image::open(&crop_path).expect("open bench crop").to_rgb8();
    assert_eq!((crop.width(), crop.height()), (640, 480));
    let ortho = naip_2014();
    let (px_m, _) = ortho.transform().pixel_size();
    let cam = vga_camera().unwrap();
    let k = cam.intrinsics;
    let scene = Scene::new(&ortho, Dem::flat(GROUND_M).unwrap(), ColourMode::Grey).unwrap();
    // Camera pixel (u, v) sees ortho pixel (100 + u, 100 + v): its centre is at ortho corner
    // coordinates (100.5 + u, 100.5 + v); the principal point (319.5, 239.5) at (420, 340).
    let (xc, yc) = ortho
        .transform()
        .pixel_to_map(100.5 + k.cx_px, 100.5 + k.cy_px);
    let agl = px_m * k.fx_px;
    let pose = RenderPose::from_opk(
        Vector3::new(xc, yc, GROUND_M + agl),
        &Opk::new(0.0, 0.0, 0.0),
    );
    let ren = Renderer::new(cam, RenderSpec::clean()).unwrap();
    let fr = ren.render(&scene, &pose, 0).unwrap();
    assert_eq!(fr.valid_fraction(), 1.0);
    let crop_grey: Vec<f64> = crop
        .pixels()
        .map(|p| {
            f64::from(LUMA_REC601[0]) * f64::from(p[0])
                + f64::from(LUMA_REC601[1]) * f64::from(p[1])
                + f64::from(LUMA_REC601[2]) * f64::from(p[2])
        })
        .collect();
    let rendered: Vec<f64> = fr.data.iter().map(|v| f64::from(*v)).collect();
    let corr = pearson(&crop_grey, &rendered);
    let mad = crop_grey
        .iter()
        .zip(&rendered)
        .map(|(a, b)| (a - b).abs())
        .sum::<f64>()
        / rendered.len() as f64;
    eprintln!(
        "bench crop vs nadir render at {agl:.1} m (GSD {px_m} m): corr {corr:.4}, MAD {mad:.2} DN"
    );
    assert!(corr >= 0.98, "correlation {corr}");
    assert!(mad < 6.0, "mean absolute difference {mad} DN");
    // The alignment is exact: over the interior, the correlation as a function of an integer
    // shift of the render peaks at zero, and the parabola through the three values around the
    // peak puts it within 0.1 px of zero on each axis.
    let corr_at = |dx: i64, dy: i64| {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for r in 1..479i64 {
            for c in 1..639i64 {
                a.push(crop_grey[(r * 640 + c) as usize]);
                b.push(rendered[((r + dy) * 640 + c + dx) as usize]);
            }
        }
        pearson(&a, &b)
    };
    let c0 = corr_at(0, 0);
    let (cxm, cxp, cym, cyp) = (corr_at(-1, 0), corr_at(1, 0), corr_at(0, -1), corr_at(0, 1));
    let peak = |m: f64, z: f64, p: f64| 0.5 * (m - p) / (m - 2.0 * z + p);
    let (px, py) = (peak(cxm, c0, cxp), peak(cym, c0, cyp));
    eprintln!(
        "shifted by one pixel: x {cxm:.4} / {cxp:.4}, y {cym:.4} / {cyp:.4}; \
         peak at ({px:.3}, {py:.3}) px"
    );
    assert!([cxm, cxp, cym, cyp].iter().all(|c| *c < c0 - 0.01));
    assert!(
        px.abs() < 0.1 && py.abs() < 0.1,
        "peak offset ({px}, {py}) px"
    );
}

#[test]
fn acceptance_frame_at_1500_m_for_visual_check() {
    let ortho = naip_2014();
    let scene = Scene::new(&ortho, Dem::flat(GROUND_M).unwrap(), ColourMode::Grey).unwrap();
    let spec = RenderSpec {
        seed: 2014,
        exposure: ExposureSpec {
            gain: 1.15,
            offset_dn: -8.0,
            gamma: 0.9,
            vignetting_corner: 0.25,
        },
        blur: BlurSpec {
            sigma_px: 0.7,
            motion_length_px: 2.0,
            motion_angle_deg: 40.0,
        },
        noise: NoiseSpec {
            read_dn: 1.5,
            conversion_gain_dn_per_e: 0.04,
        },
        ..RenderSpec::default()
    };
    let ren = Renderer::new(vga_camera().unwrap(), spec).unwrap();
    let b = ortho.bounds();
    let (xc, yc) = (0.5 * (b.min_x_m + b.max_x_m), 0.5 * (b.min_y_m + b.max_y_m));
    // Heading 40 deg (image top towards grid bearing 40), axis tilted 15 deg towards the image top.
    let r = Opk::new(0.0, 0.0, -40f64.to_radians()).r_world_cam() * rot_x(15f64.to_radians());
    let pose = RenderPose::new(Vector3::new(xc, yc, GROUND_M + 1500.0), r);
    let fr = ren.render(&scene, &pose, 0).unwrap();
    let valid = fr.valid_fraction();
    let vals: Vec<f64> = fr.data.iter().map(|v| f64::from(*v)).collect();
    let mean = vals.iter().sum::<f64>() / vals.len() as f64;
    let sd = (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / vals.len() as f64).sqrt();
    let path = out_dir().join("render_naip2014_1500m.png");
    fr.to_gray_image().save(&path).expect("write png");
    fr.mask_image()
        .save(out_dir().join("render_naip2014_1500m_mask.png"))
        .expect("write mask png");
    eprintln!(
        "wrote {}: valid {:.1} %, mean {mean:.1} DN, sd {sd:.1} DN",
        path.display(),
        100.0 * valid
    );
    assert_eq!(
        valid, 1.0,
        "the 1500 m footprint fits inside the 4.7 x 3.6 km map"
    );
    assert!(
        sd > 10.0 && mean > 40.0 && mean < 220.0,
        "mean {mean}, sd {sd}"
    );
}

fn pearson(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
        sab += (x - ma) * (y - mb);
    }
    sab / (saa * sbb).sqrt()
}
