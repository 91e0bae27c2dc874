//! Hostile and damaged input files through the `visnav` binary: files that never end or are far
//! too large are refused by name before they are read, `check-config` and `run` agree on every
//! broken `frames.csv` and on connection hosts, a damaged .tlog is replayed around the damage and
//! the damage reported, and messages quote at most a short prefix of what the user wrote.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use crate::common;

fn visnav() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_visnav"));
    c.env_remove("VISNAV_CONFIG")
        .env_remove("VISNAV_CONNECTION")
        .env_remove("VISNAV_MAP")
        .env_remove("VISNAV_CAMERA");
    c
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A valid configuration on a free loopback port, with `frames` as its directory camera source
/// when given.
fn config(frames: Option<&Path>) -> String {
    let mut text = format!(
        "[link]\nconnection = \"udpin:127.0.0.1:{}\"\n[camera]\nwidth_px = 640\n\
         height_px = 480\nhfov_deg = 60.0\n[map]\northo = [\"{}\"]\n\
         ground_height_amsl_m = 580.0\n",
        common::free_udp_port(),
        repo().join("sitl/maps/naip_nd_2009.tif").display()
    );
    if let Some(f) = frames {
        text.push_str(&format!(
            "[frames]\nsource = \"directory\"\npath = \"{}\"\n",
            f.display()
        ));
    }
    text
}

/// `visnav run` with `args` for at most `secs`: `None` while it still runs (it started), else
/// its output.
fn run_for(args: &[&str], env: &[(&str, &str)], secs: f64) -> Option<Output> {
    let mut cmd = visnav();
    cmd.arg("run").args(args);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    common::wait_with_deadline(&mut child, Duration::from_secs_f64(secs))?;
    Some(child.wait_with_output().unwrap())
}

/// Each broken frames.csv passed check-config and stopped run: both refuse it now with the same
/// words, naming `frames.path`, the file and the line; one with a byte order mark passes both.
#[test]
fn check_config_and_run_agree_on_frames_csv() {
    let d = tempfile::tempdir().unwrap();
    let frames = d.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let cfg = d.path().join("c.toml");
    std::fs::write(&cfg, config(Some(&frames))).unwrap();
    let csv = frames.join("frames.csv");
    for (text, want) in [
        ("", "frames.csv:1: empty"),
        ("file;t_s\na.png;0\n", "frames.csv:1: header \"file;t_s\""),
        (
            "file,t_s\na.png,nan\n",
            "frames.csv:2: t_s \"nan\" is not a finite number",
        ),
        (
            "file,t_s\na.png,1\nb.png,inf\n",
            "frames.csv:3: t_s \"inf\"",
        ),
        (
            "file,t_s\na.png,2\nb.png,1\n",
            "frames.csv:3: time \"1\" is not after",
        ),
        (
            "file,t_boot_us\na.png,9\nb.png,9\n",
            "frames.csv:3: time \"9\" is not after",
        ),
        (
            "file,t_boot_us\na.png,-9\n",
            "frames.csv:2: t_boot_us \"-9\"",
        ),
        (
            "file,t_boot_us\na.png,9.5\n",
            "frames.csv:2: t_boot_us \"9.5\"",
        ),
    ] {
        std::fs::write(&csv, text).unwrap();
        let out = visnav().arg("check-config").arg(&cfg).output().unwrap();
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{text:?}: {err}");
        assert!(
            err.contains("frames.path: ") && err.contains(want),
            "{text:?}: {err}"
        );
        let out = run_for(&["--config", cfg.to_str().unwrap()], &[], 60.0).unwrap_or_else(|| {
            panic!("{text:?}: run started on a frames.csv check-config refuses")
        });
        let err = stderr(&out);
        assert!(
            !out.status.success() && err.contains(want),
            "{text:?}: {err}"
        );
    }
    std::fs::write(&csv, "\u{feff}file,t_boot_us\na.png,9\nb.png,10\n").unwrap();
    let out = visnav().arg("check-config").arg(&cfg).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    if let Some(out) = run_for(&["--config", cfg.to_str().unwrap()], &[], 5.0) {
        panic!("run refused what check-config passed: {}", stderr(&out));
    }
}

/// `VISNAV_CONFIG=/dev/zero visnav run`, `visnav check-config /dev/zero` and `visnav replay
/// --tlog /dev/zero` grew without bound: each is refused at once, naming the file and its kind.
#[test]
fn an_endless_file_is_refused_not_read() {
    let out = run_for(&[], &[("VISNAV_CONFIG", "/dev/zero")], 20.0)
        .expect("run on /dev/zero as its configuration must stop at once");
    let err = stderr(&out);
    assert!(
        !out.status.success()
            && err.contains("/dev/zero")
            && err.contains("a character device, not a regular file; a TOML configuration"),
        "{err}"
    );
    let out = visnav()
        .args(["check-config", "/dev/zero"])
        .output()
        .unwrap();
    assert!(!out.status.success() && stderr(&out).contains("/dev/zero"));

    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("c.toml");
    std::fs::write(&cfg, config(None)).unwrap();
    let out = visnav()
        .args(["replay", "--config"])
        .arg(&cfg)
        .args(["--tlog", "/dev/zero"])
        .output()
        .unwrap();
    let err = stderr(&out);
    assert!(
        !out.status.success() && err.contains("/dev/zero") && err.contains("telemetry log"),
        "{err}"
    );
}

