#!/usr/bin/env python3
"""visnav's own navigation error against ArduPilot SITL's truth, from a `visnav replay` of a
flight of sitl/ardupilot/run.py: the replay's states.csv against the SIM / SIM2 records of
ArduPilot's dataflash log (WORKDIR/logs/*.BIN).

    visnav replay --config WORKDIR/visnav.toml --tlog WORKDIR/visnav.tlog \\
        --fixes WORKDIR/fixes.jsonl --out WORKDIR/replay
    python3 sitl/ardupilot/replay_error.py WORKDIR/replay/states.csv WORKDIR/logs/00000001.BIN

Needs pymavlink (its DFReader). Both use ArduPilot's boot clock (the tlog's IMU times are
ArduPilot's boot time, the log's TimeUS too), so replaying one flight with other settings compares
them on the same data and the same vision fixes.

* Truth: SIM (Lat, Lng, Roll, Pitch, Yaw; interpolated linearly / the nearest) and SIM2 (VN, VE)
  where present.
* GPS off: the logged PARM change of SIM_GPS_DISABLE to 1 (4.6+: SIM_GPS1_ENABLE to 0), or
  --gps-off-s.
* Printed: horizontal position and velocity error, the ratio of the position error to the
  replay's own horizontal sigma (the larger of north / east), roll / pitch / yaw errors, at
  +5 / 10 / 20 / 30 / 45 / 60 / 90 / 120 / 150 s after the GPS went off, and median / p90 / max
  over the window after it (--window, default: to the end).
"""

import argparse
import bisect
import csv
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sitl_common import metres_per_deg, stats  # noqa: E402

try:
    from pymavlink import DFReader
except ImportError:
    sys.exit("replay_error.py needs pymavlink: use the venv python of scripts/interop/setup_venv.sh")


def wrap180(a):
    return (a + 180.0) % 360.0 - 180.0


