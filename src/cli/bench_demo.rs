//! `visnav bench demo [--scenario F] [--seeds N] [--first-seed S] [--jobs J] [--out DIR] [--json]`:
//! the demo's seed sweep. Runs the closed-loop scenario (default: the bundled demo,
//! sitl/scenarios/closed_loop_demo.toml) once per seed (`visnav sim --seed N --json`, each in its
//! own process, `--jobs` at a time; lock-step, so a seed's figures do not depend on the load),
//! and prints per seed the fix rate, the injected position error (median / p90 / max) beside the
//! no-vision control's p90, their ratio, and whether the demo's target holds: a fix rate of at
//! least [`TARGET_FIX_RATE`] and an injected p90 of at most [`TARGET_P90_RATIO`] x the control's.
//! Each run's report folder is kept under `--out` (default: a fresh `sim-report/bench-demo`).

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

use anyhow::{Context, bail};

/// The demo's target (docs/status.md): at least 9 frames in 10 give an accepted fix...
pub const TARGET_FIX_RATE: f64 = 0.9;
/// ... and the injected error's p90 is at most a tenth of what the IMU alone drifts.
pub const TARGET_P90_RATIO: f64 = 0.1;

#[derive(clap::Args, Debug)]
pub struct DemoBenchArgs {
    /// Closed-loop scenario (default: the bundled demo).
    #[arg(long)]
    pub scenario: Option<PathBuf>,
    /// Number of seeds.
    #[arg(long, default_value_t = 10)]
    pub seeds: u64,
    /// The first seed (the sweep runs first-seed .. first-seed + seeds - 1).
    #[arg(long, default_value_t = 1)]
    pub first_seed: u64,
    /// Runs at a time (each is one process on about one core).
    #[arg(long, default_value_t = 2)]
    pub jobs: usize,
    /// Folder for the runs' report folders (default: a fresh sim-report/bench-demo).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print one JSON document instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One seed's figures.
#[derive(serde::Serialize, Clone, Debug)]
struct SeedRow {
    seed: u64,
    fix_rate: f64,
    nav_p50_m: f64,
    nav_p90_m: f64,
    nav_max_m: f64,
    control_p90_m: f64,
    /// Injected p90 over the control's p90.
    p90_ratio: f64,
    target_met: bool,
}

#[derive(serde::Serialize)]
struct DemoBench {
    scenario: String,
    target: String,
    seeds: Vec<SeedRow>,
    target_met_on: usize,
    worst_fix_rate: f64,
    worst_p90_ratio: f64,
}

pub fn run(a: DemoBenchArgs) -> anyhow::Result<ExitCode> {
    if !(1..=100).contains(&a.seeds) {
        bail!("--seeds must be in 1..=100");
    }
    if !(1..=16).contains(&a.jobs) {
        bail!("--jobs must be in 1..=16");
    }
    let scenario = a
        .scenario
        .clone()
        .unwrap_or_else(super::sim::default_scenario);
    if !scenario.is_file() {
        bail!("scenario {}: no such file", scenario.display());
    }
    let out = match a.out.clone() {
        Some(o) => {
            std::fs::create_dir_all(&o)
                .with_context(|| format!("report folder {}: cannot create it", o.display()))?;
            o
        }
        None => super::sim::fresh_report_dir(Path::new("sim-report/bench-demo"))
            .context("report folder sim-report/bench-demo")?,
    };
    let exe = std::env::current_exe().context("cannot find the visnav executable")?;
    let seeds: Vec<u64> = (a.first_seed..a.first_seed + a.seeds).collect();
    let mut rows = Vec::new();
    for chunk in seeds.chunks(a.jobs) {
        let runs: Vec<_> = chunk
            .iter()
            .map(|&s| spawn_seed(&exe, &scenario, s, &out))
            .collect::<anyhow::Result<_>>()?;
        for (seed, child) in chunk.iter().zip(runs) {
            let row = finish_seed(*seed, child)?;
            if !a.json {
                eprintln!(
                    "seed {seed}: fix rate {:.3}, p90 ratio {:.3}",
                    row.fix_rate, row.p90_ratio
                );
            }
            rows.push(row);
        }
    }
    let doc = DemoBench {
        scenario: scenario.display().to_string(),
        target: format!(
            "fix rate >= {TARGET_FIX_RATE} and injected p90 <= {TARGET_P90_RATIO} x the no-vision control's p90"
        ),
        target_met_on: rows.iter().filter(|r| r.target_met).count(),
        worst_fix_rate: rows
            .iter()
            .map(|r| r.fix_rate)
            .fold(f64::INFINITY, f64::min),
        worst_p90_ratio: rows.iter().map(|r| r.p90_ratio).fold(0.0, f64::max),
        seeds: rows,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&doc)?);
    } else {
        print_table(&doc, &out);
    }
    Ok(ExitCode::SUCCESS)
}

