//! Error-state EKF behaviour: bias estimation under GPS, late fixes applied at capture time,
//! gating, covariance health, divergence reset, initialisation from vision, health states.
#![allow(clippy::unwrap_used, clippy::expect_used)] // a test: a failed expect is a failed test

use nalgebra::{Matrix3, Vector3};
use visnav_core::nav::earth;
use visnav_core::nav::filter::Health;
use visnav_core::nav::synth::imu::{ImuErrors, SimImuConfig};
use visnav_core::nav::synth::trajectory::{Segment, Trajectory};
use visnav_core::nav::{
    AltitudeFix, AttitudeFix, ImuSample, InsState, Measurement, NavConfig, NavFilter, Outcome,
    PositionFix, VelocityFix, VoFix, VoRotation,
};
use visnav_core::rng::Rng;

/// Straight-and-level truth flown with an optional noisy IMU, feeding GPS at 5 Hz.
struct Harness {
    traj: Trajectory,
    filter: NavFilter,
    rng: Rng,
    imu: ImuErrors,
    t_us: u64,
    states: Vec<(u64, InsState)>,
    /// A faulty accelerometer: from `.0` to `.1` (µs) its x axis reads `.2` (m/s^2).
    accel_fault: Option<(u64, u64, f64)>,
    /// A jumping GPS receiver: from `.0` to `.1` (µs) its positions are off by `.2` (NED, m).
    gps_jump: Option<(u64, u64, Vector3<f64>)>,
    /// A silent link: from `.0` to `.1` (µs) the filter gets nothing; the first sample after it
    /// carries its rates over the whole gap (what the daemon's inputs give).
    silent: Option<(u64, u64)>,
    /// A gyro error that changes: from `.0` (µs) on, the rates read `.1` (body FRD, rad/s) more
    /// (an autopilot's residual bias moving with the flight phase).
    gyro_step: Option<(u64, Vector3<f64>)>,
}

const DT_US: u64 = 10_000;

fn straight() -> Trajectory {
    Trajectory::new(
        46.9f64.to_radians(),
        (-100.8f64).to_radians(),
        1500.0,
        51.44,
        90f64.to_radians(),
        vec![Segment {
            duration_s: 3600.0,
            speed_m_s: 51.44,
            turn_rate_rad_s: 0.0,
            path_angle_rad: 0.0,
            ramp_s: 1.0,
        }],
    )
}

fn fix_at(s: &InsState, t_us: u64, offset_ned: Vector3<f64>, sigma: f64) -> PositionFix {
    let (rm, rn) = earth::radii_m(s.lat_rad);
    PositionFix {
        t_capture_us: t_us,
        lat_rad: s.lat_rad + offset_ned.x / (rm + s.h_m),
        lon_rad: s.lon_rad + offset_ned.y / ((rn + s.h_m) * s.lat_rad.cos()),
        h_m: s.h_m - offset_ned.z,
        cov_ned_m2: Matrix3::identity() * sigma * sigma,
        att_dependence_ned: None,
    }
}

impl Harness {
    fn new(cfg: NavConfig, imu: SimImuConfig) -> Self {
        Self::with_trajectory(cfg, imu, straight())
    }

    fn with_trajectory(cfg: NavConfig, imu: SimImuConfig, traj: Trajectory) -> Self {
        let mut f = NavFilter::new(cfg);
        f.imu(&ImuSample {
            t_us: 0,
            dtheta_rad_body_frd: Vector3::zeros(),
            dv_m_s_body_frd: Vector3::zeros(),
            gap_sigma_dtheta_rad: 0.0,
            gap_sigma_dv_m_s: 0.0,
        });
        Self {
            traj,
            filter: f,
            rng: Rng::new(5),
            imu: ImuErrors::new(imu),
            t_us: 0,
            states: Vec::new(),
            accel_fault: None,
            gps_jump: None,
            silent: None,
            gyro_step: None,
        }
    }

    /// Fly `secs` seconds; GPS (position 1.5 m, velocity 0.1 m/s) when `gps`, attitude at 10 Hz.
    fn fly(&mut self, secs: f64, gps: bool, mut each: impl FnMut(&mut NavFilter, u64, &InsState)) {
        let mut truth = self.traj.truth();
        // Re-integrate the truth up to the current time (the harness restarts the integrator).
        let steps_done = self.t_us / DT_US;
        for _ in 0..steps_done {
            truth.step(DT_US as f64 * 1e-6);
        }
        let n = (secs * 1e6 / DT_US as f64).round() as u64;
        for _ in 0..n {
            self.t_us += DT_US;
            let (dth, dv) = truth.step(DT_US as f64 * 1e-6);
            let (dth, dv) = self
                .imu
                .corrupt(&mut self.rng, &dth, &dv, DT_US as f64 * 1e-6);
            let mut dv = dv;
            let mut dth = dth;
            if let Some((a, w)) = self.gyro_step
                && self.t_us >= a
            {
                dth += w * (DT_US as f64 * 1e-6);
            }
            if let Some((a, b, f)) = self.accel_fault
                && (a..b).contains(&self.t_us)
            {
                dv.x = f * (DT_US as f64 * 1e-6);
            }
            let ts = truth.state();
            let mut held = 1.0;
            if let Some((a, b)) = self.silent {
                if (a..b).contains(&self.t_us) {
                    self.states.push((self.t_us, ts));
                    continue;
                }
                if self.t_us == b {
                    held = (b - a + DT_US) as f64 / DT_US as f64;
                }
            }
            self.filter.imu(&ImuSample {
                t_us: self.t_us,
                dtheta_rad_body_frd: dth * held,
                dv_m_s_body_frd: dv * held,
                gap_sigma_dtheta_rad: 0.0,
                gap_sigma_dv_m_s: 0.0,
            });
            if self.t_us.is_multiple_of(100_000) {
                self.filter.measure(Measurement::Attitude(AttitudeFix {
                    t_capture_us: self.t_us,
                    q_nb: ts.q_nb,
                }));
            }
            if gps && self.t_us.is_multiple_of(200_000) {
                let n = Vector3::new(self.rng.normal(), self.rng.normal(), self.rng.normal());
                self.filter.measure(Measurement::GpsVelocity(VelocityFix {
                    t_capture_us: self.t_us,
                    v_ned_m_s: ts.v_ned_m_s + n * 0.1,
                    cov_ned_m2_s2: Matrix3::identity() * 0.01,
                }));
                let n = Vector3::new(self.rng.normal(), self.rng.normal(), self.rng.normal());
                let jump = match self.gps_jump {
                    Some((a, b, j)) if (a..b).contains(&self.t_us) => j,
                    _ => Vector3::zeros(),
                };
                self.filter.measure(Measurement::GpsPosition(fix_at(
                    &ts,
                    self.t_us,
                    n * 1.5 + jump,
                    1.5,
                )));
            }
            each(&mut self.filter, self.t_us, &ts);
            self.states.push((self.t_us, ts));
        }
    }

    fn truth_at(&self, t_us: u64) -> InsState {
        self.states[(t_us / DT_US - 1) as usize].1.clone()
    }

    fn pos_err(&self) -> Vector3<f64> {
        let s = self.filter.state().expect("initialised");
        let t = self.truth_at(self.filter.t_us().expect("t"));
        earth::ned_offset_m((s.lat_rad, s.lon_rad, s.h_m), (t.lat_rad, t.lon_rad, t.h_m))
    }
}

/// Squared horizontal distance of the filter's position from the truth `ts`, m^2.
fn horizontal_err2(f: &NavFilter, ts: &InsState) -> f64 {
    let s = f.state().expect("initialised");
    let d = earth::ned_offset_m(
        (s.lat_rad, s.lon_rad, s.h_m),
        (ts.lat_rad, ts.lon_rad, ts.h_m),
    );
    d.x * d.x + d.y * d.y
}

fn check_pd(f: &NavFilter) {
    let p = f.covariance().expect("covariance");
    assert_eq!(p.nrows(), f.n_states());
    assert!((&p - p.transpose()).abs().max() <= 1e-12 * p.abs().max());
    let min_eig = p.clone().symmetric_eigenvalues().min();
    assert!(
        min_eig > 0.0,
        "covariance not positive definite: min eigenvalue {min_eig}"
    );
}