def read_truth(path):
    """(sim rows [t, lat, lon, roll, pitch, yaw], sim2 rows [t, vn, ve], gps_off_s or None)."""
    log = DFReader.DFReader_binary(path, zero_time_base=True)
    sim, sim2, gps_off = [], [], None
    while True:
        m = log.recv_match(type=["SIM", "SIM2", "PARM"])
        if m is None:
            break
        typ = m.get_type()
        t = m.TimeUS * 1e-6
        if typ == "SIM":
            sim.append((t, m.Lat, m.Lng, m.Roll, m.Pitch, m.Yaw))
        elif typ == "SIM2":
            sim2.append((t, m.VN, m.VE))
        elif gps_off is None and ((m.Name == "SIM_GPS_DISABLE" and m.Value == 1)
                                  or (m.Name == "SIM_GPS1_ENABLE" and m.Value == 0)):
            gps_off = t
    if not sim:
        sys.exit(f"{path}: no SIM records (is it an ArduPilot SITL log?)")
    return sim, sim2, gps_off


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("states_csv")
    ap.add_argument("bin")
    ap.add_argument("--json", help="write the result here too")
    ap.add_argument("--gps-off-s", type=float, help="GPS-off boot time when the log has none")
    ap.add_argument("--window", type=float, default=1e9, help="seconds after GPS off")
    ap.add_argument("--every", type=float, default=0.0,
                    help="also print a row every this many seconds after GPS off")
    args = ap.parse_args()
    sim, sim2, t_gps_off = read_truth(args.bin)
    if args.gps_off_s is not None:
        t_gps_off = args.gps_off_s
    if t_gps_off is None:
        sys.exit("no SIM_GPS_DISABLE change in the log: give --gps-off-s")
    st = [r[0] for r in sim]
    vt = [r[0] for r in sim2]

    def truth(t):
        i = bisect.bisect_left(st, t)
        if i == 0 or i >= len(st):
            return None
        a, b = sim[i - 1], sim[i]
        u = (t - a[0]) / max(b[0] - a[0], 1e-9)
        lat = a[1] + u * (b[1] - a[1])
        lon = a[2] + u * (b[2] - a[2])
        vel = None
        j = bisect.bisect_left(vt, t)
        if 0 < j < len(vt):
            vel = sim2[j][1:3]
        return lat, lon, b[3:6], vel

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
            lat, lon, rpy, vel = tr
            mlat, mlon = metres_per_deg(lat)
            dn = (float(r["lat_deg"]) - lat) * mlat
            de = (float(r["lon_deg"]) - lon) * mlon
            eh = math.hypot(dn, de)
            sh = max(float(r["sigma_n_m"]), float(r["sigma_e_m"]))
            ev = float("nan")
            speed_t = float("nan")
            if vel is not None:
                ev = math.hypot(float(r["vn"]) - vel[0], float(r["ve"]) - vel[1])
                speed_t = math.hypot(*vel)
            rows.append({
                "t_rel_s": rel,
                "h_err_m": eh,
                "h_sigma_m": sh,
                "err_over_sigma": eh / sh if sh > 0 else float("inf"),
                "vel_err_m_s": ev,
                "speed_m_s": math.hypot(float(r["vn"]), float(r["ve"])),
                "true_speed_m_s": speed_t,
                "roll_err_deg": wrap180(float(r["roll_deg"]) - rpy[0]),
                "pitch_err_deg": wrap180(float(r["pitch_deg"]) - rpy[1]),
                "yaw_err_deg": wrap180(float(r["yaw_deg"]) - rpy[2]),
                "health": r["health"],
            })
    after = [r for r in rows if r["t_rel_s"] >= 0.0]
    if not after:
        sys.exit("no replay state after the GPS went off")
    marks = [5, 10, 20, 30, 45, 60, 90, 120, 150]
    if args.every > 0:
        end = after[-1]["t_rel_s"]
        marks = sorted(set(marks) | {round(k * args.every, 3)
                                     for k in range(1, int(end / args.every) + 1)})
    at_times = {}
    for k in marks:
        near = min(after, key=lambda r: abs(r["t_rel_s"] - k))
        if abs(near["t_rel_s"] - k) < 1.0:
            at_times[f"+{k:g}s"] = {key: (round(v, 3) if isinstance(v, float) else v)
                                    for key, v in near.items()}
    vel = [r["vel_err_m_s"] for r in after if not math.isnan(r["vel_err_m_s"])]
    out = {
        "gps_off_s": t_gps_off,
        "horizontal_m": stats([r["h_err_m"] for r in after]),
        "err_over_sigma": stats([r["err_over_sigma"] for r in after]),
        "velocity_m_s": stats(vel) if vel else None,
        "tilt_deg": stats([math.hypot(r["roll_err_deg"], r["pitch_err_deg"]) for r in after]),
        "yaw_deg": stats([abs(r["yaw_err_deg"]) for r in after]),
        "at": at_times,
    }
    print(f"GPS off at {t_gps_off:.1f} s; {len(after)} states after it "
          f"({after[-1]['t_rel_s']:.0f} s)")
    for k, v in at_times.items():
        print(f"  {k:>6}: horizontal {v['h_err_m']:7.1f} m  sigma {v['h_sigma_m']:6.1f} m  "
              f"err/sigma {v['err_over_sigma']:5.2f}  vel err {v['vel_err_m_s']:5.2f} m/s "
              f"(speed {v['speed_m_s']:5.2f}, true {v['true_speed_m_s']:5.2f})  "
              f"roll {v['roll_err_deg']:+.2f} pitch {v['pitch_err_deg']:+.2f} "
              f"yaw {v['yaw_err_deg']:+.2f} deg  {v['health']}")
    for k in ["horizontal_m", "err_over_sigma", "velocity_m_s", "tilt_deg", "yaw_deg"]:
        s = out[k]
        if s:
            print(f"  {k}: median {s['median_m']:.2f} / p90 {s['p90_m']:.2f} / "
                  f"max {s['max_m']:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
