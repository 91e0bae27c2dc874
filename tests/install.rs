//! `scripts/install.sh` end to end, into temporary roots (`--root`): the binary, the configuration
//! with the files it names, the systemd unit; an edited configuration survives a reinstall; bad
//! options fail with a message. The script is never run without `--root` as root here.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn script() -> PathBuf {
    repo().join("scripts/install.sh")
}

/// The script into `root` with the test's binary and `extra` options.
fn install(root: &Path, extra: &[&str]) -> Output {
    Command::new(script())
        .arg("--root")
        .arg(root)
        .arg("--binary")
        .arg(env!("CARGO_BIN_EXE_visnav"))
        .args(extra)
        .output()
        .unwrap()
}

use crate::common::{assert_ok, text};

fn check_config(bin: &Path, conf: &Path) -> Output {
    Command::new(bin)
        .arg("check-config")
        .arg(conf)
        .output()
        .unwrap()
}

/// The problems `check-config` lists (its lines "  section.key: reason").
fn problems(stderr: &str) -> Vec<String> {
    stderr
        .lines()
        .filter(|l| l.starts_with("  "))
        .map(|l| l.trim().to_string())
        .collect()
}

#[test]
fn installs_binary_config_and_unit_into_a_root() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let out = install(root, &[]);
    assert_ok(&out, "install.sh --root");
    let stdout = text(&out.stdout);
    // --root creates no user and runs no systemctl; it says what it would do.
    assert!(
        stdout.contains("would run: systemctl daemon-reload")
            && stdout.contains("would run: systemctl enable visnav.service"),
        "{stdout}"
    );

    // The binary: installed, executable, runs.
    let bin = root.join("usr/local/bin/visnav");
    let mode = std::fs::metadata(&bin).unwrap().permissions().mode();
    assert_eq!(mode & 0o755, 0o755, "{}: mode {mode:o}", bin.display());
    let v = Command::new(&bin).arg("--version").output().unwrap();
    assert_ok(&v, "installed visnav --version");
    assert!(
        text(&v.stdout).starts_with("visnav "),
        "{}",
        text(&v.stdout)
    );

    // The configuration (config/companion.toml) and the map it names, copied beside it with the
    // path rewritten: check-config from the installed place opens the map. The companion's serial
    // port (/dev/ttyAMA0) and its flight-record folder (/var/log/visnav) belong to the board; on
    // a machine without them those are the only problems allowed.
    let conf = root.join("etc/visnav/visnav.toml");
    let installed = std::fs::read_to_string(&conf).unwrap();
    assert!(
        installed.contains("ortho = [\"naip_nd_2009.tif\"]"),
        "{installed}"
    );
    assert!(root.join("etc/visnav/naip_nd_2009.tif").is_file());
    assert!(root.join("var/log/visnav").is_dir());
    let c = check_config(&bin, &conf);
    let err = text(&c.stderr);
    if !c.status.success() {
        let host_only = |p: &String| {
            (p.starts_with("link.connection: the serial device /dev/ttyAMA0")
                && !Path::new("/dev/ttyAMA0").exists())
                || (p.starts_with("link.tlog:")
                    && p.contains("/var/log/visnav/")
                    && p.contains("in a folder that does not exist")
                    && !Path::new("/var/log/visnav").is_dir())
        };
        let list = problems(&err);
        assert!(
            !list.is_empty() && list.iter().all(host_only),
            "check-config on the installed companion configuration:\n{err}"
        );
        println!(
            "installed companion.toml: only this machine's missing devices/folders: {}",
            list.join("; ")
        );
    }

    // The unit.
    let unit = std::fs::read_to_string(root.join("etc/systemd/system/visnav.service")).unwrap();
    for line in [
        "ExecStart=/usr/local/bin/visnav run --config /etc/visnav/visnav.toml",
        "Restart=on-failure",
        "User=visnav",
        "After=network-online.target",
        "WantedBy=multi-user.target",
        "LogsDirectory=visnav",
    ] {
        assert!(unit.lines().any(|l| l == line), "no '{line}' in\n{unit}");
    }
    let value = |key: &str| {
        unit.lines()
            .find_map(|l| l.strip_prefix(key))
            .unwrap_or_default()
            .to_string()
    };
    assert!(value("RestartSec=").parse::<u32>().unwrap() > 0, "{unit}");
    assert!(
        value("StartLimitBurst=").parse::<u32>().unwrap() > 0,
        "{unit}"
    );
    assert!(
        value("StartLimitIntervalSec=").parse::<u32>().unwrap() > 0,
        "{unit}"
    );
    assert!(
        value("SupplementaryGroups=")
            .split_whitespace()
            .any(|g| g == "dialout"),
        "{unit}"
    );
    // Hardening that would close the serial port or the camera.
    for closing in ["PrivateDevices=yes", "DevicePolicy=", "ProtectClock=yes"] {
        assert!(
            !unit.lines().any(|l| l.starts_with(closing)),
            "{closing} in\n{unit}"
        );
    }
    systemd_analyze_verify(&unit, &bin, dir.path());

    // A second install keeps an edited configuration and writes the new one beside it.
    let edited = format!("{installed}\n# edited on the board\n");
    std::fs::write(&conf, &edited).unwrap();
    let out = install(root, &[]);
    assert_ok(&out, "second install.sh --root");
    assert_eq!(std::fs::read_to_string(&conf).unwrap(), edited);
    let new = root.join("etc/visnav/visnav.toml.new");
    assert!(new.is_file(), "no {}", new.display());
    assert!(
        text(&out.stdout).contains("visnav.toml.new"),
        "{}",
        text(&out.stdout)
    );
    assert!(
        std::fs::read_to_string(&new)
            .unwrap()
            .contains("ortho = [\"naip_nd_2009.tif\"]")
    );
    // The same configuration again: nothing to write.
    std::fs::write(&conf, &installed).unwrap();
    std::fs::remove_file(&new).unwrap();
    let out = install(root, &[]);
    assert_ok(&out, "third install.sh --root");
    assert!(!new.exists(), "{}", text(&out.stdout));
}

