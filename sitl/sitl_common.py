"""What the real-SITL scripts (sitl/ardupilot/run.py, sitl/px4/run.py, sitl/px4/ulog_error.py)
share: the home over the bundled map, metres per degree, the error statistics, the scoring and
the verdict of a flight, free ports for parallel runs, and the end of a run (stop the processes,
attach visnav's last metrics line, write report.json).

Standard library only, so that ulog_error.py (pyulog), the run scripts (pymavlink) and the unit
tests (sitl/test_sitl_common.py, plain python3) can all import it:
`sys.path.insert(0, <this folder>)` then `import sitl_common`.

Scoring (ErrorScore): every position the autopilot reports (GLOBAL_POSITION_INT) against the
simulator's truth of the same instant, split into "gps_on" (airborne, before the GPS goes off)
and "gps_off" (airborne, after). The GPS-off period is split again by whether the estimator is
*aiding* its horizontal position at that instant (its status flags, `ekf_aiding`): an EKF that
stopped aiding holds its last position (ArduPilot's constant position mode), and a frozen
position over a copter that barely moves (LAND) is not accuracy. The aiding samples give the
estimator's accuracy ("gps_off_aiding"), the others are reported apart ("gps_off_not_aiding"),
with the time the estimator was not aiding ("not_aiding": first loss after GPS off, total).
The verdict's error bounds use every GPS-off airborne sample; not aiding is a failure reason of
its own.

Integrity (IntegrityScore): the position visnav injected, as the autopilot echoes it (ArduPilot:
GPS_RAW_INT of GPS instance 0 = visnav's GPS_INPUT, with its h_acc), against the truth at the
fix's time: error / claimed horizontal accuracy.

Verdict (`verdict`): pass only when the mission was completed in its mission mode, no failsafe
message came, the GPS went off, the estimator aided all through the GPS-off period, its
horizontal error over that period is within the bounds, no GPS-off position is missing for
more than a few seconds, and (where measured) the injected position stayed within `ratio` times
its claimed accuracy of the truth.
"""

import argparse
import json
import math
import os
import re
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
from collections import deque

# Centre of sitl/maps/naip_nd_2009.tif (EPSG:26914 x 488235, y 5207437), ground ~580 m AMSL.
HOME_LAT, HOME_LON, HOME_ALT_M = 47.0203485, -99.1548094, 580.0

# Below this true height above home a sample is "on the ground" and not scored.
AIRBORNE_M = 5.0

# EKF_STATUS_FLAGS (ArduPilot EKF_STATUS_REPORT.flags) and ESTIMATOR_STATUS_FLAGS (PX4
# ESTIMATOR_STATUS.flags) share these bits.
EKF_POS_HORIZ_ABS = 16     # the absolute horizontal position estimate is good
EKF_CONST_POS_MODE = 128   # constant position mode: no absolute or relative position
EKF_UNINITIALIZED = 1024   # ArduPilot: the EKF has never been healthy

# An estimator status older than this says nothing about aiding (reports come at 2-5 Hz).
FLAGS_MAX_AGE_S = 2.0

# Verdict defaults (issue 18's acceptance): EKF horizontal error over the whole GPS-off period
# p90 <= 25 m and max <= 50 m; the injected position never more than 3 x its claimed horizontal
# accuracy (1 sigma) from the truth; no time without aiding; no GPS-off position missing for
# more than 2 s (GLOBAL_POSITION_INT comes at 10 Hz; PX4 stops it when its position is invalid).
MAX_P90_M = 25.0
MAX_ERROR_M = 50.0
MAX_RATIO = 3.0
MAX_NOT_AIDING_S = 0.0
MAX_SAMPLE_GAP_S = 2.0

# STATUSTEXT (case-insensitive substrings) that mean a failsafe or an estimator alarm:
# ArduCopter "EKF Failsafe: changed to LAND Mode", "EKF variance", "GPS Glitch or Compass error",
# "Radio Failsafe", "Battery Failsafe", ...; PX4 "Failsafe activated", "... failsafe ...".
FAILSAFE_PATTERNS = ("failsafe", "ekf variance", "gps glitch")

# Reason names of the verdict, in the order they are checked.
REASONS = ("run_error", "mission_not_completed", "mode_change", "failsafe", "gps_not_off",
           "no_gps_off_samples", "gps_off_error_p90", "gps_off_error_max", "not_aiding",
           "sample_gap", "integrity_not_measured", "integrity_no_accuracy", "integrity_ratio")


def metres_per_deg(lat_deg):
    """(metres per degree of latitude, of longitude) on WGS84 at this latitude (series to 4 phi)."""
    p = math.radians(lat_deg)
    return (111132.954 - 559.822 * math.cos(2 * p) + 1.175 * math.cos(4 * p),
            111412.84 * math.cos(p) - 93.5 * math.cos(3 * p))


# The autopilots' own local projections (visnav_core::geo::autopilot_frame): a local position
# an autopilot fuses or logs is read back to latitude/longitude as the autopilot reads it.
ARDUPILOT_EARTH_RADIUS_M = 6378100.0  # AP_Math/definitions.h RADIUS_OF_EARTH
PX4_EARTH_RADIUS_M = 6371000.0  # PX4 lib/geo CONSTANTS_RADIUS_OF_EARTH


