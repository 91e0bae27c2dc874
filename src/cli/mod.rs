//! Subcommand implementations of the `visnav` binary.

#[cfg(feature = "sim")]
pub mod bench;
#[cfg(feature = "sim")]
pub mod bench_demo;
#[cfg(feature = "sim")]
pub mod bench_dtm;
#[cfg(feature = "sim")]
pub mod bench_fix;
#[cfg(feature = "sim")]
pub mod bench_surf_stages;
#[cfg(feature = "sim")]
pub mod bench_vo;
pub mod camera;
pub mod check_config;
pub mod config;
pub mod fix;
pub mod map;
pub mod overrides;
pub mod replay;
pub mod run;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(feature = "sim")]
pub mod sim_standalone;
#[cfg(feature = "sim")]
pub mod sitl_run;

/// A file of the repository (`sitl/maps/...`, `../shared/data/...`): relative to the working
/// directory when it exists there, else to the source tree the binary was built from.
#[cfg(feature = "sim")]
pub fn repo_file(rel: &str) -> std::path::PathBuf {
    let cwd = std::path::PathBuf::from(rel);
    if cwd.exists() {
        return cwd;
    }
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

/// Initialise `tracing` to stderr: `RUST_LOG` when set, otherwise info/debug/trace by `-v` count.
/// Colours only when stderr is a terminal (a redirected log or journald gets plain text).
pub fn init_logging(verbose: u8) {
    use std::io::IsTerminal;
    use tracing_subscriber::EnvFilter;
    let default = match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();
}