/// `systemd-analyze verify` on the unit, its ExecStart pointed at the installed binary (the
/// unit names /usr/local/bin/visnav, which is not on this machine). Skipped with a printed
/// reason when the tool is absent or does not work here.
fn systemd_analyze_verify(unit: &str, bin: &Path, tmp: &Path) {
    let dir = tmp.join("verify");
    std::fs::create_dir_all(&dir).unwrap();
    // A trivial unit first: if that does not verify, the tool does not work in this container.
    let probe = dir.join("visnav-probe.service");
    std::fs::write(
        &probe,
        format!("[Service]\nExecStart={} --version\n", bin.display()),
    )
    .unwrap();
    let run = |f: &Path| {
        Command::new("systemd-analyze")
            .arg("verify")
            .arg(f)
            .output()
    };
    match run(&probe) {
        Err(e) => {
            println!("SKIP: systemd-analyze verify: systemd-analyze cannot run here: {e}");
            return;
        }
        Ok(o) if !o.status.success() || !o.stderr.is_empty() => {
            println!(
                "SKIP: systemd-analyze verify does not work in this container (a trivial unit: {}: {})",
                o.status,
                text(&o.stderr).trim()
            );
            return;
        }
        Ok(_) => {}
    }
    let file = dir.join("visnav.service");
    let local = unit.replace(
        "ExecStart=/usr/local/bin/visnav ",
        &format!("ExecStart={} ", bin.display()),
    );
    std::fs::write(&file, local).unwrap();
    let o = run(&file).unwrap();
    assert!(
        o.status.success() && o.stderr.is_empty(),
        "systemd-analyze verify visnav.service: exit {:?}\n{}",
        o.status.code(),
        text(&o.stderr)
    );
    println!("systemd-analyze verify: the unit has no warnings");
}