def ardupilot_from_ned(lat0, lon0, north, east):
    """(lat, lon) of a local north/east position about ArduPilot's origin
    (Location::offset_latlng: an equirectangular sphere, longitude scaled at the mean latitude)."""
    lat = lat0 + math.degrees(north / ARDUPILOT_EARTH_RADIUS_M)
    scale = max(math.cos(math.radians(0.5 * (lat + lat0))), 0.01)
    return lat, lon0 + math.degrees(east / (ARDUPILOT_EARTH_RADIUS_M * scale))


def px4_from_ned(lat0, lon0, north, east):
    """(lat, lon) of a local north/east position about PX4's origin (MapProjection::reproject:
    azimuthal equidistant on a sphere)."""
    x, y = north / PX4_EARTH_RADIUS_M, east / PX4_EARTH_RADIUS_M
    c = math.hypot(x, y)
    if c == 0.0:
        return lat0, lon0
    s0, c0 = math.sin(math.radians(lat0)), math.cos(math.radians(lat0))
    sc, cc = math.sin(c), math.cos(c)
    lat = math.asin(cc * s0 + x * sc * c0 / c)
    dlon = math.atan2(y * sc, c * c0 * cc - x * s0 * sc)
    return math.degrees(lat), lon0 + math.degrees(dlon)


def north_east(lat_deg, lon_deg, lat_t, lon_t):
    """(north, east) metres of a position from the truth (flat earth at the truth)."""
    m_lat, m_lon = metres_per_deg(lat_t)
    return (lat_deg - lat_t) * m_lat, (lon_deg - lon_t) * m_lon


def stats(v):
    """n, median, p90 (nearest rank) and max of a list of errors in metres, or None when empty."""
    if not v:
        return None
    s = sorted(v)
    p90 = s[min(len(s) - 1, int(math.ceil(0.9 * len(s))) - 1)]
    return {"n": len(s), "median_m": round(statistics.median(s), 2), "p90_m": round(p90, 2),
            "max_m": round(s[-1], 2)}


def ekf_aiding(flags):
    """The estimator reports a valid absolute horizontal position: EKF_POS_HORIZ_ABS set, and
    neither constant position mode nor (ArduPilot) uninitialised. ArduPilot EKF3 sets
    POS_HORIZ_ABS only while it fuses an absolute position (GPS, here visnav's GPS_INPUT) without
    a timeout and is healthy, and CONST_POS_MODE once it stopped aiding (AID_NONE); PX4 EKF2 sets
    POS_HORIZ_ABS while it fuses GPS or vision position without a fault."""
    return bool(flags & EKF_POS_HORIZ_ABS) and not flags & (EKF_CONST_POS_MODE | EKF_UNINITIALIZED)


class AidingTracker:
    """Whether the estimator aids, from its status reports over time, and the periods it does
    not after the GPS went off. A report holds for FLAGS_MAX_AGE_S; with no newer report the
    estimator counts as not aiding from then on (a silent estimator proves nothing). Times are
    seconds on any one clock (the run scripts use seconds since arming)."""

    def __init__(self, max_age_s=FLAGS_MAX_AGE_S):
        self.max_age_s = max_age_s
        self.last = None    # (t, aiding) of the latest report
        self.t_off = None   # GPS off
        self.periods = []   # closed not-aiding periods after GPS off, [start, end]
        self.open = None    # start of the current not-aiding period

    def aiding_at(self, t):
        """True / False at time t (the latest report, if not older than max_age_s), None before
        the first report."""
        if self.last is None:
            return None
        return self.last[1] and t - self.last[0] <= self.max_age_s

    def _advance(self, t):
        # The latest report said "aiding" but has gone stale before t: not aiding from its expiry.
        if self.t_off is None or self.open is not None:
            return
        if self.last is None:
            self.open = self.t_off
        elif self.last[1] and t - self.last[0] > self.max_age_s:
            self.open = max(self.t_off, self.last[0] + self.max_age_s)

    def status(self, t, flags):
        """An estimator status report (EKF_STATUS_REPORT / ESTIMATOR_STATUS flags) at time t."""
        self._advance(t)
        aiding = ekf_aiding(flags)
        self.last = (t, aiding)
        if self.t_off is None:
            return
        if aiding and self.open is not None:
            self.periods.append([self.open, t])
            self.open = None
        elif not aiding and self.open is None:
            self.open = t

    def gps_off(self, t):
        if self.t_off is not None:
            return
        self.t_off = t
        if not self.aiding_at(t):
            self.open = t

    def summary(self, t_end):
        """Not-aiding time after GPS off, up to t_end: first loss (s after GPS off), total s,
        the periods (s after GPS off; an open one ends at t_end), or None before GPS off."""
        if self.t_off is None:
            return None
        self._advance(t_end)
        periods = self.periods + ([[self.open, t_end]] if self.open is not None else [])
        periods = [[a, b] for a, b in periods if b > a]
        rel = [[round(a - self.t_off, 2), round(b - self.t_off, 2)] for a, b in periods]
        return {"first_loss_after_gps_off_s": rel[0][0] if rel else None,
                "total_s": round(sum(b - a for a, b in periods), 2),
                "periods_after_gps_off_s": rel,
                "aiding_at_end": self.open is None and bool(self.aiding_at(t_end))}


