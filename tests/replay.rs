//! The navigation filter on a real autopilot's telemetry: `tests/data/arducopter_sitl_climb.tlog`
//! (130 s of ArduCopter SITL: boot, take-off and a climb to 800 m at 8 m/s; see
//! tests/data/README.md) replayed through the daemon's telemetry conversion and filter
//! (`visnav::daemon::replay`, `visnav replay`).
//!
//! This log made the live daemon reset its GPS-aided filter every 5-10 s in the climb: ArduPilot
//! sends SCALED_IMU gyro rates as integer mrad/s truncated toward zero, which loses every slow
//! rotation. With ATTITUDE's float body rates as the gyro (`[daemon] gyro_from_attitude`, the
//! default) the filter must stay consistent; without them it must not (so this test can fail).

use std::path::Path;
use std::process::Command;

use visnav::daemon::replay::{ReplayOptions, ReplayReport, replay};
use visnav::daemon::{DaemonConfig, GpsSource};
use visnav::nav::NavConfig;

const LOG: &str = "tests/data/arducopter_sitl_climb.tlog";

fn run(daemon: DaemonConfig, nav: NavConfig) -> ReplayReport {
    let bytes = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join(LOG)).unwrap();
    let records = visnav::link::tlog::read_tlog(&bytes);
    replay(
        &records,
        &[],
        &[],
        &ReplayOptions {
            daemon,
            // GPS_INPUT feeds instance 0: the SITL's receiver is GPS2_RAW.
            gps: GpsSource::Gps2,
            nav,
            autopilot_system_id: None,
            autopilot_component_id: 1,
            state_interval_s: 0.1,
        },
    )
}

/// Largest |autopilot attitude - filter attitude| (roll, pitch, yaw), deg, after `t0_s`.
fn max_attitude_diff_deg(rep: &ReplayReport, t0_s: f64) -> [f64; 3] {
    let mut m = [0.0f64; 3];
    for r in rep
        .meas
        .iter()
        .filter(|r| r.kind == "attitude" && r.t_s > t0_s)
    {
        for (k, v) in m.iter_mut().enumerate() {
            *v = v.max(r.innov[k].abs());
        }
    }
    m
}

#[test]
fn arducopter_climb_replays_without_resets() {
    let rep = run(DaemonConfig::default(), NavConfig::default());
    let gp = &rep.kinds["gps_position"];
    let gv = &rep.kinds["gps_velocity"];
    let att = max_attitude_diff_deg(&rep, 20.0);
    eprintln!(
        "{} IMU samples over {:.0}..{:.0} s; GPS position {}/{} accepted, NIS mean {:.2} p95 {:.2}; \
         velocity NIS mean {:.2}; resets {:?}; max attitude difference to the autopilot \
         {:.2} / {:.2} / {:.2} deg",
        rep.imu_samples,
        rep.t_span_s[0],
        rep.t_span_s[1],
        gp.accepted,
        gp.n,
        gp.nis_mean,
        gp.nis_p95,
        gv.nis_mean,
        rep.resets,
        att[0],
        att[1],
        att[2]
    );
    assert_eq!(rep.autopilot_system_id, Some(1));
    assert_eq!(rep.undecodable, 0);
    assert!(rep.imu_samples > 12_000, "{}", rep.imu_samples);
    assert!(rep.t_span_s[1] - rep.t_span_s[0] > 120.0);
    // Initialised once, never reset.
    assert_eq!(rep.resets.len(), 1, "{:?}", rep.resets);
    assert!(rep.resets[0].1.starts_with("initialised"));
    assert!(
        gp.n > 600 && gp.rejected == 0 && gp.accepted + 2 >= gp.n,
        "{gp:?}"
    );
    assert!(gv.rejected == 0, "{gv:?}");
    // Consistent or conservative: the NIS mean is at most its degrees of freedom.
    assert!(gp.nis_mean < 3.0 && gv.nis_mean < 3.0, "{gp:?} {gv:?}");
    // The filter's tilt follows the autopilot's within 0.5 deg through the climb.
    assert!(att[0] < 0.5 && att[1] < 0.5, "{att:?}");
}

