//! `visnav bench vo [--runs N] [--json]`: visual odometry (docs/vo.md) on real frames and its cost.
//! NGI 3324C frames 0182 -> 0184 with measured poses (`../shared/data/ngi_3324c`): the 2.6 km
//! baseline's direction and length error (`visnav::sitl::vo_eval::ngi_vo`); and the per-frame time
//! on one thread of corners, tracking and motion on a VGA pair made from a real NAIP frame by a
//! known motion (`vga_vo`), beside SURF matched between the same frames instead of tracked
//! (`vga_surf_vo`, the other candidate method). Build with `--release`.

use std::process::ExitCode;

use anyhow::{Context, bail};
use visnav::sitl::vo_eval::{NgiVo, VgaSurfVo, VgaVo, ngi_vo, vga_surf_vo, vga_vo};

use super::repo_file;

#[derive(clap::Args, Debug)]
pub struct VoBenchArgs {
    /// Frames of the VGA sequence (the per-frame median and 95th percentile are reported).
    #[arg(long, default_value_t = 40)]
    pub frames: usize,
    /// Print one JSON document instead of a summary.
    #[arg(long)]
    pub json: bool,
}

#[derive(serde::Serialize)]
struct VoBench {
    /// NGI 0182 -> 0184 (absent without ../shared/data).
    ngi_dir_err_deg: Option<f64>,
    ngi_len_err_pct: Option<f64>,
    /// VGA frame on one thread, ms.
    ms_p50_vga: f64,
    /// The same with SURF matched between the frames instead of tracked, ms.
    ms_p50_vga_surf: f64,
    ngi: Option<NgiVo>,
    vga: VgaVo,
    vga_surf: VgaSurfVo,
}

pub fn run(a: VoBenchArgs) -> anyhow::Result<ExitCode> {
    if !(2..=60).contains(&a.frames) {
        bail!("--frames must be in 2..=60 (the sequence stays over the photo)");
    }
    let ngi_dir = repo_file("../shared/data/ngi_3324c");
    let ngi = if ngi_dir.join("frames_truth.csv").is_file() {
        Some(ngi_vo(&ngi_dir).with_context(|| format!("NGI frames in {}", ngi_dir.display()))?)
    } else {
        eprintln!("SKIP NGI: {} not found", ngi_dir.display());
        None
    };
    let bench = repo_file("../shared/data/bench/naip2014_1280x960.png");
    // One thread: the per-frame cost on one core.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let vga = pool
        .install(|| vga_vo(&bench, a.frames))
        .with_context(|| format!("VGA sequence over {}", bench.display()))?;
    let vga_surf = pool
        .install(|| vga_surf_vo(&bench, a.frames))
        .with_context(|| format!("VGA sequence over {} (SURF)", bench.display()))?;
    let out = VoBench {
        ngi_dir_err_deg: ngi.as_ref().map(|n| n.dir_err_deg),
        ngi_len_err_pct: ngi.as_ref().map(|n| n.len_err_pct),
        ms_p50_vga: vga.ms_p50,
        ms_p50_vga_surf: vga_surf.ms_p50,
        ngi,
        vga,
        vga_surf,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(ExitCode::SUCCESS);
    }
    if let Some(n) = &out.ngi {
        println!(
            "NGI 0182 -> 0184 ({:.0} m baseline): direction error {:.3} deg, length error {:+.3} % (targets 0.5 deg, 1 %); sigma along {:.1} m, across {:.1} m; {} matches, {} inliers, rms {:.2} px",
            n.truth_dp_m[0].hypot(n.truth_dp_m[1]),
            n.dir_err_deg,
            n.len_err_pct,
            n.sigma_along_m,
            n.sigma_across_m,
            n.matches,
            n.inliers,
            n.rms_px
        );
    }
    let v = &out.vga;
    println!(
        "VGA, one thread, per frame: p50 {:.2} ms, p95 {:.2} ms, min {:.2} ms (target 5 ms; pyramid {:.2}, tracking forward + backward {:.2}, motion {:.2}, new corners {:.2} on {} of {} frames); {:.0} tracks, {:.0} inliers per frame; step error median {:.3} m (max {:.3}, {:.2} sigma) of {:.2} m; chained alone over {:.0} m: {:.2} m",
        v.ms_p50,
        v.ms_p95,
        v.ms_min,
        v.ms_pyramid,
        v.ms_track,
        v.ms_motion,
        v.ms_replenish,
        v.replenished,
        v.frames,
        v.tracks_mean,
        v.inliers_mean,
        v.step_err_m_p50,
        v.step_err_m_max,
        v.step_err_over_sigma_p50,
        v.step_m,
        v.distance_m,
        v.chained_err_m
    );
    let w = &out.vga_surf;
    println!(
        "VGA with SURF matched between the frames instead, same thread: p50 {:.2} ms, p95 {:.2} ms (SURF {:.2}, matching {:.2}, motion {:.2}); {:.0} matches, {:.0} inliers per frame; step error median {:.3} m (max {:.3})",
        w.ms_p50,
        w.ms_p95,
        w.ms_surf,
        w.ms_match,
        w.ms_motion,
        w.matches_mean,
        w.inliers_mean,
        w.step_err_m_p50,
        w.step_err_m_max
    );
    Ok(ExitCode::SUCCESS)
}