class ErrorScore:
    """The autopilot's position (GLOBAL_POSITION_INT) against the simulator's truth: horizontal
    and vertical error per phase, only above AIRBORNE_M (the ground before take-off does not
    count):

    * "gps_on": before the GPS is off;
    * "gps_off": every sample after (what the verdict's bounds use);
    * "gps_off_aiding" / "gps_off_not_aiding": the same samples split by whether the estimator
      was aiding at that instant (`status` gives its flags): only the first is accuracy, the
      second is a position the estimator no longer corrects (frozen in ArduPilot's constant
      position mode).

    Every sample is kept for samples.json ([t_s, phase, agl_m, north_m, east_m, up_m, aiding],
    aiding true / false / null before any status), a log line every 100 samples."""

    PHASES = ("gps_on", "gps_off", "gps_off_aiding", "gps_off_not_aiding")

    def __init__(self, estimator, log, flags_max_age_s=FLAGS_MAX_AGE_S, home_alt_m=HOME_ALT_M):
        self.estimator = estimator  # "EKF3", "EKF2": for the log line and the verdict
        self.log = log
        self.home_alt_m = home_alt_m  # the take-off ground, m AMSL: heights above it are agl
        self.errs = {ph: ([], []) for ph in self.PHASES}
        self.samples = []
        self.aiding = AidingTracker(flags_max_age_s)
        self.t_last_off = None  # time of the latest GPS-off sample (any height)
        self.max_gap_s = 0.0    # longest GPS-off time without a sample

    def status(self, t_s, flags):
        """The estimator's status flags (EKF_STATUS_REPORT / ESTIMATOR_STATUS) at t_s."""
        self.aiding.status(t_s, flags)

    def gps_switched_off(self, t_s):
        self.aiding.gps_off(t_s)
        if self.t_last_off is None:
            self.t_last_off = t_s

    def add(self, t_s, gps_off, lat_deg, lon_deg, alt_m, lat_t, lon_t, alt_t):
        dn, de = north_east(lat_deg, lon_deg, lat_t, lon_t)
        eh = math.hypot(dn, de)
        ev = alt_m - alt_t
        agl = alt_t - self.home_alt_m
        aiding = self.aiding.aiding_at(t_s)
        if gps_off:
            self.gps_switched_off(t_s)  # no-op once told
            self.max_gap_s = max(self.max_gap_s, t_s - self.t_last_off)
            self.t_last_off = t_s
        phase = "gps_off" if gps_off else "gps_on"
        if agl > AIRBORNE_M:
            phases = [phase]
            if gps_off:
                phases.append("gps_off_aiding" if aiding else "gps_off_not_aiding")
            for ph in phases:
                self.errs[ph][0].append(eh)
                self.errs[ph][1].append(abs(ev))
        self.samples.append([round(t_s, 2), phase, round(agl, 1), round(dn, 2), round(de, 2),
                             round(ev, 2), aiding])
        if len(self.samples) % 100 == 0:
            state = {None: "", True: ", aiding", False: ", NOT aiding"}[aiding]
            self.log(f"t {t_s:.0f} s {phase} agl {agl:.0f} m: {self.estimator} error "
                     f"horizontal {eh:.1f} m vertical {ev:+.1f} m{state}")

    def summary(self, t_end=None):
        """Per phase {"horizontal": stats, "vertical": stats}; with t_end (end of the flight, same
        clock) also "not_aiding" (AidingTracker.summary) and "gps_off_max_sample_gap_s"."""
        out = {ph: {"horizontal": stats(h), "vertical": stats(v)}
               for ph, (h, v) in self.errs.items()}
        if t_end is not None:
            out["not_aiding"] = self.aiding.summary(t_end)
            if self.aiding.t_off is not None:
                gap = max(self.max_gap_s, t_end - self.t_last_off)
                out["gps_off_max_sample_gap_s"] = round(gap, 2)
        return out

    def save(self, workdir):
        with open(os.path.join(workdir, "samples.json"), "w") as f:
            json.dump(self.samples, f)


