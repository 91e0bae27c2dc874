//! `visnav bench fix`: every mode the fix's figures come from (docs/status.md) runs from the
//! command line and prints its JSON document with the fields the figures are read from; bad
//! arguments are clear errors. The NAIP maps are bundled (sitl/maps), so these run everywhere;
//! the Autzen case needs ../shared/data/autzen and skips visibly without it.

use std::path::Path;
use std::process::Command;

/// `visnav bench fix ARGS --json`: the parsed document (the run must succeed).
fn bench_fix(args: &[&str]) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["bench", "fix", "--json"])
        .args(args)
        .output()
        .expect("run visnav");
    assert!(
        out.status.success(),
        "visnav bench fix {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON document on stdout")
}

/// The fields every figure of docs/status.md is read from, with values that can be true.
fn check_fields(doc: &serde_json::Value, frames: u64) {
    assert_eq!(doc["frames"], frames, "{doc}");
    let accepted = doc["accepted"].as_u64().expect("accepted");
    assert!(accepted <= frames);
    let rate = doc["fix_rate"].as_f64().expect("fix_rate");
    assert!((rate - accepted as f64 / frames as f64).abs() < 1e-9);
    // Integrity: not one of these few frames may be fixed wrongly, in any mode.
    assert_eq!(doc["wrong_fixes"], 0, "{doc}");
    assert!(doc["beyond_3_sigma"].as_u64().expect("beyond_3_sigma") <= accepted);
    let (p50, p95) = (
        doc["ms_p50"].as_f64().expect("ms_p50"),
        doc["ms_p95"].as_f64().expect("ms_p95"),
    );
    assert!(p50 > 0.0 && p95 >= p50, "{p50} {p95}");
    // Statistics of the accepted fixes: numbers with a fix, null (not a made-up 0) without.
    let with_fix = accepted > 0;
    assert_eq!(doc["nees6_mean"].is_number(), with_fix, "{doc}");
    for k in ["median", "p90", "max"] {
        assert_eq!(
            doc["err_h_m"][k].is_number(),
            with_fix,
            "err_h_m.{k}: {doc}"
        );
        assert_eq!(
            doc["err_v_m"][k].is_number(),
            with_fix,
            "err_v_m.{k}: {doc}"
        );
    }
    let rejected: u64 = doc["rejections"]
        .as_array()
        .expect("rejections")
        .iter()
        .map(|r| r["count"].as_u64().expect("a count per reason"))
        .sum();
    assert_eq!(
        rejected + accepted,
        frames,
        "every frame accepted or rejected once"
    );
}

#[test]
fn bench_fix_prints_the_issue_fields_with_a_position_prior() {
    let doc = bench_fix(&["--frames", "4"]);
    check_fields(&doc, 4);
    assert_eq!(doc["site"], "naip");
    assert_eq!(doc["same_imagery_diagnostic"], false);
    let prior = doc["prior"].as_str().expect("prior");
    assert!(prior.contains("position prior 100 m off"), "{prior}");
    assert!(prior.contains("heading sigma 0.5 deg"), "{prior}");
    assert!(doc["accepted"].as_u64() > Some(0), "{doc}");
}

#[test]
fn bench_fix_modes_say_what_they_ran() {
    let cases: [(&[&str], &[&str]); 4] = [
        (
            &["--frames", "2", "--yaw-error-deg", "25"],
            &["heading 25 deg off", "heading sigma 30 deg"],
        ),
        (
            &["--frames", "1", "--tilt-only", "--no-prior"],
            &["tilt only", "no position prior (the altitude prior kept)"],
        ),
        (
            &[
                "--frames",
                "1",
                "--no-attitude",
                "--no-prior",
                "--no-altitude",
            ],
            &["no attitude", "no position prior, no altitude"],
        ),
        (&["--frames", "2", "--same-imagery"], &["position prior"]),
    ];
    for (args, says) in cases {
        let frames: u64 = args[1].parse().expect("frames");
        let doc = bench_fix(args);
        check_fields(&doc, frames);
        let prior = doc["prior"].as_str().expect("prior");
        for s in says {
            assert!(prior.contains(s), "{args:?}: {prior:?} lacks {s:?}");
        }
        let same = args.contains(&"--same-imagery");
        assert_eq!(doc["same_imagery_diagnostic"], same, "{args:?}");
    }
}

#[test]
fn bench_fix_autzen_case_names_its_map_heights() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/autzen");
    if !dir.is_dir() {
        println!(
            "SKIP bench_fix_autzen_case_names_its_map_heights: {} absent",
            dir.display()
        );
        return;
    }
    for heights in ["surface", "constant"] {
        let doc = bench_fix(&[
            "--site",
            "autzen",
            "--agl-m",
            "80",
            "--frames",
            "2",
            "--map-heights",
            heights,
        ]);
        check_fields(&doc, 2);
        assert_eq!(doc["site"], "autzen");
        assert_eq!(doc["map_heights"], heights);
    }
}

#[test]
fn bench_fix_refuses_bad_arguments_clearly() {
    let cases: [(&[&str], &str); 5] = [
        (&["--agl-m", "5"], "--agl-m \"5\""),
        (&["--yaw-error-deg", "200"], "--yaw-error-deg 200"),
        (&["--descriptor", "32"], "--descriptor 32"),
        (&["--set", "ratio = ["], "--set"),
        (&["--site", "autzen", "--same-imagery"], "NAIP site only"),
    ];
    for (args, names) in cases {
        let out = Command::new(env!("CARGO_BIN_EXE_visnav"))
            .args(["bench", "fix", "--frames", "1"])
            .args(args)
            .output()
            .expect("run visnav");
        assert!(!out.status.success(), "{args:?} was accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(names), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}
