#!/usr/bin/env python3
"""The IMU and the GPS of a PX4 SITL flight against the simulator's truth, from PX4's log: what
visnav's [nav.imu] noise model and [daemon] gps_delay_s should say for that simulator.

    python3 sitl/px4/imu_check.py WORKDIR [--imu-hz 100]

WORKDIR is a sitl/px4/run.py work folder (its px4/log/*/*.ulg). Needs pyulog and numpy.
It reads the raw IMU (sensor_combined); PX4's HIGHRES_IMU, which visnav receives, is that minus
EKF2's bias estimates (estimator_sensor_bias; docs/real-sitl.md, PX4 section).

* On the ground before take-off (truth speed < 0.05 m/s, the first 20 s of data after 5 s):
  gyro and accelerometer (sensor_combined, about 250 Hz) mean and standard deviation per axis
  (the accelerometer's z plus g), and the white-noise densities they imply for visnav, which
  samples the IMU at --imu-hz (HIGHRES_IMU; each sample stands for 1/imu_hz s):
  ARW = std * sqrt(1 / imu_hz) (rad/sqrt(s) -> deg/sqrt(h): * 180/pi * 60), VRW = std *
  sqrt(1 / imu_hz) (m/s/sqrt(s) -> m/s/sqrt(h): * 60).
* In flight: the gyro, resampled at --imu-hz (the latest sample at each tick, as visnav receives
  HIGHRES_IMU), integrated from the truth attitude (vehicle_attitude_groundtruth) over windows of
  2 to 30 s: RMS attitude error per body axis and the equivalent ARW = rms / sqrt(window).
* In flight: the accelerometer against the truth specific force (R_bn (dv/dt - g), dv/dt from
  vehicle_local_position_groundtruth's velocity at 50 Hz, differenced over 0.1 s): mean (bias,
  milli-g) and standard deviation per axis.
* The GPS (vehicle_gps_position, stamped with its sample time, or its publication time when
  the simulator leaves that at 0, as jMAVSim's HIL_GPS path does) against the truth position
  (vehicle_global_position_groundtruth) shifted by 0..500 ms while the copter moves faster than
  3 m/s: the shift with the least RMS horizontal error is the receiver's latency that PX4 does
  not remove (visnav's [daemon] gps_delay_s, EKF2_GPS_DELAY).

Convention: quaternions are PX4's (w, x, y, z), rotating body FRD to NED (R_nb).
"""

import argparse
import glob
import math
import sys

import os

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sitl_common import ulog_topic as topic  # noqa: E402

try:
    from pyulog import ULog
except ImportError:
    sys.exit("imu_check.py needs pyulog and numpy (python3 -m pip install pyulog numpy)")

G_M_S2 = 9.80665


def qmul(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2],
                    -1)