class IntegrityScore:
    """The position visnav injected, as the autopilot echoes it, against the truth at the fix's
    time: horizontal error, the claimed horizontal accuracy h_acc (1 sigma, m) and their ratio.
    Samples without a claimed accuracy (h_acc 0: not sent or ignored) are counted apart
    ("no_accuracy"); `skip(reason)` counts echoes that could not be scored."""

    def __init__(self, ratio_limit=MAX_RATIO):
        self.ratio_limit = ratio_limit
        self.samples = []  # [t_s, phase, error_m, h_acc_m, ratio or None]
        self.skipped = {}

    def skip(self, reason):
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    def add(self, t_s, phase, lat_deg, lon_deg, h_acc_m, lat_t, lon_t):
        dn, de = north_east(lat_deg, lon_deg, lat_t, lon_t)
        err = math.hypot(dn, de)
        ratio = err / h_acc_m if h_acc_m > 0 else None
        self.samples.append([round(t_s, 2), phase, round(err, 2), round(h_acc_m, 2),
                             None if ratio is None else round(ratio, 3)])
        return ratio

    def summary(self):
        with_acc = [s for s in self.samples if s[4] is not None]
        ratios = [s[4] for s in with_acc]
        out = {"n": len(self.samples),
               "error": stats([s[2] for s in self.samples]),
               "h_acc": stats([s[3] for s in with_acc]),
               "ratio_median": round(statistics.median(ratios), 3) if ratios else None,
               "ratio_max": max(ratios) if ratios else None,
               "ratio_limit": self.ratio_limit,
               "over_limit": sum(1 for r in ratios if r > self.ratio_limit),
               "no_accuracy": len(self.samples) - len(with_acc),
               "skipped": dict(self.skipped)}
        for ph in sorted({s[1] for s in self.samples}):
            out[ph] = {"n": sum(1 for s in self.samples if s[1] == ph),
                       "error": stats([s[2] for s in self.samples if s[1] == ph]),
                       "ratio_max": max([s[4] for s in with_acc if s[1] == ph], default=None)}
        return out

    def save(self, workdir, name="injected.json"):
        with open(os.path.join(workdir, name), "w") as f:
            json.dump(self.samples, f)


class TruthHistory:
    """The truth (lat, lon, alt) of the last `keep_s` seconds by (local) time, linearly
    interpolated at any instant between two samples at most `max_gap_s` apart, or taken from the
    nearest sample within `max_gap_s` at the ends."""

    def __init__(self, keep_s=20.0, max_gap_s=0.2):
        self.keep_s = keep_s
        self.max_gap_s = max_gap_s
        self.s = deque()  # (t, lat, lon, alt), t increasing

    def add(self, t, lat, lon, alt):
        if self.s and t <= self.s[-1][0]:
            return
        self.s.append((t, lat, lon, alt))
        while self.s and self.s[0][0] < t - self.keep_s:
            self.s.popleft()

    def at(self, t):
        s = self.s
        if not s or t < s[0][0] - self.max_gap_s or t > s[-1][0] + self.max_gap_s:
            return None
        if t <= s[0][0]:
            return s[0][1:]
        if t >= s[-1][0]:
            return s[-1][1:]
        lo, hi = 0, len(s) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if s[mid][0] <= t:
                lo = mid
            else:
                hi = mid
        a, b = s[lo], s[hi]
        if b[0] - a[0] > self.max_gap_s:
            return None
        w = (t - a[0]) / (b[0] - a[0])
        return tuple(a[i] + w * (b[i] - a[i]) for i in (1, 2, 3))


class BootClock:
    """The autopilot's boot time (time_boot_ms of its messages) on the local clock: local =
    boot + the smallest (arrival - boot) offset of the last `window_s` seconds (the message
    with the least transport delay)."""

    def __init__(self, window_s=30.0):
        self.window_s = window_s
        self.offsets = deque()  # (t_arrival, offset)

    def on(self, time_boot_ms, t_arrival):
        self.offsets.append((t_arrival, t_arrival - time_boot_ms * 1e-3))
        while self.offsets and self.offsets[0][0] < t_arrival - self.window_s:
            self.offsets.popleft()

    def local(self, boot_s):
        if not self.offsets:
            return None
        return boot_s + min(o for _, o in self.offsets)


class Bounds:
    """The verdict's limits (defaults: the module constants)."""

    def __init__(self, p90_m=MAX_P90_M, max_m=MAX_ERROR_M, ratio=MAX_RATIO,
                 not_aiding_s=MAX_NOT_AIDING_S, sample_gap_s=MAX_SAMPLE_GAP_S):
        self.p90_m, self.max_m, self.ratio = p90_m, max_m, ratio
        self.not_aiding_s, self.sample_gap_s = not_aiding_s, sample_gap_s

    def as_dict(self):
        return {"gps_off_p90_m": self.p90_m, "gps_off_max_m": self.max_m,
                "injected_ratio": self.ratio, "not_aiding_s": self.not_aiding_s,
                "sample_gap_s": self.sample_gap_s}


def add_bounds_args(ap):
    """The verdict's limits as command-line options of a run script."""
    g = ap.add_argument_group("verdict bounds")
    g.add_argument("--max-p90-m", type=float, default=MAX_P90_M,
                   help="GPS-off horizontal error p90 bound, m (default %(default)s)")
    g.add_argument("--max-error-m", type=float, default=MAX_ERROR_M,
                   help="GPS-off horizontal error max bound, m (default %(default)s)")
    g.add_argument("--max-ratio", type=float, default=MAX_RATIO,
                   help="injected position error / its claimed h_acc bound (default %(default)s)")
    g.add_argument("--max-not-aiding-s", type=float, default=MAX_NOT_AIDING_S,
                   help="time the estimator may stop aiding after GPS off, s (default %(default)s)")
    g.add_argument("--max-sample-gap-s", type=float, default=MAX_SAMPLE_GAP_S,
                   help="longest GPS-off time without a position sample, s (default %(default)s)")


