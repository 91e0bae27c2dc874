#!/usr/bin/env python3
"""Score visnav's visual odometry in a real-SITL flight against the simulator's truth.

    python3 sitl/vo_check.py WORKDIR [--from-s T] [--json]

WORKDIR is a run.py work folder: `vo.jsonl` (visnav's `[daemon] vo_log`: one line per frame the
odometer ran on) and `frames_truth.jsonl` (`visnav sitl-run --truth-log`: the true pose of every
rendered frame, by the same capture time). For every motion: the true displacement of the
vehicle between the two capture times (NED, local tangent plane at the first; the simulated
camera sits at the body origin, so the body's displacement is the camera's), the error of the
measured one, and that error over the claimed covariance (NEES: horizontal 2 dof, 95 % of
honest motions under 5.99). The drift is the sum of the measured displacements minus the sum of
the true ones over the longest run of consecutive motions: what VO alone would have made of the track. Scale error
is the measured length along the true direction over the true length, minus one; direction error
the angle between them. Standard library only.
"""
import argparse
import json
import math
import os
import statistics
import sys
from collections import Counter

WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3
NEES2_95 = 5.991  # chi-square, 2 dof, 95 %
NEES2_999 = 13.82  # chi-square, 2 dof, 99.9 %


def read_jsonl(path):
    out = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError as e:
                # The last line of a log cut by a kill may be partial: skip it, say so.
                print(f"{path}: line {i}: {e} (skipped)", file=sys.stderr)
    return out


def ned_between(a, b):
    """Displacement NED (m) from truth sample a to b (local tangent plane at a)."""
    lat = math.radians(a["lat_deg"])
    s = 1.0 - WGS84_E2 * math.sin(lat) ** 2
    r_n = WGS84_A * (1.0 - WGS84_E2) / s ** 1.5  # meridian radius
    r_e = WGS84_A / math.sqrt(s)  # prime vertical radius
    h = a["alt_amsl_m"]
    dn = math.radians(b["lat_deg"] - a["lat_deg"]) * (r_n + h)
    de = math.radians(b["lon_deg"] - a["lon_deg"]) * (r_e + h) * math.cos(lat)
    dd = -(b["alt_amsl_m"] - a["alt_amsl_m"])
    return [dn, de, dd]


def nees_h(err, cov):
    """e^T C^-1 e of the horizontal (N, E) part; None when C is not positive definite."""
    a, b, c = cov[0][0], cov[0][1], cov[1][1]
    det = a * c - b * b
    if not (a > 0 and det > 0):
        return None
    en, ee = err[0], err[1]
    return (c * en * en - 2 * b * en * ee + a * ee * ee) / det


def pct(xs, q):
    if not xs:
        return None
    s = sorted(xs)
    k = (len(s) - 1) * q
    lo = math.floor(k)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)


def stats(xs, nd=3):
    if not xs:
        return None
    return {"n": len(xs), "p50": round(pct(xs, 0.5), nd), "p90": round(pct(xs, 0.9), nd),
            "max": round(max(xs), nd)}


def score(vo, truth, from_s=None):
    by_t = {r["t_capture_us"]: r for r in truth}
    t0 = min(by_t) if by_t else 0
    steps = Counter(r.get("step", "?") for r in vo)
    outcomes = Counter(r.get("outcome", "") for r in vo if r.get("step") == "motion")
    reasons = Counter(r.get("reason", "") for r in vo if r.get("step") == "refused")
    rows = []
    for r in vo:
        if r.get("step") != "motion" or r.get("dp_ned_m") is None:
            continue
        t_prev, t_next = r.get("t_prev_us"), r["t_capture_us"]
        if from_s is not None and (t_prev - t0) * 1e-6 < from_s:
            continue
        a, b = by_t.get(t_prev), by_t.get(t_next)
        if a is None or b is None:
            continue
        true = ned_between(a, b)
        meas = r["dp_ned_m"]
        err = [m - t for m, t in zip(meas, true)]
        cov = r.get("cov_ned_m2")
        len_t = math.hypot(true[0], true[1])
        row = {"t_prev_us": t_prev, "t_next_us": t_next, "t_s": (t_next - t0) * 1e-6, "dt_s": (t_next - t_prev) * 1e-6, "true": true,
               "meas": meas, "err": err, "err_h": math.hypot(err[0], err[1]),
               "sigma_h": None if cov is None else math.sqrt(max(cov[0][0] + cov[1][1], 0.0)),
               "nees_h": None if cov is None else nees_h(err, cov),
               "agl_m": r.get("agl_m"), "alt_m": b["alt_amsl_m"], "outcome": r.get("outcome"),
               "len_true_m": len_t, "rot_los_deg": r.get("rot_los_deg"),
               "rot_los_sigma_deg": r.get("rot_los_sigma_deg")}
        if len_t > 1.0:
            ut = (true[0] / len_t, true[1] / len_t)
            along = meas[0] * ut[0] + meas[1] * ut[1]
            cross = -meas[0] * ut[1] + meas[1] * ut[0]
            row["scale_err"] = along / len_t - 1.0
            row["dir_err_deg"] = math.degrees(math.atan2(cross, along))
        rows.append(row)
    return steps, outcomes, reasons, rows