#[test]
fn covariance_stays_symmetric_pd_and_outlier_is_gated() {
    let mut imu = SimImuConfig::perfect(100.0);
    imu.gyro_arw_deg_sqrt_h = 0.1;
    imu.accel_vrw_m_s_sqrt_h = 0.03;
    let mut h = Harness::new(NavConfig::default(), imu);
    assert_eq!(h.filter.health().0, Health::Lost);
    let mut k = 0;
    h.fly(60.0, true, |f, _, _| {
        k += 1;
        if k % 250 == 0 && f.is_initialised() {
            check_pd(f);
        }
    });
    assert!(h.filter.is_initialised());
    assert_eq!(h.filter.health().0, Health::Ok, "{:?}", h.filter.health());
    assert!(h.pos_err().norm() < 3.0, "{:?}", h.pos_err());
    // A vision fix 50 m off with a 3 m sigma is rejected and counted; a good one is accepted.
    let t = h.filter.t_us().expect("t");
    let truth = h.truth_at(t);
    let out = h.filter.measure(Measurement::Vision(fix_at(
        &truth,
        t,
        Vector3::new(30.0, 40.0, 0.0),
        3.0,
    )));
    assert!(
        matches!(out, Outcome::Rejected { nis, .. } if nis > 100.0),
        "{out:?}"
    );
    assert_eq!(h.filter.counters().vision.rejected, 1);
    let out = h.filter.measure(Measurement::Vision(fix_at(
        &truth,
        t,
        Vector3::new(1.0, -1.0, 0.5),
        3.0,
    )));
    assert!(matches!(out, Outcome::Accepted { .. }), "{out:?}");
    assert_eq!(h.filter.counters().vision.accepted, 1);
    // Malformed and stale inputs are refused and counted.
    let mut bad = fix_at(&truth, t, Vector3::zeros(), 3.0);
    bad.lat_rad = f64::NAN;
    assert!(matches!(
        h.filter.measure(Measurement::Vision(bad)),
        Outcome::Invalid(_)
    ));
    let mut bad = fix_at(&truth, t, Vector3::zeros(), 3.0);
    bad.cov_ned_m2[(0, 0)] = -1.0;
    assert!(matches!(
        h.filter.measure(Measurement::Vision(bad)),
        Outcome::Invalid(_)
    ));
    let old = fix_at(&truth, t - 5_000_000, Vector3::zeros(), 3.0);
    assert_eq!(h.filter.measure(Measurement::Vision(old)), Outcome::TooOld);
    let c = h.filter.counters().vision;
    assert_eq!((c.invalid, c.too_old), (2, 1));
    check_pd(&h.filter);
}

#[test]
fn divergence_reset_after_consecutive_rejections() {
    let mut h = Harness::new(NavConfig::default(), SimImuConfig::perfect(100.0));
    h.fly(30.0, true, |_, _, _| {});
    // The aircraft is really 300 m north of where the filter thinks (e.g. after a wrong init):
    // fixes keep being rejected until the divergence detector resets onto them. 300 m within a
    // second of the last GPS fix is more than the filter can have drifted (a step: a jumping
    // source looks the same), so the reset waits until they have been rejected `step_reset_s`.
    let health = NavConfig::default().health;
    let n_reset = (health.divergence_reject_count as usize).max(health.step_reset_s as usize + 1);
    let mut outcomes = Vec::new();
    let mut waiting_said = false;
    h.fly(15.0, false, |f, t, ts| {
        if t.is_multiple_of(1_000_000) {
            outcomes.push(f.measure(Measurement::Vision(fix_at(
                ts,
                t,
                Vector3::new(300.0, 0.0, 0.0),
                3.0,
            ))));
            waiting_said |= f.health().1.to_string().contains("stepped 300 m");
        }
    });
    assert!(waiting_said, "the health never said why it waits");
    let resets = outcomes.iter().filter(|o| **o == Outcome::Reset).count();
    assert_eq!(resets, 1, "{outcomes:?}");
    assert_eq!(
        outcomes.iter().position(|o| *o == Outcome::Reset),
        Some(n_reset - 1)
    );
    assert!(
        matches!(outcomes.last(), Some(Outcome::Accepted { .. })),
        "{outcomes:?}"
    );
    assert_eq!(h.filter.counters().divergence_resets, 1);
    let e = h.pos_err();
    assert!((e.x - 300.0).abs() < 10.0 && e.y.abs() < 10.0, "{e:?}");
    let (health, why) = h.filter.health();
    assert_eq!(health, Health::Degraded);
    assert!(why.to_string().contains("reset"), "{why}");
}

/// Wrong relocalisations (fixes without a prior land hundreds of metres off, each
/// claiming tens of metres) disagree with each other: the filter must not reset onto any of them,
/// however many it rejects, and says why in its health.
#[test]
fn scattered_wrong_fixes_never_reset_the_filter() {
    let mut h = Harness::new(NavConfig::default(), SimImuConfig::perfect(100.0));
    h.fly(30.0, true, |_, _, _| {});
    let offsets = [
        Vector3::new(310.0, -40.0, 0.0),
        Vector3::new(-250.0, 380.0, 0.0),
        Vector3::new(20.0, 600.0, 0.0),
        Vector3::new(500.0, 90.0, 0.0),
        Vector3::new(-330.0, -280.0, 0.0),
        Vector3::new(420.0, -510.0, 0.0),
        Vector3::new(-60.0, 350.0, 0.0),
    ];
    let mut outcomes = Vec::new();
    h.fly(8.0, false, |f, t, ts| {
        if t.is_multiple_of(1_000_000) {
            let k = outcomes.len() % offsets.len();
            outcomes.push(f.measure(Measurement::Vision(fix_at(ts, t, offsets[k], 40.0))));
        }
    });
    assert!(
        outcomes
            .iter()
            .all(|o| matches!(o, Outcome::Rejected { .. })),
        "{outcomes:?}"
    );
    let c = h.filter.counters();
    assert_eq!(c.divergence_resets, 0);
    assert!(c.resets_refused >= 1, "{c:?}");
    let e = h.pos_err();
    assert!(e.x.abs() < 5.0 && e.y.abs() < 5.0, "{e:?}");
    let (health, why) = h.filter.health();
    assert_eq!(health, Health::Degraded);
    assert!(why.to_string().contains("disagree"), "{why}");
}

#[test]
fn health_degrades_without_fixes() {
    let mut h = Harness::new(NavConfig::default(), SimImuConfig::perfect(100.0));
    h.fly(20.0, true, |_, _, _| {});
    assert_eq!(h.filter.health().0, Health::Ok);
    h.fly(12.0, false, |_, _, _| {});
    let (health, why) = h.filter.health();
    assert_eq!(health, Health::Degraded);
    assert!(
        why.to_string().contains("no accepted position fix"),
        "{why}"
    );
    let out = h.filter.output().expect("output");
    assert_eq!(out.health, Health::Degraded);
    assert!(out.cov_pos_ned_m2[0][0] > 0.0);
}

/// Horizontal position sigma of the filter's output, m.
fn sigma_h(f: &NavFilter) -> f64 {
    let c = f.output().expect("output").cov_pos_ned_m2;
    (c[0][0] + c[1][1]).sqrt()
}

/// A sigma hovering at the `degraded` threshold does not flip the health at every fix: once
/// over it, health is `ok` again only below `SIGMA_HEALTH_RECOVER_FRACTION` of it.
#[test]
fn health_recovers_from_sigma_only_past_the_hysteresis() {
    use visnav_core::nav::filter::SIGMA_HEALTH_RECOVER_FRACTION as RECOVER;
    let mut cfg = NavConfig::default();
    cfg.health.degraded_no_fix_s = 1e4; // only the sigma speaks here
    cfg.health.lost_no_fix_s = 2e4;
    let thr = cfg.health.degraded_pos_sigma_m;
    let mut h = Harness::new(cfg, SimImuConfig::perfect(100.0));
    h.fly(20.0, true, |_, _, _| {});
    assert_eq!(h.filter.health().0, Health::Ok);
    // Dead reckoning until the sigma passes the threshold.
    for _ in 0..600 {
        if sigma_h(&h.filter) > thr {
            break;
        }
        h.fly(1.0, false, |_, _, _| {});
    }
    assert!(sigma_h(&h.filter) > thr, "sigma never reached {thr} m");
    assert_eq!(h.filter.health().0, Health::Degraded);
    // A fix that takes the sigma just under the threshold (inside the hysteresis band).
    let target = 0.5 * (1.0 + RECOVER) * thr;
    let fix_sigma = |f: &NavFilter, target: f64| {
        let p = sigma_h(f).powi(2) / 2.0; // per axis
        let q = target * target / 2.0;
        (p * q / (p - q)).sqrt()
    };
    let mut band = None;
    h.fly(0.02, false, |f, t, ts| {
        if band.is_none() {
            let r = fix_sigma(f, target);
            f.measure(Measurement::GpsPosition(fix_at(ts, t, Vector3::zeros(), r)));
            band = Some((sigma_h(f), f.health()));
        }
    });
    let (sig, (health, why)) = band.expect("fix");
    assert!(
        sig > RECOVER * thr && sig < thr,
        "test set-up: sigma {sig} m not in the band ({}, {thr}) m",
        RECOVER * thr
    );
    assert_eq!(health, Health::Degraded, "left degraded inside the band");
    assert!(why.to_string().contains("horizontal sigma"), "{why}");
    // Below the band: ok again.
    h.fly(0.02, false, |f, t, ts| {
        if sigma_h(f) > RECOVER * thr {
            let r = fix_sigma(f, 0.7 * thr);
            f.measure(Measurement::GpsPosition(fix_at(ts, t, Vector3::zeros(), r)));
        }
    });
    assert!(sigma_h(&h.filter) < RECOVER * thr);
    assert_eq!(h.filter.health().0, Health::Ok, "{}", h.filter.health().1);
}

