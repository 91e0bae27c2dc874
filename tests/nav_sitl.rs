//! SITL: scenario parsing rigour, the seed experiment (vision vs INS-only over a 60 s GPS
//! outage) and a short Monte Carlo consistency check. The full 50-run Monte Carlo is
//! `visnav sim --scenario sitl/scenarios/seed_outage.toml --monte-carlo 50 --json`.

use nalgebra::Vector3;
use visnav::sitl::Scenario;
use visnav::sitl::run::{RunOptions, monte_carlo, run};

fn seed() -> Scenario {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/scenarios/seed_outage.toml");
    Scenario::load(&path).expect("seed scenario loads")
}

#[test]
fn all_scenario_files_load() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/scenarios");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).expect("scenario dir") {
        let p = e.expect("entry").path();
        if p.extension().is_some_and(|x| x == "toml") {
            Scenario::load(&p).unwrap_or_else(|e| panic!("{e}"));
            n += 1;
        }
    }
    assert!(n >= 2);
}

#[test]
fn scenario_errors_name_file_and_key() {
    let text = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/scenarios/seed_outage.toml"),
    )
    .expect("read");
    // Unknown key.
    let bad = text.replace(
        "sigma_vel_m_s = 0.1",
        "sigma_vel_m_s = 0.1\nsigma_speed = 1.0",
    );
    let e = Scenario::parse(&bad, "x.toml")
        .expect_err("unknown key")
        .to_string();
    assert!(e.contains("x.toml") && e.contains("sigma_speed"), "{e}");
    // Out-of-range values, all reported with their dotted keys.
    let bad = text
        .replace("rate_hz = 100.0", "rate_hz = -100.0")
        .replace(
            "until_s = 300.0\nsigma_h_m = 2.5",
            "until_s = 900.0\nsigma_h_m = 2.5",
        )
        .replace(
            "[nav.imu]                  # the filter's model: the simulated IMU's datasheet values\ngyro_arw_deg_sqrt_h = 0.1",
            "[nav.imu]\ngyro_arw_deg_sqrt_h = 0.0",
        );
    let e = Scenario::parse(&bad, "y.toml")
        .expect_err("invalid")
        .to_string();
    for key in [
        "y.toml",
        "imu.rate_hz",
        "vision.until_s",
        "nav.imu.gyro_arw_deg_sqrt_h",
    ] {
        assert!(e.contains(key), "missing {key} in: {e}");
    }
    // Segment kind consistency.
    let bad = text.replace(
        "kind = \"straight\"\nduration_s = 300.0",
        "kind = \"turn\"\nduration_s = 300.0",
    );
    let e = Scenario::parse(&bad, "z.toml")
        .expect_err("turn without rate")
        .to_string();
    assert!(e.contains("segments[0].turn_rate_deg_s"), "{e}");
}

#[test]
fn seed_experiment_vision_vs_ins_only() {
    let sc = seed();
    let vis = run(&sc, RunOptions::new(true, 0)).expect("vision run");
    let ins = run(&sc, RunOptions::new(false, 0)).expect("INS-only run");
    eprintln!(
        "seed experiment max error e/n/u: vision {:.2}/{:.2}/{:.2} m (horizontal {:.2}), INS-only {:.2}/{:.2}/{:.2} m (horizontal {:.2})",
        vis.max_err_m.e,
        vis.max_err_m.n,
        vis.max_err_m.u,
        vis.max_horiz_err_m,
        ins.max_err_m.e,
        ins.max_err_m.n,
        ins.max_err_m.u,
        ins.max_horiz_err_m
    );
    // The target: with vision, max horizontal error over the outage at most 5 m.
    assert!(vis.max_horiz_err_m <= 5.0, "{:?}", vis.max_err_m);
    // Every fix arrives late and is applied at its capture time through the history.
    assert!(
        vis.counters.vision.accepted >= 55,
        "{:?}",
        vis.counters.vision
    );
    assert!(vis.counters.replays >= vis.counters.vision.accepted);
    assert_eq!(ins.counters.vision.accepted, 0);
    // Without aiding the error keeps growing: the INS-only run ends worse than the vision run.
    let end_h = |r: &visnav::sitl::run::RunResult| r.final_err_m.e.hypot(r.final_err_m.n);
    assert!(
        end_h(&ins) > end_h(&vis),
        "{} vs {}",
        end_h(&ins),
        end_h(&vis)
    );
    assert!(vis.final_health.starts_with("ok"), "{}", vis.final_health);
    assert!(
        ins.final_health.starts_with("degraded"),
        "{}",
        ins.final_health
    );
}

