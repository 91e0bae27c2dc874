//! `visnav bench surf [--image F]... [--json] [--stages] [--quality] [--export-pairs DIR]`: time
//! SURF detect+describe (median of `--runs`) on 1 thread and on all threads, upright and rotation
//! invariant (with `--stages` each stage on one thread), on the bench images of ../shared/data/bench; optionally run the repeatability /
//! matching-score table on the bundled NAIP maps and export the pairs for scripts/bench_opencv.py.
//! `visnav bench pose`: the resection's timing suite. `visnav bench render`: the camera renderer.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};

use super::repo_file;
use visnav::vision::eval::{self, PairScore};
use visnav::vision::{
    DescriptorKind, Features, GrayImage, GrayImageFile, IntegralImage, MatchParams, Surf,
    SurfParams, match_features,
};

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

#[derive(clap::Subcommand, Debug)]
pub enum BenchWhat {
    /// Time SURF detect+describe and count features.
    Surf(SurfBenchArgs),
    /// Time the space resection (P3P RANSAC + LM + integrity) on synthetic aerial scenes.
    Pose(PoseBenchArgs),
    /// Time the camera renderer (VGA, 60 deg FOV) over the bundled NAIP 2014 map (flat ground) and,
    /// when ../shared/data is present, the NGI ortho over its 24 m DEM and the drone scenario's
    /// camera (1280 x 960, 80 deg, 60 m) over Autzen's lidar surface model.
    Render(RenderBenchArgs),
    /// The vision fix on NAIP cross-date frames (map 2009, frames 2014): fix rate, error
    /// against truth, frame-to-fix time p50/p95.
    Fix(super::bench_fix::FixBenchArgs),
    /// Visual odometry: NGI frames 0182 -> 0184 against their measured poses (direction and
    /// length of the baseline), and the per-frame time on a VGA pair.
    Vo(super::bench_vo::VoBenchArgs),
    /// The demo's seed sweep: the bundled closed-loop demo once per seed, its fix rate and
    /// injected error beside the no-vision control's, against the demo's target.
    Demo(super::bench_demo::DemoBenchArgs),
    /// DTM navigation: NGI frame 0182's pose from the flow to frame 0184 and the DEM alone
    /// against its measured pose; refusals over flat ground; the solve time per frame pair.
    Dtm(super::bench_dtm::DtmBenchArgs),
}

#[derive(clap::Args, Debug)]
pub struct PoseBenchArgs {
    /// Trials per case (100/300/1000 correspondences at 50 % outliers, 300 at 90 %).
    #[arg(long, default_value_t = 50)]
    pub trials: usize,
}

#[derive(clap::Args, Debug)]
pub struct RenderBenchArgs {
    /// Timed renders per scene.
    #[arg(long, default_value_t = 20)]
    pub iterations: usize,
    /// Height above ground, metres.
    #[arg(long, default_value_t = 1500.0)]
    pub agl_m: f64,
}