def bounds_from_args(args):
    return Bounds(args.max_p90_m, args.max_error_m, args.max_ratio, args.max_not_aiding_s,
                  args.max_sample_gap_s)


def failsafe_texts(texts, patterns=FAILSAFE_PATTERNS):
    """The (t, text) pairs whose text contains one of the patterns (case-insensitive)."""
    return [(t, x) for t, x in texts if any(p in x.lower() for p in patterns)]


def _list(items, n=4):
    shown = ", ".join(items[:n])
    return shown + (f" and {len(items) - n} more" if len(items) > n else "")


def verdict(*, estimator, mission_completed, mission_detail, modes, allowed_modes, texts,
            ekf, integrity=None, integrity_expected=False, integrity_note=None, error=None,
            bounds=None):
    """Pass / fail of a flight with named reasons ("name: detail", names in REASONS).

    estimator: "EKF3" / "EKF2". mission_completed: the last mission item was reached;
    mission_detail: says how far it got. modes: [(t_s, mode)] seen after arming; allowed_modes:
    the mission modes ({"AUTO"}, {"MISSION"}). texts: [(t_s, STATUSTEXT)] after arming.
    ekf: ErrorScore.summary(t_end). integrity: IntegrityScore.summary() or None when not
    measured; integrity_expected: the run injects a position the autopilot echoes (a missing or
    empty score is then a failure); integrity_note: why it is not measured (a note). error: the
    run stopped on an error (a failure)."""
    b = bounds or Bounds()
    reasons, notes = [], []
    if error:
        reasons.append(f"run_error: {error}")
    if not mission_completed:
        reasons.append(f"mission_not_completed: {mission_detail}")
    bad = {}
    for t, mode in modes:
        if mode not in allowed_modes and mode not in bad:
            bad[mode] = t
    if bad:
        reasons.append("mode_change: " + _list([f"{m} at +{t:.1f} s" for m, t in bad.items()]))
    fs = failsafe_texts(texts)
    if fs:
        reasons.append("failsafe: " + _list([f"'{x}' at +{t:.1f} s" for t, x in fs]))
    na = ekf.get("not_aiding")
    off = ekf.get("gps_off", {}).get("horizontal")
    if na is None:
        reasons.append("gps_not_off: the GPS was never switched off, no GPS-off period to score")
    elif off is None:
        reasons.append(f"no_gps_off_samples: no airborne {estimator} position after GPS off")
    if off is not None:
        if off["p90_m"] > b.p90_m:
            reasons.append(f"gps_off_error_p90: {estimator} horizontal error p90 {off['p90_m']} m "
                           f"> {b.p90_m:g} m ({off['n']} GPS-off samples)")
        if off["max_m"] > b.max_m:
            reasons.append(f"gps_off_error_max: {estimator} horizontal error max {off['max_m']} m "
                           f"> {b.max_m:g} m")
    if na is not None and na["total_s"] > b.not_aiding_s:
        reasons.append(f"not_aiding: {estimator} not aiding its horizontal position for "
                       f"{na['total_s']} s after GPS off (first at +{na['first_loss_after_gps_off_s']} s,"
                       f" {len(na['periods_after_gps_off_s'])} period(s))")
    gap = ekf.get("gps_off_max_sample_gap_s")
    if gap is not None and gap > b.sample_gap_s:
        reasons.append(f"sample_gap: no {estimator} position for {gap} s after GPS off "
                       f"(> {b.sample_gap_s:g} s)")
    if integrity is None or integrity.get("n", 0) == 0:
        if integrity_expected:
            reasons.append("integrity_not_measured: no injected position echoed by the autopilot "
                           "was scored")
        elif integrity_note:
            notes.append(integrity_note)
    else:
        if integrity["no_accuracy"]:
            reasons.append(f"integrity_no_accuracy: {integrity['no_accuracy']} injected positions "
                           f"without a claimed accuracy")
        rmax = integrity["ratio_max"]
        if rmax is not None and rmax > b.ratio:
            reasons.append(f"integrity_ratio: injected position {rmax:.2f} x its claimed h_acc "
                           f"from the truth ({integrity['over_limit']} of {integrity['n']} over "
                           f"{b.ratio:g})")
    return {"pass": not reasons, "reasons": reasons, "notes": notes, "bounds": b.as_dict()}


def verdict_lines(label, v):
    """Human lines for a verdict: 'LABEL: PASS' / 'LABEL: FAIL' then one line per reason."""
    lines = [f"{label}: {'PASS' if v['pass'] else 'FAIL'}"]
    lines += [f"{label}:   - {r}" for r in v["reasons"]]
    lines += [f"{label}:   (note) {n}" for n in v.get("notes", [])]
    return lines


def exit_code(v, control, run_completed):
    """0 / 1 of a run script: a visnav run exits 0 only when its verdict passes; a control run
    (no visnav), whose verdict is expected to fail, exits 0 when the run itself completed (the
    GPS went off and the flight ended on its own) and 1 when it did not."""
    if control:
        return 0 if run_completed else 1
    return 0 if v["pass"] else 1


# ---- free ports and instances -------------------------------------------------------------