#[test]
fn initialises_from_vision_and_attitude_without_gps() {
    let mut imu = SimImuConfig::perfect(100.0);
    imu.gyro_arw_deg_sqrt_h = 0.1;
    imu.accel_vrw_m_s_sqrt_h = 0.03;
    let mut h = Harness::new(NavConfig::default(), imu);
    let mut rng = Rng::new(11);
    let mut outs = Vec::new();
    h.fly(60.0, false, |f, t, ts| {
        if t.is_multiple_of(1_000_000) {
            let n = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 2.5;
            outs.push(f.measure(Measurement::Vision(fix_at(ts, t, n, 2.5))));
        }
    });
    // First fix held (no velocity yet), second initialises (velocity from the two fixes).
    assert_eq!(outs[0], Outcome::Held);
    assert_eq!(outs[1], Outcome::Initialised);
    assert!(
        outs[2..]
            .iter()
            .all(|o| matches!(o, Outcome::Accepted { .. })),
        "{outs:?}"
    );
    let e = h.pos_err();
    assert!(e.xy().norm() < 6.0, "{e:?}");
    let p = h.filter.covariance().expect("p");
    assert!(p[(0, 0)].sqrt() < 5.0);
    check_pd(&h.filter);
}

#[test]
fn fifteen_twentyone_and_twentyseven_states() {
    for (scale, drift, n) in [
        (false, false, 15),
        (true, false, 21),
        (false, true, 21),
        (true, true, 27),
    ] {
        let cfg = NavConfig {
            scale_factor_states: scale,
            bias_drift_states: drift,
            ..Default::default()
        };
        let mut h = Harness::new(cfg, SimImuConfig::perfect(100.0));
        h.fly(20.0, true, |_, _, _| {});
        assert_eq!(h.filter.n_states(), n);
        check_pd(&h.filter);
        assert!(h.pos_err().norm() < 3.0, "{n} states: {}", h.pos_err());
        // The 15 navigation errors with the total bias: symmetric PD whatever the layout.
        let p = h.filter.nav_error_covariance().expect("p15");
        assert!((p - p.transpose()).abs().max() < 1e-12);
        assert!(p.cholesky().is_some());
    }
}

/// `[nav] vision_attitude`: a vision fix fused as a full pose (position + attitude with their 6x6
/// covariance) keeps the tilt observable when the gyro is poor (PX4 SIH's gyro random walk is
/// about 25 deg/sqrt(h)), where the same fixes fused as positions (their marginal covariance)
/// leave the tilt to the slow position innovations. The fix errors are drawn from the stated
/// covariance, with the flat-ground ambiguity of a real resection: the horizontal position error
/// is the height times the tilt error (correlation 0.99), so neither is known alone.
#[test]
fn vision_pose_fixes_keep_the_tilt_observable_with_a_noisy_gyro() {
    use nalgebra::{Matrix6, UnitQuaternion, Vector6};
    use visnav_core::nav::PoseFix;
    let height_m = 1500.0;
    let tilt_sd = 1.0f64.to_radians();
    let (pos_sd, yaw_sd, vert_sd) = (3.0, 0.3f64.to_radians(), 5.0);
    // Latent independent errors [tilt about N, tilt about E, yaw, n_N, n_E, n_D] to the error
    // vector [pos N, E, D, psi N, E, D].
    let mut a = Matrix6::<f64>::zeros();
    a[(1, 0)] = height_m * tilt_sd; // a tilt about north shifts the solution east
    a[(0, 1)] = -height_m * tilt_sd;
    a[(3, 0)] = tilt_sd;
    a[(4, 1)] = tilt_sd;
    a[(5, 2)] = yaw_sd;
    a[(0, 3)] = pos_sd;
    a[(1, 4)] = pos_sd;
    a[(2, 5)] = vert_sd;
    let cov6 = a * a.transpose();
    let run = |pose: bool| -> (f64, f64, f64) {
        let mut imu = SimImuConfig::perfect(100.0);
        imu.gyro_arw_deg_sqrt_h = 25.0;
        imu.accel_vrw_m_s_sqrt_h = 0.5;
        let mut cfg = NavConfig::default();
        cfg.imu.gyro_arw_deg_sqrt_h = 25.0;
        cfg.imu.accel_vrw_m_s_sqrt_h = 0.5;
        let mut h = Harness::new(cfg, imu);
        h.fly(30.0, true, |_, _, _| {});
        assert!(h.filter.is_initialised());
        let mut rng = Rng::new(9);
        let (mut tilt2, mut pos2, mut n) = (0.0, 0.0, 0usize);
        let (mut nis_sum, mut nis_n) = (0.0, 0usize);
        let t_off = h.t_us;
        h.fly(120.0, false, |f, t, ts| {
            if t.is_multiple_of(500_000) {
                let z = Vector6::from_fn(|_, _| rng.normal());
                let e = a * z;
                let fix = fix_at(ts, t, Vector3::new(e[0], e[1], e[2]), 1.0);
                let psi = Vector3::new(e[3], e[4], e[5]);
                let m = if pose {
                    Measurement::VisionPose(PoseFix {
                        position: PositionFix {
                            cov_ned_m2: cov6.fixed_view::<3, 3>(0, 0).into_owned(),
                            ..fix
                        },
                        q_nb: UnitQuaternion::from_scaled_axis(psi) * ts.q_nb,
                        cov6,
                    })
                } else {
                    Measurement::Vision(PositionFix {
                        cov_ned_m2: cov6.fixed_view::<3, 3>(0, 0).into_owned(),
                        ..fix
                    })
                };
                if let Outcome::Accepted { nis } = f.measure(m) {
                    nis_sum += nis;
                    nis_n += 1;
                }
            }
            // Score the last 60 s.
            if t > t_off + 60_000_000 && t.is_multiple_of(100_000) {
                let s = f.state().expect("initialised");
                let tilt = (s.q_nb * ts.q_nb.inverse()).scaled_axis();
                tilt2 += tilt.x * tilt.x + tilt.y * tilt.y;
                pos2 += horizontal_err2(f, ts);
                n += 1;
            }
        });
        assert!(nis_n > 200, "fixes accepted: {nis_n}");
        let nis_mean = nis_sum / nis_n as f64;
        (
            (tilt2 / n as f64).sqrt().to_degrees(),
            (pos2 / n as f64).sqrt(),
            nis_mean,
        )
    };
    let (tilt_pose, pos_pose, nis_pose) = run(true);
    let (tilt_pos, pos_pos, nis_pos) = run(false);
    eprintln!(
        "last 60 s RMS: pose fixes tilt {tilt_pose:.3} deg, horizontal {pos_pose:.1} m, NIS {nis_pose:.2} (6 dof); \
         position fixes tilt {tilt_pos:.3} deg, horizontal {pos_pos:.1} m, NIS {nis_pos:.2} (3 dof)"
    );
    // Each pose fix knows the tilt to 1 deg alone, two per second against a 25 deg/sqrt(h) gyro:
    // the steady-state sigma of that random walk is sqrt(q R dt) = 0.54 deg (measured 0.46).
    assert!(tilt_pose < 0.6, "tilt with pose fixes {tilt_pose} deg");
    assert!(tilt_pose < 0.7 * tilt_pos, "{tilt_pose} vs {tilt_pos}");
    assert!(pos_pose < pos_pos, "{pos_pose} vs {pos_pos}");
    assert!((4.0..8.0).contains(&nis_pose), "6-dof NIS mean {nis_pose}");
}

