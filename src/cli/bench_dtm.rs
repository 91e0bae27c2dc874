//! `visnav bench dtm [--runs N] [--pairs N] [--json]`: DTM navigation (docs/dtm.md), the pose from
//! optical flow and the terrain model alone (`visnav::sitl::dtm_eval`). NGI 3324C frame 0182's
//! pose from its flow to frame 0184 and the 24 m DEM against the measured pose, with the claimed
//! sigma (`ngi_err_m`, `ngi_sigma_m`: the 1-sigma along the error's direction); flat ground (a
//! real NAIP photo laid flat, VGA pairs): how many solutions were accepted (`flat_accepted`, due
//! 0) and why the rest were refused; the solve time per frame pair on one core (`ms_p50`: the
//! NGI pair, median of `--runs`). Build with `--release`.

use std::process::ExitCode;

use anyhow::{Context, bail};
use visnav::sitl::dtm_eval::{
    FlatDtm, NGI_GUESS, NgiDtm, NgiOrder, SweepCase, flat_dtm, ngi_dtm, ngi_sweep,
};
use visnav::stats::percentile;

use super::repo_file;

#[derive(clap::Args, Debug)]
pub struct DtmBenchArgs {
    /// Timed NGI solutions (the median is reported).
    #[arg(long, default_value_t = 5)]
    pub runs: usize,
    /// Flat-ground frame pairs.
    #[arg(long, default_value_t = 20)]
    pub pairs: usize,
    /// Print one JSON document instead of a summary.
    #[arg(long)]
    pub json: bool,
    /// Solve frame 0184's pose from its flow back to 0182 (the pair in the other order).
    #[arg(long)]
    pub reverse: bool,
    /// Also solve from guesses 200, 400 and 600 m off in 8 directions, in both frame orders,
    /// and count the accepted poses outside their claimed 3 sigma (`sweep_wrong`, due 0).
    #[arg(long)]
    pub sweep: bool,
}

/// The sweep's guess offsets, m, and directions.
const SWEEP_OFFSETS_M: [f64; 3] = [200.0, 400.0, 600.0];
const SWEEP_DIRECTIONS: usize = 8;

#[derive(serde::Serialize)]
struct DtmBench {
    /// NGI 0182 from flow + DEM (absent without ../shared/data): position error and its claimed
    /// 1-sigma along the error, m.
    ngi_err_m: Option<f64>,
    ngi_sigma_m: Option<f64>,
    /// Flat pairs accepted with the default settings (due 0).
    flat_accepted: usize,
    /// The frame order of `ngi_*`.
    order: NgiOrder,
    /// With `--sweep`: guesses solved, refused, and accepted outside their 3 sigma (due 0).
    sweep_solved: Option<usize>,
    sweep_refused: Option<usize>,
    sweep_wrong: Option<usize>,
    /// Solve time per frame pair on one core, median, ms (NGI; the flat pairs' when NGI is
    /// absent).
    ms_p50: f64,
    ngi: Option<NgiDtm>,
    flat: FlatDtm,
    sweep: Vec<SweepCase>,
}