#[test]
fn short_monte_carlo_is_consistent() {
    let sc = seed();
    let mc = monte_carlo(&sc, 10).expect("monte carlo");
    let pos = mc.nees_pos.as_ref().expect("nees");
    eprintln!(
        "10-run Monte Carlo: {}",
        serde_json::to_string(&mc).expect("json")
    );
    assert_eq!(pos.runs, 10);
    assert!(pos.epochs >= 60);
    assert!(
        pos.mean_inside,
        "mean position NEES {} outside {:?}",
        pos.mean, pos.band_95
    );
    // About 95 % of the epochs are expected inside the band; allow for a short run.
    assert!(pos.fraction_inside >= 0.8, "{}", pos.fraction_inside);
    // Every navigation block (position, velocity, attitude, all nine): the run-averaged NEES
    // inside its 95 % band. The bias blocks barely change over the 60 s window, so with 10 runs
    // their time average is about one chi-square(30) draw: reported by the 50/100-run Monte
    // Carlo of `visnav sim`, not asserted here.
    for (name, s) in &mc.nees {
        if name.contains("bias") || name == "all15" {
            continue;
        }
        let s = s.as_ref().expect("nees block");
        assert!(
            s.mean_inside,
            "mean {name} NEES {} outside {:?}",
            s.mean, s.band_95
        );
    }
    assert_eq!(mc.runs_over_target, 0);
}

fn scenario_text(name: &str) -> String {
    std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("sitl/scenarios")
            .join(name),
    )
    .expect("read scenario")
}

/// Camera lever arm through turns and climbs (vision only): the fixes are positions of the camera
/// projection centre 1.5 m forward, 0.8 m right and 0.6 m above the IMU. A filter that ignores the
/// lever arm puts its IMU position on the camera (mean error in body axes = the lever arm); with
/// `[nav] camera_lever_arm_body_frd_m` the mean error is that of the run without a lever arm.
#[test]
fn camera_lever_arm_bias_without_correction_none_with_it() {
    let text = scenario_text("turns_vision_only.toml");
    let arm = "lever_arm_body_frd_m = [1.5, 0.8, -0.6]";
    let truth_arm = text.replace("outlier_m = 50.0", &format!("outlier_m = 50.0\n{arm}"));
    let corrected = truth_arm.replace(
        "[nav]\n",
        "[nav]\ncamera_lever_arm_body_frd_m = [1.5, 0.8, -0.6]\n",
    );
    let go = |t: &str| {
        let sc = Scenario::parse(t, "turns_vision_only.toml").expect("valid");
        run(&sc, RunOptions::new(true, 0)).expect("run")
    };
    let (base, unc, cor) = (go(&text), go(&truth_arm), go(&corrected));
    let b = |r: &visnav::sitl::run::RunResult| r.mean_err_body_frd_m;
    eprintln!(
        "mean error body FRD [m]: no lever arm {:.3?}, lever arm ignored {:.3?}, corrected {:.3?}; max horizontal {:.2} / {:.2} / {:.2}",
        b(&base),
        b(&unc),
        b(&cor),
        base.max_horiz_err_m,
        unc.max_horiz_err_m,
        cor.max_horiz_err_m
    );
    // Ignored: the estimate sits on the camera, estimate - truth = the lever arm (forward, right;
    // measured 1.50 / 1.10 m: the vertical part, pulled to the barometer, leaks into body y in
    // the banked turns).
    assert!(
        (b(&unc)[0] - b(&base)[0] - 1.5).abs() < 0.4,
        "{:?}",
        b(&unc)
    );
    assert!(
        (b(&unc)[1] - b(&base)[1] - 0.8).abs() < 0.4,
        "{:?}",
        b(&unc)
    );
    // Corrected: no lever-arm bias left (same noise draws as the run without a lever arm;
    // measured within 2 mm).
    for k in 0..3 {
        assert!((b(&cor)[k] - b(&base)[k]).abs() < 0.05, "{:?}", b(&cor));
    }
    assert!(cor.counters.vision.accepted >= 190);
}

/// GPS antenna 0.4 m forward and 1.2 m above the IMU on the calibration racetrack (turns, climbs):
/// the GPS update with the lever arm and its attitude Jacobian removes the bias.
#[test]
fn gps_lever_arm_bias_without_correction_none_with_it() {
    let text = scenario_text("gps_calibration.toml");
    let truth_arm = text.replace(
        "sigma_vel_m_s = 0.1",
        "sigma_vel_m_s = 0.1\nlever_arm_body_frd_m = [0.4, 0.0, -1.2]",
    );
    let corrected = truth_arm.replace(
        "[nav.imu]",
        "[nav]\ngps_lever_arm_body_frd_m = [0.4, 0.0, -1.2]\n\n[nav.imu]",
    );
    let go = |t: &str| {
        let sc = Scenario::parse(t, "gps_calibration.toml").expect("valid");
        run(&sc, RunOptions::new(false, 0)).expect("run")
    };
    let (base, unc, cor) = (go(&text), go(&truth_arm), go(&corrected));
    let b = |r: &visnav::sitl::run::RunResult| r.mean_err_body_frd_m;
    eprintln!(
        "GPS lever arm, mean error body FRD [m]: none {:.3?}, ignored {:.3?}, corrected {:.3?}",
        b(&base),
        b(&unc),
        b(&cor)
    );
    assert!(
        (b(&unc)[0] - b(&base)[0] - 0.4).abs() < 0.2,
        "{:?}",
        b(&unc)
    );
    assert!(
        (b(&unc)[2] - b(&base)[2] + 1.2).abs() < 0.3,
        "{:?}",
        b(&unc)
    );
    for k in 0..3 {
        assert!((b(&cor)[k] - b(&base)[k]).abs() < 0.05, "{:?}", b(&cor));
    }
}