/// A position fix solved with the filter's own attitude as its prior follows that attitude's
/// error: `z = p + D psi_filter + e`. Fused with `D` in the attitude Jacobian
/// (`PositionFix::att_dependence_ned`) and the image's covariance, the filter does not read its
/// own tilt back as a position confirmation; fused as a plain position with the total covariance
/// (`Cov(e) + D P D^T`, what the fix reports), it does, and its position error grows.
#[test]
fn position_fixes_with_their_prior_dependence_are_not_double_counted() {
    // A 5 deg/sqrt(h) gyro without autopilot attitude: the filter's tilt wanders by tenths of a
    // degree, hundreds of metres per radian at this height.
    let height_m = 1500.0;
    // The fix follows 90 % of the prior's tilt (a strong prior over flat ground).
    let w = 0.9 * height_m;
    let d = Matrix3::new(0.0, -w, 0.0, w, 0.0, 0.0, 0.0, 0.0, 0.0);
    let img_sd = 4.0;
    let prior_tilt_sd = 0.5f64.to_radians();
    let p_prior = Matrix3::from_diagonal(&Vector3::new(
        prior_tilt_sd * prior_tilt_sd,
        prior_tilt_sd * prior_tilt_sd,
        0.0,
    ));
    let total = Matrix3::identity() * img_sd * img_sd + d * p_prior * d.transpose();
    let run = |model: bool| -> (f64, f64) {
        let mut imu = SimImuConfig::perfect(100.0);
        imu.gyro_arw_deg_sqrt_h = 5.0;
        imu.accel_vrw_m_s_sqrt_h = 0.5;
        let mut cfg = NavConfig::default();
        cfg.imu.gyro_arw_deg_sqrt_h = 5.0;
        cfg.imu.accel_vrw_m_s_sqrt_h = 0.5;
        cfg.attitude_sigma_tilt_deg = 0.5;
        let mut h = Harness::new(cfg, imu);
        h.fly(30.0, true, |_, _, _| {});
        assert!(h.filter.is_initialised());
        let mut rng = Rng::new(17);
        let (mut pos2, mut n, mut nis_sum, mut nis_n) = (0.0, 0usize, 0.0, 0usize);
        let t_off = h.t_us;
        h.fly(120.0, false, |f, t, ts| {
            if t.is_multiple_of(500_000) {
                let s = f.state().expect("initialised");
                let psi = (s.q_nb * ts.q_nb.inverse()).scaled_axis();
                let e = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * img_sd;
                let fix = fix_at(ts, t, d * psi + e, img_sd);
                let m = if model {
                    PositionFix {
                        att_dependence_ned: Some(d),
                        ..fix
                    }
                } else {
                    PositionFix {
                        cov_ned_m2: total,
                        ..fix
                    }
                };
                if let Outcome::Accepted { nis } = f.measure(Measurement::Vision(m)) {
                    nis_sum += nis;
                    nis_n += 1;
                }
            }
            if t > t_off + 60_000_000 && t.is_multiple_of(100_000) {
                pos2 += horizontal_err2(f, ts);
                n += 1;
            }
        });
        assert!(nis_n > 150, "fixes accepted: {nis_n}");
        ((pos2 / n as f64).sqrt(), nis_sum / nis_n as f64)
    };
    let (pos_model, nis_model) = run(true);
    let (pos_plain, nis_plain) = run(false);
    eprintln!(
        "last 60 s horizontal RMS: with the dependence {pos_model:.1} m (NIS {nis_model:.2}), \
         plain position {pos_plain:.1} m (NIS {nis_plain:.2})"
    );
    assert!(pos_model < 0.7 * pos_plain, "{pos_model} vs {pos_plain}");
    assert!((1.5..5.0).contains(&nis_model), "NIS {nis_model}");
}

/// The vision position bias states (`[nav] vision_bias_*`): fixes whose error is mostly a
/// ground-shared bias (a Gauss-Markov process in distance, the model's own) plus 3 m of noise.
/// GPS for 60 s with fixes (the bias is calibrated), then 120 s of fixes alone, then 30 s without
/// anything. Without bias states the filter follows the biased fixes and claims their white
/// noise's accuracy; with them it starts the outage on the calibrated bias and its covariance
/// covers the error throughout.
#[test]
fn vision_bias_states_calibrate_the_map_offset_and_stay_honest() {
    let (sig_h, sig_v, dist_m, noise_m) = (6.0, 4.0, 3000.0, 3.0);
    // corr_s > 0: no bias states, the fixes de-weighted by `vision_error_corr_time_s` instead.
    let run = |bias_states: bool, corr_s: f64, seed: u64| -> (f64, f64, f64) {
        let mut imu = SimImuConfig::perfect(100.0);
        imu.gyro_arw_deg_sqrt_h = 0.3;
        imu.accel_vrw_m_s_sqrt_h = 0.1;
        let mut cfg = NavConfig::default();
        cfg.imu.gyro_arw_deg_sqrt_h = 0.3;
        cfg.imu.accel_vrw_m_s_sqrt_h = 0.1;
        cfg.attitude_sigma_tilt_deg = 0.5;
        if bias_states {
            cfg.vision_bias_sigma_h_m = sig_h;
            cfg.vision_bias_sigma_v_m = sig_v;
            cfg.vision_bias_corr_dist_m = dist_m;
        }
        cfg.vision_error_corr_time_s = corr_s;
        let mut h = Harness::new(cfg, imu);
        // 15 + 6 drift states (default) + 3 bias states.
        assert_eq!(h.filter.n_states(), if bias_states { 24 } else { 21 });
        let mut rng = Rng::new(seed);
        let sig = Vector3::new(sig_h, sig_h, sig_v);
        let mut b = sig.component_mul(&Vector3::new(rng.normal(), rng.normal(), rng.normal()));
        // Truth bias: the same Gauss-Markov process in distance (51.44 m/s, fixes at 2 Hz).
        let phi = (-51.44 * 0.5 / dist_m).exp();
        let mut step_fix = |f: &mut NavFilter, t: u64, ts: &InsState, rng: &mut Rng| {
            let w = Vector3::new(rng.normal(), rng.normal(), rng.normal());
            b = b * phi + sig.component_mul(&w) * (1.0 - phi * phi).sqrt();
            let e = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * noise_m;
            f.measure(Measurement::Vision(fix_at(ts, t, b + e, noise_m)));
        };
        h.fly(60.0, true, |f, t, ts| {
            if t.is_multiple_of(500_000) {
                step_fix(f, t, ts, &mut rng);
            }
        });
        let t_off = h.t_us;
        let (mut e2_early, mut n_early, mut nees, mut n_nees) = (0.0, 0usize, 0.0, 0usize);
        h.fly(150.0, false, |f, t, ts| {
            if t <= t_off + 120_000_000 && t.is_multiple_of(500_000) {
                step_fix(f, t, ts, &mut rng);
            }
            if t.is_multiple_of(1_000_000) {
                let e2 = horizontal_err2(f, ts);
                if t <= t_off + 30_000_000 {
                    e2_early += e2;
                    n_early += 1;
                }
                // Horizontal NEES (2 dof) against the filter's position covariance.
                let s = f.state().expect("initialised");
                let d = earth::ned_offset_m(
                    (s.lat_rad, s.lon_rad, s.h_m),
                    (ts.lat_rad, ts.lon_rad, ts.h_m),
                );
                let p = f.covariance().expect("covariance");
                let c = nalgebra::Matrix2::new(p[(0, 0)], p[(0, 1)], p[(1, 0)], p[(1, 1)]);
                let dh = nalgebra::Vector2::new(d.x, d.y);
                nees += dh.dot(&(c.try_inverse().expect("pd") * dh));
                n_nees += 1;
            }
        });
        check_pd(&h.filter);
        if bias_states {
            // The bias was calibrated under GPS and then decayed over 9 km: its variance is back
            // near the stationary one, not collapsed.
            let (_, pb) = h.filter.vision_bias().expect("bias states");
            assert!(pb[(0, 0)] > 0.25 * sig_h * sig_h && pb[(2, 2)] > 0.25 * sig_v * sig_v);
        } else {
            assert!(h.filter.vision_bias().is_none());
        }
        (
            (e2_early / n_early as f64).sqrt(),
            nees / n_nees as f64,
            h.filter.counters().vision.accepted as f64,
        )
    };
    let (mut rms_b, mut nees_b, mut rms_p, mut nees_p) = (0.0, 0.0, 0.0, 0.0);
    let (mut rms_c, mut nees_c) = (0.0, 0.0);
    let seeds = [3u64, 8, 21, 34];
    for &seed in &seeds {
        let (r, n, acc) = run(true, 0.0, seed);
        assert!(acc > 300.0, "fixes accepted with bias states: {acc}");
        let (r0, n0, _) = run(false, 0.0, seed);
        // The correlation time of the truth bias: L / v.
        let (rc, nc, _) = run(false, dist_m / 51.44, seed);
        eprintln!(
            "seed {seed}: first 30 s without GPS horizontal RMS {r:.2} m (bias states) vs \
             {r0:.2} m (none) and {rc:.2} m (correlation time); horizontal NEES over the \
             outage {n:.2} vs {n0:.2} and {nc:.2}"
        );
        rms_b += r / seeds.len() as f64;
        nees_b += n / seeds.len() as f64;
        rms_p += r0 / seeds.len() as f64;
        nees_p += n0 / seeds.len() as f64;
        rms_c += rc / seeds.len() as f64;
        nees_c += nc / seeds.len() as f64;
    }
    eprintln!(
        "mean: RMS {rms_b:.2} vs {rms_p:.2} and {rms_c:.2} m, NEES {nees_b:.2} vs {nees_p:.2} \
         and {nees_c:.2} (2 dof: 2 is honest)"
    );
    // The correlation time de-weights the fixes enough here, but its covariance is less honest.
    assert!(nees_c > nees_b, "{nees_c} vs {nees_b}");
    assert!(rms_b < 0.6 * rms_p, "{rms_b} vs {rms_p}");
    assert!(
        (0.5..4.0).contains(&nees_b),
        "NEES with bias states {nees_b}"
    );
    assert!(nees_p > 2.0 * nees_b, "NEES without bias states {nees_p}");
}

