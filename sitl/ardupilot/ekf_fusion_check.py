#!/usr/bin/env python3
"""EKF3's horizontal error after the GPS loss of a sitl/ardupilot/run.py flight, beside what the
model of sitl/consumer_fusion.py makes of the same injected stream with and without fusing its
velocity:

    python3 sitl/ardupilot/ekf_fusion_check.py WORKDIR/logs/00000001.BIN

Reads ArduPilot's dataflash log (pymavlink's DFReader): the truth (SIM, SIM2), EKF3's output
(POS), the injected stream as ArduPilot received it (GPS and GPA of instance 0, visnav's
GPS_INPUT) and the GPS-off time (PARM SIM_GPS_DISABLE = 1). Scored like run.py's verdict: every
sample from 5 s after the GPS went off while the copter flies faster than 5 m/s. The "model, as
flown" row checks the model against EKF3 (it uses the flight's EK3_SRC1_VELXY); the other rows
answer "what would EKF3 have done".
"""

import argparse
import bisect
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from consumer_fusion import (SCORE_AFTER_GPS_OFF_S, SCORE_MIN_SPEED_M_S,  # noqa: E402
                             print_comparison)
from sitl_common import metres_per_deg  # noqa: E402

try:
    from pymavlink import DFReader
except ImportError:
    sys.exit("ekf_fusion_check.py needs pymavlink: use the venv python of scripts/interop/setup_venv.sh")


def read_log(path):
    log = DFReader.DFReader_binary(path, zero_time_base=True)
    sim, sim2, pos, gps, gpa, params, off = [], [], [], [], [], {}, None
    while True:
        m = log.recv_match(type=["SIM", "SIM2", "POS", "GPS", "GPA", "PARM"])
        if m is None:
            break
        t = m.TimeUS * 1e-6
        typ = m.get_type()
        if typ == "SIM":
            sim.append((t, m.Lat, m.Lng))
        elif typ == "SIM2":
            sim2.append((t, m.VN, m.VE))
        elif typ == "POS":
            pos.append((t, m.Lat, m.Lng))
        elif typ == "GPS" and m.I == 0 and m.Status >= 3:
            crs = math.radians(m.GCrs)
            gps.append((t, m.Lat, m.Lng, m.Spd * math.cos(crs), m.Spd * math.sin(crs)))
        elif typ == "GPA" and m.I == 0:
            gpa.append((t, m.HAcc, m.SAcc))
        elif typ == "PARM":
            params[m.Name] = m.Value
            if off is None and ((m.Name == "SIM_GPS_DISABLE" and m.Value == 1)
                                or (m.Name == "SIM_GPS1_ENABLE" and m.Value == 0)):
                off = t
    if not (sim and sim2 and gps and gpa):
        sys.exit(f"{path}: needs SIM, SIM2, GPS and GPA records (an ArduPilot SITL log of run.py)")
    if off is None:
        sys.exit(f"{path}: no SIM_GPS_DISABLE change: the GPS was never switched off")
    return sim, sim2, pos, gps, gpa, params, off


def interp(ts, rows, t, i):
    j = min(max(bisect.bisect_left(ts, t), 1), len(ts) - 1)
    a, b = rows[j - 1], rows[j]
    w = (t - a[0]) / max(b[0] - a[0], 1e-9)
    return a[i] + w * (b[i] - a[i])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bin")
    args = ap.parse_args()
    sim, sim2, pos, gps, gpa, params, off = read_log(args.bin)
    lat0, lon0 = sim[0][1], sim[0][2]
    mn, me = metres_per_deg(lat0)

    def ne(lat, lon):
        return ((lat - lat0) * mn, (lon - lon0) * me)

    st, vt, at = [r[0] for r in sim], [r[0] for r in sim2], [r[0] for r in gpa]

    def truth_pos(t):
        return ne(interp(st, sim, t, 1), interp(st, sim, t, 2))

    def truth_vel(t):
        return (interp(vt, sim2, t, 1), interp(vt, sim2, t, 2))

    def truth_acc(t0, t1):
        a, b = truth_vel(t0), truth_vel(t1)
        dt = max(t1 - t0, 1e-6)
        return ((b[0] - a[0]) / dt, (b[1] - a[1]) / dt)

    def scored(t):
        return (t >= off + SCORE_AFTER_GPS_OFF_S
                and math.hypot(*truth_vel(t)) > SCORE_MIN_SPEED_M_S)

    msgs = []
    for t, lat, lon, vn, ve in gps:
        if t < off - 30.0:
            continue
        acc = gpa[min(bisect.bisect_left(at, t), len(at) - 1)]
        n, e = ne(lat, lon)
        msgs.append((t, n, e, vn, ve, acc[1], acc[2]))

    print(f"GPS off at boot {off:.1f} s; EK3_SRC1_VELXY {params.get('EK3_SRC1_VELXY', '?'):.0f}")
    ekf = [math.hypot(*(a - b for a, b in zip(ne(la, lo), truth_pos(t))))
           for t, la, lo in pos if scored(t)]
    inj = [math.hypot(m[1] - truth_pos(m[0])[0], m[2] - truth_pos(m[0])[1])
           for m in msgs if scored(m[0])]
    print_comparison(("EKF3 (POS), as flown", ekf), ("injected (GPS1 echo)", inj), msgs,
                     truth_pos, truth_acc, scored,
                     as_flown=params.get("EK3_SRC1_VELXY", 3) == 3)


if __name__ == "__main__":
    main()