/// Start `visnav sim --scenario F --seed N --json --out OUT/seed-N`.
fn spawn_seed(
    exe: &Path,
    scenario: &Path,
    seed: u64,
    out: &Path,
) -> anyhow::Result<std::process::Child> {
    Command::new(exe)
        .arg("sim")
        .arg("--scenario")
        .arg(scenario)
        .args(["--seed", &seed.to_string(), "--json", "--out"])
        .arg(out.join(format!("seed-{seed}")))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .with_context(|| format!("cannot start {} sim (seed {seed})", exe.display()))
}

/// Wait for one seed's run and read its summary.
fn finish_seed(seed: u64, child: std::process::Child) -> anyhow::Result<SeedRow> {
    let res = child
        .wait_with_output()
        .with_context(|| format!("seed {seed}: the simulation did not finish"))?;
    if !res.status.success() {
        let err = String::from_utf8_lossy(&res.stderr);
        let last: Vec<&str> = err.lines().rev().take(5).collect();
        bail!(
            "seed {seed}: visnav sim failed: {}",
            last.into_iter().rev().collect::<Vec<_>>().join("\n")
        );
    }
    let v: serde_json::Value = serde_json::from_slice(&res.stdout)
        .with_context(|| format!("seed {seed}: the summary is not JSON"))?;
    let num = |key: &str, field: Option<&str>| -> anyhow::Result<f64> {
        let x = match field {
            Some(f) => &v[key][f],
            None => &v[key],
        };
        x.as_f64()
            .with_context(|| format!("seed {seed}: the summary has no number {key}"))
    };
    let (nav_p90_m, control_p90_m) = (
        num("nav_err_m", Some("p90"))?,
        num("control_err_m", Some("p90"))?,
    );
    let fix_rate = num("fix_rate", None)?;
    let p90_ratio = nav_p90_m / control_p90_m;
    Ok(SeedRow {
        seed,
        fix_rate,
        nav_p50_m: num("nav_err_m", Some("median"))?,
        nav_p90_m,
        nav_max_m: num("nav_err_m", Some("max"))?,
        control_p90_m,
        p90_ratio,
        target_met: fix_rate >= TARGET_FIX_RATE && p90_ratio <= TARGET_P90_RATIO,
    })
}

fn print_table(doc: &DemoBench, out: &Path) {
    println!("scenario {}", doc.scenario);
    println!("target: {}", doc.target);
    println!(
        "seed  fix rate  injected error p50 / p90 / max [m]  control p90 [m]  p90 ratio  target"
    );
    for r in &doc.seeds {
        println!(
            "{:>4}  {:>8.3}  {:>10.1} / {:>5.1} / {:>5.1}          {:>9.1}      {:>7.3}    {}",
            r.seed,
            r.fix_rate,
            r.nav_p50_m,
            r.nav_p90_m,
            r.nav_max_m,
            r.control_p90_m,
            r.p90_ratio,
            if r.target_met { "met" } else { "MISSED" }
        );
    }
    println!(
        "target met on {} of {} seeds; worst fix rate {:.3}, worst p90 ratio {:.3}",
        doc.target_met_on,
        doc.seeds.len(),
        doc.worst_fix_rate,
        doc.worst_p90_ratio
    );
    println!("reports: {}", out.display());
}