/// Bias states with a horizontal bias only (`vision_bias_sigma_v_m = 0`): initialised from vision,
/// then a divergence reset onto vision fixes 300 m off. The zero vertical variance is floored, so
/// the reset does not leave a singular covariance (which would trigger a covariance reset).
#[test]
fn vision_bias_states_survive_init_and_reset_from_vision_with_a_zero_vertical_sigma() {
    let mut imu = SimImuConfig::perfect(100.0);
    imu.gyro_arw_deg_sqrt_h = 0.1;
    imu.accel_vrw_m_s_sqrt_h = 0.03;
    let cfg = NavConfig {
        vision_bias_sigma_h_m: 5.0,
        vision_bias_sigma_v_m: 0.0,
        ..NavConfig::default()
    };
    let n_reset = cfg.health.divergence_reject_count;
    let mut h = Harness::new(cfg, imu);
    let mut rng = Rng::new(13);
    let mut outs = Vec::new();
    h.fly(20.0, false, |f, t, ts| {
        if t.is_multiple_of(1_000_000) {
            let n = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 2.0;
            outs.push(f.measure(Measurement::Vision(fix_at(ts, t, n, 2.0))));
        }
    });
    assert_eq!(outs[1], Outcome::Initialised, "{outs:?}");
    // Initialised on a vision fix: the position carries the bias's variance.
    let p = h.filter.covariance().expect("covariance");
    assert!(p[(0, 0)] > 2.0 * 2.0, "{}", p[(0, 0)]);
    let mut resets = 0;
    // A 300 m step: reset onto after `step_reset_s` of rejections (see the test above).
    let wait_s = (n_reset as f64).max(h.filter.config().health.step_reset_s + 1.0);
    h.fly(wait_s + 5.0, false, |f, t, ts| {
        if t.is_multiple_of(1_000_000) {
            let o = f.measure(Measurement::Vision(fix_at(
                ts,
                t,
                Vector3::new(300.0, 0.0, 0.0),
                2.0,
            )));
            resets += usize::from(o == Outcome::Reset);
        }
    });
    let c = h.filter.counters();
    assert_eq!((resets, c.divergence_resets), (1, 1));
    assert_eq!(
        c.covariance_resets, 0,
        "the reset left a singular covariance"
    );
    let (b, pb) = h.filter.vision_bias().expect("bias states");
    assert!(b.iter().all(|x| x.is_finite()));
    assert!(
        (pb[(0, 0)] - 25.0).abs() < 25.0 && pb[(2, 2)] >= 0.0,
        "{pb}"
    );
}

/// In a steep turn the specific force has a horizontal part, so a tilt error drives a vertical
/// velocity error and the barometer observes the tilt (PX4 SIH replays: barometer
/// updates at 15-34 deg of bank moved the roll by about 2 deg). Those corrections must go the
/// right way: with a gyro that lets the tilt wander, a 30 deg turn on the barometer alone keeps
/// the tilt within the filter's own bounds and no worse than flying the turn without it. A
/// wrong-signed coupling would feed the barometer's noise into the tilt.
#[test]
fn barometer_in_a_steep_turn_corrects_the_tilt_the_right_way() {
    let g = 9.80665;
    let v = 51.44;
    let turn_rate = g * 30f64.to_radians().tan() / v; // coordinated, 30 deg of bank
    let traj = || {
        let seg = |duration_s: f64, turn_rate_rad_s: f64| Segment {
            duration_s,
            speed_m_s: v,
            turn_rate_rad_s,
            path_angle_rad: 0.0,
            ramp_s: 2.0,
        };
        Trajectory::new(
            46.9f64.to_radians(),
            (-100.8f64).to_radians(),
            1500.0,
            v,
            90f64.to_radians(),
            vec![seg(60.0, 0.0), seg(90.0, turn_rate), seg(600.0, 0.0)],
        )
    };
    // Returns (RMS tilt error deg, largest tilt NEES (2 dof), largest bank deg) over the turn.
    let fly = |baro: bool| -> (f64, f64, f64) {
        let mut imu = SimImuConfig::perfect(100.0);
        imu.gyro_arw_deg_sqrt_h = 3.0;
        imu.accel_vrw_m_s_sqrt_h = 0.1;
        let mut cfg = NavConfig::default();
        cfg.imu.gyro_arw_deg_sqrt_h = 3.0;
        cfg.imu.accel_vrw_m_s_sqrt_h = 0.1;
        let mut h = Harness::with_trajectory(cfg, imu, traj());
        h.fly(60.0, true, |_, _, _| {});
        assert!(h.filter.is_initialised());
        let mut rng = Rng::new(21);
        let (mut sum2, mut n, mut nees_max, mut bank_max) = (0.0, 0usize, 0.0f64, 0.0f64);
        h.fly(90.0, false, |f, t, ts| {
            if !t.is_multiple_of(100_000) {
                return;
            }
            if baro {
                let out = f.measure(Measurement::Altitude(AltitudeFix {
                    t_capture_us: t,
                    h_m: ts.h_m + 0.5 * rng.normal(),
                    var_m2: 0.25,
                }));
                assert!(matches!(out, Outcome::Accepted { .. }), "{out:?}");
            }
            let s = f.state().expect("initialised");
            let psi = (s.q_nb * ts.q_nb.inverse()).scaled_axis();
            let p = f.nav_error_covariance().expect("covariance");
            let p2 = p.fixed_view::<2, 2>(6, 6).into_owned();
            let e = nalgebra::Vector2::new(psi.x, psi.y);
            let nees = (e.transpose() * p2.try_inverse().expect("pd") * e)[0];
            nees_max = nees_max.max(nees);
            sum2 += e.norm_squared();
            n += 1;
            let (roll, _, _) = ts.q_nb.euler_angles();
            bank_max = bank_max.max(roll.abs().to_degrees());
        });
        ((sum2 / n as f64).sqrt().to_degrees(), nees_max, bank_max)
    };
    let (rms_baro, nees_baro, bank) = fly(true);
    let (rms_free, nees_free, _) = fly(false);
    eprintln!(
        "30 deg turn: tilt RMS {rms_baro:.3} deg with the barometer (NEES max {nees_baro:.1}), {rms_free:.3} deg without ({nees_free:.1}); bank {bank:.1} deg"
    );
    assert!((25.0..35.0).contains(&bank), "bank {bank}");
    // chi-square(2) 99.9 % is 13.8; over 900 correlated epochs allow a little more.
    assert!(nees_baro < 16.0, "tilt NEES {nees_baro} with the barometer");
    // The barometer observes the tilt in the turn (0.22 against 0.43 deg when written): it must
    // correct it, not merely leave it alone.
    assert!(
        rms_baro < 0.8 * rms_free,
        "the barometer did not correct the tilt: {rms_baro} vs {rms_free} deg"
    );
}