#[test]
fn shipped_ardupilot_config_keeps_the_filter_on_the_autopilots_attitude() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let cfg =
        visnav::daemon::config::Config::load(&root.join("config/ardupilot-sitl.toml")).unwrap();
    assert!(cfg.daemon.gyro_from_attitude && cfg.nav.use_autopilot_attitude);
    let rep = run(cfg.daemon.clone(), cfg.nav.clone());
    let gp = &rep.kinds["gps_position"];
    let att = max_attitude_diff_deg(&rep, 20.0);
    let late = max_attitude_diff_deg(&rep, 100.0);
    eprintln!(
        "config/ardupilot-sitl.toml: GPS position {}/{} accepted, NIS mean {:.2}; resets {}; \
         attitude difference max {:.2} / {:.2} / {:.2} deg after 20 s, yaw {:.2} deg after 100 s",
        gp.accepted,
        gp.n,
        gp.nis_mean,
        rep.resets.len(),
        att[0],
        att[1],
        att[2],
        late[2]
    );
    assert_eq!(rep.resets.len(), 1, "{:?}", rep.resets);
    assert!(gp.rejected == 0 && gp.nis_mean < 3.0, "{gp:?}");
    assert!(
        att[0] < 0.5 && att[1] < 0.5 && late[2] < 1.0,
        "{att:?} {late:?}"
    );
}

#[test]
fn the_16_bit_gyro_alone_tilts_the_filter_off() {
    let rep = run(
        DaemonConfig {
            gyro_from_attitude: false,
            ..DaemonConfig::default()
        },
        NavConfig::default(),
    );
    let att = max_attitude_diff_deg(&rep, 20.0);
    eprintln!(
        "without ATTITUDE rates: resets {}, max attitude difference {:.2} / {:.2} deg",
        rep.resets.len(),
        att[0],
        att[1]
    );
    assert!(rep.resets.len() > 1, "{:?}", rep.resets);
    assert!(att[0].max(att[1]) > 1.0, "{att:?}");
}

#[test]
fn autopilot_attitude_aiding_pulls_the_heading_onto_the_autopilots() {
    // The filter initialises (9.5 s) before ArduPilot's compass yaw alignment (16 s): its
    // heading starts several degrees off and a hovering or climbing copter does not make it
    // observable. With the autopilot's heading as a measurement it converges (default IMU
    // model here; the shipped ArduPilot config's MEMS model converges faster, test above).
    let base = run(DaemonConfig::default(), NavConfig::default());
    let aided = run(
        DaemonConfig::default(),
        NavConfig {
            use_autopilot_attitude: true,
            ..NavConfig::default()
        },
    );
    let (b, a) = (
        max_attitude_diff_deg(&base, 100.0),
        max_attitude_diff_deg(&aided, 100.0),
    );
    eprintln!(
        "yaw difference after 100 s: {:.2} deg unaided, {:.2} deg aided",
        b[2], a[2]
    );
    // Heading only, each sample's weight cut by the AHRS error's correlation time: it pulls
    // the heading over, without collapsing the filter's heading sigma at 50 Hz.
    assert!(a[2] < 0.5 * b[2], "{a:?} vs {b:?}");
    assert_eq!(aided.resets.len(), 1, "{:?}", aided.resets);
}

#[test]
fn cli_prints_the_table_and_writes_the_csvs() {
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("v.toml");
    let map = Path::new(env!("CARGO_MANIFEST_DIR")).join("sitl/maps/naip_nd_2009.tif");
    std::fs::write(
        &cfg,
        format!(
            "[link]\nconnection = \"udpin:127.0.0.1:14551\"\n\n[camera]\nwidth_px = 640\n\
             height_px = 480\nhfov_deg = 60.0\n\n[map]\northo = [{:?}]\n\
             ground_height_amsl_m = 580.0\n\n[output]\nmodes = [\"gps_input\"]\ngps_id = 0\n",
            map.display().to_string()
        ),
    )
    .unwrap();
    let log = Path::new(env!("CARGO_MANIFEST_DIR")).join(LOG);
    let out = d.path().join("out");
    let res = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["replay", "--config"])
        .arg(&cfg)
        .arg("--tlog")
        .arg(&log)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&res.stdout);
    assert!(
        res.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&res.stderr)
    );
    assert!(
        stdout.contains("gps_position") && stdout.contains("resets: 1"),
        "{stdout}"
    );
    let meas = std::fs::read_to_string(out.join("measurements.csv")).unwrap();
    assert!(meas.lines().count() > 8000);
    assert!(meas.starts_with("t_s,lag_s,kind,outcome,nis,"));
    let states = std::fs::read_to_string(out.join("states.csv")).unwrap();
    assert!(states.lines().count() > 1000);
    // Not a tlog: a clear error naming the file.
    let junk = d.path().join("junk.tlog");
    std::fs::write(&junk, b"hello, not a log").unwrap();
    let res = Command::new(env!("CARGO_BIN_EXE_visnav"))
        .args(["replay", "--config"])
        .arg(&cfg)
        .arg("--tlog")
        .arg(&junk)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success());
    assert!(
        err.contains("junk.tlog") && err.contains("no MAVLink packet"),
        "{err}"
    );
}