def port_free(port, proto="udp", hosts=("127.0.0.1", "0.0.0.0")):
    """Nothing is bound to this port: a bind test (without SO_REUSEADDR, so a port in TIME_WAIT
    counts as taken) on each host address."""
    kind = socket.SOCK_DGRAM if proto == "udp" else socket.SOCK_STREAM
    for host in hosts:
        s = socket.socket(socket.AF_INET, kind)
        try:
            s.bind((host, port))
        except OSError:
            return False
        finally:
            s.close()
    return True


def os_free_port(proto="udp"):
    """A port the OS picks as free on 127.0.0.1 (then released)."""
    kind = socket.SOCK_DGRAM if proto == "udp" else socket.SOCK_STREAM
    s = socket.socket(socket.AF_INET, kind)
    try:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
    finally:
        s.close()


def pick_port(preferred, proto="udp", is_free=port_free, taken=()):
    """`preferred` when given and free (and not in `taken`), else a free port from the OS."""
    if preferred is not None and preferred not in taken and is_free(preferred, proto):
        return preferred
    for _ in range(50):
        p = os_free_port(proto)
        if p not in taken and is_free(p, proto):
            return p
    raise RuntimeError(f"no free {proto} port")


def try_lock(path):
    """An open file holding an exclusive non-blocking flock on `path` (created), or None when
    another process holds it. Keep the file object open for as long as the lock should last."""
    import fcntl
    f = open(path, "a+")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        return None
    return f


def instance_lock_path(kind, n):
    return os.path.join(tempfile.gettempdir(), f"visnav-sitl-{kind}-{n}.lock")


def choose_instance(ports_of, candidates, is_free=port_free, lock=None):
    """The first instance n of `candidates` whose ports (`ports_of(n)`: [(proto, port)]) are all
    free and, when `lock(n)` is given, whose lock it returns (a held lock object, else None).
    Returns (n, lock object or None) or (None, None)."""
    for n in candidates:
        if not all(is_free(port, proto) for proto, port in ports_of(n)):
            continue
        held = None
        if lock is not None:
            held = lock(n)
            if held is None:
                continue
        return n, held
    return None, None


def ardupilot_ports(n):
    """The ports ArduPilot SITL `-I n` binds: TCP 5760 + 10 n (SERIAL0) and the following
    serial ports (5762, 5763 and 5765-5768 + 10 n when not redirected), UDP 5501 + 10 n (RC
    input). Its simulator ports (9002/9003 + 10 n) are used by external simulators only."""
    base = 5760 + 10 * n
    return [("tcp", base + i) for i in (0, 2, 3, 5, 6, 7, 8)] + [("udp", 5501 + 10 * n)]


def px4_ports(n):
    """The local ports PX4 SITL `-i n` binds (v1.14 px4-rc.mavlink): UDP 18570 + n (GCS link),
    14580 + n (onboard/API link), 14280 + n (camera), 13030 + n (gimbal), 19450 + n (SIH
    display), and TCP 4560 + n, where jMAVSim listens for PX4's simulator_mavlink."""
    return [("udp", 18570 + n), ("udp", 14580 + n), ("udp", 14280 + n), ("udp", 13030 + n),
            ("udp", 19450 + n), ("tcp", 4560 + n)]


