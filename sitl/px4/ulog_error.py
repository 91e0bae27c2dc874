#!/usr/bin/env python3
"""EKF2's position error against the simulator's ground truth (SIH, jMAVSim) from a PX4 SITL
flight log (.ulg).

    python3 sitl/px4/ulog_error.py WORKDIR/px4/log/*/*.ulg [--json out.json]

Needs pyulog (`python3 -m pip install pyulog`). run.py measures GLOBAL_POSITION_INT, which PX4
stops sending when EKF2 declares its global position invalid (EKF2.cpp PublishGlobalPosition:
only while `global_position_is_valid()`), e.g. in the GPS-off control. This reads the log PX4
writes in every SITL run instead:

* EKF2: `vehicle_local_position` (x, y, z NED metres about its origin `ref_lat`, `ref_lon`,
  `ref_alt`; published whether or not the position is valid, with `xy_valid`), turned into
  latitude / longitude / altitude with the local flat-earth metres per degree at the origin.
* Truth: `vehicle_global_position_groundtruth` (SIH, jMAVSim), linearly interpolated to each EKF2
  sample. jMAVSim's altitude there is its local z (down) from the home ground: turned into
  HOME_ALT_M - z (`--sim`, detected from SYS_AUTOSTART 10017).
* GPS off: the time of the logged parameter change `EKF2_GPS_CTRL` to 0 (run.py sets it).

Horizontal and |vertical| error median / p90 / max: airborne (true height above the first
truth sample > 5 m) with the GPS on, after the GPS is off (all samples, and only those EKF2 marks
`xy_valid`), and the error at fixed times after the GPS went off.
"""

import argparse
import bisect
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sitl_common import HOME_ALT_M, metres_per_deg, stats, ulog_topic as topic  # noqa: E402

try:
    from pyulog import ULog
except ImportError:
    sys.exit("ulog_error.py needs pyulog: python3 -m pip install pyulog")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ulg")
    ap.add_argument("--json", help="write the result here too")
    ap.add_argument("--sim", choices=["auto", "sih", "jmavsim"], default="auto",
                    help="the simulator (auto: jMAVSim when SYS_AUTOSTART is 10017)")
    args = ap.parse_args()
    u = ULog(args.ulg, ["vehicle_local_position", "vehicle_global_position_groundtruth"])
    lp = topic(u, "vehicle_local_position")
    gt = topic(u, "vehicle_global_position_groundtruth")
    sim = args.sim
    if sim == "auto":
        sim = "jmavsim" if int(u.initial_parameters.get("SYS_AUTOSTART", 0)) == 10017 else "sih"
    if sim == "jmavsim":
        # jMAVSim's HIL_STATE_QUATERNION.alt is its local z (down, from the home ground), not the
        # altitude AMSL (run.py, jmavsim_truth_alt): the truth's altitude is home - z.
        gt = dict(gt)
        gt["alt"] = HOME_ALT_M - gt["alt"].astype(float)
    t_gps_off = None
    for t, name, value in u.changed_parameters:
        if name == "EKF2_GPS_CTRL" and value == 0 and t > 0:
            t_gps_off = t
            break
    gt_t = list(gt["timestamp"])
    if not gt_t:
        sys.exit("no ground truth samples")
    home_alt = float(gt["alt"][0])
    errs = {"gps_on": ([], []), "gps_off": ([], []), "gps_off_xy_valid": ([], [])}
    after = {}
    marks = [1, 5, 10, 20, 30, 60, 90, 120, 180, 240]
    for i in range(len(lp["timestamp"])):
        t = int(lp["timestamp"][i])
        k = bisect.bisect_left(gt_t, t)
        if k == 0 or k >= len(gt_t):
            continue
        t0, t1 = gt_t[k - 1], gt_t[k]
        if t1 - t0 > 500_000:
            continue
        w = (t - t0) / (t1 - t0)

        def g(f):
            return float(gt[f][k - 1]) * (1 - w) + float(gt[f][k]) * w

        lat_t, lon_t, alt_t = g("lat"), g("lon"), g("alt")
        ref_lat, ref_lon = float(lp["ref_lat"][i]), float(lp["ref_lon"][i])
        if not (math.isfinite(ref_lat) and math.isfinite(ref_lon)) or lp["xy_global"][i] == 0:
            continue
        m_lat, m_lon = metres_per_deg(ref_lat)
        lat_e = ref_lat + float(lp["x"][i]) / m_lat
        lon_e = ref_lon + float(lp["y"][i]) / m_lon
        alt_e = float(lp["ref_alt"][i]) - float(lp["z"][i])
        m_lat, m_lon = metres_per_deg(lat_t)
        eh = math.hypot((lat_e - lat_t) * m_lat, (lon_e - lon_t) * m_lon)
        ev = abs(alt_e - alt_t)
        if not (math.isfinite(eh) and math.isfinite(ev)):
            continue
        if t_gps_off is not None and t >= t_gps_off:
            errs["gps_off"][0].append(eh)
            errs["gps_off"][1].append(ev)
            if lp["xy_valid"][i]:
                errs["gps_off_xy_valid"][0].append(eh)
                errs["gps_off_xy_valid"][1].append(ev)
            dt_s = (t - t_gps_off) * 1e-6
            for mk in marks:
                if mk not in after and dt_s >= mk:
                    after[mk] = {"horizontal_m": round(eh, 1), "vertical_m": round(ev, 1),
                                 "xy_valid": bool(lp["xy_valid"][i])}
        elif alt_t - home_alt > 5:
            errs["gps_on"][0].append(eh)
            errs["gps_on"][1].append(ev)
    out = {
        "ulg": args.ulg,
        "sim": sim,
        "gps_off_at_s": None if t_gps_off is None else round(t_gps_off * 1e-6, 1),
        "log_end_s": round(int(lp["timestamp"][-1]) * 1e-6, 1),
        "ekf2_error": {ph: {"horizontal": stats(h), "vertical": stats(v)}
                       for ph, (h, v) in errs.items()},
        "after_gps_off_s": {str(k): v for k, v in sorted(after.items())},
    }
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