pub fn run(a: DtmBenchArgs) -> anyhow::Result<ExitCode> {
    if !(1..=100).contains(&a.runs) {
        bail!("--runs must be in 1..=100");
    }
    if !(1..=40).contains(&a.pairs) {
        bail!("--pairs must be in 1..=40 (the sequence stays over the photo)");
    }
    // One thread: the cost on one core.
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let ngi_dir = repo_file("../shared/data/ngi_3324c");
    let order = if a.reverse {
        NgiOrder::Reverse
    } else {
        NgiOrder::Forward
    };
    let have_ngi = ngi_dir.join("frames_truth.csv").is_file();
    let ngi = if have_ngi {
        let runs: Vec<NgiDtm> = (0..a.runs)
            .map(|_| pool.install(|| ngi_dtm(&ngi_dir, &NGI_GUESS, order)))
            .collect::<Result<_, _>>()
            .with_context(|| format!("NGI frames in {}", ngi_dir.display()))?;
        let times: Vec<f64> = runs.iter().map(|r| r.ms_solve).collect();
        runs.into_iter()
            .next()
            .map(|r| (r, percentile(&times, 0.5)))
    } else {
        eprintln!("SKIP NGI: {} not found", ngi_dir.display());
        None
    };
    let photo = repo_file("../shared/data/bench/naip2014_1280x960.png");
    let flat = pool
        .install(|| flat_dtm(&photo, a.pairs))
        .with_context(|| format!("flat pairs over {}", photo.display()))?;
    let mut sweep = Vec::new();
    if a.sweep && have_ngi {
        for o in [NgiOrder::Forward, NgiOrder::Reverse] {
            let cases = ngi_sweep(&ngi_dir, o, &SWEEP_OFFSETS_M, SWEEP_DIRECTIONS)
                .with_context(|| format!("NGI sweep in {}", ngi_dir.display()))?;
            sweep.extend(cases);
        }
    }
    let count = |f: &dyn Fn(&SweepCase) -> bool| {
        a.sweep
            .then(|| sweep.iter().filter(|c| f(c)).count())
            .filter(|_| have_ngi)
    };
    let out = DtmBench {
        order,
        sweep_solved: count(&|c| c.solved.is_some()),
        sweep_refused: count(&|c| c.refused.is_some()),
        sweep_wrong: count(&|c| c.wrong()),
        ngi_err_m: ngi.as_ref().map(|(n, _)| n.err_norm_m),
        ngi_sigma_m: ngi.as_ref().map(|(n, _)| n.sigma_along_err_m),
        flat_accepted: flat.accepted,
        ms_p50: ngi.as_ref().map_or(flat.ms_solve_p50, |(_, ms)| *ms),
        ngi: ngi.map(|(n, _)| n),
        flat,
        sweep,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(ExitCode::SUCCESS);
    }
    if let Some(n) = &out.ngi {
        println!(
            "NGI {} and the 24 m DEM: position error {:.1} m ({:+.1} E, {:+.1} N, {:+.1} up) = {:.2} sigma (claimed {:.1} m along it; squared Mahalanobis distance {:.1}; sigma E/N/up {:.1}/{:.1}/{:.1} m, horizontal given the attitude {:.1} m); attitude error {:.3} deg (sigma {:.3}); guess was {:.0} m off; {} corners, {} flow vectors, {} inliers, rms {:.2} px, sigma0 {:.2}; {} in {} iterations; flow {:.0} ms, solve {:.1} ms (median of {} on one core: {:.1} ms)",
            out.order.label(),
            n.err_norm_m,
            n.err_m[0],
            n.err_m[1],
            n.err_m[2],
            n.err_over_sigma,
            n.sigma_along_err_m,
            n.err_mahalanobis2,
            n.sigma_m[0],
            n.sigma_m[1],
            n.sigma_m[2],
            n.sigma_h_given_attitude_m,
            n.att_err_deg,
            n.att_sigma_deg,
            n.guess_err_m,
            n.corners,
            n.tracks,
            n.inliers,
            n.rms_px,
            n.sigma0,
            n.method,
            n.iterations,
            n.ms_flow,
            n.ms_solve,
            a.runs,
            out.ms_p50
        );
    }
    if a.sweep && have_ngi {
        println!(
            "Sweep (guesses {} m off in {SWEEP_DIRECTIONS} directions, both orders): {} solved, {} refused, {} accepted outside 3 sigma (due 0)",
            visnav_core::text::numbers(&SWEEP_OFFSETS_M),
            out.sweep_solved.unwrap_or(0),
            out.sweep_refused.unwrap_or(0),
            out.sweep_wrong.unwrap_or(0)
        );
        for c in &out.sweep {
            let what = match (&c.solved, &c.refused) {
                (Some(r), _) => format!(
                    "{:.1} m off = {:.2} sigma along it, squared Mahalanobis {:.1}, largest axis {:.2} sigma (claimed E/N/up {:.1}/{:.1}/{:.1} m){}",
                    r.err_norm_m,
                    r.err_over_sigma,
                    r.err_mahalanobis2,
                    r.err_axis_sigmas,
                    r.sigma_m[0],
                    r.sigma_m[1],
                    r.sigma_m[2],
                    if c.wrong() { " WRONG" } else { "" }
                ),
                (None, Some(why)) => format!("refused: {why}"),
                (None, None) => "no outcome".to_string(),
            };
            println!(
                "  {} guess {:.0} m at {:.0} deg: {what}",
                c.order.label(),
                c.offset_m,
                c.direction_deg
            );
        }
    }
    let f = &out.flat;
    println!(
        "Flat ground (NAIP photo laid flat, {} VGA pairs, {:.0} flow vectors each): {} accepted (due 0), {} with the relief screen off; solve {:.1} ms median",
        f.pairs, f.tracks_mean, f.accepted, f.accepted_unscreened, f.ms_solve_p50
    );
    for r in &f.reasons {
        println!("  refused: {r}");
    }
    Ok(ExitCode::SUCCESS)
}
