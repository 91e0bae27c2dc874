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

/// run.py's command line without pymavlink or SITL: a stub `pymavlink.mavutil` lets the module
/// load, then `--denial` / `--restore-wp` are parsed and checked, the ExternalNav configuration
/// is derived from the recipe's, and the parameter files of the source-set recipe and of
/// config/ are `NAME VALUE` lines.
#[test]
fn ardupilot_run_denial_arguments() {
    let script = r##"
import importlib.util, os, re, sys, types
pm = types.ModuleType("pymavlink"); mu = types.ModuleType("pymavlink.mavutil"); pm.mavutil = mu
sys.modules["pymavlink"] = pm; sys.modules["pymavlink.mavutil"] = mu
spec = importlib.util.spec_from_file_location("ap_run", "sitl/ardupilot/run.py")
run = importlib.util.module_from_spec(spec); spec.loader.exec_module(run)
base = ["--arducopter", "arducopter"]
a = run.parse_args(base)
assert a.denial == "gps-disable" and a.restore_wp is None, vars(a)
assert run.source_set_parm(a) == []
for d in ("source-set", "source-set-gps-on"):
    a = run.parse_args(base + ["--denial", d])
    assert a.denial == d and a.restore_wp is None, vars(a)
    assert [os.path.basename(p) for p in run.source_set_parm(a)] == ["visnav-source-set.parm"]
a = run.parse_args(base + ["--denial", "source-set", "--gps-off-wp", "3", "--restore-wp", "5"])
assert (a.gps_off_wp, a.restore_wp) == (3, 5), vars(a)
bad = [["--denial", "nope"], ["--denial", "source-set", "--no-visnav"],
       ["--denial", "source-set", "--restore-wp", "2"],
       ["--denial", "source-set", "--gps-off-alt", "100"], ["--restore-wp", "5"]]
stderr, sys.stderr = sys.stderr, open(os.devnull, "w")
for b in bad:
    try:
        run.parse_args(base + b)
    except SystemExit as e:
        assert e.code == 2, (b, e.code)
    else:
        raise AssertionError(f"accepted: {b}")
sys.stderr = stderr
for cfg in ("sitl/ardupilot/visnav.toml", "sitl/ardupilot/drone/visnav.toml"):
    t = run.external_nav_config(open(cfg).read())
    out = re.search(r"(?ms)^\[output\]\n(.*?)(?=^\[|\Z)", t).group(1)
    assert re.findall(r"(?m)^modes = .*$", out) == ['modes = ["vision_position_estimate"]'], out
    assert re.findall(r"(?m)^set_origin = .*$", out) == ["set_origin = false"], out
    assert "gps_input" not in out, out
parms = {}
for f in ("sitl/ardupilot/visnav-source-set.parm", "config/ardupilot-copter-source-sets.parm",
          "config/ardupilot-plane-source-sets.parm", "config/px4-visnav.params"):
    p = {}
    for line in open(f):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, value = line.split()
        assert re.fullmatch(r"[A-Z][A-Z0-9_]*", name), (f, line)
        float(value)
        p[name] = float(value)
    parms[f] = p
for f in ("sitl/ardupilot/visnav-source-set.parm", "config/ardupilot-copter-source-sets.parm",
          "config/ardupilot-plane-source-sets.parm"):
    p = parms[f]
    assert (p["EK3_SRC1_POSXY"], p["EK3_SRC2_POSXY"], p["VISO_TYPE"]) == (3, 6, 1), f
    assert (p["EK3_SRC2_VELXY"], p["EK3_SRC_OPTIONS"]) == (0, 0), f
for f in ("config/ardupilot-copter-source-sets.parm", "config/ardupilot-plane-source-sets.parm"):
    assert sorted(v for k, v in parms[f].items() if re.fullmatch(r"RC\d+_OPTION", k)) == [65, 90], f
print("denial arguments ok")
"##;
    let Some(out) = python3(&["-c", script]) else {
        return;
    };
    assert!(
        out.status.success(),
        "run.py argument check failed:\n{}",
        text(&out)
    );
}