def drift(rows):
    """Sum of (measured - true) over runs of consecutive motions (each starting at the frame the
    one before ended on); the longest run: its start / end (s), motions (n), length flown and
    end drift (e, NED)."""
    best = None
    cur = None
    last_us = None
    for r in rows:
        if cur is None or r["t_prev_us"] != last_us:
            cur = {"t0_s": r["t_s"] - r["dt_s"], "e": [0.0, 0.0, 0.0], "flown_m": 0.0, "n": 0}
        for i in range(3):
            cur["e"][i] += r["err"][i]
        cur["flown_m"] += r["len_true_m"]
        cur["n"] += 1
        cur["t1_s"] = r["t_s"]
        last_us = r["t_next_us"]
        if best is None or cur["n"] >= best["n"]:
            best = dict(cur, e=list(cur["e"]))
    return best


def summary(steps, outcomes, reasons, rows):
    out = {"steps": dict(steps), "motion_outcomes": dict(outcomes),
           "refusals": dict(reasons.most_common(8)), "scored_motions": len(rows)}
    if not rows:
        return out
    nees = [r["nees_h"] for r in rows if r["nees_h"] is not None]
    out["err_h_m"] = stats([r["err_h"] for r in rows])
    out["err_down_m"] = stats([abs(r["err"][2]) for r in rows])
    out["sigma_h_m"] = stats([r["sigma_h"] for r in rows if r["sigma_h"] is not None])
    out["nees_h"] = stats(nees, 2)
    if nees:
        out["nees_h_over_95pct"] = round(sum(n > NEES2_95 for n in nees) / len(nees), 3)
        out["nees_h_over_99_9pct"] = round(sum(n > NEES2_999 for n in nees) / len(nees), 3)
    sc = [r["scale_err"] for r in rows if "scale_err" in r]
    dr = [r["dir_err_deg"] for r in rows if "dir_err_deg" in r]
    if sc:
        out["scale_err_pct"] = {"mean": round(100 * statistics.fmean(sc), 3),
                                "p50": round(100 * pct(sc, 0.5), 3),
                                "abs_p90": round(100 * pct([abs(x) for x in sc], 0.9), 3)}
    if dr:
        out["dir_err_deg"] = {"mean": round(statistics.fmean(dr), 3),
                              "p50": round(pct(dr, 0.5), 3),
                              "abs_p90": round(pct([abs(x) for x in dr], 0.9), 3)}
    # Systematic part: the mean error per second (a velocity bias), N and E.
    t = sum(r["dt_s"] for r in rows)
    out["mean_err_rate_ne_m_s"] = [round(sum(r["err"][i] for r in rows) / t, 4) for i in (0, 1)]
    rot = [r for r in rows if r["rot_los_deg"] is not None]
    if rot:
        # The rotation the images saw beyond the gyros' about the line of sight: its mean per
        # second is the gyros' residual bias along it as the filter compensated it (no truth
        # needed); its scatter against its claimed sigma.
        a = [r["rot_los_deg"] for r in rot]
        out["rot_los"] = {
            "n": len(rot),
            "mean_deg_h": round(3600 * sum(a) / sum(r["dt_s"] for r in rot), 2),
            "sd_deg": round(statistics.pstdev(a), 5),
            "sigma_p50_deg": round(pct([r["rot_los_sigma_deg"] for r in rot
                                        if r["rot_los_sigma_deg"] is not None] or [0], 0.5), 5)}
    d = drift(rows)
    if d is not None:
        out["longest_run"] = {"from_s": round(d["t0_s"], 1), "to_s": round(d["t1_s"], 1),
                              "motions": d["n"], "flown_m": round(d["flown_m"], 1),
                              "drift_ned_m": [round(x, 2) for x in d["e"]],
                              "drift_h_pct": round(100 * math.hypot(d["e"][0], d["e"][1])
                                                   / max(d["flown_m"], 1e-9), 3)}
    # By height: where the error and its claim part.
    bands = {}
    for r in rows:
        if r["agl_m"] is None:
            continue
        b = f"{int(r['agl_m'] // 500) * 500}-{int(r['agl_m'] // 500) * 500 + 500}"
        bands.setdefault(b, []).append(r)
    out["by_agl_m"] = {
        b: {"n": len(rs), "err_h_p50": round(pct([r["err_h"] for r in rs], 0.5), 3),
            "sigma_h_p50": round(pct([r["sigma_h"] for r in rs if r["sigma_h"]] or [0], 0.5), 3),
            "nees_h_p50": round(pct([r["nees_h"] for r in rs if r["nees_h"] is not None] or [0],
                                    0.5), 2),
            "scale_err_pct_p50": round(100 * pct([r["scale_err"] for r in rs
                                                  if "scale_err" in r] or [0], 0.5), 3)}
        for b, rs in sorted(bands.items(), key=lambda kv: float(kv[0].split("-")[0]))}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdir")
    ap.add_argument("--from-s", type=float, default=None,
                    help="only motions from this many seconds after the first frame")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON only")
    args = ap.parse_args(argv)
    paths = [os.path.join(args.workdir, n) for n in ("vo.jsonl", "frames_truth.jsonl")]
    for p in paths:
        if not os.path.exists(p):
            sys.exit(f"{p}: missing (a run.py work folder of a visnav run with this version)")
    vo, truth = (read_jsonl(p) for p in paths)
    out = summary(*score(vo, truth, args.from_s))
    if args.json:
        print(json.dumps(out))
        return
    for k, v in out.items():
        print(f"{k}: {json.dumps(v)}")


if __name__ == "__main__":
    main()
