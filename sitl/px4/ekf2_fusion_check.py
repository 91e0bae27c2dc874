#!/usr/bin/env python3
"""EKF2's horizontal error after the GPS loss of a sitl/px4/run.py flight, beside what the model
of sitl/consumer_fusion.py makes of the same ODOMETRY stream with and without fusing its
velocity (the PX4 counterpart of sitl/ardupilot/ekf_fusion_check.py):

    python3 sitl/px4/ekf2_fusion_check.py WORKDIR/px4/log/*/*.ulg

Needs pyulog. Reads PX4's log: the truth (`vehicle_local_position_groundtruth`: position and
velocity about its own origin), EKF2's output (`vehicle_local_position`), visnav's ODOMETRY as
PX4 received it (`vehicle_visual_odometry`: position NED about EKF2's origin at
`timestamp_sample`, velocity in the body frame, rotated to NED with the message's attitude) and
the GPS-off time (`EKF2_GPS_CTRL` set to 0). Every sample from 5 s after the GPS went off while the
copter flies faster than 5 m/s. The claimed accuracies are the square roots of the larger of the
horizontal variances (PX4 logs no covariance).
"""

import argparse
import bisect
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from consumer_fusion import (SCORE_AFTER_GPS_OFF_S, SCORE_MIN_SPEED_M_S,  # noqa: E402
                             print_comparison)
from sitl_common import metres_per_deg, px4_from_ned, ulog_topic as topic  # noqa: E402

try:
    from pyulog import ULog
except ImportError:
    sys.exit("ekf2_fusion_check.py needs pyulog: python3 -m pip install pyulog")


def rotate_body_to_ned(q, v):
    """v_ned = R(q) v_body, q = (w, x, y, z) Hamilton (PX4's vehicle_odometry q)."""
    w, x, y, z = q
    r = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return [sum(r[i][k] * v[k] for k in range(3)) for i in range(3)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ulg")
    args = ap.parse_args()
    u = ULog(args.ulg, ["vehicle_local_position", "vehicle_local_position_groundtruth",
                        "vehicle_visual_odometry"])
    names = {d.name for d in u.data_list}
    for need in ("vehicle_local_position", "vehicle_local_position_groundtruth",
                 "vehicle_visual_odometry"):
        if need not in names:
            sys.exit(f"{args.ulg}: no {need} (a PX4 SITL log of run.py with visnav?)")
    off = next((t * 1e-6 for t, n, v in u.changed_parameters
                if n == "EKF2_GPS_CTRL" and v == 0 and t > 0), None)
    if off is None:
        sys.exit(f"{args.ulg}: EKF2_GPS_CTRL never set to 0: the GPS was never switched off")
    gt, lp, ev = (topic(u, n) for n in ("vehicle_local_position_groundtruth",
                                        "vehicle_local_position", "vehicle_visual_odometry"))
    lat0, lon0 = float(gt["ref_lat"][0]), float(gt["ref_lon"][0])
    mn, me = metres_per_deg(lat0)

    def to_common(ref_lat, ref_lon, x, y):
        """NE metres about the truth's origin of a local NED position about (ref_lat, ref_lon),
        read back with PX4's own projection."""
        lat, lon = px4_from_ned(ref_lat, ref_lon, x, y)
        return ((lat - lat0) * mn, (lon - lon0) * me)

    gt_t = [int(t) * 1e-6 for t in gt["timestamp"]]
    gt_n, gt_e, gt_vn, gt_ve = [], [], [], []
    for i in range(len(gt_t)):
        n, e = to_common(float(gt["ref_lat"][i]), float(gt["ref_lon"][i]), float(gt["x"][i]),
                         float(gt["y"][i]))
        gt_n.append(n)
        gt_e.append(e)
        gt_vn.append(float(gt["vx"][i]))
        gt_ve.append(float(gt["vy"][i]))

    def interp(series, t):
        j = min(max(bisect.bisect_left(gt_t, t), 1), len(gt_t) - 1)
        w = (t - gt_t[j - 1]) / max(gt_t[j] - gt_t[j - 1], 1e-9)
        return series[j - 1] + w * (series[j] - series[j - 1])

    def truth_pos(t):
        return (interp(gt_n, t), interp(gt_e, t))

    def truth_acc(t0, t1):
        dt = max(t1 - t0, 1e-6)
        return ((interp(gt_vn, t1) - interp(gt_vn, t0)) / dt,
                (interp(gt_ve, t1) - interp(gt_ve, t0)) / dt)

    def scored(t):
        return (t >= off + SCORE_AFTER_GPS_OFF_S
                and math.hypot(interp(gt_vn, t), interp(gt_ve, t)) > SCORE_MIN_SPEED_M_S)

    lp_t = [int(t) * 1e-6 for t in lp["timestamp"]]
    msgs = []
    for i in range(len(ev["timestamp"])):
        t = int(ev["timestamp_sample"][i]) * 1e-6
        if t < off - 30.0 or int(ev["pose_frame"][i]) != 1:
            continue
        j = min(bisect.bisect_left(lp_t, t), len(lp_t) - 1)
        n, e = to_common(float(lp["ref_lat"][j]), float(lp["ref_lon"][j]),
                         float(ev["position[0]"][i]), float(ev["position[1]"][i]))
        q = [float(ev[f"q[{k}]"][i]) for k in range(4)]
        v = [float(ev[f"velocity[{k}]"][i]) for k in range(3)]
        if int(ev["velocity_frame"][i]) == 3:  # VELOCITY_FRAME_BODY_FRD
            v = rotate_body_to_ned(q, v)
        h_acc = math.sqrt(max(float(ev["position_variance[0]"][i]),
                              float(ev["position_variance[1]"][i]), 0.0))
        s_acc = math.sqrt(max(float(ev[f"velocity_variance[{k}]"][i]) for k in range(3)))
        if all(math.isfinite(x) for x in (n, e, v[0], v[1], h_acc, s_acc)):
            msgs.append((t, n, e, v[0], v[1], h_acc, s_acc))
    if not msgs:
        sys.exit(f"{args.ulg}: no usable ODOMETRY samples after the GPS went off")

    ev_ctrl = int(u.initial_parameters.get("EKF2_EV_CTRL", -1))
    print(f"GPS off at boot {off:.1f} s; EKF2_EV_CTRL {ev_ctrl}")
    ekf = []
    for i in range(len(lp_t)):
        if scored(lp_t[i]):
            n, e = to_common(float(lp["ref_lat"][i]), float(lp["ref_lon"][i]), float(lp["x"][i]),
                             float(lp["y"][i]))
            tn, te = truth_pos(lp_t[i])
            ekf.append(math.hypot(n - tn, e - te))
    inj = [math.hypot(m[1] - truth_pos(m[0])[0], m[2] - truth_pos(m[0])[1]) for m in msgs
           if scored(m[0])]
    print_comparison(("EKF2 (vehicle_local_position)", ekf),
                     ("injected (ODOMETRY as received)", inj), msgs, truth_pos, truth_acc, scored)


if __name__ == "__main__":
    main()