#[test]
fn prefix_and_a_config_of_ones_own_with_relative_files() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("root");
    std::fs::create_dir(&root).unwrap();
    // A configuration that refers to a map below its folder and to one beside its folder, on a
    // UDP link with its flight record in an existing folder: check-config passes outright.
    let src = dir.path().join("src");
    std::fs::create_dir_all(src.join("conf/maps")).unwrap();
    std::fs::create_dir_all(src.join("other")).unwrap();
    let ortho = repo().join("sitl/maps/naip_nd_2009.tif");
    std::fs::copy(&ortho, src.join("conf/maps/area.tif")).unwrap();
    std::fs::copy(&ortho, src.join("other/second.tif")).unwrap();
    let records = dir.path().join("records");
    std::fs::create_dir(&records).unwrap();
    let config = src.join("conf/udp.toml");
    std::fs::write(
        &config,
        format!(
            "# a comment naming \"maps/area.tif\" stays as it is\n\
             [link]\nconnection = \"udpin:127.0.0.1:14550\"\ntlog = \"{}/flight-{{t}}.tlog\"\n\
             [camera]\nwidth_px = 640\nheight_px = 480\nhfov_deg = 60.0\n\
             [map]\northo = [\n  \"maps/area.tif\",\n  '../other/second.tif',\n]\n\
             ground_height_amsl_m = 580.0\n",
            records.display()
        ),
    )
    .unwrap();
    let out = install(
        &root,
        &[
            "--prefix",
            "/opt/visnav",
            "--config",
            config.to_str().unwrap(),
            "--no-enable",
        ],
    );
    assert_ok(&out, "install.sh --prefix --config --no-enable");
    let stdout = text(&out.stdout);
    assert!(!stdout.contains("systemctl enable"), "{stdout}");

    let bin = root.join("opt/visnav/bin/visnav");
    assert!(bin.is_file(), "no {}", bin.display());
    assert!(!root.join("usr/local/bin/visnav").exists());
    let unit = std::fs::read_to_string(root.join("etc/systemd/system/visnav.service")).unwrap();
    assert!(
        unit.lines()
            .any(|l| l == "ExecStart=/opt/visnav/bin/visnav run --config /etc/visnav/visnav.toml"),
        "{unit}"
    );

    let etc = root.join("etc/visnav");
    assert!(etc.join("maps/area.tif").is_file(), "{stdout}");
    assert!(etc.join("second.tif").is_file(), "{stdout}");
    let installed = std::fs::read_to_string(etc.join("visnav.toml")).unwrap();
    assert!(installed.contains("  \"maps/area.tif\",\n"), "{installed}");
    assert!(installed.contains("  'second.tif',\n"), "{installed}");
    assert!(
        installed.contains("# a comment naming \"maps/area.tif\" stays as it is"),
        "{installed}"
    );
    let c = check_config(&bin, &etc.join("visnav.toml"));
    assert_ok(&c, "check-config on the installed configuration");
    assert!(text(&c.stdout).contains(": OK"), "{}", text(&c.stdout));
}

#[test]
fn bad_options_fail_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        let o = Command::new(script()).args(args).output().unwrap();
        (o.status.code(), text(&o.stderr))
    };
    let root = dir.path().to_str().unwrap();

    let (code, err) = run(&["--root", root, "--frobnicate"]);
    assert_ne!(code, Some(0));
    assert!(err.contains("unknown option '--frobnicate'"), "{err}");
    let (code, err) = run(&["--root"]);
    assert_ne!(code, Some(0));
    assert!(err.contains("--root needs a value"), "{err}");
    let (code, err) = run(&["--root", root, "--binary", "/nonexistent/visnav"]);
    assert_ne!(code, Some(0));
    assert!(
        err.contains("/nonexistent/visnav") && err.contains("no such file"),
        "{err}"
    );
    let (code, err) = run(&[
        "--root",
        root,
        "--binary",
        env!("CARGO_BIN_EXE_visnav"),
        "--config",
        "/nonexistent/visnav.toml",
    ]);
    assert_ne!(code, Some(0));
    assert!(err.contains("/nonexistent/visnav.toml"), "{err}");
    let (code, err) = run(&["--root", "/nonexistent/root"]);
    assert_ne!(code, Some(0));
    assert!(err.contains("/nonexistent/root"), "{err}");
    let (code, err) = run(&["--root", root, "--prefix", "usr/local"]);
    assert_ne!(code, Some(0));
    assert!(err.contains("absolute"), "{err}");
    // Nothing was installed by any of these.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);

    let help = Command::new(script()).arg("--help").output().unwrap();
    assert_ok(&help, "install.sh --help");
    assert!(text(&help.stdout).contains("--root DIR"));
}

/// Without --root it needs root. As root the test drops to nobody (setpriv) rather than run the
/// script against this machine.
#[test]
fn without_root_it_refuses_to_install_into_the_system() {
    let uid = Command::new("id").arg("-u").output().unwrap();
    let is_root = text(&uid.stdout).trim() == "0";
    let mut cmd = if is_root {
        let have_setpriv = Command::new("setpriv").arg("--version").output().is_ok();
        if !have_setpriv {
            println!(
                "SKIP: running as root and setpriv is absent: cannot test the non-root refusal"
            );
            return;
        }
        let mut c = Command::new("setpriv");
        c.args(["--reuid=65534", "--regid=65534", "--clear-groups", "--"]);
        c.arg(script());
        c
    } else {
        Command::new(script())
    };
    let o = cmd
        .args(["--binary", env!("CARGO_BIN_EXE_visnav")])
        .output()
        .unwrap();
    let err = text(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("needs root"), "{err}");
}
