//! Strapdown INS against analytic truth: a stationary IMU on the rotating earth and a
//! turning/climbing trajectory flown with a perfect IMU.
#![allow(clippy::unwrap_used, clippy::expect_used)] // a test: a failed expect is a failed test

use nalgebra::{UnitQuaternion, Vector3};
use visnav_core::nav::earth;
use visnav_core::nav::synth::trajectory::{Segment, Trajectory};
use visnav_core::nav::{InsState, Strapdown};

fn ned_err(a: &InsState, b: &InsState) -> Vector3<f64> {
    earth::ned_offset_m((a.lat_rad, a.lon_rad, a.h_m), (b.lat_rad, b.lon_rad, b.h_m))
}

#[test]
fn stationary_perfect_imu_ten_minutes() {
    let lat = 46.9f64.to_radians();
    let h = 500.0;
    let st = InsState {
        lat_rad: lat,
        lon_rad: (-100.8f64).to_radians(),
        h_m: h,
        v_ned_m_s: Vector3::zeros(),
        q_nb: UnitQuaternion::from_euler_angles(0.02, 0.05, 2.0),
    };
    let c_nb = st.q_nb.inverse().to_rotation_matrix().into_inner();
    let w_b = c_nb * earth::earth_rate_ned(lat);
    let f_b = c_nb * Vector3::new(0.0, 0.0, -earth::normal_gravity_m_s2(lat, h));
    let mut ins = Strapdown::new(st.clone());
    let dt = 0.01;
    for _ in 0..60_000 {
        ins.step(&(w_b * dt), &(f_b * dt), dt);
    }
    let d = ned_err(&ins.state, &st);
    eprintln!(
        "stationary 10 min drift NED {d:?} m, v {:?}",
        ins.state.v_ned_m_s
    );
    assert!(d.norm() < 0.05, "drift {d:?}");
    assert!(ins.state.v_ned_m_s.norm() < 1e-3);
    let att = (ins.state.q_nb * st.q_nb.inverse()).angle();
    assert!(att < 1e-6, "attitude drift {att}");
}

#[test]
fn stationary_uncompensated_earth_rate_drifts() {
    // Control: dropping the earth rate from the gyro makes the same run drift by far more, so
    // the stationary test above does exercise the earth-rate/Coriolis terms.
    let lat = 46.9f64.to_radians();
    let st = InsState {
        lat_rad: lat,
        lon_rad: 0.0,
        h_m: 0.0,
        v_ned_m_s: Vector3::zeros(),
        q_nb: UnitQuaternion::identity(),
    };
    let f_b = Vector3::new(0.0, 0.0, -earth::normal_gravity_m_s2(lat, 0.0));
    let mut ins = Strapdown::new(st.clone());
    for _ in 0..60_000 {
        ins.step(&Vector3::zeros(), &(f_b * 0.01), 0.01);
    }
    let d = ned_err(&ins.state, &st);
    eprintln!("uncompensated earth rate: drift {d:?}");
    assert!(d.xy().norm() > 100.0, "{d:?}");
}

fn flight() -> Trajectory {
    let seg = |d: f64, v: f64, r_deg: f64, climb: f64| Segment {
        duration_s: d,
        speed_m_s: v,
        turn_rate_rad_s: r_deg.to_radians(),
        path_angle_rad: (climb / v).asin(),
        ramp_s: 3.0,
    };
    Trajectory::new(
        46.9f64.to_radians(),
        (-100.8f64).to_radians(),
        1500.0,
        51.44,
        30f64.to_radians(),
        vec![
            seg(10.0, 51.44, 0.0, 0.0),
            seg(120.0, 51.44, 3.0, 0.0), // full coordinated turn, ~15 deg bank
            seg(40.0, 60.0, 0.0, 5.0),   // accelerate and climb
            seg(30.0, 60.0, -6.0, 0.0),  // steeper turn the other way
            seg(20.0, 60.0, 0.0, 0.0),
        ],
    )
}

fn fly(dt: f64) -> (f64, f64, f64, f64) {
    let traj = flight();
    let mut truth = traj.truth();
    let mut ins = Strapdown::new(truth.state());
    let n = (traj.duration_s() / dt).round() as usize;
    let mut max_err: f64 = 0.0;
    let mut dist = 0.0;
    for _ in 0..n {
        let (dth, dv) = truth.step(dt);
        ins.step(&dth, &dv, dt);
        dist += truth.kin.v_ned_m_s.norm() * dt;
        max_err = max_err.max(ned_err(&ins.state, &truth.state()).norm());
    }
    let ts = truth.state();
    let verr = (ins.state.v_ned_m_s - ts.v_ned_m_s).norm();
    let aerr = (ins.state.q_nb * ts.q_nb.inverse()).angle();
    (dist, max_err, verr, aerr)
}

#[test]
fn coordinated_turn_perfect_imu_tracks_truth() {
    let (dist, max_err, verr, aerr) = fly(0.01);
    eprintln!(
        "100 Hz perfect IMU over {:.1} km: max position error {max_err:.4} m, final velocity error {verr:.2e} m/s, attitude {aerr:.2e} rad",
        dist / 1000.0
    );
    assert!(dist > 11_000.0);
    assert!(max_err < 0.03, "max position error {max_err} m");
    assert!(verr < 5e-3);
    assert!(aerr < 1e-5);
}

#[test]
fn coordinated_turn_perfect_imu_20hz() {
    // The same flight with a 20 Hz IMU: the two-sample coning/sculling algorithm keeps it at the
    // decimetre level.
    let (_, max_err, verr, _) = fly(0.05);
    eprintln!("20 Hz perfect IMU: max position error {max_err:.4} m, velocity {verr:.2e}");
    assert!(max_err < 0.3, "{max_err}");
}
