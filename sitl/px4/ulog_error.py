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
  latitude / longitude / altitude with PX4's own projection (MapProjection::reproject, as EKF2
  turns it into its global position).
* Truth: `vehicle_global_position_groundtruth` (SIH, jMAVSim), linearly interpolated to each EKF2
  sample. jMAVSim's altitude there is its local z (down) from the home ground: turned into
  HOME_ALT_M - z (`--sim`, detected from SYS_AUTOSTART 10017).
* GPS off: the time of the logged parameter change `EKF2_GPS_CTRL` to 0 (run.py sets it).

Horizontal and |vertical| error median / p90 / max: airborne (true height above the first
truth sample > 5 m) with the GPS on, after the GPS is off (all samples, and only those EKF2 marks
`xy_valid`), and the error at fixed times after the GPS went off.

Injected-position integrity ("injected", `injected_integrity`; run.py's verdict uses it): PX4
sends back nothing of the ODOMETRY it fuses, but logs it as received (`vehicle_visual_odometry`,
10 Hz here: position NED about EKF2's origin, its variances, `timestamp_sample` = the estimate's
validity time in PX4's clock). Each sample in MAV_FRAME_LOCAL_NED (pose_frame 1) against the truth
at `timestamp_sample`, the position through EKF2's origin (`vehicle_local_position` ref_lat /
ref_lon) to latitude / longitude with PX4's projection; claimed accuracy = sqrt of the larger of the north / east
variances (PX4 logs no covariance, so this can be below visnav's sqrt(lambda_max): the ratio is
at most slightly stricter than ArduPilot's h_acc); phases gps_on / gps_off as above
(sitl_common.IntegrityScore, times in PX4 boot seconds).
"""

import argparse
import bisect
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sitl_common import (HOME_ALT_M, IntegrityScore, MAX_RATIO, metres_per_deg,  # noqa: E402
                         px4_from_ned, stats, ulog_topic as topic)

try:
    from pyulog import ULog
except ImportError:
    sys.exit("ulog_error.py needs pyulog: python3 -m pip install pyulog")


def load(path, sim="auto"):
    """(ULog with the topics used here, the ground truth's data with the altitude AMSL, the
    simulator "sih" / "jmavsim", GPS-off time in us or None) of a PX4 SITL log."""
    u = ULog(path, ["vehicle_local_position", "vehicle_global_position_groundtruth",
                    "vehicle_visual_odometry"])
    gt = topic(u, "vehicle_global_position_groundtruth")
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
    return u, gt, sim, t_gps_off


def injected_integrity(u, gt, t_gps_off, ratio_limit=MAX_RATIO):
    """IntegrityScore of visnav's ODOMETRY as PX4 logged it (module docstring) against the truth
    `gt` (vehicle_global_position_groundtruth data, altitude already fixed for jMAVSim); None when
    the log has no vehicle_visual_odometry (a run without visnav). `u`: a ULog with
    vehicle_visual_odometry and vehicle_local_position; t_gps_off: us, or None."""
    names = {d.name for d in u.data_list}
    if "vehicle_visual_odometry" not in names:
        return None
    ev = topic(u, "vehicle_visual_odometry")
    lp = topic(u, "vehicle_local_position")
    lp_t = list(lp["timestamp"])
    gt_t = list(gt["timestamp"])
    score = IntegrityScore(ratio_limit)
    for i in range(len(ev["timestamp"])):
        if int(ev["pose_frame"][i]) != 1:  # POSE_FRAME_NED; visnav sends LOCAL_NED to PX4
            score.skip("not_ned")
            continue
        t = int(ev["timestamp_sample"][i])
        k = bisect.bisect_left(gt_t, t)
        if k == 0 or k >= len(gt_t) or gt_t[k] - gt_t[k - 1] > 500_000:
            score.skip("no_truth")
            continue
        w = (t - gt_t[k - 1]) / (gt_t[k] - gt_t[k - 1])
        lat_t = float(gt["lat"][k - 1]) * (1 - w) + float(gt["lat"][k]) * w
        lon_t = float(gt["lon"][k - 1]) * (1 - w) + float(gt["lon"][k]) * w
        j = min(bisect.bisect_left(lp_t, t), len(lp_t) - 1)
        ref_lat, ref_lon = float(lp["ref_lat"][j]), float(lp["ref_lon"][j])
        x, y = float(ev["position[0]"][i]), float(ev["position[1]"][i])
        var = max(float(ev["position_variance[0]"][i]), float(ev["position_variance[1]"][i]))
        if not all(math.isfinite(v) for v in (ref_lat, ref_lon, x, y, var)):
            score.skip("not_finite")
            continue
        lat, lon = px4_from_ned(ref_lat, ref_lon, x, y)
        phase = "gps_off" if t_gps_off is not None and t >= t_gps_off else "gps_on"
        score.add(t * 1e-6, phase, lat, lon, math.sqrt(max(var, 0.0)), lat_t, lon_t)
    return score


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ulg")
    ap.add_argument("--json", help="write the result here too")
    ap.add_argument("--sim", choices=["auto", "sih", "jmavsim"], default="auto",
                    help="the simulator (auto: jMAVSim when SYS_AUTOSTART is 10017)")
    args = ap.parse_args()
    u, gt, sim, t_gps_off = load(args.ulg, args.sim)
    lp = topic(u, "vehicle_local_position")
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
        lat_e, lon_e = px4_from_ned(ref_lat, ref_lon, float(lp["x"][i]), float(lp["y"][i]))
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
    integ = injected_integrity(u, gt, t_gps_off)
    if integ is not None:
        out["injected"] = integ.summary()
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