/// 4 s of the accelerometer's x axis stuck at 16 g or 50 g (a vibration burst,
/// a glitch) while the GPS aids, then normal data. The samples at or beyond the sensor's range
/// are clipped, so what they say is not integrated; the filter must be navigating again within
/// seconds, without a reset loop (before: no usable output for 40-90 s, a divergence reset about
/// once a second).
#[test]
fn a_strong_accelerometer_fault_is_survived() {
    for g in [16.0, 50.0] {
        let mut imu = SimImuConfig::perfect(100.0);
        imu.accel_vrw_m_s_sqrt_h = 0.03;
        let mut h = Harness::new(NavConfig::default(), imu);
        h.fly(60.0, true, |_, _, _| {});
        let (a, b) = (h.t_us, h.t_us + 4_000_000);
        h.accel_fault = Some((a, b, g * 9.80665));
        let mut lost_after = Vec::new();
        h.fly(20.0, true, |f, t, _| {
            if t > b + 3_000_000 && f.health().0 == Health::Lost {
                lost_after.push(t);
            }
        });
        assert!(
            lost_after.is_empty(),
            "{g} g: navigation lost {} times more than 3 s after the fault ({:?})",
            lost_after.len(),
            h.filter.health()
        );
        let c = h.filter.counters();
        assert_eq!(c.hard_resets, 0, "{g} g");
        assert!(
            c.divergence_resets <= 1,
            "{g} g: {} resets",
            c.divergence_resets
        );
        assert!(h.pos_err().norm() < 5.0, "{g} g: {:?}", h.pos_err());
        assert!(c.imu_clipped >= 390, "{g} g: {} clipped", c.imu_clipped);
    }
}

/// Scripted link silence: 5 s without any message from the autopilot (no IMU, no
/// attitude, no GPS), then the stream again. Before, the filter hard-reset on the gap and, with
/// vision alone, took 20 s or more to relocalise. Now the gap is bridged: no reset, an output on
/// the first sample after it, whose covariance grew by what the vehicle could have done unseen
/// and still contains the error; a gap beyond `max_imu_bridge_s` still restarts the filter.
#[test]
fn a_silent_link_is_bridged_not_reset() {
    let cfg = NavConfig {
        max_imu_gap_s: 0.5,
        ..NavConfig::default()
    };
    let mut h = Harness::new(cfg.clone(), SimImuConfig::perfect(100.0));
    h.fly(60.0, true, |_, _, _| {});
    let sigma_h = |f: &NavFilter| {
        let o = f.output().expect("output");
        (o.cov_pos_ned_m2[0][0].max(o.cov_pos_ned_m2[1][1])).sqrt()
    };
    let before = sigma_h(&h.filter);
    let (a, b) = (h.t_us + DT_US, h.t_us + DT_US + 5_000_000);
    h.silent = Some((a, b));
    let mut first_after = None;
    h.fly(5.2, false, |f, t, ts| {
        if t >= b && first_after.is_none() {
            first_after = Some((sigma_h(f), horizontal_err2(f, ts).sqrt()));
        }
    });
    let (after, err) = first_after.expect("an output after the gap");
    let c = h.filter.counters();
    assert_eq!((c.hard_resets, c.imu_bridged), (0, 1));
    eprintln!("5 s gap: sigma_h {before:.2} -> {after:.1} m, error {err:.2} m");
    // 3 m/s^2 unseen for 5 s: about 0.6 * 3 * 25 = 43 m.
    assert!(
        after > 20.0 && after < 100.0,
        "sigma after the gap {after} m"
    );
    assert!(
        err < 3.0 * after,
        "error {err} m beyond 3 sigma ({after} m)"
    );
    // The GPS back: the solution converges again without a reset.
    h.fly(20.0, true, |_, _, _| {});
    assert!(h.pos_err().norm() < 5.0, "{:?}", h.pos_err());
    assert_eq!(h.filter.counters().hard_resets, 0);

    // Beyond max_imu_bridge_s (10 s): a restart, as before.
    let mut h = Harness::new(cfg, SimImuConfig::perfect(100.0));
    h.fly(60.0, true, |_, _, _| {});
    h.silent = Some((h.t_us + DT_US, h.t_us + DT_US + 12_000_000));
    h.fly(12.1, true, |_, _, _| {});
    let c = h.filter.counters();
    assert_eq!((c.hard_resets, c.imu_bridged), (1, 0));
}

/// One finite but impossible sample (x = 1e30 m/s^2) every half second for
/// 30 s: before, each hard-reset the filter (141 of 309 outputs, a sigma of 3.5e23 m logged).
/// Now each is clipped and bridged; the solution stays healthy and its sigma small.
#[test]
fn impossible_imu_samples_change_nothing() {
    let mut h = Harness::new(NavConfig::default(), SimImuConfig::perfect(100.0));
    h.fly(60.0, true, |_, _, _| {});
    let mut worst_sigma: f64 = 0.0;
    for _ in 0..60 {
        // The next sample (at t + DT_US) is the impossible one.
        let t = h.t_us + 1;
        h.accel_fault = Some((t, t + DT_US, 1e30));
        h.fly(0.5, true, |f, _, _| {
            if let Some(o) = f.output() {
                let s = (o.cov_pos_ned_m2[0][0] + o.cov_pos_ned_m2[1][1]).sqrt();
                worst_sigma = worst_sigma.max(s);
                assert_ne!(o.health, Health::Lost, "{}", o.reason);
            }
        });
    }
    let c = h.filter.counters();
    assert_eq!(c.hard_resets, 0);
    assert_eq!(c.imu_clipped, 60);
    assert!(worst_sigma < 5.0, "sigma {worst_sigma} m");
    assert!(h.pos_err().norm() < 5.0, "{:?}", h.pos_err());
}

/// The aiding GPS jumps 10 km for 4 s. Before, the filter reset onto it after 5
/// rejections (1.2 s) and claimed 0.4-0.9 m. A step that the filter's error cannot have built
/// (here the GPS velocity keeps confirming the filter) is not reset onto while it is shorter than
/// `step_reset_s`: the solution stays on the truth, says the fixes are rejected, and takes the
/// GPS again when it comes back.
#[test]
fn a_jumping_gps_is_not_followed() {
    let mut h = Harness::new(NavConfig::default(), SimImuConfig::perfect(100.0));
    h.fly(60.0, true, |_, _, _| {});
    let (a, b) = (h.t_us, h.t_us + 4_000_000);
    h.gps_jump = Some((a, b, Vector3::new(10_000.0, 0.0, 0.0)));
    let mut worst: f64 = 0.0;
    let mut ok_during_jump = 0;
    h.fly(15.0, true, |f, t, ts| {
        worst = worst.max(horizontal_err2(f, ts).sqrt());
        if (a + 1_500_000..b).contains(&t) && f.health().0 == Health::Ok {
            ok_during_jump += 1;
        }
    });
    let c = h.filter.counters();
    assert_eq!(c.divergence_resets, 0);
    assert!(worst < 5.0, "followed the jump: {worst} m off");
    assert_eq!(
        ok_during_jump, 0,
        "health Ok while every GPS fix is rejected"
    );
    assert!(c.gps_position.rejected >= 19, "{:?}", c.gps_position);
    assert_eq!(h.filter.health().0, Health::Ok, "{:?}", h.filter.health());
}

/// A small aircraft's survey route at 300 m above flat ground: 20 m/s, legs of 20 s joined by
/// 90-degree turns of 10 s (bank about 18 deg).
fn survey_route() -> Trajectory {
    let leg = |turn: f64| Segment {
        duration_s: if turn == 0.0 { 20.0 } else { 10.0 },
        speed_m_s: 20.0,
        turn_rate_rad_s: turn,
        path_angle_rad: 0.0,
        ramp_s: 1.0,
    };
    let mut segs = Vec::new();
    for i in 0..12 {
        segs.push(leg(0.0));
        // Alternate the turn direction: a lawnmower pattern.
        let dir = if i % 2 == 0 { 1.0 } else { -1.0 };
        segs.push(leg(dir * 9f64.to_radians()));
    }
    Trajectory::new(
        46.9f64.to_radians(),
        (-100.8f64).to_radians(),
        880.0,
        20.0,
        0.0,
        segs,
    )
}

