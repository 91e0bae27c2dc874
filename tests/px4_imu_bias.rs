//! PX4's bias-corrected HIGHRES_IMU through the daemon's telemetry conversion into the
//! navigation filter (`Inputs` + `NavFilter`, no sockets): a copter flies a 250 Hz IMU like
//! jMAVSim's, the autopilot sends HIGHRES_IMU = IMU - EKF2's swinging bias estimate and
//! SCALED_IMU = trunc(IMU) in shuffled order (PX4 v1.14's streams), GPS aids the filter for 90 s
//! and is then lost. Compared 40 s after the loss: the raw IMU (what PX4 does not send), the
//! bias-corrected HIGHRES_IMU as visnav used it before (`imu_bias_restore = "off"`), and the
//! restored one (`"scaled_imu"`).

use mavlink::MavHeader;
use mavlink::dialects::ardupilotmega::{HIGHRES_IMU_DATA, MavMessage, SCALED_IMU_DATA};
use nalgebra::{Matrix3, Vector3};
use visnav::daemon::inputs::{Inputs, NavInput};
use visnav::daemon::{DaemonConfig, GpsSource, ImuBiasRestore};
use visnav::link::Telemetry;
use visnav::nav::earth;
use visnav::nav::synth::trajectory::{Segment, Trajectory};
use visnav::nav::{AttitudeFix, Measurement, NavConfig, NavFilter, PositionFix, VelocityFix};
use visnav_core::rng::Rng;

const G0: f64 = 9.806_65;
const DT_US: u64 = 4_000;
const GPS_OFF_S: f64 = 90.0;
const DEG_H: f64 = std::f64::consts::PI / 180.0 / 3600.0;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Stream {
    /// HIGHRES_IMU carries the raw IMU (restoration off).
    Raw,
    /// HIGHRES_IMU minus EKF2's estimate, restoration off (visnav before).
    Corrected,
    /// HIGHRES_IMU minus EKF2's estimate, restored from SCALED_IMU.
    Restored,
}

fn trajectory() -> Trajectory {
    let seg = |duration_s: f64, turn_rate_rad_s: f64| Segment {
        duration_s,
        speed_m_s: 15.0,
        turn_rate_rad_s,
        path_angle_rad: 0.0,
        ramp_s: 2.0,
    };
    Trajectory::new(
        47.02f64.to_radians(),
        (-99.15f64).to_radians(),
        2400.0,
        15.0,
        -45f64.to_radians(),
        vec![
            seg(30.0, 0.0),
            seg(15.0, 0.2),
            seg(20.0, 0.0),
            seg(15.0, -0.2),
            seg(15.0, 0.0),
            seg(12.0, 0.25),
            seg(200.0, 0.0),
        ],
    )
}

/// EKF2's gyro / accelerometer bias estimate as it swung in jMAVSim flight jm-v2 once the GPS
/// was off (x: -14, -125, -189, -55 deg/h at +0 / 10 / 20 / 30 s) and SIH's s8a (-5 to -14 mg).
fn ekf2_bias(t_s: f64) -> (Vector3<f64>, Vector3<f64>) {
    let u = (t_s - GPS_OFF_S).max(0.0);
    let swing = (std::f64::consts::PI * u / 40.0).sin();
    (
        Vector3::new(-14.0 - 175.0 * swing, 60.0 * swing, -120.0 * swing) * DEG_H,
        Vector3::new(-0.05 - 0.08 * swing, 0.06 * swing, 0.0),
    )
}

fn nav_config() -> NavConfig {
    // sitl/px4/visnav-jmavsim.toml's IMU model.
    let mut c = NavConfig::default();
    c.imu.gyro_arw_deg_sqrt_h = 6.0;
    c.imu.gyro_bias_deg_h = 50.0;
    c.imu.gyro_bias_instability_deg_h = 5.0;
    c.imu.gyro_bias_corr_time_s = 300.0;
    c.imu.accel_vrw_m_s_sqrt_h = 0.5;
    c.imu.accel_bias_ug = 1000.0;
    c.imu.accel_bias_instability_ug = 50.0;
    c.imu.accel_bias_corr_time_s = 300.0;
    c
}

fn tel(t_us: u64, msg: MavMessage) -> Telemetry {
    Telemetry {
        t_companion_ns: t_us as i64 * 1000,
        t_boot_us: Some(t_us),
        boot_epoch: 0,
        header: MavHeader::default(),
        msg,
    }
}