/// The bundled ArduCopter log replayed with `damage` done to the byte at the start of its
/// record `k` (`None`: clean): the summary as JSON and stderr.
fn replay_damaged(
    damage: impl Fn(&mut Vec<u8>, usize),
    k: usize,
) -> (serde_json::Value, String, usize) {
    let log = std::fs::read(repo().join("tests/data/arducopter_sitl_climb.tlog")).unwrap();
    let records = visnav::link::tlog::read_tlog(&log);
    let at: usize = records[..k].iter().map(|(_, p)| 8 + p.len()).sum();
    let mut bytes = log.clone();
    damage(&mut bytes, at);
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("c.toml");
    std::fs::write(&cfg, config(None)).unwrap();
    let tlog = d.path().join("damaged.tlog");
    std::fs::write(&tlog, &bytes).unwrap();
    let out = visnav()
        .args(["replay", "--json", "--config"])
        .arg(&cfg)
        .arg("--tlog")
        .arg(&tlog)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    (json, stderr(&out), records.len())
}

/// One flipped length byte (or 3 junk bytes) ended the replay at packet 101 of 22,141, rc 0 and
/// nothing said: the replay goes on at the next valid record and says what it skipped.
#[test]
fn replay_resynchronises_after_damage_and_says_so() {
    let (clean, err, all) = replay_damaged(|_, _| {}, 0);
    assert_eq!(clean["packets"], all as u64, "{err}");
    assert_eq!(clean["skipped_bytes"], 0);
    assert!(!err.contains("skipped"), "{err}");

    // The length byte of record 101 flipped: that record is lost, the rest is replayed.
    let (flipped, err, _) = replay_damaged(|b, at| b[at + 9] ^= 0x20, 101);
    assert_eq!(flipped["packets"], all as u64 - 1, "{err}");
    assert_eq!(flipped["skipped_runs"], 1);
    let skipped = flipped["skipped_bytes"].as_u64().unwrap();
    assert!(skipped > 8, "{flipped}");
    assert!(
        err.contains("damaged.tlog")
            && err.contains(&format!("skipped {skipped} bytes in 1 place(s)")),
        "{err}"
    );

    // Three junk bytes before record 101: every record replayed, 3 bytes skipped.
    let (junk, err, _) = replay_damaged(|b, at| drop(b.splice(at..at, [7, 0xFE, 7])), 101);
    assert_eq!(junk["packets"], all as u64, "{err}");
    assert_eq!(
        (
            junk["skipped_bytes"].as_u64(),
            junk["skipped_runs"].as_u64()
        ),
        (Some(3), Some(1))
    );
    assert!(err.contains("skipped 3 bytes in 1 place(s)"), "{err}");
}

/// A calibration with a 10 MB line was echoed whole; an XML one was "not a calibration"; one
/// with a byte order mark was refused; no distortion was taken as none without a word.
#[test]
fn camera_import_of_hostile_calibrations() {
    let d = tempfile::tempdir().unwrap();
    let f = d.path().join("cal.yaml");
    let ros = "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n  \
               data: [520.1, 0, 321.4, 0, 519.8, 238.9, 0, 0, 1]\ndistortion_model: plumb_bob\n\
               distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.21, 0.08, 0, 0, 0]\n";
    let import = |text: &str| {
        std::fs::write(&f, text).unwrap();
        visnav()
            .args(["camera", "import"])
            .arg(&f)
            .output()
            .unwrap()
    };
    // Half a MiB on one line: within the size limit, so refused for what it says, quoted short.
    let out = import(&ros.replace("640", &"6".repeat(1 << 19)));
    let err = stderr(&out);
    assert!(
        !out.status.success() && err.len() < 400,
        "{} bytes",
        err.len()
    );
    assert!(
        err.contains("image_width") && err.contains("(524288 bytes)"),
        "{err}"
    );
    // Ten MB: over the limit, refused before it is read, naming the file and the limit.
    let out = import(&ros.replace("640", &"6".repeat(10_000_000)));
    let err = stderr(&out);
    assert!(
        err.len() < 400 && err.contains("cal.yaml") && err.contains("1 MiB"),
        "{err}"
    );

    let out = import("<?xml version=\"1.0\"?>\n<opencv_storage>\n</opencv_storage>\n");
    let err = stderr(&out);
    assert!(!out.status.success() && err.contains("XML"), "{err}");

    let out = import(&format!("\u{feff}{ros}"));
    assert!(out.status.success(), "{}", stderr(&out));

    let out = import(
        &ros.replace("[-0.21, 0.08, 0, 0, 0]", "[]")
            .replace("cols: 5", "cols: 0"),
    );
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stderr(&out).contains("warning") && stderr(&out).contains("no distortion"));

    let out = import(&format!("{ros}image_width: 1280\n"));
    let err = stderr(&out);
    assert!(
        !out.status.success() && err.contains("given twice"),
        "{err}"
    );
}

/// `udpin:300.1.1.1:14871` passed check-config and run retried "failed to lookup address" for
/// ever: both refuse it, naming the key.
#[test]
fn an_invalid_ipv4_host_is_refused_by_check_config_and_run() {
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("c.toml");
    std::fs::write(&cfg, config(None)).unwrap();
    let bad = "udpin:300.1.1.1:14871";
    let out = visnav()
        .arg("check-config")
        .arg(&cfg)
        .args(["--connection", bad])
        .output()
        .unwrap();
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("link.connection") && err.contains("\"300.1.1.1\" is not an IPv4 address"),
        "{err}"
    );
    let out = run_for(
        &["--config", cfg.to_str().unwrap(), "--connection", bad],
        &[],
        30.0,
    )
    .expect("run must refuse the host at start, not retry it");
    let err = stderr(&out);
    assert!(
        !out.status.success() && err.contains("is not an IPv4 address"),
        "{err}"
    );
}