def px4_instance_running(n):
    """PX4 holds its per-instance lock file (/tmp/px4_lock-n; newer versions ~/.px4/...)."""
    import fcntl
    for d in ("/tmp", os.path.join(os.path.expanduser("~"), ".px4")):
        path = os.path.join(d, f"px4_lock-{n}")
        if not os.path.exists(path):
            continue
        try:
            with open(path, "r+") as f:
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    fcntl.flock(f.fileno(), fcntl.LOCK_UN)
                    fcntl.lockf(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    fcntl.lockf(f.fileno(), fcntl.LOCK_UN)
                except OSError:
                    return True
        except OSError:
            return True  # cannot even open it: assume another user's PX4
    return False


def px4_rc_mavlink_with_ports(text, gcs_port, link_port):
    """PX4's init.d-posix/px4-rc.mavlink (v1.14) with its GCS link sending to UDP `gcs_port`
    (`-o gcs_port` added to the GCS `mavlink start`, whose remote port is otherwise 14550 for every
    instance) and its onboard (API) link to `link_port` (udp_offboard_port_remote, set just before
    the first `mavlink start`). ValueError when the file does not look like that."""
    lines = text.split("\n")
    starts = [i for i, ln in enumerate(lines) if ln.lstrip().startswith("mavlink start")]
    gcs = [i for i in starts if "$udp_gcs_port_local" in lines[i]]
    if not starts or len(gcs) != 1 or " -o " in lines[gcs[0]] + " ":
        raise ValueError("no GCS `mavlink start -u $udp_gcs_port_local` line without -o")
    if not any("-o $udp_offboard_port_remote" in lines[i] for i in starts):
        raise ValueError("no onboard `mavlink start ... -o $udp_offboard_port_remote` line")
    lines[gcs[0]] = lines[gcs[0]].rstrip() + f" -o {gcs_port}"
    lines.insert(starts[0], f"udp_offboard_port_remote={link_port}  # sitl/px4/run.py")
    lines.insert(starts[0], "# sitl/px4/run.py: this run's ports (GCS link -o below).")
    return "\n".join(lines)


CONNECTION_RE = re.compile(r'^(\s*connection\s*=\s*"udpin:[^"]*:)(\d+)(")', re.M)


def set_connection_port(text, port):
    """visnav.toml text with the UDP port of its `connection = "udpin:HOST:PORT"` replaced."""
    new, n = CONNECTION_RE.subn(lambda m: f"{m.group(1)}{port}{m.group(3)}", text, count=1)
    if n != 1:
        raise ValueError('no connection = "udpin:HOST:PORT" line in the visnav configuration')
    return new


def connection_port(text):
    m = CONNECTION_RE.search(text)
    return int(m.group(2)) if m else None


def instance_arg(value):
    """argparse type of --instance: a number or "auto"."""
    if value == "auto":
        return None
    n = int(value)
    if n < 0:
        raise argparse.ArgumentTypeError("instance must be >= 0")
    return n


# ---- processes ------------------------------------------------------------------------------

def stop_processes(procs, timeout_s=15.0):
    """Stop the run's processes [(name, Popen started with start_new_session)]: visnav with SIGINT
    so it flushes its .tlog and fix log, the rest with SIGTERM, each process group SIGKILLed
    after `timeout_s`. Processes already ended are left alone, so a second call does nothing."""
    for name, p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT if name == "visnav" else signal.SIGTERM)
    for name, p in procs:
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def finish_run(procs, workdir, report, log):
    """Stop the run's processes (`stop_processes`, if still running), add visnav's last metrics
    line (WORKDIR/visnav.json) to the report, write WORKDIR/report.json and print it."""
    stop_processes(procs)
    vj = os.path.join(workdir, "visnav.json")
    if os.path.exists(vj):
        try:
            with open(vj) as f:
                lines = [ln for ln in f if ln.strip()]
            if lines:
                report["visnav"] = json.loads(lines[-1])
        except ValueError:
            pass
    path = os.path.join(workdir, "report.json")
    with open(path, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report, indent=1))
    log(f"report: {path}")


def add_visnav_args(ap):
    """The options both recipes give start_visnav: visual odometry on or off, and another map."""
    ap.add_argument("--vo", choices=["on", "off"], default=None,
                    help="visual odometry ([vo] enabled) on or off (default: the configuration's)")
    ap.add_argument("--map-ortho", default=None, metavar="GEOTIFF",
                    help="visnav's map orthophoto instead of the configuration's (e.g. one the "
                         "camera's ground cannot be matched on: sitl/featureless_map.py)")
    ap.add_argument("--map-tile-m", type=float, default=None, metavar="M",
                    help="build the configuration's map as a tiled map of squares of M metres "
                         "in the work folder (visnav map build --tile-m) and fly it paged "
                         "([map] file = the folder, memory_mb = --map-memory-mb)")
    ap.add_argument("--map-memory-mb", type=int, default=16, metavar="MB",
                    help="[map] memory_mb of the tiled map (--map-tile-m; default 16, the least)")


def tiled_map_config(text, map_dir, memory_mb):
    """TEXT (a configuration with absolute paths) with its `[map] ortho = [...]` line replaced by
    `file = MAP_DIR` and `memory_mb = MEMORY_MB`, and the orthophoto and the constant ground
    height that line and `ground_height_amsl_m` named (what the tiled map is built from). Exits
    naming what is missing."""
    m = re.search(r"(?m)^ortho = \[[ \t]*(\"[^\"]+\")[ \t]*\][ \t]*$", text)
    g = re.search(r"(?m)^ground_height_amsl_m = ([-0-9.eE+]+)[ \t]*$", text)
    if m is None or g is None:
        sys.exit("--map-tile-m: the configuration's [map] needs one `ortho = [\"...\"]` line and "
                 "`ground_height_amsl_m = ...`")
    ortho = json.loads(m.group(1))
    file_lines = f"file = {json.dumps(os.path.abspath(map_dir))}\nmemory_mb = {int(memory_mb)}"
    return text[:m.start()] + file_lines + text[m.end():], ortho, float(g.group(1))


def build_tiled_map(exe, ortho, ground_height_m, tile_m, map_dir, log):
    """`visnav map build` of ORTHO (flat at GROUND_HEIGHT_M) as a tiled map of TILE_M squares
    in MAP_DIR (its output beside it, map_build.log); exits when the build fails."""
    cmd = [exe, "map", "build", "--ortho", ortho, "--ground-height", repr(ground_height_m),
           "--tile-m", repr(tile_m), "--out", map_dir]
    log("visnav: " + " ".join(cmd))
    with open(map_dir + "_build.log", "w") as out:
        rc = subprocess.call(cmd, stdout=out, stderr=subprocess.STDOUT)
    if rc != 0:
        sys.exit(f"the tiled map's build failed (exit {rc}): see {map_dir}_build.log")


