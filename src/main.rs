//! The `visnav` command-line interface (clap). Each subcommand lives in `src/cli/<name>.rs`;
//! this file only parses arguments, sets up logging and reports errors with context.

// Nothing from outside may be unwrapped (clippy.toml allows it in tests; the end-to-end tests
// in tests/ may unwrap too).
#![deny(clippy::unwrap_used, clippy::expect_used)]

mod cli;

use clap::{Parser, Subcommand};

/// `visnav --version`: the package version and the git commit it was built from (build.rs:
/// short hash, `-dirty` with uncommitted changes, `unknown` outside a git checkout), so a log or
/// a bug report names the exact source.
const VERSION: &str = concat!(
    env!("CARGO_PKG_VERSION"),
    " (commit ",
    env!("VISNAV_GIT_COMMIT"),
    ")"
);

#[derive(Parser, Debug)]
#[command(name = "visnav", version = VERSION, about = "Vision-aided navigation for drones without GPS", long_about = None)]
struct Args {
    /// More log output (-v: debug, -vv: trace). RUST_LOG overrides this when set.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Load and validate a configuration file, printing every problem found.
    CheckConfig(cli::check_config::CheckConfigArgs),
    /// The configuration's defaults and key reference (`config default`, `config reference`).
    Config(cli::config::ConfigArgs),
    /// Run a SITL scenario through the navigation filter and print errors against truth.
    #[cfg(feature = "sim")]
    Sim(cli::sim::SimArgs),
    /// One vision fix from one camera frame against a reference map.
    Fix(cli::fix::FixArgs),
    /// Camera calibration (`camera import`: an OpenCV / ROS / Kalibr calibration file as the
    /// configuration's [camera] section).
    Camera(cli::camera::CameraArgs),
    /// Benchmarks (`bench surf`: SURF speed, feature counts and quality table). They use the
    /// simulator's scenes and evaluation tooling, so they come with the `sim` feature.
    #[cfg(feature = "sim")]
    Bench(cli::bench::BenchArgs),
    /// Reference maps (`map build`: orthophoto + DEM -> .vnm; `map info`: print a map's header).
    Map(cli::map::MapArgs),
    /// Run the navigation service: autopilot link, navigation filter, injection.
    Run(cli::run::RunArgs),
    /// Run a recorded .tlog through the navigation filter offline: NIS per measurement type, resets.
    Replay(cli::replay::ReplayArgs),
    /// The service against a real ArduPilot/PX4 SITL, the camera rendered from the simulator's truth.
    #[cfg(feature = "sim")]
    SitlRun(cli::sitl_run::SitlRunArgs),
}

/// Counts the heap in use (`visnav_daemon::heap`): the soak's memory figures and
/// `visnav_heap_bytes`.
#[global_allocator]
static ALLOC: visnav_daemon::heap::CountingAlloc = visnav_daemon::heap::CountingAlloc;

/// At most this many glibc malloc arenas (its default is 8 per core). Freed memory stays in the
/// arena of the thread that used it, so with many arenas a long-running daemon's resident set
/// wanders with thread timing: the 1-hour soak measured +0.05 to +12.9 MB over 50 minutes with
/// the heap in use flat, and with 2 arenas 12-16 MB less resident at the same speed
/// (docs/status.md). A `MALLOC_ARENA_MAX` in the environment is left to glibc.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MALLOC_ARENAS: libc::c_int = 2;

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn limit_malloc_arenas() {
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        // SAFETY: mallopt only sets an allocator parameter; called before any thread exists.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, MALLOC_ARENAS);
        }
    }
}

fn main() -> std::process::ExitCode {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    limit_malloc_arenas();
    let args = Args::parse();
    cli::init_logging(args.verbose);
    let result = match args.command {
        Command::CheckConfig(a) => cli::check_config::run(a),
        Command::Config(a) => cli::config::run(a),
        #[cfg(feature = "sim")]
        Command::Sim(a) => cli::sim::run_cmd(a),
        #[cfg(feature = "sim")]
        Command::Bench(a) => cli::bench::run(a),
        Command::Fix(a) => cli::fix::run(a),
        Command::Camera(a) => cli::camera::run(a),
        Command::Map(a) => cli::map::run(a),
        Command::Run(a) => cli::run::run(a),
        #[cfg(feature = "sim")]
        Command::SitlRun(a) => cli::sitl_run::run(a),
        Command::Replay(a) => cli::replay::run(a),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
