#!/usr/bin/env python3
"""visnav's own navigation error against the simulator's truth, from a `visnav replay` of a PX4
SITL flight (SIH or jMAVSim): the replay's states.csv against the ground truth in PX4's log.

    visnav replay --config WORKDIR/visnav.toml --tlog WORKDIR/visnav.tlog \\
        --fixes WORKDIR/fixes.jsonl --out WORKDIR/replay
    python3 sitl/px4/replay_error.py WORKDIR/replay/states.csv WORKDIR/px4/log/*/*.ulg [--json F]

Needs pyulog. Both files use PX4's boot clock (the tlog's IMU times are PX4's `time_usec`, the
log's timestamps are PX4's). Replaying one flight with different settings (e.g. `[daemon]
imu_bias_restore` on and off) compares them on the same data and the same vision fixes.

* Truth: `vehicle_global_position_groundtruth` (latitude / longitude, interpolated linearly) and
  `vehicle_attitude_groundtruth` (the next sample) at each state row; horizontal only (jMAVSim's
  logged altitude is its local z, see ulog_error.py).
* GPS off: the logged `EKF2_GPS_CTRL` change to 0.
* Printed: horizontal error, its ratio to the replay's own horizontal sigma (the larger of north /
  east), and roll / pitch errors, at +5 / 10 / 20 / 30 / 45 / 60 s after the GPS went off, and
  median / p90 / max over the first 60 s after it.
"""

import argparse
import bisect
import csv
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sitl_common import metres_per_deg, stats, ulog_topic as topic  # noqa: E402

try:
    from pyulog import ULog
except ImportError:
    sys.exit("replay_error.py needs pyulog: python3 -m pip install pyulog")


def quat_rpy_deg(w, x, y, z):
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


def wrap180(a):
    return (a + 180.0) % 360.0 - 180.0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("states_csv")
    ap.add_argument("ulg")
    ap.add_argument("--json", help="write the result here too")
    ap.add_argument("--window", type=float, default=60.0, help="seconds after GPS off")
    args = ap.parse_args()
    u = ULog(args.ulg, ["vehicle_global_position_groundtruth", "vehicle_attitude_groundtruth"])
    gt = topic(u, "vehicle_global_position_groundtruth")
    at = topic(u, "vehicle_attitude_groundtruth")
    jmavsim = int(u.initial_parameters.get("SYS_AUTOSTART", 0)) == 10017
    t_gps_off = None
    for t, name, value in u.changed_parameters:
        if name == "EKF2_GPS_CTRL" and int(value) == 0:
            t_gps_off = t * 1e-6
            break
    if t_gps_off is None:
        sys.exit("no EKF2_GPS_CTRL change to 0 in the log: was the GPS switched off?")
    gt_t = [float(v) * 1e-6 for v in gt["timestamp"]]
    at_t = [float(v) * 1e-6 for v in at["timestamp"]]

    def truth(t):
        i = bisect.bisect_left(gt_t, t)
        if i == 0 or i >= len(gt_t):
            return None
        a = (t - gt_t[i - 1]) / max(gt_t[i] - gt_t[i - 1], 1e-9)
        lat = gt["lat"][i - 1] + a * (gt["lat"][i] - gt["lat"][i - 1])
        lon = gt["lon"][i - 1] + a * (gt["lon"][i] - gt["lon"][i - 1])
        j = min(bisect.bisect_left(at_t, t), len(at_t) - 1)
        rpy = quat_rpy_deg(*(float(at[f"q[{k}]"][j]) for k in range(4)))
        return float(lat), float(lon), rpy

    rows = []
    with open(args.states_csv) as f:
        for r in csv.DictReader(f):
            t = float(r["t_s"])
            rel = t - t_gps_off
            if rel < -5.0 or rel > args.window:
                continue
            tr = truth(t)
            if tr is None:
                continue
            lat, lon, rpy = tr
            mlat, mlon = metres_per_deg(lat)
            dn = (float(r["lat_deg"]) - lat) * mlat
            de = (float(r["lon_deg"]) - lon) * mlon
            eh = math.hypot(dn, de)
            sh = max(float(r["sigma_n_m"]), float(r["sigma_e_m"]))
            rows.append({
                "t_rel_s": rel,
                "h_err_m": eh,
                "h_sigma_m": sh,
                "err_over_sigma": eh / sh if sh > 0 else float("inf"),
                "roll_err_deg": wrap180(float(r["roll_deg"]) - rpy[0]),
                "pitch_err_deg": wrap180(float(r["pitch_deg"]) - rpy[1]),
            })
    after = [r for r in rows if r["t_rel_s"] >= 0.0]
    if not after:
        sys.exit("no replay state after the GPS went off")
    at_times = {}
    for k in [5, 10, 20, 30, 45, 60]:
        near = min(after, key=lambda r: abs(r["t_rel_s"] - k))
        if abs(near["t_rel_s"] - k) < 1.0:
            at_times[f"+{k}s"] = {key: round(v, 3) for key, v in near.items()}
    out = {
        "simulator": "jmavsim" if jmavsim else "sih",
        "gps_off_s": t_gps_off,
        "horizontal_m": stats([r["h_err_m"] for r in after]),
        "err_over_sigma": stats([r["err_over_sigma"] for r in after]),
        "tilt_deg": stats([math.hypot(r["roll_err_deg"], r["pitch_err_deg"]) for r in after]),
        "at": at_times,
    }
    print(f"GPS off at {t_gps_off:.1f} s; {len(after)} states in the {args.window:.0f} s after")
    for k, v in at_times.items():
        print(f"  {k:>5}: horizontal {v['h_err_m']:7.1f} m  sigma {v['h_sigma_m']:6.1f} m  "
              f"error/sigma {v['err_over_sigma']:5.2f}  roll {v['roll_err_deg']:+.2f}  "
              f"pitch {v['pitch_err_deg']:+.2f} deg")
    for k in ["horizontal_m", "err_over_sigma", "tilt_deg"]:
        s = out[k]
        print(f"  {k}: median {s['median_m']:.2f} / p90 {s['p90_m']:.2f} / max {s['max_m']:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
