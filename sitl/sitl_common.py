"""What the real-SITL scripts (sitl/ardupilot/run.py, sitl/px4/run.py, sitl/px4/ulog_error.py)
share: the home over the bundled map, metres per degree, the error statistics, and the end of a
run (stop the processes, attach visnav's last metrics line, write report.json).

Standard library only, so that ulog_error.py (pyulog) and the run scripts (pymavlink) can both
import it: `sys.path.insert(0, <this folder>)` then `import sitl_common`.
"""

import json
import math
import os
import signal
import statistics
import subprocess
import sys

# Centre of sitl/maps/naip_nd_2009.tif (EPSG:26914 x 488235, y 5207437), ground ~580 m AMSL.
HOME_LAT, HOME_LON, HOME_ALT_M = 47.0203485, -99.1548094, 580.0


def metres_per_deg(lat_deg):
    """(metres per degree of latitude, of longitude) on WGS84 at this latitude (series to 4 phi)."""
    p = math.radians(lat_deg)
    return (111132.954 - 559.822 * math.cos(2 * p) + 1.175 * math.cos(4 * p),
            111412.84 * math.cos(p) - 93.5 * math.cos(3 * p))


def stats(v):
    """n, median, p90 (nearest rank) and max of a list of errors in metres, or None when empty."""
    if not v:
        return None
    s = sorted(v)
    p90 = s[min(len(s) - 1, int(math.ceil(0.9 * len(s))) - 1)]
    return {"n": len(s), "median_m": round(statistics.median(s), 2), "p90_m": round(p90, 2),
            "max_m": round(s[-1], 2)}


def finish_run(procs, workdir, report, log):
    """Stop the run's processes (visnav with SIGINT so it flushes its .tlog and fix log, the rest
    with SIGTERM, SIGKILL after 15 s), add visnav's last metrics line (WORKDIR/visnav.json) to the
    report, write WORKDIR/report.json and print it."""
    for name, p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGINT if name == "visnav" else signal.SIGTERM)
    for name, p in procs:
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
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


def start_visnav(exe, config_src, workdir, kind, truth_port, camera_hz, repo, log):
    """Start `visnav sitl-run` in WORKDIR (stdout: visnav.json, the metrics lines; stderr:
    visnav.log) on a copy of CONFIG_SRC with absolute map paths, a .tlog of all link traffic
    (visnav.tlog) and the vision fix log (fixes.jsonl):
    `visnav replay --config visnav.toml --tlog visnav.tlog --fixes fixes.jsonl` in the work
    folder then replays the flight through the filter offline. The camera renders the 2014 image
    (the map is the 2009 one)."""
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
    text = text.replace('"../maps/', '"' + os.path.join(repo, "sitl", "maps") + "/")
    text = text.replace("[link]\n", '[link]\ntlog = "visnav.tlog"\n', 1)
    if "\n[daemon]\n" in text:
        text = text.replace("\n[daemon]\n", '\n[daemon]\nfix_log = "fixes.jsonl"\n', 1)
    else:
        text += '\n[daemon]\nfix_log = "fixes.jsonl"\n'
    config = os.path.join(workdir, "visnav.toml")
    with open(config, "w") as f:
        f.write(text)
    cmd = [exe, "sitl-run", "--kind", kind, "--config", config,
           "--truth", f"udpin:127.0.0.1:{truth_port}",
           "--ortho", os.path.join(repo, "sitl", "maps", "naip_nd_2014.tif"),
           "--rate-hz", str(camera_hz)]
    log("visnav: " + " ".join(cmd))
    return subprocess.Popen(cmd, cwd=workdir,
                            stdout=open(os.path.join(workdir, "visnav.json"), "w"),
                            stderr=open(os.path.join(workdir, "visnav.log"), "w"),
                            start_new_session=True)


class ErrorScore:
    """The autopilot's position (GLOBAL_POSITION_INT) against the simulator's truth: horizontal
    and vertical error per phase ("gps_on", "gps_off"; only above 5 m, so the ground before
    take-off does not count), every sample kept for samples.json
    ([t_s, phase, agl_m, north_m, east_m, up_m]), a log line every 100 samples."""

    def __init__(self, estimator, log):
        self.estimator = estimator  # "EKF3", "EKF2": for the log line
        self.log = log
        self.errs = {"gps_on": ([], []), "gps_off": ([], [])}
        self.samples = []

    def add(self, t_s, gps_off, lat_deg, lon_deg, alt_m, lat_t, lon_t, alt_t):
        m_lat, m_lon = metres_per_deg(lat_t)
        dn = (lat_deg - lat_t) * m_lat
        de = (lon_deg - lon_t) * m_lon
        eh = math.hypot(dn, de)
        ev = alt_m - alt_t
        agl = alt_t - HOME_ALT_M
        phase = "gps_off" if gps_off else "gps_on"
        if agl > 5:
            self.errs[phase][0].append(eh)
            self.errs[phase][1].append(abs(ev))
        self.samples.append([round(t_s, 2), phase, round(agl, 1), round(dn, 2), round(de, 2),
                             round(ev, 2)])
        if len(self.samples) % 100 == 0:
            self.log(f"t {t_s:.0f} s {phase} agl {agl:.0f} m: {self.estimator} error "
                     f"horizontal {eh:.1f} m vertical {ev:+.1f} m")

    def summary(self):
        return {ph: {"horizontal": stats(h), "vertical": stats(v)}
                for ph, (h, v) in self.errs.items()}

    def save(self, workdir):
        with open(os.path.join(workdir, "samples.json"), "w") as f:
            json.dump(self.samples, f)


def ulog_topic(ulog, name):
    """The first instance of a pyulog ULog's topic `name` (its data dict); exits naming the topic
    when the log does not have it."""
    for d in ulog.data_list:
        if d.name == name and d.multi_id == 0:
            return d.data
    sys.exit(f"topic {name} not in the log")