/// The filter estimates the IMU biases when GPS and manoeuvres make them observable.
#[test]
fn bias_estimation_converges_under_gps_with_manoeuvres() {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/sitl/scenarios/gps_calibration.toml"
    ))
    .expect("scenario file");
    let sc = Scenario::parse(&text, "gps_calibration.toml").expect("valid scenario");
    let r = run(&sc, RunOptions::new(false, 0)).expect("run");
    eprintln!(
        "bias errors: gyro {:?} deg/h (truth {:?}), accel {:?} ug (truth {:?})",
        r.gyro_bias_err_deg_h, sc.imu.gyro_bias_deg_h, r.accel_bias_err_ug, sc.imu.accel_bias_ug
    );
    eprintln!(
        "filter sigmas: gyro {:?} deg/h, accel {:?} ug",
        r.gyro_bias_sigma_deg_h, r.accel_bias_sigma_ug
    );
    // With turns and climbs under GPS all six biases become observable: starting from zero (100 %
    // error) the residual must be a small fraction of the truth, and within 4 sigma of the
    // filter's own uncertainty.
    for i in 0..3 {
        let (eg, sg, tg) = (
            r.gyro_bias_err_deg_h[i].abs(),
            r.gyro_bias_sigma_deg_h[i],
            sc.imu.gyro_bias_deg_h[i].abs(),
        );
        let (ea, sa, ta) = (
            r.accel_bias_err_ug[i].abs(),
            r.accel_bias_sigma_ug[i],
            sc.imu.accel_bias_ug[i].abs(),
        );
        assert!(
            eg < 0.4 * tg && eg < 4.0 * sg,
            "gyro axis {i}: error {eg} sigma {sg}"
        );
        assert!(
            ea < 0.4 * ta && ea < 4.0 * sa,
            "accel axis {i}: error {ea} sigma {sa}"
        );
        assert!(sg < 0.2 * tg && sa < 0.2 * ta, "axis {i}: sigmas {sg} {sa}");
    }
}

/// A late fix (stamped at capture, replayed) gives what an on-time fix gives.
#[test]
fn late_fixes_equal_on_time_fixes() {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/sitl/scenarios/seed_outage.toml"
    ))
    .expect("scenario file");
    let mut sc = Scenario::parse(&text, "seed_outage.toml").expect("valid scenario");
    // Shorten: 60 s GPS, 30 s vision.
    sc.segments[0].duration_s = 91.0;
    let gps = sc.gps.as_mut().expect("gps");
    gps.until_s = 60.0;
    let v = sc.vision.as_mut().expect("vision");
    v.from_s = 60.0;
    v.until_s = 90.0;
    v.rate_hz = 2.0;
    sc.evaluation.from_s = 60.0;
    sc.evaluation.until_s = 91.0;
    let mut on_time = sc.clone();
    let vt = on_time.vision.as_mut().expect("vision");
    vt.latency_min_ms = 0.0;
    vt.latency_max_ms = 0.0;
    let late = run(&sc, RunOptions::new(true, 0)).expect("run");
    let now = run(&on_time, RunOptions::new(true, 0)).expect("run");
    let d = Vector3::new(
        late.final_err_m.e - now.final_err_m.e,
        late.final_err_m.n - now.final_err_m.n,
        late.final_err_m.u - now.final_err_m.u,
    );
    eprintln!(
        "final error late {:?} vs on time {:?}; replays {} / {}",
        late.final_err_m, now.final_err_m, late.counters.replays, now.counters.replays
    );
    assert_eq!(late.counters.vision.accepted, now.counters.vision.accepted);
    assert!(late.counters.replays >= 55);
    assert!(
        d.norm() < 1e-3,
        "late and on-time results differ by {d:?} m"
    );
    // Control: ignoring the latency (stamping the fix with its arrival time) is much worse.
    let naive = run(
        &sc,
        RunOptions {
            stamp_at_arrival: true,
            ..RunOptions::new(true, 0)
        },
    )
    .expect("run");
    eprintln!(
        "max horizontal error: at capture time {:.2} m, stamped at arrival {:.2} m",
        late.max_horiz_err_m, naive.max_horiz_err_m
    );
    assert!(naive.max_horiz_err_m > 2.0 * late.max_horiz_err_m);
}
