//! The real-SITL recipe scripts (sitl/, docs/real-sitl.md) under `cargo test`: the unit tests
//! of their scoring and verdict layer (sitl/test_sitl_common.py on sitl/sitl_common.py: the
//! EKF error split by aiding, the frozen position after the EKF stops aiding, the injected
//! position's integrity, the verdict's reasons, free ports) and a compile check of both
//! run.py. Plain python3, standard library only (no pymavlink, no autopilot); without python3
//! the tests print SKIP and pass.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// python3 with the bytecode caches kept out of the source tree.
fn python3(args: &[&str]) -> Option<Output> {
    let cache = Path::new(env!("CARGO_TARGET_TMPDIR")).join("sitl-pycache");
    match Command::new("python3")
        .args(args)
        .current_dir(repo())
        .env("PYTHONPYCACHEPREFIX", &cache)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .output()
    {
        Ok(out) => Some(out),
        Err(e) => {
            eprintln!("SKIP sitl_scripts: cannot run python3: {e}");
            None
        }
    }
}

fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

#[test]
fn sitl_python_unit_tests_pass() {
    let Some(out) = python3(&[
        "-m",
        "unittest",
        "discover",
        "-s",
        "sitl",
        "-p",
        "test_*.py",
        "-v",
    ]) else {
        return;
    };
    let log = text(&out);
    assert!(
        out.status.success(),
        "sitl Python unit tests failed:\n{log}"
    );
    // unittest exits 0 with "Ran 0 tests" (Python < 3.12) when discovery finds nothing.
    let ran: usize = log
        .lines()
        .find_map(|l| {
            l.strip_prefix("Ran ")?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .unwrap_or(0);
    assert!(ran >= 30, "only {ran} sitl Python tests ran:\n{log}");
}

#[test]
fn sitl_run_scripts_compile() {
    let files = [
        "sitl/ardupilot/run.py",
        "sitl/px4/run.py",
        "sitl/sitl_common.py",
    ];
    for f in files {
        assert!(repo().join(f).is_file(), "{f} missing");
    }
    // py_compile writes its .pyc under PYTHONPYCACHEPREFIX (target/tmp), not beside the source.
    let mut args = vec!["-m", "py_compile"];
    args.extend(files);
    let Some(out) = python3(&args) else { return };
    assert!(out.status.success(), "py_compile failed:\n{}", text(&out));
}