def r_nb(q):
    """Rotation matrices body -> NED of quaternions (..., 4) w first."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir")
    ap.add_argument("--imu-hz", type=float, default=100.0,
                    help="visnav's IMU rate (HIGHRES_IMU, [link.streams] imu_hz)")
    args = ap.parse_args()
    logs = sorted(glob.glob(f"{args.workdir}/px4/log/*/*.ulg"))
    if not logs:
        sys.exit(f"{args.workdir}: no px4/log/*/*.ulg")
    u = ULog(logs[-1], ["sensor_combined", "vehicle_attitude_groundtruth",
                        "vehicle_local_position_groundtruth", "vehicle_global_position_groundtruth",
                        "vehicle_gps_position"])
    sc = topic(u, "sensor_combined")
    ts = sc["timestamp"] * 1e-6
    gyro = np.stack([sc[f"gyro_rad[{i}]"] for i in range(3)], 1)
    acc_t = ts + sc["accelerometer_timestamp_relative"] * 1e-6
    acc = np.stack([sc[f"accelerometer_m_s2[{i}]"] for i in range(3)], 1)
    at = topic(u, "vehicle_attitude_groundtruth")
    ta = at["timestamp"] * 1e-6
    q = np.stack([at[f"q[{i}]"] for i in range(4)], 1)
    lp = topic(u, "vehicle_local_position_groundtruth")
    tl = lp["timestamp"] * 1e-6
    vel = np.stack([lp["vx"], lp["vy"], lp["vz"]], 1)
    speed = np.linalg.norm(vel, axis=1)
    dt_imu = 1.0 / args.imu_hz
    k_arw = math.degrees(1.0) * 60.0

    # Ground.
    moving = tl[speed > 0.05]
    t_move = moving[0] if len(moving) else tl[-1]
    g0, g1 = ts[0] + 5.0, min(ts[0] + 25.0, t_move - 1.0)
    m = (ts > g0) & (ts < g1)
    print(f"ground: {m.sum()} samples ({g1 - g0:.0f} s, {m.sum() / (g1 - g0):.0f} Hz)")
    if m.sum() > 100:
        gm, gs = gyro[m].mean(0), gyro[m].std(0)
        am = acc[m].mean(0) + np.array([0.0, 0.0, G_M_S2])
        asd = acc[m].std(0)
        print(f"  gyro mean {np.round(gm, 5)} rad/s, std {np.round(gs, 5)} rad/s"
              f" -> ARW at {args.imu_hz:.0f} Hz {np.round(gs * math.sqrt(dt_imu) * k_arw, 2)}"
              f" deg/sqrt(h)")
        print(f"  accel mean (z + g) {np.round(am, 4)} m/s^2, std {np.round(asd, 4)} m/s^2"
              f" -> VRW at {args.imu_hz:.0f} Hz {np.round(asd * math.sqrt(dt_imu) * 60, 3)}"
              f" m/s/sqrt(h)")

    # Flight: gyro integration against the truth attitude, at visnav's rate.
    fl = (ts > t_move + 5) & (ts < ta[-1] - 1)
    tick = np.arange(ts[fl][0], ts[fl][-1], dt_imu)
    k = np.searchsorted(ts, tick, side="right") - 1
    w = gyro[k]
    qq = q[np.searchsorted(ta, tick[0])].copy()
    Q = np.empty((len(tick), 4))
    for i in range(len(tick)):
        Q[i] = qq
        wv = w[i] * dt_imu
        a = np.linalg.norm(wv)
        if a > 0:
            qq = qmul(qq, np.r_[math.cos(a / 2), math.sin(a / 2) * wv / a])
            qq /= np.linalg.norm(qq)
    qt = q[np.clip(np.searchsorted(ta, tick), 0, len(ta) - 1)]
    err = qmul(qt * np.array([1, -1, -1, -1]), Q)  # truth^-1 * integrated: body-frame error
    print(f"flight: gyro integrated at {args.imu_hz:.0f} Hz over {tick[-1] - tick[0]:.0f} s")
    for win in (2, 5, 10, 20, 30):
        n = int(round(win / dt_imu))
        idx = np.arange(0, len(tick) - n, max(1, n // 4))
        if len(idx) < 5:
            continue
        d = qmul(err[idx] * np.array([1, -1, -1, -1]), err[idx + n])
        ang = np.degrees(2 * d[:, 1:] * np.sign(d[:, :1]))
        rms = np.sqrt((ang ** 2).mean(0))
        print(f"  window {win:2d} s: RMS error x/y/z {np.round(rms, 3)} deg -> ARW "
              f"{np.round(rms / math.sqrt(win / 3600.0), 2)} deg/sqrt(h)")

    # Flight: accelerometer against the truth specific force.
    h = 5  # 0.1 s at 50 Hz
    tc = 0.5 * (tl[h:] + tl[:-h])
    a_ned = (vel[h:] - vel[:-h]) / (tl[h:] - tl[:-h])[:, None]
    f_ned = a_ned - np.array([0.0, 0.0, G_M_S2])
    sel = (acc_t > tc[0]) & (acc_t < tc[-1]) & (acc_t > t_move + 5)
    ti = acc_t[sel]
    f_i = np.stack([np.interp(ti, tc, f_ned[:, j]) for j in range(3)], 1)
    rb = r_nb(q[np.clip(np.searchsorted(ta, ti), 0, len(ta) - 1)])
    f_b = np.einsum("nji,nj->ni", rb, f_i)
    e = acc[sel] - f_b
    print(f"flight: accelerometer - truth specific force, {len(ti)} samples: mean "
          f"{np.round(e.mean(0) / G_M_S2 * 1000, 2)} mg, std {np.round(e.std(0), 3)} m/s^2")

    # GPS latency.
    gp = topic(u, "vehicle_gps_position")
    # simulator_mavlink (jMAVSim) leaves timestamp_sample at 0: the publication time then.
    tg = (gp["timestamp_sample"] if gp["timestamp_sample"].any() else gp["timestamp"]) * 1e-6
    gt = topic(u, "vehicle_global_position_groundtruth")
    tt = gt["timestamp"] * 1e-6
    lat0 = float(np.median(gt["lat"]))
    m_lat = 111132.954 - 559.822 * math.cos(2 * math.radians(lat0))
    m_lon = 111412.84 * math.cos(math.radians(lat0))
    v_at = np.interp(tg, tl, speed)
    ok = (v_at > 3.0) & (tg > tt[0] + 1) & (tg < tt[-1] - 1)
    glat = gp["lat"] * (1e-7 if gp["lat"].dtype.kind == "i" else 1.0)
    glon = gp["lon"] * (1e-7 if gp["lon"].dtype.kind == "i" else 1.0)
    if ok.sum() < 20:
        print("GPS: fewer than 20 samples above 3 m/s")
        return
    best = None
    for lag_ms in range(0, 501, 20):
        lag = lag_ms * 1e-3
        tl_ = tg[ok] - lag
        dn = (glat[ok] - np.interp(tl_, tt, gt["lat"])) * m_lat
        de = (glon[ok] - np.interp(tl_, tt, gt["lon"])) * m_lon
        rms = float(np.sqrt(np.mean(dn ** 2 + de ** 2)))
        if best is None or rms < best[1]:
            best = (lag_ms, rms)
        if lag_ms % 100 == 0:
            print(f"  GPS shifted {lag_ms:3d} ms: RMS horizontal {rms:.2f} m ({ok.sum()} samples)")
    print(f"GPS latency (least RMS): {best[0]} ms ({best[1]:.2f} m)")


if __name__ == "__main__":
    main()