#[derive(clap::Args, Debug)]
pub struct SurfBenchArgs {
    /// Image to time (repeatable). Default: naip2014_640x480.png and naip2014_1280x960.png in
    /// ../shared/data/bench.
    #[arg(long)]
    pub image: Vec<PathBuf>,
    /// Print one JSON document instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Timed runs per configuration (the median is reported).
    #[arg(long, default_value_t = 15)]
    pub runs: usize,
    /// Hessian threshold (OpenCV meaning).
    #[arg(long, default_value_t = 100.0)]
    pub threshold: f32,
    /// Sampling step of the first octave (OpenCV: 1, OpenSURF: 2).
    #[arg(long, default_value_t = 1)]
    pub init_step: usize,
    /// Layers searched per octave (OpenCV's nOctaveLayers).
    #[arg(long, default_value_t = 2)]
    pub octave_layers: usize,
    /// Which SURF modes to time: `both`, `upright` or `oriented`.
    #[arg(long, default_value = "both")]
    pub mode: String,
    /// Also compute the quality table on the bundled NAIP maps (sitl/maps).
    #[arg(long)]
    pub quality: bool,
    /// Write the quality pairs (PNG), homographies and SURF keypoints to DIR (implies --quality).
    /// Per pair also `pairNN_{1,2}_{usurf64,surf64}.f32`: the SURF-64 descriptors (little-endian
    /// f32, 64 per keypoint, keypoints in the manifest's order).
    #[arg(long)]
    pub export_pairs: Option<PathBuf>,
    /// Write the keypoints and SURF-64 descriptors of every timed image and mode to DIR as
    /// `<image stem>_<mode>.json` (for scripts/compare_opencv_surf.py).
    #[arg(long)]
    pub export_features: Option<PathBuf>,
    /// `cpu`, or `gpu`: also time the GPU path (crates/visnav-gpu; a binary built with
    /// `--features gpu`) beside the CPU in the same run, at 640x480, 1280x960 and 1920x1080 (the
    /// 1280x960 frame resampled), SURF and then brute-force matching, naming the adapter (a
    /// software one is labelled so).
    #[arg(long, default_value = "cpu", value_parser = ["cpu", "gpu"])]
    pub backend: String,
    /// Also time each stage on one thread (integral image, response layers, extrema,
    /// orientation, descriptors; the median of `--runs` each).
    #[arg(long)]
    pub stages: bool,
}

#[derive(serde::Serialize)]
struct Timing {
    image: String,
    width: usize,
    height: usize,
    mode: &'static str,
    /// `cpu`, or `gpu: <adapter>`.
    backend: String,
    threads: usize,
    median_ms: f64,
    min_ms: f64,
    /// Median of integral image + detection alone.
    detect_ms: f64,
    features: usize,
}

/// Brute-force matching of one image's upright features against its oriented ones (ratio 0.8,
/// Laplacian gate): the matcher's cost on a frame's worth of features, CPU beside GPU.
#[derive(serde::Serialize)]
struct MatchTiming {
    image: String,
    query: usize,
    train: usize,
    /// `cpu`, or `gpu: <adapter>`.
    backend: String,
    threads: usize,
    median_ms: f64,
    matches: usize,
}

#[derive(serde::Serialize)]
struct QualityRow {
    change: String,
    repeatability: f64,
    n1: usize,
    n2: usize,
    ms_usurf64: f64,
    ms_surf64: f64,
    ms_surf128: f64,
    ms_surf36: f64,
}

pub fn run(args: BenchArgs) -> anyhow::Result<ExitCode> {
    match args.what {
        BenchWhat::Surf(a) => run_surf(a),
        BenchWhat::Pose(a) => run_pose(a),
        BenchWhat::Render(a) => run_render(a),
        BenchWhat::Fix(a) => super::bench_fix::run(a),
        BenchWhat::Vo(a) => super::bench_vo::run(a),
        BenchWhat::Dtm(a) => super::bench_dtm::run(a),
        BenchWhat::Demo(a) => super::bench_demo::run(a),
    }
}

fn run_pose(a: PoseBenchArgs) -> anyhow::Result<ExitCode> {
    if a.trials == 0 {
        bail!("--trials must be at least 1");
    }
    for r in visnav::pose::bench::bench_suite(a.trials) {
        println!("{r}");
    }
    Ok(ExitCode::SUCCESS)
}