/// What one VO flight gives.
struct VoFlight {
    /// Horizontal error at the end of the outage, m.
    final_err_h_m: f64,
    /// The filter's horizontal sigma then, m.
    final_sigma_h_m: f64,
    /// Horizontal distance flown during the outage, m.
    distance_m: f64,
    /// Largest heading error during the outage, deg.
    yaw_err_deg_max: f64,
    /// Health and its reason at the end.
    health: (Health, visnav_core::nav::filter::HealthReason),
    counters: visnav_core::nav::Counters,
}

/// 60 s of GPS, then `outage_s` without any position fix: a barometer throughout and, when `vo`,
/// visual odometry at 5 Hz computed the way the daemon does it: from the filter's own pose at
/// the previous frame (its yaw error rotates the displacement, its height error and a terrain
/// model 0.8 m off scale it), 5 cm / 10 cm of image noise. The demo's consumer IMU; no autopilot
/// attitude after the initialisation (the heading is the filter's own).
fn vo_flight(vo: bool, outage_s: f64) -> VoFlight {
    vo_flight_with(vo, outage_s, YawRate::Consumer)
}

/// The gyros' yaw-rate error in a VO flight and whether the VO measures its rotation.
#[derive(Clone, Copy, PartialEq)]
enum YawRate {
    /// The demo's consumer IMU (10 deg/h about z), VO without a rotation measurement.
    Consumer,
    /// An autopilot's bias-compensated rates whose yaw-rate error moves by `bias_deg_h` as the
    /// GPS is lost (ArduCopter SITL's moved by up to 300 deg/h between flight phases), modelled
    /// by the filter as 200 deg/h of bias instability over 60 s; `rotation`: the VO also
    /// measures the rotation the images saw beyond the gyros' about the (vertical) line of sight.
    Autopilot { bias_deg_h: f64, rotation: bool },
}

fn vo_flight_with(vo: bool, outage_s: f64, yaw_rate: YawRate) -> VoFlight {
    const AGL_M: f64 = 300.0;
    const TERRAIN_ERR_M: f64 = 0.8;
    // The images' rotation about the line of sight per frame pair: what the odometer's
    // image-only resection gives at VGA (0.012 deg claimed, 0.004 deg scattered in the SITL).
    const ROT_SIGMA_RAD: f64 = 2e-4;
    let mut imu = SimImuConfig::perfect(100.0);
    imu.gyro_bias_deg_h = [20.0, -15.0, 10.0];
    let (mut rotation, mut step_deg_h, mut instability_deg_h) = (false, 0.0, 5.0);
    if let YawRate::Autopilot {
        bias_deg_h,
        rotation: r,
    } = yaw_rate
    {
        (rotation, step_deg_h, instability_deg_h) = (r, bias_deg_h, 200.0);
    }
    imu.accel_bias_ug = [800.0, -600.0, 500.0];
    imu.gyro_arw_deg_sqrt_h = 0.3;
    imu.accel_vrw_m_s_sqrt_h = 0.06;
    imu.gyro_bias_instability_deg_h = 5.0;
    imu.accel_bias_instability_ug = 50.0;
    let mut cfg = NavConfig::default();
    cfg.imu.gyro_arw_deg_sqrt_h = 0.4;
    cfg.imu.gyro_bias_deg_h = 30.0;
    cfg.imu.gyro_bias_instability_deg_h = instability_deg_h;
    if step_deg_h != 0.0 {
        cfg.imu.gyro_bias_corr_time_s = 60.0;
    }
    cfg.imu.accel_vrw_m_s_sqrt_h = 0.08;
    cfg.imu.accel_bias_ug = 1000.0;
    cfg.imu.accel_bias_instability_ug = 50.0;
    cfg.use_autopilot_attitude = false;
    cfg.health.lost_no_fix_s = 60.0;
    let step = Vector3::new(0.0, 0.0, step_deg_h);
    let imu_bias_deg_h = Vector3::from(imu.gyro_bias_deg_h) + step;
    let mut h = Harness::with_trajectory(cfg, imu, survey_route());
    h.gyro_step = Some((60_000_000, step * DEG_H_TO_RAD_S));
    let mut rng = Rng::new(23);
    let baro = |f: &mut NavFilter, t: u64, ts: &InsState, rng: &mut Rng| {
        if t.is_multiple_of(100_000) {
            f.measure(Measurement::Altitude(AltitudeFix {
                t_capture_us: t,
                h_m: ts.h_m + 0.5 * rng.normal(),
                var_m2: 0.25,
            }));
        }
    };
    h.fly(60.0, true, |f, t, ts| baro(f, t, ts, &mut rng));
    assert!(h.filter.is_initialised());
    let mut prev: Option<(u64, InsState, f64, f64)> = None;
    let (mut dist, mut yaw_max) = (0.0, 0.0f64);
    let mut last_ts: Option<InsState> = None;
    h.fly(outage_s, false, |f, t, ts| {
        baro(f, t, ts, &mut rng);
        if let Some(l) = &last_ts {
            dist += earth::ned_offset_m(
                (ts.lat_rad, ts.lon_rad, ts.h_m),
                (l.lat_rad, l.lon_rad, l.h_m),
            )
            .xy()
            .norm();
        }
        last_ts = Some(ts.clone());
        let s = f.state().expect("initialised").clone();
        let psi = (s.q_nb * ts.q_nb.inverse()).scaled_axis();
        yaw_max = yaw_max.max(psi.z.abs().to_degrees());
        if !(vo && t.is_multiple_of(200_000)) {
            return;
        }
        if let Some((tp, tsp, yaw_err, dh)) = prev.take() {
            let dp = earth::ned_offset_m(
                (ts.lat_rad, ts.lon_rad, ts.h_m),
                (tsp.lat_rad, tsp.lon_rad, tsp.h_m),
            );
            let agl_used = AGL_M + dh - TERRAIN_ERR_M;
            let rot = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), yaw_err);
            let noise = Vector3::new(0.05 * rng.normal(), 0.05 * rng.normal(), 0.1 * rng.normal());
            let z = rot * dp * (agl_used / AGL_M) + noise;
            // The gyros' rotation over the interval, compensated with the filter's bias
            // estimate, is wrong by `C (b_est - b_true) dt` (the instability's few deg/h aside);
            // the images see the truth.
            let rot = rotation.then(|| {
                let b_est = Vector3::from(f.output().expect("output").gyro_bias_deg_h);
                let db = (b_est - imu_bias_deg_h) * DEG_H_TO_RAD_S;
                let c_bn = ts.q_nb.to_rotation_matrix().into_inner();
                VoRotation {
                    about_los_rad: (c_bn * db).z * 0.2 + ROT_SIGMA_RAD * rng.normal(),
                    sigma_rad: ROT_SIGMA_RAD,
                }
            });
            f.measure(Measurement::Vo(VoFix {
                t_prev_us: tp,
                t_next_us: t,
                dp_ned_m: z,
                cov_ned_m2: Matrix3::from_diagonal(&Vector3::new(0.0025, 0.0025, 0.01)),
                agl_m: agl_used,
                terrain_sigma_m: 1.0,
                terrain_corr_dist_m: 2000.0,
                // The test's VO has no gyro error: any line of sight (nadir here) is right.
                look_ned_m: Vector3::new(0.0, 0.0, agl_used),
                rotation: rot,
                rotation_sensitivity_ned: None,
            }));
        }
        prev = Some((t, ts.clone(), psi.z, s.h_m - ts.h_m));
    });
    let out = h.filter.output().expect("output");
    let e = h.pos_err();
    VoFlight {
        final_err_h_m: e.xy().norm(),
        final_sigma_h_m: (out.cov_pos_ned_m2[0][0] + out.cov_pos_ned_m2[1][1]).sqrt(),
        distance_m: dist,
        yaw_err_deg_max: yaw_max,
        health: h.filter.health(),
        counters: *h.filter.counters(),
    }
}