/// Boot time offset of the log: the smallest `arrival - time_boot` over its ATTITUDE packets
/// (MAVLink 1 or 2, read by hand: the payload's first field), µs.
fn boot_offset_us(records: &[(u64, Vec<u8>)]) -> i64 {
    records
        .iter()
        .filter_map(|(unix_us, p)| {
            let (id, payload) = match p.first()? {
                0xFD => (
                    u32::from_le_bytes([*p.get(7)?, *p.get(8)?, *p.get(9)?, 0]),
                    10,
                ),
                0xFE => (u32::from(*p.get(5)?), 6),
                _ => return None,
            };
            let b = p.get(payload..payload + 4)?;
            (id == 30).then(|| {
                *unix_us as i64 - i64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])) * 1000
            })
        })
        .min()
        .expect("ATTITUDE packets in the log")
}

/// `replay` gives the VO log's motions to the filter when they arrived: motions that agree with
/// the flight (the filter's own velocity over half a second) are fused, the same motions 5 m off
/// are refused, and each is counted.
#[test]
fn vo_motions_are_replayed_when_they_arrived() {
    let bytes = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join(LOG)).unwrap();
    let records = visnav::link::tlog::read_tlog(&bytes);
    let offset_us = boot_offset_us(&records);
    let opts = ReplayOptions {
        daemon: DaemonConfig::default(),
        gps: GpsSource::Gps2,
        nav: NavConfig::default(),
        autopilot_system_id: None,
        autopilot_component_id: 1,
        state_interval_s: 0.1,
    };
    let plain = replay(&records, &[], &[], &opts);
    let [t0, t1] = plain.t_span_s;
    let v_at = |t: f64| {
        let s = plain
            .states
            .iter()
            .min_by(|a, b| (a.t_s - t).abs().total_cmp(&(b.t_s - t).abs()))
            .expect("states");
        nalgebra::Vector3::from(s.v_ned_m_s)
    };
    let motions = |off_m: f64| -> Vec<(u64, visnav::nav::VoFix)> {
        let mut out = Vec::new();
        let mut t = t0 + 0.4 * (t1 - t0);
        while t < t0 + 0.6 * (t1 - t0) {
            let (tp, tn) = ((t * 1e6) as u64, ((t + 0.5) * 1e6) as u64);
            let dp = 0.25 * (v_at(t) + v_at(t + 0.5)) + nalgebra::Vector3::new(off_m, 0.0, 0.0);
            let fix = visnav::nav::VoFix {
                t_prev_us: tp,
                t_next_us: tn,
                dp_ned_m: dp,
                cov_ned_m2: nalgebra::Matrix3::identity() * 0.01,
                agl_m: 100.0,
                terrain_sigma_m: 1.0,
                terrain_corr_dist_m: 1000.0,
                look_ned_m: nalgebra::Vector3::new(0.0, 0.0, 100.0),
                rotation: None,
                rotation_sensitivity_ned: None,
            };
            out.push(((tn as i64 + offset_us + 50_000) as u64, fix));
            t += 0.5;
        }
        out
    };
    for (off_m, fused) in [(0.0, true), (5.0, false)] {
        let vo = motions(off_m);
        let rep = replay(&records, &[], &vo, &opts);
        let k = &rep.kinds["vo"];
        eprintln!(
            "{off_m} m off: {} motions, {} fused, {} refused",
            k.n, k.accepted, k.rejected
        );
        assert_eq!(rep.vo_motions as usize, vo.len());
        assert_eq!(k.n as usize, vo.len());
        let (good, bad) = if fused {
            (k.accepted, k.rejected)
        } else {
            (k.rejected, k.accepted)
        };
        assert!(good as f64 >= 0.9 * vo.len() as f64, "{off_m} m: {k:?}");
        assert!(bad as f64 <= 0.1 * vo.len() as f64, "{off_m} m: {k:?}");
    }
}