def visnav_config_text(text, repo, link_port=None, vo=None, map_ortho=None):
    """The configuration sitl-run gets (start_visnav): absolute map paths, the tlog, the fix log
    (fixes.jsonl), the VO log (vo.jsonl), the link port, and the --vo / --map-ortho overrides."""
    text = text.replace('"../maps/', '"' + os.path.join(repo, "sitl", "maps") + "/")
    text = text.replace('"../../../../shared/', '"' + os.path.join(os.path.dirname(repo), "shared") + "/")
    text = text.replace("[link]\n", '[link]\ntlog = "visnav.tlog"\n', 1)
    logs = 'fix_log = "fixes.jsonl"\nvo_log = "vo.jsonl"\n'
    if "\n[daemon]\n" in text:
        text = text.replace("\n[daemon]\n", "\n[daemon]\n" + logs, 1)
    else:
        text += "\n[daemon]\n" + logs
    if link_port is not None:
        text = set_connection_port(text, link_port)
    if map_ortho is not None:
        path = os.path.abspath(map_ortho)
        text, n = re.subn(r"(?m)^ortho = .*$", lambda _m: f"ortho = [{json.dumps(path)}]", text, 1)
        if n != 1:
            sys.exit("--map-ortho: the configuration has no `ortho = ...` line to replace")
    if vo is not None:
        text = set_vo_enabled(text, vo == "on")
    return text


def set_vo_enabled(text, on):
    """TEXT with `[vo] enabled` set to ON: the section's own `enabled` line replaced (a second one
    would be a duplicate key), else one added at the top of the section, else the section added."""
    line = f"enabled = {'true' if on else 'false'}"
    m = re.search(r"(?m)^\[vo\][ \t]*\n", text)
    if m is None:
        return text + "\n[vo]\n" + line + "\n"
    end = re.search(r"(?m)^\[", text[m.end():])
    body_end = m.end() + end.start() if end else len(text)
    body = text[m.end():body_end]
    body, n = re.subn(r"(?m)^enabled[ \t]*=.*$", line, body, 1)
    if n == 0:
        body = line + "\n" + body
    return text[:m.end()] + body + text[body_end:]


def start_visnav(exe, config_src, workdir, kind, truth_port, camera_hz, repo, log,
                 link_port=None, vo=None, map_ortho=None, camera_world=None,
                 map_tile_m=None, map_memory_mb=16):
    """Start `visnav sitl-run` in WORKDIR (stdout: visnav.json, the metrics lines; stderr:
    visnav.log) on a copy of CONFIG_SRC with absolute map paths, a .tlog of all link traffic
    (visnav.tlog), the vision fix log (fixes.jsonl), the visual odometry log (vo.jsonl) and the
    camera's true pose per frame (frames_truth.jsonl: `sitl/vo_check.py WORKDIR` scores the VO),
    with `link_port` (when given) as the UDP port of its autopilot connection and the --vo /
    --map-ortho overrides (visnav_config_text):
    `visnav replay --config visnav.toml --tlog visnav.tlog --fixes fixes.jsonl` in the work
    folder then replays the flight through the filter offline. The camera renders the 2014 image
    (the map is the 2009 one), or with `camera_world` (a scenario file) that scenario's camera
    world (`sitl-run --scenario`: its orthophoto on its surface model, the map from another
    degraded copy). With `map_tile_m` the configuration's map is built as a tiled map in
    WORKDIR/map and flown paged within `map_memory_mb` (tiled_map_config)."""
    if exe is None:
        for c in ("target/release/visnav", "target/debug/visnav"):
            if os.path.exists(os.path.join(repo, c)):
                exe = os.path.join(repo, c)
                break
    if exe is None:
        sys.exit("no visnav binary: cargo build --release, or give --visnav")
    exe = os.path.abspath(exe)
    with open(config_src) as f:
        text = f.read()
    text = visnav_config_text(text, repo, link_port, vo, map_ortho)
    if map_tile_m is not None:
        if camera_world is not None:
            sys.exit("--map-tile-m: only with the NAIP scenario (its map is one orthophoto, flat)")
        map_dir = os.path.join(workdir, "map")
        text, ortho, ground_m = tiled_map_config(text, map_dir, map_memory_mb)
        build_tiled_map(exe, ortho, ground_m, map_tile_m, map_dir, log)
    config = os.path.join(workdir, "visnav.toml")
    with open(config, "w") as f:
        f.write(text)
    world = (["--scenario", os.path.abspath(camera_world)] if camera_world else
             ["--ortho", os.path.join(repo, "sitl", "maps", "naip_nd_2014.tif")])
    cmd = [exe, "sitl-run", "--kind", kind, "--config", config,
           "--truth", f"udpin:127.0.0.1:{truth_port}"] + world + [
           "--rate-hz", str(camera_hz), "--truth-log", "frames_truth.jsonl"]
    log("visnav: " + " ".join(cmd))
    return subprocess.Popen(cmd, cwd=workdir,
                            stdout=open(os.path.join(workdir, "visnav.json"), "w"),
                            stderr=open(os.path.join(workdir, "visnav.log"), "w"),
                            start_new_session=True)


def ulog_topic(ulog, name):
    """The first instance of a pyulog ULog's topic `name` (its data dict); exits naming the topic
    when the log does not have it."""
    for d in ulog.data_list:
        if d.name == name and d.multi_id == 0:
            return d.data
    sys.exit(f"topic {name} not in the log")