/// deg/h in rad/s.
const DEG_H_TO_RAD_S: f64 = std::f64::consts::PI / 180.0 / 3600.0;

/// An autopilot's rates with 150 deg/h of yaw-rate bias left (ArduCopter SITL's
/// ATTITUDE rates carried up to 170): VO measures the motion in the heading the filter believes,
/// so a drifting heading is cross-track drift. With the images' rotation about the line of sight
/// against the gyros' fused, the filter learns the bias and keeps the heading; without it the
/// heading wanders with the bias.
#[test]
fn the_images_rotation_holds_the_heading_against_a_yaw_rate_bias() {
    let bias = 150.0;
    let with = vo_flight_with(
        true,
        120.0,
        YawRate::Autopilot {
            bias_deg_h: bias,
            rotation: true,
        },
    );
    let without = vo_flight_with(
        true,
        120.0,
        YawRate::Autopilot {
            bias_deg_h: bias,
            rotation: false,
        },
    );
    eprintln!(
        "yaw-rate bias {bias} deg/h, {:.0} m flown: rotation fused {:.1} m, yaw max {:.2} deg \
         ({} accepted, {} rejected); displacement only {:.1} m, yaw max {:.2} deg",
        with.distance_m,
        with.final_err_h_m,
        with.yaw_err_deg_max,
        with.counters.vo.accepted,
        with.counters.vo.rejected,
        without.final_err_h_m,
        without.yaw_err_deg_max
    );
    assert!(with.yaw_err_deg_max <= 1.0, "yaw {}", with.yaw_err_deg_max);
    assert!(
        with.final_err_h_m <= 0.01 * with.distance_m,
        "VO error {:.1} m over {:.0} m",
        with.final_err_h_m,
        with.distance_m
    );
    assert!(
        without.yaw_err_deg_max > 2.0 * with.yaw_err_deg_max,
        "without the rotation: yaw {} deg",
        without.yaw_err_deg_max
    );
    assert!(with.counters.vo.rejected < 10, "{:?}", with.counters.vo);
    assert!(with.final_err_h_m < 3.0 * with.final_sigma_h_m);
}

/// A rotation about the line of sight that the gyros contradict (1 deg per frame at a claimed
/// 0.01) fails the 4-dof gate; the displacement beside it, which agrees with the filter, is
/// still fused on its own gate: the filter ends exactly as if no rotation had been measured (the
/// rotation's 1 deg a frame, fused, would be a yaw-rate bias of 18000 deg/h). A displacement 5 m
/// off (at a claimed 5 cm) is refused with or without its rotation.
#[test]
fn a_rotation_the_gyros_contradict_leaves_a_good_displacement_fused() {
    let wild = VoRotation {
        about_los_rad: 1f64.to_radians(),
        sigma_rad: 0.01f64.to_radians(),
    };
    let (c, bias, sent) = vo_with_rotation(Some(wild));
    let (c0, bias0, _) = vo_with_rotation(None);
    eprintln!(
        "{sent} VO motions with a contradicted rotation: {} accepted, {} rejected, z gyro bias \
         {:.2} deg/h; without the rotation: {} accepted, {} rejected, {:.2} deg/h",
        c.accepted, c.rejected, bias.z, c0.accepted, c0.rejected, bias0.z
    );
    // 49 good motions (10 s at 5 Hz; the first frame has no predecessor), 10 bad ones.
    assert!(c.accepted >= 47, "{c:?}");
    assert!(c.rejected >= 9, "{c:?}");
    assert_eq!(c.accepted + c.rejected, sent, "{c:?}");
    assert_eq!(c, c0);
    assert!((bias - bias0).norm() < 1e-9, "{bias} vs {bias0}");
}

/// 60 s of GPS over the survey route, then 12 s of VO at 5 Hz without it: 10 s of displacements
/// as measured (5 cm of noise), then 2 s of displacements 5 m off, each with `rotation`. The VO
/// counters, the gyro bias estimate at the end (deg/h) and the number of motions sent.
fn vo_with_rotation(
    rotation: Option<VoRotation>,
) -> (visnav_core::nav::filter::TypeCounters, Vector3<f64>, u64) {
    let mut imu = SimImuConfig::perfect(100.0);
    imu.gyro_bias_deg_h = [20.0, -15.0, 10.0];
    imu.gyro_arw_deg_sqrt_h = 0.3;
    imu.accel_vrw_m_s_sqrt_h = 0.06;
    let mut cfg = NavConfig::default();
    cfg.imu.gyro_arw_deg_sqrt_h = 0.4;
    cfg.imu.gyro_bias_deg_h = 30.0;
    cfg.use_autopilot_attitude = false;
    let mut h = Harness::with_trajectory(cfg, imu, survey_route());
    h.fly(60.0, true, |_, _, _| {});
    assert!(h.filter.is_initialised());
    let mut rng = Rng::new(31);
    let mut prev: Option<(u64, InsState)> = None;
    let mut sent = 0u64;
    h.fly(12.0, false, |f, t, ts| {
        if !t.is_multiple_of(200_000) {
            return;
        }
        if let Some((tp, tsp)) = prev.take() {
            let dp = earth::ned_offset_m(
                (ts.lat_rad, ts.lon_rad, ts.h_m),
                (tsp.lat_rad, tsp.lon_rad, tsp.h_m),
            );
            let bad = if t > 70_000_000 { 5.0 } else { 0.0 };
            let noise = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.05;
            f.measure(Measurement::Vo(VoFix {
                t_prev_us: tp,
                t_next_us: t,
                dp_ned_m: dp + noise + Vector3::new(bad, 0.0, 0.0),
                cov_ned_m2: Matrix3::identity() * 0.0025,
                agl_m: 880.0,
                terrain_sigma_m: 1.0,
                terrain_corr_dist_m: 2000.0,
                look_ned_m: Vector3::new(0.0, 0.0, 880.0),
                rotation,
                rotation_sensitivity_ned: None,
            }));
            sent += 1;
        }
        prev = Some((t, ts.clone()));
    });
    let bias = Vector3::from(h.filter.output().expect("output").gyro_bias_deg_h);
    (h.filter.counters().vo, bias, sent)
}

/// VO between fixes. 120 s without a position fix over a survey route: with VO the
/// horizontal error stays within 1 % of the distance flown and the heading within 1 deg, the
/// INS-only control drifts by far more; the filter's claimed sigma covers its error; VO never
/// hides the missing fixes (health goes Lost after `lost_no_fix_s` with that reason, and the
/// sigma grows instead of shrinking).
#[test]
fn visual_odometry_bridges_two_minutes_without_fixes_and_says_so() {
    let with = vo_flight(true, 120.0);
    let control = vo_flight(false, 120.0);
    eprintln!(
        "120 s without fixes, {:.0} m flown: VO {:.1} m (sigma {:.1} m, yaw max {:.2} deg, \
         {} VO accepted, {} rejected), INS only {:.1} m (sigma {:.1} m, yaw max {:.2} deg)",
        with.distance_m,
        with.final_err_h_m,
        with.final_sigma_h_m,
        with.yaw_err_deg_max,
        with.counters.vo.accepted,
        with.counters.vo.rejected,
        control.final_err_h_m,
        control.final_sigma_h_m,
        control.yaw_err_deg_max
    );
    assert!(with.distance_m > 2000.0, "{}", with.distance_m);
    assert!(
        with.final_err_h_m <= 0.01 * with.distance_m,
        "VO error {:.1} m over {:.0} m",
        with.final_err_h_m,
        with.distance_m
    );
    assert!(with.yaw_err_deg_max <= 1.0, "yaw {}", with.yaw_err_deg_max);
    assert!(
        control.final_err_h_m > 5.0 * with.final_err_h_m,
        "control {:.1} m vs VO {:.1} m",
        control.final_err_h_m,
        with.final_err_h_m
    );
    // Honest: the error inside 3 sigma, and the sigma only grows without fixes.
    assert!(with.final_err_h_m < 3.0 * with.final_sigma_h_m);
    assert!(with.final_sigma_h_m > 3.0, "sigma {}", with.final_sigma_h_m);
    assert!(with.counters.vo.accepted > 550, "{:?}", with.counters.vo);
    assert!(with.counters.vo.rejected < 10, "{:?}", with.counters.vo);
    assert_eq!(with.health.0, Health::Lost, "{}", with.health.1);
    assert!(
        with.health
            .1
            .to_string()
            .contains("no accepted position fix"),
        "{}",
        with.health.1
    );
}