fn run_render(a: RenderBenchArgs) -> anyhow::Result<ExitCode> {
    use visnav::geo::dem::Dem;
    use visnav::geo::geotiff::load_geotiff;
    use visnav::sitl::render::{ColourMode, RenderSpec, Scene, bench_drone, bench_vga};
    if a.iterations == 0 || !(a.agl_m.is_finite() && a.agl_m > 10.0) {
        bail!("--iterations must be at least 1 and --agl-m a height above 10 m");
    }
    let mut scenes = Vec::new();
    let naip = repo_file("sitl/maps/naip_nd_2014.tif");
    let ortho = load_geotiff(&naip, None).with_context(|| format!("{}", naip.display()))?;
    scenes.push(("NAIP 2014, flat ground 580 m", ortho, Dem::flat(580.0)?));
    // An orthophoto and its DEM from the shared data folder.
    let load = |dir: &std::path::Path, ortho: &str, dem: &str| -> anyhow::Result<_> {
        let (o, d) = (dir.join(ortho), dir.join(dem));
        let ortho = load_geotiff(&o, None).with_context(|| format!("{}", o.display()))?;
        let dem =
            visnav::geo::dem::load_dem(&d, None).with_context(|| format!("{}", d.display()))?;
        Ok((ortho, dem))
    };
    let ngi = repo_file("../shared/data/ngi_3324c");
    if ngi.is_dir() {
        let (ortho, dem) = load(&ngi, "ngi_ortho_5m_tile1.tif", "dem.tif")?;
        scenes.push(("NGI 5 m ortho, 24 m DEM", ortho, dem));
    } else {
        eprintln!("skipping the NGI scene: {} not found", ngi.display());
    }
    let print = |name: &str, label: &str, agl_m: f64, t: &visnav::sitl::render::RenderTiming| {
        println!(
            "render {name}, {label}: {}x{} at {} m AGL  geometry min {:.1} / median {:.1} ms  effects min {:.1} / median {:.1} ms  valid {:.1} %",
            t.width,
            t.height,
            agl_m,
            t.radiance_min_ms,
            t.radiance_median_ms,
            t.photometric_min_ms,
            t.photometric_median_ms,
            100.0 * t.valid_fraction
        );
    };
    for (name, ortho, dem) in scenes {
        let scene = Scene::new(&ortho, dem, ColourMode::Grey)?;
        for (label, spec) in [
            ("clean", RenderSpec::clean()),
            ("default spec", RenderSpec::default()),
        ] {
            let t = bench_vga(&scene, spec, a.agl_m, a.iterations)?;
            print(name, label, a.agl_m, &t);
        }
    }
    // The drone scenario's camera over the 0.3 m orthophoto on the 1 m lidar surface model.
    let autzen = repo_file("../shared/data/autzen");
    if autzen.is_dir() {
        let (ortho, dem) = load(
            &autzen,
            "autzen_ortho_0p3m_utm10n.tif",
            "autzen_dsm_1m_utm10n.tif",
        )?;
        let scene = Scene::new(&ortho, dem, ColourMode::Grey)?;
        let name = format!(
            "Autzen 0.3 m ortho, 1 m surface model, {} deg tilt",
            visnav::sitl::render::DRONE_BENCH_TILT_DEG
        );
        let t = bench_drone(&scene, RenderSpec::default(), a.iterations)?;
        print(
            &name,
            "default spec",
            visnav::sitl::render::DRONE_BENCH_AGL_M,
            &t,
        );
    } else {
        eprintln!("skipping the Autzen scene: {} not found", autzen.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// Median and minimum total ms, median detection ms (integral image + fast-Hessian), features.
fn time_one(
    pool: &rayon::ThreadPool,
    surf: &Surf,
    img: &GrayImage,
    runs: usize,
) -> (f64, f64, f64, usize) {
    pool.install(|| {
        let _ = surf.detect_and_describe(img); // warm-up
        let r: anyhow::Result<_> = time_runs(
            runs,
            || {
                let ii = IntegralImage::new(img);
                let kps = surf.detect(&ii);
                Ok((ii, kps))
            },
            |(ii, kps)| surf.describe(&ii, kps).len(),
        );
        r.unwrap_or((f64::NAN, f64::NAN, f64::NAN, 0))
    })
}

/// The matching rows of `--backend gpu`: per image, the CPU on each pool and the GPU.
fn match_timings(
    inputs: &[(String, GrayImage)],
    pools: &[(usize, rayon::ThreadPool)],
    gpu: &GpuBench,
    runs: usize,
    threshold: f32,
) -> anyhow::Result<Vec<MatchTiming>> {
    let mut out = Vec::new();
    for (name, img) in inputs {
        let features = |upright: bool| -> anyhow::Result<Features> {
            let surf = Surf::new(SurfParams {
                hessian_threshold: threshold,
                upright,
                ..SurfParams::default()
            })?;
            Ok(surf.detect_and_describe(img))
        };
        let (q, t) = (features(true)?, features(false)?);
        let p = MatchParams::default();
        let row =
            |backend: String, threads: usize, (median_ms, matches): (f64, usize)| MatchTiming {
                image: name.clone(),
                query: q.len(),
                train: t.len(),
                backend,
                threads,
                median_ms,
                matches,
            };
        for (n, pool) in pools {
            let r = pool.install(|| {
                time_runs(runs, || Ok(match_features(&q, &t, &p, None)?), |m| m.len())
            })?;
            out.push(row("cpu".into(), *n, (r.0, r.3)));
        }
        let (label, timing) = gpu.time_match(&q, &t, &p, runs)?;
        let threads = pools.last().map_or(1, |(n, _)| *n);
        out.push(row(label, threads, timing));
    }
    Ok(out)
}

/// `runs` timed runs of `detect` then `describe`: median and minimum total ms, median detection
/// ms, and the last run's feature count.
fn time_runs<T>(
    runs: usize,
    mut detect: impl FnMut() -> anyhow::Result<T>,
    mut describe: impl FnMut(T) -> usize,
) -> anyhow::Result<(f64, f64, f64, usize)> {
    let mut times = Vec::with_capacity(runs);
    let mut det_times = Vec::with_capacity(runs);
    let mut n = 0;
    for _ in 0..runs.max(1) {
        let t = Instant::now();
        let d = detect()?;
        let t_det = t.elapsed();
        n = describe(d);
        times.push(t.elapsed().as_secs_f64() * 1e3);
        det_times.push(t_det.as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    det_times.sort_by(f64::total_cmp);
    Ok((
        times[times.len() / 2],
        times[0],
        det_times[det_times.len() / 2],
        n,
    ))
}

fn run_surf(a: SurfBenchArgs) -> anyhow::Result<ExitCode> {
    let images = if a.image.is_empty() {
        let dir = repo_file("../shared/data/bench");
        let v = vec![
            dir.join("naip2014_640x480.png"),
            dir.join("naip2014_1280x960.png"),
        ];
        for p in &v {
            if !p.exists() {
                bail!(
                    "{}: bench image missing (expected ../shared/data/bench; pass --image FILE)",
                    p.display()
                );
            }
        }
        v
    } else {
        a.image.clone()
    };
    if !["both", "upright", "oriented"].contains(&a.mode.as_str()) {
        bail!(
            "--mode {}: expected both, upright or oriented",
            visnav_core::text::quote(&a.mode)
        );
    }
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    let pools = [1, all]
        .into_iter()
        .map(|n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map(|p| (n, p))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let gpu = open_gpu(&a.backend)?;
    let mut inputs = Vec::new();
    for path in &images {
        inputs.push((path.display().to_string(), GrayImage::load(path)?));
    }
    if gpu.is_some()
        && let Some((name, hd)) = inputs
            .iter()
            .find(|(_, i)| i.width() == 1280 && i.height() == 960)
            .map(|(n, i)| (format!("{n} resampled"), hd_from_1280x960(i)))
    {
        inputs.push((name, hd?));
    }
    let mut timings = Vec::new();
    let mut stage_rows = Vec::new();
    for (path, img) in &inputs {
        let path = Path::new(path);
        let img = img.clone();
        for (mode, upright) in [("upright", true), ("oriented", false)] {
            if a.mode != "both" && a.mode != mode {
                continue;
            }
            let surf = Surf::new(SurfParams {
                hessian_threshold: a.threshold,
                upright,
                init_sample_step: a.init_step,
                n_octave_layers: a.octave_layers,
                ..SurfParams::default()
            })?;
            if let Some(dir) = &a.export_features {
                export_features(dir, path, mode, &surf, &img, a.threshold)?;
            }
            if a.stages
                && let Some((_, one)) = pools.first()
            {
                let (stages_ms, total_ms, features) =
                    super::bench_surf_stages::time_stages(one, &surf, &img, a.runs);
                stage_rows.push(super::bench_surf_stages::StageTiming {
                    image: path.display().to_string(),
                    mode,
                    features,
                    stages_ms,
                    total_ms,
                });
            }
            for (n, pool) in &pools {
                let (median, min, detect, feats) = time_one(pool, &surf, &img, a.runs);
                timings.push(Timing {
                    image: path.display().to_string(),
                    width: img.width(),
                    height: img.height(),
                    mode,
                    backend: "cpu".into(),
                    threads: *n,
                    median_ms: median,
                    min_ms: min,
                    detect_ms: detect,
                    features: feats,
                });
            }
            if let Some(g) = &gpu {
                let (median, min, detect, feats, backend) = g.time(&surf, &img, a.runs)?;
                timings.push(Timing {
                    image: path.display().to_string(),
                    width: img.width(),
                    height: img.height(),
                    mode,
                    backend,
                    threads: all,
                    median_ms: median,
                    min_ms: min,
                    detect_ms: detect,
                    features: feats,
                });
            }
        }
    }
    let matching = match &gpu {
        Some(g) => match_timings(&inputs, &pools, g, a.runs.min(5), a.threshold)?,
        None => Vec::new(),
    };
    let quality = if a.quality || a.export_pairs.is_some() {
        Some(quality_table(&a, a.export_pairs.as_deref())?)
    } else {
        None
    };
    if a.json {
        let doc = serde_json::json!({
            "surf": timings,
            "stages": stage_rows,
            "match": matching,
            "quality": quality,
        });
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        println!(
            "SURF-64 detect+describe, hessian_threshold {}, median of {} runs",
            a.threshold, a.runs
        );
        if let Some(g) = &gpu {
            println!("GPU adapter: {}", g.describe());
            println!(
                "  gpu rows: every stage on the GPU (integral image, response layers, extrema, orientation, descriptors); the host sorts and selects the keypoints"
            );
        }
        println!(
            "{:<38} {:>9} {:>8} {:>7} {:>7} {:>10} {:>10} {:>8}",
            "image", "size", "mode", "backend", "threads", "median ms", "detect ms", "features"
        );
        for t in &timings {
            let name = Path::new(&t.image)
                .file_name()
                .map_or(t.image.clone(), |s| s.to_string_lossy().into_owned());
            println!(
                "{:<38} {:>9} {:>8} {:>7} {:>7} {:>10.2} {:>10.2} {:>8}",
                name,
                format!("{}x{}", t.width, t.height),
                t.mode,
                if t.backend == "cpu" { "cpu" } else { "gpu" },
                t.threads,
                t.median_ms,
                t.detect_ms,
                t.features
            );
        }
        if a.stages {
            super::bench_surf_stages::print(&stage_rows, a.runs);
        }
        if !matching.is_empty() {
            println!();
            println!(
                "matching, brute force (upright against oriented SURF-64 of one image, ratio 0.8, Laplacian gate), median of {} runs",
                a.runs.min(5)
            );
            println!(
                "{:<38} {:>13} {:>7} {:>7} {:>10} {:>8}",
                "image", "features", "backend", "threads", "median ms", "matches"
            );
            for m in &matching {
                let name = Path::new(&m.image)
                    .file_name()
                    .map_or(m.image.clone(), |s| s.to_string_lossy().into_owned());
                println!(
                    "{:<38} {:>13} {:>7} {:>7} {:>10.2} {:>8}",
                    name,
                    format!("{}x{}", m.query, m.train),
                    if m.backend == "cpu" { "cpu" } else { "gpu" },
                    m.threads,
                    m.median_ms,
                    m.matches
                );
            }
        }
        if let Some(q) = &quality {
            println!();
            println!(
                "| change | n1 | n2 | repeatability | MS U-SURF-64 | MS SURF-64 | MS SURF-128 | MS SURF-36 |"
            );
            println!("|---|---|---|---|---|---|---|---|");
            for r in q {
                println!(
                    "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} |",
                    r.change,
                    r.n1,
                    r.n2,
                    r.repeatability,
                    r.ms_usurf64,
                    r.ms_surf64,
                    r.ms_surf128,
                    r.ms_surf36
                );
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Keypoints as `[x, y, size, scale, orientation_rad, laplacian, response, octave]` rows.
fn keypoint_rows(f: &Features) -> Vec<[f32; 8]> {
    f.keypoints
        .iter()
        .map(|k| {
            [
                k.x,
                k.y,
                k.size,
                k.scale,
                k.orientation_rad,
                f32::from(k.laplacian),
                k.response,
                f32::from(k.octave),
            ]
        })
        .collect()
}

/// `<dir>/<image stem>_<mode>.json`: parameters, keypoints and descriptors of one image.
fn export_features(
    dir: &Path,
    image: &Path,
    mode: &str,
    surf: &Surf,
    img: &GrayImage,
    threshold: f32,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    let f = surf.detect_and_describe(img);
    let stem = image
        .file_stem()
        .map_or("image".into(), |s| s.to_string_lossy().into_owned());
    let desc: Vec<&[f32]> = (0..f.len()).map(|i| f.descriptor(i)).collect();
    let doc = serde_json::json!({
        "image": image.display().to_string(),
        "mode": mode,
        "params": surf.params(),
        "hessian_threshold": threshold,
        "columns": ["x", "y", "size", "scale", "orientation_rad", "laplacian", "response", "octave"],
        "keypoints": keypoint_rows(&f),
        "descriptors": desc,
    });
    let path = dir.join(format!("{stem}_{mode}.json"));
    std::fs::write(&path, serde_json::to_string(&doc)?)
        .with_context(|| format!("{}: cannot write", path.display()))?;
    Ok(())
}

/// Write the descriptors of `f` as little-endian f32 rows of `kind().len()` values.
fn write_descriptors(path: &Path, f: &Features) -> anyhow::Result<()> {
    let mut bytes = Vec::with_capacity(f.len() * f.kind().len() * 4);
    for i in 0..f.len() {
        for v in f.descriptor(i) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).with_context(|| format!("{}: cannot write", path.display()))
}

/// The quality table of docs/surf.md: the standard changes on a 320x320 window of the 2014 map and
/// the 2009-vs-2014 pair; optionally exported for scripts/bench_opencv.py.
fn quality_table(a: &SurfBenchArgs, export: Option<&Path>) -> anyhow::Result<Vec<QualityRow>> {
    let p14 = repo_file("sitl/maps/naip_nd_2014.tif");
    let p09 = repo_file("sitl/maps/naip_nd_2009.tif");
    let m14 = GrayImage::load(&p14)?;
    let m09 = GrayImage::load(&p09)?;
    let window = (307, 202, 320, 320);
    let mut pairs = Vec::new();
    for c in eval::standard_changes() {
        pairs.push(eval::make_pair(&m14, window, c)?);
    }
    let (x0, y0, w, h) = window;
    let crop = |m: &GrayImage| {
        m.crop(x0, y0, w, h)
            .context("quality window outside the map")
    };
    pairs.push(eval::ImagePair {
        label: "2009 vs 2014 (same window)".into(),
        img1: crop(&m09)?,
        img2: crop(&m14)?,
        h12: nalgebra::Matrix3::identity(),
    });
    let mk = |upright, descriptor| {
        Surf::new(SurfParams {
            hessian_threshold: a.threshold,
            upright,
            descriptor,
            init_sample_step: a.init_step,
            n_octave_layers: a.octave_layers,
            ..SurfParams::default()
        })
    };
    let configs = [
        mk(true, DescriptorKind::Surf64)?,
        mk(false, DescriptorKind::Surf64)?,
        mk(false, DescriptorKind::Surf128)?,
        mk(false, DescriptorKind::Surf36)?,
    ];
    if let Some(dir) = export {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("{}: cannot create", dir.display()))?;
    }
    let mut rows = Vec::new();
    let mut manifest = Vec::new();
    for (i, pair) in pairs.iter().enumerate() {
        let mut scores: Vec<PairScore> = Vec::new();
        let mut feats: Vec<(Features, Features)> = Vec::new();
        for s in &configs {
            let f1 = s.detect_and_describe(&pair.img1);
            let f2 = s.detect_and_describe(&pair.img2);
            scores.push(eval::score_pair(
                &f1,
                &f2,
                &pair.h12,
                (pair.img1.width(), pair.img1.height()),
                (pair.img2.width(), pair.img2.height()),
            )?);
            feats.push((f1, f2));
        }
        rows.push(QualityRow {
            change: pair.label.clone(),
            repeatability: scores[1].repeatability,
            n1: scores[1].n1,
            n2: scores[1].n2,
            ms_usurf64: scores[0].matching_score,
            ms_surf64: scores[1].matching_score,
            ms_surf128: scores[2].matching_score,
            ms_surf36: scores[3].matching_score,
        });
        if let Some(dir) = export {
            let f1 = dir.join(format!("pair{i:02}_1.png"));
            let f2 = dir.join(format!("pair{i:02}_2.png"));
            pair.img1.save_png(&f1)?;
            pair.img2.save_png(&f2)?;
            let kp = |f: &Features| -> Vec<[f32; 3]> {
                f.keypoints.iter().map(|k| [k.x, k.y, k.scale]).collect()
            };
            manifest.push(serde_json::json!({
                "label": pair.label,
                "img1": f1.file_name().map(|s| s.to_string_lossy().into_owned()),
                "img2": f2.file_name().map(|s| s.to_string_lossy().into_owned()),
                "h12": [pair.h12.row(0).iter().copied().collect::<Vec<_>>(),
                        pair.h12.row(1).iter().copied().collect::<Vec<_>>(),
                        pair.h12.row(2).iter().copied().collect::<Vec<_>>()],
                "surf_kp1": kp(&feats[1].0),
                "surf_kp2": kp(&feats[1].1),
                "surf_repeatability": scores[1].repeatability,
                "surf_matching_score": scores[1].matching_score,
                "usurf_matching_score": scores[0].matching_score,
                "keypoint_columns": ["x", "y", "size", "scale", "orientation_rad", "laplacian", "response", "octave"],
                "surf_keypoints1": keypoint_rows(&feats[1].0),
                "surf_keypoints2": keypoint_rows(&feats[1].1),
                "usurf_keypoints1": keypoint_rows(&feats[0].0),
                "usurf_keypoints2": keypoint_rows(&feats[0].1),
                "params": configs[1].params(),
            }));
            for (k, tag) in [(0, "usurf64"), (1, "surf64")] {
                write_descriptors(&dir.join(format!("pair{i:02}_1_{tag}.f32")), &feats[k].0)?;
                write_descriptors(&dir.join(format!("pair{i:02}_2_{tag}.f32")), &feats[k].1)?;
            }
        }
    }
    if let Some(dir) = export {
        let path = dir.join("pairs.json");
        std::fs::write(&path, serde_json::to_string_pretty(&manifest)?)
            .with_context(|| format!("{}: cannot write", path.display()))?;
    }
    Ok(rows)
}

/// A 1920 x 1080 frame from a 1280 x 960 one: its middle 1280 x 720 rows, resampled by 1.5
/// (bilinear). The HD size the GPU SURF targets are timed at (docs/status.md).
fn hd_from_1280x960(img: &GrayImage) -> anyhow::Result<GrayImage> {
    let (w, h) = (1920usize, 1080usize);
    let top = 120.0f32;
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        let sy = (top + (y as f32 + 0.5) / 1.5 - 0.5).clamp(0.0, (img.height() - 1) as f32);
        let (y0, fy) = (sy.floor() as usize, sy.fract());
        let y1 = (y0 + 1).min(img.height() - 1);
        for x in 0..w {
            let sx = ((x as f32 + 0.5) / 1.5 - 0.5).clamp(0.0, (img.width() - 1) as f32);
            let (x0, fx) = (sx.floor() as usize, sx.fract());
            let x1 = (x0 + 1).min(img.width() - 1);
            let a = img.get(x0, y0) * (1.0 - fx) + img.get(x1, y0) * fx;
            let b = img.get(x0, y1) * (1.0 - fx) + img.get(x1, y1) * fx;
            data.push(a * (1.0 - fy) + b * fy);
        }
    }
    Ok(GrayImage::new(w, h, data)?)
}

/// The GPU of `--backend gpu` (None for `cpu`).
#[cfg(feature = "gpu")]
fn open_gpu(backend: &str) -> anyhow::Result<Option<GpuBench>> {
    if backend != "gpu" {
        return Ok(None);
    }
    let g = visnav::gpu::GpuSurf::new(visnav::gpu::AdapterPolicy::AllowSoftware)
        .context("--backend gpu")?;
    Ok(Some(GpuBench(g)))
}

#[cfg(not(feature = "gpu"))]
fn open_gpu(backend: &str) -> anyhow::Result<Option<GpuBench>> {
    if backend == "gpu" {
        bail!(
            "--backend gpu: this visnav is built without the GPU path; build it with `cargo build --release --features gpu`"
        );
    }
    Ok(None)
}

/// The GPU path under timing.
#[cfg(feature = "gpu")]
struct GpuBench(visnav::gpu::GpuSurf);

#[cfg(not(feature = "gpu"))]
enum GpuBench {}

/// Median and minimum total ms, median detection ms, features, and the backend's label.
type GpuTiming = (f64, f64, f64, usize, String);

impl GpuBench {
    #[cfg(feature = "gpu")]
    fn describe(&self) -> String {
        self.0.adapter().to_string()
    }

    #[cfg(feature = "gpu")]
    fn time(&self, surf: &Surf, img: &GrayImage, runs: usize) -> anyhow::Result<GpuTiming> {
        let g = &self.0;
        let _ = g.detect_and_describe(surf, img)?; // warm-up (pipelines, buffers)
        // Every stage is on the GPU, on buffers kept between frames: the whole path and the
        // detection alone are timed in separate runs.
        let (median, min, _, n) =
            time_runs(runs, || Ok(g.detect_and_describe(surf, img)?), |f| f.len())?;
        let (detect, _, _, _) = time_runs(runs, || Ok(g.detect(surf, img)?), |k| k.len())?;
        Ok((median, min, detect, n, format!("gpu: {}", g.adapter())))
    }

    /// Median ms and match count of the GPU's matching.
    #[cfg(feature = "gpu")]
    fn time_match(
        &self,
        q: &Features,
        t: &Features,
        p: &MatchParams,
        runs: usize,
    ) -> anyhow::Result<(String, (f64, usize))> {
        let g = &self.0;
        let _ = g.match_features(q, t, p, None)?; // warm-up
        let r = time_runs(runs, || Ok(g.match_features(q, t, p, None)?), |m| m.len())?;
        Ok((format!("gpu: {}", g.adapter()), (r.0, r.3)))
    }

    #[cfg(not(feature = "gpu"))]
    fn describe(&self) -> String {
        match *self {}
    }

    #[cfg(not(feature = "gpu"))]
    fn time_match(
        &self,
        _: &Features,
        _: &Features,
        _: &MatchParams,
        _: usize,
    ) -> anyhow::Result<(String, (f64, usize))> {
        match *self {}
    }

    #[cfg(not(feature = "gpu"))]
    fn time(&self, _: &Surf, _: &GrayImage, _: usize) -> anyhow::Result<GpuTiming> {
        match *self {}
    }
}