/// Fly; returns (tilt error deg, horizontal position error m) `after_s` after the GPS loss,
/// and the restorer's bootstrap count.
fn fly(stream: Stream, after_s: f64) -> (f64, f64, u64) {
    let traj = trajectory();
    let mut truth = traj.truth();
    let mut rng = Rng::new(11);
    let dcfg = DaemonConfig {
        gps: GpsSource::None,
        baro: false,
        imu_bias_restore: if stream == Stream::Restored {
            ImuBiasRestore::ScaledImu
        } else {
            ImuBiasRestore::Off
        },
        ..DaemonConfig::default()
    };
    let mut inputs = Inputs::new(dcfg, GpsSource::None);
    let mut filter = NavFilter::new(nav_config());
    let n = ((GPS_OFF_S + after_s) * 1e6 / DT_US as f64) as u64;
    let dt = DT_US as f64 * 1e-6;
    let mut last = None;
    for k in 1..=n {
        let t_us = k * DT_US;
        let t_s = t_us as f64 * 1e-6;
        let (dth, dv) = truth.step(dt);
        let ts = truth.state();
        // jMAVSim's IMU: white noise per 250 Hz sample, no bias.
        let w = dth / dt + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.006;
        let f = dv / dt + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.03;
        let (bg, ba) = if stream == Stream::Raw {
            (Vector3::zeros(), Vector3::zeros())
        } else {
            ekf2_bias(t_s)
        };
        let hw = (w - bg).map(|v| v as f32);
        let hf = (f - ba).map(|v| v as f32);
        let highres = MavMessage::HIGHRES_IMU(HIGHRES_IMU_DATA {
            time_usec: t_us,
            xacc: hf.x,
            yacc: hf.y,
            zacc: hf.z,
            xgyro: hw.x,
            ygyro: hw.y,
            zgyro: hw.z,
            ..HIGHRES_IMU_DATA::DEFAULT
        });
        let sw = w.map(|v| ((v as f32) * 1000.0) as i16);
        let sf = f.map(|v| ((v as f32) * 1000.0 / G0 as f32) as i16);
        let scaled = MavMessage::SCALED_IMU(SCALED_IMU_DATA {
            time_boot_ms: ((t_us + 300) / 1000) as u32,
            xacc: sf.x,
            yacc: sf.y,
            zacc: sf.z,
            xgyro: sw.x,
            ygyro: sw.y,
            zgyro: sw.z,
            ..SCALED_IMU_DATA::DEFAULT
        });
        let msgs = if rng.uniform() < 0.5 {
            [scaled, highres]
        } else {
            [highres, scaled]
        };
        for m in msgs {
            for input in inputs.convert(&tel(t_us, m)) {
                if let NavInput::Imu(s) = input {
                    filter.imu(&s);
                }
            }
        }
        if k % 25 == 0 {
            filter.measure(Measurement::Attitude(AttitudeFix {
                t_capture_us: t_us,
                q_nb: ts.q_nb,
            }));
        }
        if t_s <= GPS_OFF_S && k % 50 == 0 {
            let (rm, rn) = earth::radii_m(ts.lat_rad);
            let e = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.5;
            filter.measure(Measurement::GpsPosition(PositionFix {
                t_capture_us: t_us,
                lat_rad: ts.lat_rad + e.x / (rm + ts.h_m),
                lon_rad: ts.lon_rad + e.y / ((rn + ts.h_m) * ts.lat_rad.cos()),
                h_m: ts.h_m - e.z,
                cov_ned_m2: Matrix3::identity() * 0.25,
                att_dependence_ned: None,
            }));
            let e = Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.05;
            filter.measure(Measurement::GpsVelocity(VelocityFix {
                t_capture_us: t_us,
                v_ned_m_s: ts.v_ned_m_s + e,
                cov_ned_m2_s2: Matrix3::identity() * 0.0025,
            }));
        }
        last = Some(ts);
    }
    let ts = last.expect("flown");
    let s = filter.state().expect("initialised");
    assert_eq!(
        filter.t_us(),
        Some(n * DT_US),
        "{stream:?}: IMU samples lost"
    );
    let psi = (s.q_nb * ts.q_nb.inverse()).scaled_axis();
    let d = earth::ned_offset_m(
        (s.lat_rad, s.lon_rad, s.h_m),
        (ts.lat_rad, ts.lon_rad, ts.h_m),
    );
    let boots = inputs.imu_bias_status().map_or(0, |b| b.bootstraps);
    (psi.xy().norm().to_degrees(), d.xy().norm(), boots)
}

#[test]
fn restored_px4_imu_navigates_like_the_raw_imu() {
    let after_s = 40.0;
    let (tilt_raw, pos_raw, _) = fly(Stream::Raw, after_s);
    let (tilt_corr, pos_corr, _) = fly(Stream::Corrected, after_s);
    let (tilt_rest, pos_rest, boots) = fly(Stream::Restored, after_s);
    eprintln!(
        "{after_s} s after the GPS loss: tilt / horizontal error: raw IMU {tilt_raw:.3} deg / \
         {pos_raw:.1} m; PX4's HIGHRES_IMU as it is {tilt_corr:.3} deg / {pos_corr:.1} m; \
         restored from SCALED_IMU {tilt_rest:.3} deg / {pos_rest:.1} m"
    );
    assert_eq!(boots, 1);
    // The swing as it is tilts the filter and throws the position off ...
    assert!(
        tilt_corr > 3.0 * tilt_raw.max(0.05) && pos_corr > 2.0 * pos_raw.max(5.0),
        "the bias swing should hurt: {tilt_corr} deg / {pos_corr} m vs {tilt_raw} / {pos_raw}"
    );
    // ... the restored IMU navigates like the raw one.
    assert!(
        tilt_rest < tilt_raw + 0.05 && pos_rest < 1.3 * pos_raw + 2.0,
        "restored {tilt_rest} deg / {pos_rest} m vs raw {tilt_raw} / {pos_raw}"
    );
}
