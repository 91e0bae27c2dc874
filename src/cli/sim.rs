//! `visnav sim --scenario FILE [--json] [--monte-carlo N]`: run a SITL scenario through the
//! navigation filter, with vision and as the INS-only control, and print the errors against truth.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;
use visnav::sitl::Scenario;
use visnav::sitl::run::{RunOptions, TruthPlusNoise, VisionFixSource, monte_carlo, run};

#[derive(clap::Args, Debug)]
pub struct SimArgs {
    /// Scenario file (sitl/scenarios/*.toml). Default: the bundled seed GPS-outage experiment,
    /// sitl/scenarios/seed_outage.toml (looked up in the current folder, then in the source tree).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Print one JSON document on stdout.
    #[arg(long)]
    pub json: bool,
    /// Also run an N-run Monte Carlo (vision runs and their INS-only controls) and report the
    /// NEES consistency.
    #[arg(long, default_value_t = 0)]
    pub monte_carlo: usize,
}

pub fn run_cmd(args: SimArgs) -> anyhow::Result<ExitCode> {
    let path = args.scenario.clone().unwrap_or_else(default_scenario);
    let sc = Scenario::load(&path)?;
    let t0 = Instant::now();
    let vis = run(&sc, RunOptions::new(true, 0))?;
    let ins = run(&sc, RunOptions::new(false, 0))?;
    let single_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let mc = if args.monte_carlo > 0 {
        Some(monte_carlo(&sc, args.monte_carlo)?)
    } else {
        None
    };
    let mc_s = t1.elapsed().as_secs_f64();
    let vision_source = sc.vision.as_ref().map(|v| {
        format!(
            "{}; {} Hz, delivered {}-{} ms after capture and applied at capture time; true camera lever arm {:?} m body FRD, filter's {:?} m",
            TruthPlusNoise::from_config(v).describe(),
            v.rate_hz,
            v.latency_min_ms,
            v.latency_max_ms,
            v.lever_arm_body_frd_m,
            sc.nav.camera_lever_arm()
        )
    });
    let target = sc.evaluation.target_max_horiz_err_m;
    let doc = serde_json::json!({
        "scenario": sc.name,
        "description": sc.description,
        "vision_source": vision_source,
        "imu": sc.imu,
        "filter_states": sc.nav.n_states(),
        "evaluation_window_s": [sc.evaluation.from_s, sc.evaluation.until_s],
        "max_err_m": { "vision": vis.max_err_m, "ins_only": ins.max_err_m },
        "max_horiz_err_m": { "vision": vis.max_horiz_err_m, "ins_only": ins.max_horiz_err_m },
        "target_max_horiz_err_m": target,
        "target_met": target.map(|t| vis.max_horiz_err_m <= t),
        "reference": sc.reference,
        "vision_run": vis,
        "ins_only_run": ins,
        "monte_carlo": &mc,
        "runtime_s": { "two_runs": single_s, "monte_carlo": mc_s },
    });
    if args.json {
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        println!("scenario {}", sc.name);
        println!(
            "max error e/n/u [m]  vision: {:.2} / {:.2} / {:.2}   INS-only: {:.2} / {:.2} / {:.2}",
            vis.max_err_m.e,
            vis.max_err_m.n,
            vis.max_err_m.u,
            ins.max_err_m.e,
            ins.max_err_m.n,
            ins.max_err_m.u
        );
        println!(
            "max horizontal error [m]  vision: {:.2}  INS-only: {:.2}",
            vis.max_horiz_err_m, ins.max_horiz_err_m
        );
        if let Some(mc) = &mc {
            println!(
                "monte carlo, {} runs: max horizontal error with vision mean {:.2} m, median {:.2} m, worst {:.2} m, {} runs over target; INS-only mean {:.2} m",
                mc.runs,
                mc.mean_max_horiz_err_m,
                mc.median_max_horiz_err_m,
                mc.worst_max_horiz_err_m,
                mc.runs_over_target,
                mc.ins_only_mean_max_horiz_err_m
            );
            println!("NEES (run average; two-sided 95 % band; fraction of epochs inside):");
            for (name, s) in &mc.nees {
                if let Some(s) = s {
                    println!(
                        "  {name:<12} dof {:>2}  mean {:>7.3}  band [{:.3}, {:.3}]  {}  inside {:.0} %",
                        s.dof,
                        s.mean,
                        s.band_95[0],
                        s.band_95[1],
                        if s.mean_inside { "in " } else { "OUT" },
                        100.0 * s.fraction_inside
                    );
                }
            }
            let nse: Vec<String> = mc
                .state_nse_mean
                .iter()
                .map(|(n, v)| format!("{n} {v:.2}"))
                .collect();
            println!(
                "mean normalised squared error per state: {}",
                nse.join(", ")
            );
        }
        println!("runtime: two runs {single_s:.2} s, monte carlo {mc_s:.2} s");
    }
    Ok(ExitCode::SUCCESS)
}

/// The bundled default scenario: relative to the current folder (a checkout), else to the source
/// tree this binary was built from.
fn default_scenario() -> PathBuf {
    let rel = PathBuf::from("sitl/scenarios/seed_outage.toml");
    if rel.is_file() {
        rel
    } else {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(rel)
    }
}
