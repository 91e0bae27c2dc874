#!/usr/bin/env python3
"""visnav against a real ArduPilot SITL (ArduCopter): fly an AUTO mission over the bundled NAIP
map, switch the simulated GPS off after take-off, score EKF3's position against the simulator's
truth and give a verdict.

    python3 sitl/ardupilot/run.py --arducopter /path/to/ardupilot/build/sitl/bin/arducopter
    python3 sitl/ardupilot/run.py --sim-vehicle /path/to/ardupilot/Tools/autotest/sim_vehicle.py
    python3 sitl/ardupilot/run.py --arducopter ... --no-visnav      # the GPS-off control run
    python3 sitl/ardupilot/run.py --arducopter ... --scenario drone # 100 m over Autzen
    python3 sitl/ardupilot/run.py --arducopter ... --denial source-set # EKF source sets

`--denial source-set` takes the GPS away as on a real vehicle (docs/real-sitl.md, "EKF source
sets"; config/ardupilot-copter-source-sets.parm): visnav sends VISION_POSITION_ESTIMATE
(ExternalNav, the work folder's visnav.toml gets `modes = ["vision_position_estimate"]`,
`set_origin = false`), visnav-source-set.parm is loaded last (the simulated receiver GPS1 and
EKF source set 1, visnav source set 2). At --gps-off-wp the script sends
MAV_CMD_SET_EKF_SOURCE_SET 2 and MAV_CMD_DO_AUX_FUNCTION 65 (GPS Disable) high: the simulated
receiver stays on, but every GPS instance reports no fix, so neither EKF3 nor visnav uses it. At
--restore-wp (default: the item before the last) it sends GPS Disable low, waits for the 3D fix
and sends MAV_CMD_SET_EKF_SOURCE_SET 1; the last leg flies on the GPS again. The denied leg is
scored as "gps_off" (the not-aiding time and the sample gap over it only), the leg after as
"gps_back"; report.json has "denial", "switches" (each command with its COMMAND_ACK result) and
"gps_back_after_s", and the verdict fails when a switch was not accepted or set 1 was never
restored. visnav's injected position is scored from its own visnav.tlog (ArduPilot echoes no
VISION_POSITION_ESTIMATE). `--denial source-set-gps-on` switches the source set only: visnav
keeps aiding itself with the GPS (the switch's mechanics, not GPS-denied navigation).

`--scenario drone` is the drone recipe (docs/real-sitl.md, "The drone recipe"): home at Autzen
(../shared/data/autzen), sitl/ardupilot/drone/ (mission, parameters after
visnav-gps-input.parm, configuration), the camera of `visnav sitl-run --scenario
sitl/scenarios/drone_autzen.toml`, bounds p90 1.5 m and max 4 m. What follows describes the
default (`naip`) recipe; the drone one differs in those.

It does not build ArduPilot (see docs/real-sitl.md). Needs pymavlink (`bash
scripts/interop/setup_venv.sh` prints a venv python that has it) and a built visnav
(`cargo build --release`, or give --visnav).

What runs (all on loopback; N = the SITL instance, --instance, by default the first free one):
* SITL `-I N`, home at the centre of sitl/maps (47.0203485 N, 99.1548094 W, 580 m AMSL),
  parameters Tools/autotest/default_params/copter.parm + visnav-gps-input.parm (or
  control-no-visnav.parm); SERIAL0 tcp 5760 + 10 N = this script, SERIAL1 udpclient VISNAV_PORT =
  visnav's autopilot link, SERIAL2 udpclient TRUTH_PORT = visnav's truth connection (SIMSTATE +
  SIM_STATE for the simulated camera). `-I N` moves every SITL port by 10 N (TCP 5760-5768, UDP
  5501 RC input); the instance is taken only when all of them are free (bind test) and no other
  run.py holds its lock (TMPDIR/visnav-sitl-ardupilot-N.lock), so runs can share a host.
  VISNAV_PORT / TRUTH_PORT (--visnav-port / --truth-port): 14551 / 14552 on instance 0 when free,
  else free UDP ports picked by the OS; the work folder's copy of visnav.toml gets VISNAV_PORT.
* `visnav sitl-run --config WORKDIR/visnav.toml --truth udpin:127.0.0.1:TRUTH_PORT --ortho
  sitl/maps/naip_nd_2014.tif` (the camera sees the 2014 image; the map is the 2009 one).
* This script: waits for EKF3 to have a position (and, with visnav, for visnav's GPS_INPUT to be
  a 3D fix), uploads mission.waypoints, sets AUTO and arms (AUTO_OPTIONS = 3 takes off without
  throttle), sets SIM_GPS_DISABLE = 1 (4.6+: SIM_GPS1_ENABLE = 0) once the copter reaches the
  first corner of the loop at 1800 m (--gps-off-wp; or --gps-off-alt metres up), and stops at the
  last waypoint (or --timeout, --after-gps-off, or when the copter lands or disarms).

Measured (sitl_common.py):
* every GLOBAL_POSITION_INT (EKF3's output, 10 Hz) against the truth of the same instant
  (SIMSTATE latitude/longitude degE7 and SIM_STATE altitude, 50 Hz, propagated over the arrival
  gap with the true velocity): horizontal and vertical error, median / p90 / max, while the GPS
  is on (airborne), after it is off (all airborne samples), and after it is off split by whether
  EKF3 was aiding (EKF_STATUS_REPORT flags: EKF_POS_HORIZ_ABS set, not EKF_CONST_POS_MODE /
  EKF_UNINITIALIZED). Once EKF3 stops aiding it holds its last position: those samples are
  reported as "gps_off_not_aiding", with the not-aiding time (first loss after GPS off, total).
* visnav runs: the injected position as ArduPilot echoes it, GPS_RAW_INT of GPS instance 0 (=
  GPS1 = visnav's GPS_INPUT, visnav-gps-input.parm), against the truth at the fix's time
  (time_usec: ArduPilot's fix time, mapped onto this computer's clock through the autopilot's
  time_boot_ms): error, h_acc (MAVLink 2 extension, 1 sigma) and error / h_acc.
* STATUSTEXT after arming (failsafes: "EKF Failsafe", "EKF variance", "GPS Glitch", any
  "failsafe") and the flight modes after arming.
Written to WORKDIR/report.json (with "verdict") and printed; WORKDIR/samples.json (every EKF3
sample with its aiding flag), WORKDIR/injected.json (every scored GPS_RAW_INT).

Verdict (sitl_common.verdict; bounds --max-p90-m 25, --max-error-m 50, --max-ratio 3,
--max-not-aiding-s 0, --max-sample-gap-s 2): pass only when the last waypoint was reached in AUTO
(no other mode after arming), no failsafe STATUSTEXT came, the GPS went off, EKF3 aided all
through the GPS-off period, its horizontal error over every GPS-off airborne sample has p90 and
max within the bounds, and (visnav runs) every injected position was within 3 x its h_acc of the
truth. With --after-gps-off the mission is not completed: such a run always fails.

Exit code: 0 = a visnav run passed; 1 = its verdict failed. The control run (--no-visnav) gets the
same verdict, printed as "control: ..." (it is expected to fail: without aiding EKF3 stops
aiding and the EKF failsafe lands the copter); it exits 0 when the control run itself completed
(the GPS went off and the flight ended on its own: last waypoint, --after-gps-off, landed or
--timeout), 1 when it did not (stopped by a signal, never reached the GPS-off point). 2 = the run
could not be made (SITL or visnav did not start, not ready, could not arm, an error in flight).
"""


import argparse
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import traceback

# MAVLink 2 from the start: GPS_RAW_INT's h_acc is a MAVLink 2 extension field.
os.environ.setdefault("MAVLINK20", "1")
try:
    from pymavlink import mavutil
except ImportError:
    print("run.py needs pymavlink: python3 -m pip install pymavlink "
          "(or use the venv python printed by scripts/interop/setup_venv.sh)", file=sys.stderr)
    sys.exit(2)

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.dirname(HERE))
import sitl_common  # noqa: E402
from sitl_common import (HOME_ALT_M, HOME_LAT, HOME_LON, BootClock, ErrorScore,  # noqa: E402
                         IntegrityScore, TruthHistory, ekf_aiding, finish_run, metres_per_deg)
HOME_HDG = 0  # SITL start heading, deg
# The recipes (--scenario): home (lat, lon, m AMSL), mission, parameters loaded after
# visnav-gps-input.parm, visnav's configuration, the camera world (None: the 2014 NAIP image on a
# flat ground; else a scenario file whose [closed_loop] sitl-run renders), the mission item whose
# arrival switches the GPS off, the camera rate and the verdict's error bounds (p90, max; m).
SCENARIOS = {
    "naip": {
        "home": (HOME_LAT, HOME_LON, HOME_ALT_M),
        "mission": os.path.join(HERE, "mission.waypoints"),
        "parm": None,
        "config": os.path.join(HERE, "visnav.toml"),
        "world": None,
        "gps_off_wp": 2,
        "camera_hz": 2.0,
        "bounds": (sitl_common.MAX_P90_M, sitl_common.MAX_ERROR_M),
    },
    # A multirotor 100 m above Autzen Stadium (../shared/data/autzen: the 0.3 m orthophoto on the
    # 1 m lidar surface model; not shipped): home on the surface model at x 494250, y 4877900
    # (EPSG:32610), the camera of sitl/scenarios/drone_autzen.toml (the map from one degraded copy,
    # the camera rendering another), the drone bounds: EKF3 GPS-off p90 1.5 m, max 4 m.
    "drone": {
        "home": (44.0542428, -123.0717843, 132.0),
        "mission": os.path.join(HERE, "drone", "mission.waypoints"),
        "parm": os.path.join(HERE, "drone", "drone.parm"),
        "config": os.path.join(HERE, "drone", "visnav.toml"),
        "world": os.path.join(REPO, "sitl", "scenarios", "drone_autzen.toml"),
        "gps_off_wp": 2,
        "camera_hz": 2.0,
        "bounds": (1.5, 4.0),
    },
}
# Instance 0's visnav link and truth ports (other instances: free ports picked by the OS).
VISNAV_PORT, TRUTH_PORT = 14551, 14552
MAX_INSTANCE = 31
STOP = None  # set by SIGTERM/SIGINT/SIGHUP during the flight
# How the GPS is taken away (--denial): the simulated receiver switched off, or the EKF source set
# switched to visnav (ExternalNav) by MAV_CMD_SET_EKF_SOURCE_SET with the receiver left on, the
# GPS withheld from autopilot and visnav by the "GPS Disable" auxiliary function (source-set) or
# not (source-set-gps-on: visnav keeps aiding itself with the GPS).
DENIALS = ("gps-disable", "source-set", "source-set-gps-on")
MAV_CMD_SET_EKF_SOURCE_SET = 42007
MAV_CMD_DO_AUX_FUNCTION = 218
AUX_GPS_DISABLE = 65  # RCx_OPTION 65: GPS Disable (high: every GPS instance reports no fix)


def log(msg):
    print(f"[run.py {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def find_copter_parm(path):
    """Tools/autotest/default_params/copter.parm of the ArduPilot tree that holds `path`."""
    d = os.path.dirname(os.path.abspath(path))
    for _ in range(6):
        c = os.path.join(d, "Tools", "autotest", "default_params", "copter.parm")
        if os.path.exists(c):
            return c
        d = os.path.dirname(d)
    return None


def choose_ports(args):
    """SITL instance N (--instance, or the first whose ports are free and whose lock no other
    run.py holds), its SERIAL0 TCP port and visnav's link / truth UDP ports. Returns (instance,
    control port, visnav port, truth port, held lock file)."""
    lock = (lambda n: sitl_common.try_lock(sitl_common.instance_lock_path("ardupilot", n)))
    if args.instance is None:
        n, held = sitl_common.choose_instance(sitl_common.ardupilot_ports,
                                              range(MAX_INSTANCE + 1), lock=lock)
        if n is None:
            sys.exit(f"no free ArduPilot SITL instance in 0-{MAX_INSTANCE}")
    else:
        n = args.instance
        busy = [f"{proto} {port}" for proto, port in sitl_common.ardupilot_ports(n)
                if not sitl_common.port_free(port, proto)]
        if busy:
            sys.exit(f"instance {n}: ports in use ({', '.join(busy)}); another SITL? "
                     f"(--instance auto picks a free one)")
        held = lock(n)
        if held is None:
            sys.exit(f"instance {n} is used by another run.py "
                     f"({sitl_common.instance_lock_path('ardupilot', n)})")
    ports = []
    for given, default in ((args.visnav_port, VISNAV_PORT), (args.truth_port, TRUTH_PORT)):
        if given is not None:
            if given in ports or not sitl_common.port_free(given, "udp"):
                sys.exit(f"UDP port {given} is in use")
            ports.append(given)
        else:
            ports.append(sitl_common.pick_port(default if n == 0 else None, "udp",
                                               taken=set(ports)))
    return n, 5760 + 10 * n, ports[0], ports[1], held


def start_sitl(args, workdir, instance, visnav_port, truth_port):
    sc = SCENARIOS[args.scenario]
    parms = [os.path.join(HERE, "control-no-visnav.parm" if args.no_visnav else "visnav-gps-input.parm")]
    serials = [f"--serial1=udpclient:127.0.0.1:{visnav_port}",
               f"--serial2=udpclient:127.0.0.1:{truth_port}"]
    lat, lon, alt = sc["home"]
    home = f"{lat},{lon},{alt},{HOME_HDG}"
    own = [sc["parm"]] if sc["parm"] else []
    if args.arducopter:
        base = args.defaults or find_copter_parm(args.arducopter)
        if base is None:
            sys.exit("cannot find Tools/autotest/default_params/copter.parm beside the binary: give --defaults")
        # The scenario's parameters after visnav-gps-input.parm, the control's last (same flight,
        # GPS types changed).
        files = [base, os.path.join(HERE, "visnav-gps-input.parm")] + own + (parms if args.no_visnav else [])
        files += source_set_parm(args)
        cmd = [args.arducopter, "-S", "--model", "+", "--speedup", "1", "--home", home,
               f"-I{instance}", "--wipe", "--defaults", ",".join(files)] + serials
    else:
        files = [os.path.join(HERE, "visnav-gps-input.parm")] + own + (parms if args.no_visnav else [])
        files += source_set_parm(args)
        cmd = [sys.executable, args.sim_vehicle, "-v", "ArduCopter", "-f", "quad", "--no-rebuild",
               "--no-mavproxy", "-I", str(instance), "-w", "-l", home, "-A", " ".join(serials)]
        for f in files:
            cmd += ["--add-param-file", f]
    log("SITL: " + " ".join(cmd))
    out = open(os.path.join(workdir, "sitl.log"), "w")
    return subprocess.Popen(cmd, cwd=workdir, stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


def source_set_parm(args):
    """The parameters of the source-set denials (loaded last), none for gps-disable."""
    return [] if args.denial == "gps-disable" else [os.path.join(HERE, "visnav-source-set.parm")]


def external_nav_config(text):
    """A visnav configuration with `[output] modes` replaced by VISION_POSITION_ESTIMATE and the
    EKF origin taken from the autopilot (the GPS sets it; visnav must not set its own)."""
    m = re.search(r"(?m)^\[output\][ \t]*\n", text)
    if m is None:
        sys.exit("the configuration has no [output] section")
    end = re.search(r"(?m)^\[", text[m.end():])
    body_end = m.end() + end.start() if end else len(text)
    body = text[m.end():body_end]
    body = re.sub(r"(?m)^(modes|set_origin)[ \t]*=.*\n", "", body)
    body = 'modes = ["vision_position_estimate"]\nset_origin = false\n' + body
    return text[:m.end()] + body + text[body_end:]


def start_visnav(args, workdir, visnav_port, truth_port):
    sc = SCENARIOS[args.scenario]
    config = sc["config"]
    if args.denial != "gps-disable":
        # Relative map paths are resolved by text (sitl_common.visnav_config_text), so the
        # derived file may live in the work folder.
        with open(config) as f:
            text = external_nav_config(f.read())
        config = os.path.join(workdir, "visnav-external-nav.toml")
        with open(config, "w") as f:
            f.write(text)
    return sitl_common.start_visnav(args.visnav, config, workdir,
                                    "ardupilot", truth_port, args.camera_hz, REPO, log,
                                    link_port=visnav_port, vo=args.vo, map_ortho=args.map_ortho,
                                    camera_world=sc["world"], map_tile_m=args.map_tile_m,
                                    map_memory_mb=args.map_memory_mb)


def is_autopilot(m, hb):
    """The autopilot's own HEARTBEAT (ArduPilot forwards visnav's, same system id, to this link)."""
    return (hb.get_srcSystem() == m.target_system and hb.get_srcComponent() == 1
            and hb.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID)


def request_rates(m, rates):
    for msg_id, hz in rates.items():
        m.mav.command_long_send(m.target_system, m.target_component,
                                mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                msg_id, 1e6 / hz, 0, 0, 0, 0, 0)


def set_param(m, name, value, timeout=5.0, on=None):
    """PARAM_SET and wait for the PARAM_VALUE echo; False when the autopilot has no such name.
    Every other message meanwhile goes to `on(msg)` (when given)."""
    end = time.time() + timeout
    while time.time() < end:
        m.mav.param_set_send(m.target_system, m.target_component, name.encode(), float(value),
                             mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
        t_ask = time.time() + 1.0
        while time.time() < t_ask:
            r = m.recv_match(blocking=True, timeout=max(0.01, t_ask - time.time()))
            if r is None:
                continue
            if r.get_type() == "PARAM_VALUE" and r.param_id == name:
                return abs(r.param_value - value) < 1e-3
            if on is not None:
                on(r)
    return False


def upload_mission(m, path):
    items = []
    with open(path) as f:
        if not f.readline().startswith("QGC WPL 110"):
            sys.exit(f"{path}: not a QGC WPL 110 file")
        for line in f:
            v = line.strip().split("\t")
            if len(v) != 12:
                continue
            items.append(v)
    m.mav.mission_count_send(m.target_system, m.target_component, len(items),
                             mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
    sent = set()
    end = time.time() + 30
    while time.time() < end:
        r = m.recv_match(type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"],
                         blocking=True, timeout=2.0)
        if r is None:
            continue
        if r.get_type() == "MISSION_ACK":
            if r.type == mavutil.mavlink.MAV_MISSION_ACCEPTED and len(sent) == len(items):
                log(f"mission: {len(items)} items uploaded")
                return len(items)
            sys.exit(f"mission upload refused: MISSION_ACK type {r.type}")
        v = items[r.seq]
        m.mav.mission_item_int_send(m.target_system, m.target_component, int(v[0]), int(v[2]),
                                    int(v[3]), 0, int(v[11]), float(v[4]), float(v[5]),
                                    float(v[6]), float(v[7]), int(round(float(v[8]) * 1e7)),
                                    int(round(float(v[9]) * 1e7)), float(v[10]),
                                    mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
        sent.add(r.seq)
    sys.exit("mission upload timed out")


def gps_off(m, on=None):
    """Switch SITL's simulated GPS 1 off (4.5: SIM_GPS_DISABLE, 4.6+: SIM_GPS1_ENABLE); returns
    the time the autopilot echoed the change."""
    if not (set_param(m, "SIM_GPS_DISABLE", 1, on=on) or set_param(m, "SIM_GPS1_ENABLE", 0, on=on)):
        sys.exit("cannot switch the simulated GPS off (SIM_GPS_DISABLE / SIM_GPS1_ENABLE)")
    log("simulated GPS OFF")
    return time.time()


def command(m, cmd, params, on=None, tries=3, wait_s=1.5):
    """COMMAND_LONG `cmd` with up to 7 params; the COMMAND_ACK result (MAV_RESULT) of that command,
    or None when none came after `tries` sends. Every other message meanwhile goes to `on(msg)`."""
    p = list(params) + [0] * (7 - len(params))
    for attempt in range(tries):
        m.mav.command_long_send(m.target_system, m.target_component, cmd, attempt, *p)
        end = time.time() + wait_s
        while time.time() < end:
            r = m.recv_match(blocking=True, timeout=max(0.01, end - time.time()))
            if r is None:
                continue
            if r.get_type() == "COMMAND_ACK" and r.command == cmd:
                return int(r.result)
            if on is not None:
                on(r)
    return None


def result_name(result):
    if result is None:
        return "no COMMAND_ACK"
    e = mavutil.mavlink.enums["MAV_RESULT"].get(result)
    return e.name if e is not None else str(result)


class Switches:
    """The source-set denial's commands and their COMMAND_ACK results, for the report."""

    def __init__(self):
        self.done = []  # {"t_s", "command", "param", "result"}

    def send(self, m, t_fly, what, cmd, params, on):
        result = command(m, cmd, params, on=on)
        self.done.append({"t_s": round(time.time() - t_fly, 1), "command": what,
                          "params": list(params), "result": result_name(result)})
        log(f"{what} {list(params)}: {result_name(result)}")
        return result == mavutil.mavlink.MAV_RESULT_ACCEPTED

    def summary(self):
        return {"commands": self.done,
                "acked": sum(1 for d in self.done if d["result"] == "MAV_RESULT_ACCEPTED"),
                "sent": len(self.done)}


class SourceSetScore(ErrorScore):
    """ErrorScore whose GPS-off period ends when the GPS is given back (`gps_back`): the samples
    after it form the phase "gps_back", and the not-aiding time and the sample gap are measured
    over the denied leg only."""

    PHASES = ErrorScore.PHASES + ("gps_back",)

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.t_back = None

    def gps_back(self, t_s):
        self.t_back = t_s

    def add(self, t_s, gps_off, lat_deg, lon_deg, alt_m, lat_t, lon_t, alt_t):
        if self.t_back is None or t_s < self.t_back:
            return super().add(t_s, gps_off, lat_deg, lon_deg, alt_m, lat_t, lon_t, alt_t)
        dn, de = sitl_common.north_east(lat_deg, lon_deg, lat_t, lon_t)
        eh, ev = math.hypot(dn, de), alt_m - alt_t
        agl = alt_t - self.home_alt_m
        if agl > sitl_common.AIRBORNE_M:
            self.errs["gps_back"][0].append(eh)
            self.errs["gps_back"][1].append(abs(ev))
        self.samples.append([round(t_s, 2), "gps_back", round(agl, 1), round(dn, 2),
                             round(de, 2), round(ev, 2), self.aiding.aiding_at(t_s)])

    def summary(self, t_end=None):
        back = self.errs["gps_back"]
        if t_end is not None and self.t_back is not None:
            t_end = min(t_end, self.t_back)
        out = super().summary(t_end)
        out["gps_back"] = {"horizontal": sitl_common.stats(back[0]),
                           "vertical": sitl_common.stats(back[1])}
        return out


def external_nav_integrity(workdir, history, t_fly, t_off, t_back, integ):
    """Score every VISION_POSITION_ESTIMATE visnav sent (its visnav.tlog; ArduPilot echoes none)
    against the truth at the estimate's validity time: x/y about the autopilot's EKF origin
    (GPS_GLOBAL_ORIGIN in the same tlog), read back with ArduPilot's own projection, h_acc = sqrt of the larger eigenvalue of the horizontal
    covariance (as GPS_INPUT's horiz_accuracy). The validity time is in visnav's monotonic clock:
    mapped onto this computer's clock by the smallest (tlog send time - validity time), i.e. the
    freshest estimate's age is taken as zero."""
    path = os.path.join(workdir, "visnav.tlog")
    if not os.path.exists(path):
        integ.skip("no_tlog")
        return
    tl = mavutil.mavlink_connection(path, dialect="ardupilotmega")
    origin, sent = None, []
    while True:
        r = tl.recv_match(type=["VISION_POSITION_ESTIMATE", "GPS_GLOBAL_ORIGIN"])
        if r is None:
            break
        if r.get_type() == "GPS_GLOBAL_ORIGIN":
            origin = (r.latitude * 1e-7, r.longitude * 1e-7)
        elif r.get_srcComponent() != 1 and origin is not None:
            c = r.covariance
            a, b, d = c[0], c[1], c[6]
            lam = 0.5 * (a + d) + math.sqrt(max(0.0, 0.25 * (a - d) ** 2 + b * b))
            sent.append((r._timestamp, r.usec * 1e-6, r.x, r.y, math.sqrt(max(lam, 0.0)), origin))
    if not sent:
        integ.skip("no_vision_position_estimate")
        return
    offset = min(ts - tv for ts, tv, *_ in sent)
    for _ts, tv, x, y, h_acc, (lat0, lon0) in sent:
        t = tv + offset
        tr = history.at(t)
        if tr is None:
            integ.skip("no_truth")
            continue
        lat, lon = sitl_common.ardupilot_from_ned(lat0, lon0, x, y)
        phase = ("gps_on" if t_off is None or t < t_off else
                 "gps_off" if t_back is None or t < t_back else "gps_back")
        integ.add(t - t_fly, phase, lat, lon, h_acc, tr[0], tr[1])


class Truth:
    """Latest SIMSTATE (lat/lng degE7) and SIM_STATE (alt, NED velocity) with arrival times."""

    def __init__(self):
        self.pos = None  # (t_arrival, lat_deg, lon_deg)
        self.alt = None  # (t_arrival, alt_m, vn, ve, vd)

    def on(self, msg, t):
        if msg.get_type() == "SIMSTATE":
            self.pos = (t, msg.lat * 1e-7, msg.lng * 1e-7)
        elif msg.get_type() == "SIM_STATE":
            self.alt = (t, msg.alt, msg.vn, msg.ve, msg.vd)

    def at(self, t):
        """(lat, lon, alt) propagated to arrival time `t`, or None when older than 0.1 s."""
        if self.pos is None or self.alt is None:
            return None
        tp, lat, lon = self.pos
        ta, alt, vn, ve, vd = self.alt
        if t - tp > 0.1 or t - ta > 0.1:
            return None
        m_lat, m_lon = metres_per_deg(lat)
        return (lat + vn * (t - tp) / m_lat, lon + ve * (t - tp) / m_lon, alt - vd * (t - ta))


def parse_args(argv=None):
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--scenario", choices=sorted(SCENARIOS), default="naip")
    scenario = pre.parse_known_args(argv)[0].scenario
    sc = SCENARIOS[scenario]
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", choices=sorted(SCENARIOS), default="naip",
                    help="naip: the high-altitude recipe over the bundled NAIP map (default); "
                         "drone: a multirotor 100 m above Autzen (../shared/data/autzen)")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--arducopter", help="path of the arducopter SITL binary (build/sitl/bin/arducopter)")
    g.add_argument("--sim-vehicle", help="path of Tools/autotest/sim_vehicle.py (copter already built)")
    ap.add_argument("--defaults", help="copter.parm (default: found beside --arducopter)")
    ap.add_argument("--visnav", help="visnav binary (default: target/release/visnav, else target/debug)")
    ap.add_argument("--no-visnav", action="store_true", help="the GPS-off control run (no visnav)")
    ap.add_argument("--mission", default=sc["mission"])
    ap.add_argument("--gps-off-wp", type=int, default=sc["gps_off_wp"],
                    help="switch the simulated GPS off when this mission item is reached (2: the "
                         "first corner, after the climb; visnav's filter lags fast climbs)")
    ap.add_argument("--gps-off-alt", type=float, default=None,
                    help="instead, switch it off at this true height above home, m")
    ap.add_argument("--denial", choices=DENIALS, default="gps-disable",
                    help="how the GPS is taken away at --gps-off-wp: gps-disable (default) "
                         "switches the simulated receiver off (SIM_GPS_DISABLE); source-set "
                         "leaves it on, switches EKF3 to source set 2 (visnav as ExternalNav, "
                         "visnav-source-set.parm) with MAV_CMD_SET_EKF_SOURCE_SET and withholds "
                         "the GPS from autopilot and visnav with the GPS Disable auxiliary "
                         "function (MAV_CMD_DO_AUX_FUNCTION 65), and gives both back at "
                         "--restore-wp; source-set-gps-on switches the source set only (visnav "
                         "keeps aiding itself with the GPS)")
    ap.add_argument("--restore-wp", type=int, default=None,
                    help="source-set denials: give the GPS back (GPS Disable low, then source "
                         "set 1) when this mission item is reached (default: the one before the "
                         "last, so the last leg flies on the GPS again)")
    ap.add_argument("--camera-hz", type=float, default=sc["camera_hz"])
    sitl_common.add_visnav_args(ap)
    ap.add_argument("--after-gps-off", type=float, default=None,
                    help="stop this many seconds after the GPS is off (default: at the last "
                         "waypoint); a run stopped so has not completed its mission: it fails")
    ap.add_argument("--timeout", type=float, default=1500.0, help="whole run, s")
    ap.add_argument("--workdir", help="logs and report (default: a new temporary directory)")
    ap.add_argument("--instance", type=sitl_common.instance_arg, default=None, metavar="N|auto",
                    help="SITL instance (-I N: ports 5760 + 10 N ...); default auto: the first "
                         "free one")
    ap.add_argument("--visnav-port", type=int, default=None,
                    help="UDP port of visnav's autopilot link (SITL SERIAL1); default 14551 on "
                         "instance 0 if free, else a free port")
    ap.add_argument("--truth-port", type=int, default=None,
                    help="UDP port of visnav's truth connection (SITL SERIAL2); default 14552 on "
                         "instance 0 if free, else a free port")
    sitl_common.add_bounds_args(ap)
    ap.set_defaults(max_p90_m=sc["bounds"][0], max_error_m=sc["bounds"][1])
    args = ap.parse_args(argv)
    if args.denial != "gps-disable":
        if args.no_visnav:
            ap.error(f"--denial {args.denial} needs visnav (source set 2 is visnav)")
        if args.gps_off_alt is not None:
            ap.error(f"--denial {args.denial} switches at a waypoint: --gps-off-wp, not --gps-off-alt")
        if args.restore_wp is not None and args.restore_wp <= args.gps_off_wp:
            ap.error("--restore-wp must come after --gps-off-wp")
    elif args.restore_wp is not None:
        ap.error("--restore-wp belongs to the source-set denials")
    return args


def main():
    args = parse_args()
    bounds = sitl_common.bounds_from_args(args)
    in_flight = False

    def stop(signum, _frame):
        # Also when started in the background (SIGINT ignored). In flight: end the flight loop and
        # report; before: exit (cleaning up in `finally`).
        global STOP
        if in_flight:
            STOP = f"stopped by signal {signum}"
        else:
            raise SystemExit(f"stopped by signal {signum}")

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, stop)

    workdir = os.path.abspath(args.workdir or tempfile.mkdtemp(prefix="visnav-ardupilot-sitl-"))
    os.makedirs(workdir, exist_ok=True)
    log(f"workdir {workdir}")
    procs = []
    home = SCENARIOS[args.scenario]["home"]
    source_set = args.denial != "gps-disable"
    report = {"run": ("control (no visnav)" if args.no_visnav else
                      "visnav VISION_POSITION_ESTIMATE (ExternalNav, EKF source set 2)"
                      if source_set else "visnav GPS_INPUT"),
              "scenario": args.scenario, "home": list(home), "denial": args.denial}
    # What the verdict needs, filled in as the run goes.
    score = (SourceSetScore if source_set else ErrorScore)("EKF3", log, home_alt_m=home[2])
    integ = None if args.no_visnav else IntegrityScore(bounds.ratio)
    switches = Switches()
    t_back = None
    modes, texts = [], []
    error = None
    why = None
    t_fly = t_gps_off = None
    reached, last_seq = -1, None
    held = None
    try:
        instance, control_port, visnav_port, truth_port, held = choose_ports(args)
        report.update({"instance": instance,
                       "ports": {"sitl_serial0_tcp": control_port, "visnav_udp": visnav_port,
                                 "truth_udp": truth_port}})
        log(f"SITL instance {instance}: SERIAL0 tcp {control_port}, visnav link udp "
            f"{visnav_port}, truth udp {truth_port}")
        if not args.no_visnav:
            procs.append(("visnav", start_visnav(args, workdir, visnav_port, truth_port)))
        procs.append(("sitl", start_sitl(args, workdir, instance, visnav_port, truth_port)))
        m = None
        end = time.time() + 60
        while m is None and time.time() < end:
            try:
                m = mavutil.mavlink_connection(f"tcp:127.0.0.1:{control_port}", source_system=255,
                                               autoreconnect=True)
            except OSError:
                time.sleep(0.5)
        if m is None:
            sys.exit(f"cannot connect to SITL on tcp {control_port} (see sitl.log)")
        hb = m.wait_heartbeat(timeout=60)
        if hb is None:
            sys.exit("no HEARTBEAT from SITL within 60 s (see sitl.log)")
        log(f"SITL heartbeat: system {m.target_system}")
        # 33 GLOBAL_POSITION_INT, 164 SIMSTATE, 108 SIM_STATE (truth), 24 GPS_RAW_INT (GPS1 =
        # visnav's injection), 124 GPS2_RAW, 193 EKF_STATUS_REPORT, 42 MISSION_CURRENT.
        rates = {33: 10, 164: 50, 108: 50, 24: 5, 124: 2, 193: 5, 42: 2}
        request_rates(m, rates)
        truth = Truth()
        # The source-set runs score visnav's VISION_POSITION_ESTIMATE after the flight: the
        # whole flight's truth.
        history = TruthHistory(keep_s=4 * args.timeout) if source_set else TruthHistory()
        clock = BootClock()
        t0 = time.time()
        last_ask = t0
        ready = False
        # 1. EKF3 has an absolute position, and (with visnav) GPS1 = visnav is a 3D fix.
        gps = {0: 0, 1: 0}
        ekf_flags = 0
        while not ready:
            if time.time() - t0 > 240:
                sys.exit(f"not ready within 240 s: EKF flags {ekf_flags:#x}, GPS fix types {gps}")
            r = m.recv_match(blocking=True, timeout=1.0)
            now = time.time()
            if now - last_ask > 5:
                request_rates(m, rates)
                last_ask = now
            if r is None:
                continue
            typ = r.get_type()
            truth.on(r, now)
            if typ == "GPS_RAW_INT":
                gps[0] = r.fix_type
            elif typ == "GPS2_RAW":
                gps[1] = r.fix_type
            elif typ == "EKF_STATUS_REPORT":
                ekf_flags = r.flags
            elif typ == "STATUSTEXT":
                log(f"STATUSTEXT {r.text}")
            # EKF_POS_HORIZ_ABS (16) and EKF_PRED_POS_HORIZ_ABS (512); 30 s for the EKF to settle.
            need_gps = [0] if args.no_visnav or source_set else [0, 1]
            ready = (ekf_flags & 16 and ekf_flags & 512 and all(gps[i] >= 3 for i in need_gps)
                     and now - t0 > 30)
        log(f"ready: EKF flags {ekf_flags:#x}, GPS fix types {gps}")
        n_items = upload_mission(m, args.mission)
        report["waypoints"] = n_items
        last_seq = n_items - 1
        restore_wp = args.restore_wp if args.restore_wp is not None else last_seq - 1
        # 2. AUTO + arm (AUTO_OPTIONS = 3: arming in AUTO and take-off without throttle).
        m.set_mode("AUTO")
        armed = False
        t_arm = time.time()
        while not armed:
            # Source sets: visnav's VISION_POSITION_ESTIMATE must flow (VisOdom pre-arm check).
            if time.time() - t_arm > (180 if source_set else 60):
                sys.exit("could not arm in time (pre-arm messages above)")
            m.mav.command_long_send(m.target_system, m.target_component,
                                    mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            end = time.time() + 2
            while time.time() < end:
                r = m.recv_match(blocking=True, timeout=0.5)
                if r is None:
                    continue
                truth.on(r, time.time())
                if r.get_type() == "STATUSTEXT":
                    log(f"STATUSTEXT {r.text}")
                elif r.get_type() == "HEARTBEAT" and is_autopilot(m, r):
                    armed = bool(r.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        log("armed in AUTO: taking off")
        in_flight = True
        # 3. Fly; GPS off after take-off; measure.
        t_fly = time.time()
        why = "timeout"
        aiding = None
        last_fix_us = None
        n_over = 0

        # Everything but the flight's own decisions (waypoints, modes, GPS off): also for the
        # messages that arrive while a parameter is being set.
        def observe(r, now):
            nonlocal aiding
            typ = r.get_type()
            truth.on(r, now)
            if typ in ("SIMSTATE", "SIM_STATE"):
                tr = truth.at(now)
                if tr is not None:
                    history.add(now, *tr)
                return
            own = r.get_srcSystem() == m.target_system and r.get_srcComponent() == 1
            if own and getattr(r, "time_boot_ms", None):
                clock.on(r.time_boot_ms, now)
            if typ == "STATUSTEXT":
                log(f"STATUSTEXT {r.text}")
                texts.append((round(now - t_fly, 1), r.text))
            elif typ == "EKF_STATUS_REPORT" and own:
                score.status(now - t_fly, r.flags)
                if ekf_aiding(r.flags) != aiding:
                    aiding = ekf_aiding(r.flags)
                    when = "" if t_gps_off is None else f" ({now - t_gps_off:+.1f} s after GPS off)"
                    log(f"EKF3 {'aiding' if aiding else 'NOT aiding'}: flags {r.flags:#x}{when}")
            elif typ == "GPS_RAW_INT" and own and integ is not None and not source_set:
                injected(r)

        def injected(r):
            # GPS instance 0 = visnav's GPS_INPUT; time_usec = its fix time (boot clock).
            nonlocal last_fix_us, n_over
            if r.fix_type < 3:
                integ.skip("no_fix")
                return
            if r.time_usec == last_fix_us:
                return  # the same fix sent again
            last_fix_us = r.time_usec
            t_fix = clock.local(r.time_usec * 1e-6)
            tr = None if t_fix is None else history.at(t_fix)
            if tr is None:
                integ.skip("no_truth")
                return
            phase = "gps_off" if t_gps_off is not None and t_fix >= t_gps_off else "gps_on"
            h_acc = getattr(r, "h_acc", 0) * 1e-3
            ratio = integ.add(t_fix - t_fly, phase, r.lat * 1e-7, r.lon * 1e-7, h_acc, tr[0], tr[1])
            if ratio is None or ratio > bounds.ratio:
                n_over += 1
                if n_over <= 5 or n_over % 50 == 0:
                    log(f"injected position {integ.samples[-1][2]} m from the truth, h_acc "
                        f"{h_acc:.2f} m ({n_over} over {bounds.ratio:g} x h_acc so far)")

        def switch_gps_off():
            on = (lambda r: observe(r, time.time()))
            if source_set:
                # Source set 2 first, so that EKF3 never runs on set 1 without the GPS.
                ok = switches.send(m, t_fly, "MAV_CMD_SET_EKF_SOURCE_SET",
                                   MAV_CMD_SET_EKF_SOURCE_SET, [2], on)
                if args.denial == "source-set":
                    ok &= switches.send(m, t_fly, "MAV_CMD_DO_AUX_FUNCTION GPS Disable high",
                                        MAV_CMD_DO_AUX_FUNCTION, [AUX_GPS_DISABLE, 2], on)
                log(f"GPS denied ({args.denial}){'' if ok else ': NOT every command accepted'}")
                t = time.time()
            else:
                t = gps_off(m, on=on)
            score.gps_switched_off(t - t_fly)
            return t

        def give_gps_back():
            # GPS Disable low, wait for a 3D fix on GPS1, then source set 1: EKF3 resets its
            # position to the GPS.
            on = (lambda r: observe(r, time.time()))
            if args.denial == "source-set":
                switches.send(m, t_fly, "MAV_CMD_DO_AUX_FUNCTION GPS Disable low",
                              MAV_CMD_DO_AUX_FUNCTION, [AUX_GPS_DISABLE, 0], on)
                end = time.time() + 10
                while time.time() < end:
                    r = m.recv_match(blocking=True, timeout=0.5)
                    if r is None:
                        continue
                    observe(r, time.time())
                    if r.get_type() == "GPS_RAW_INT" and r.fix_type >= 3:
                        break
            switches.send(m, t_fly, "MAV_CMD_SET_EKF_SOURCE_SET",
                          MAV_CMD_SET_EKF_SOURCE_SET, [1], on)
            t = time.time()
            score.gps_back(t - t_fly)
            log("GPS given back: source set 1")
            return t

        while True:
            now = time.time()
            if STOP:
                why = STOP
                break
            if now - t_fly > args.timeout:
                break
            if t_gps_off is not None and args.after_gps_off and now - t_gps_off > args.after_gps_off:
                why = f"{args.after_gps_off:.0f} s after GPS off"
                break
            if now - last_ask > 5:
                request_rates(m, rates)
                last_ask = now
            r = m.recv_match(blocking=True, timeout=1.0)
            if r is None:
                continue
            now = time.time()
            observe(r, now)
            typ = r.get_type()
            if typ == "MISSION_ITEM_REACHED":
                reached = max(reached, r.seq)
                log(f"waypoint {r.seq} reached")
                if t_gps_off is None and args.gps_off_alt is None and r.seq >= args.gps_off_wp:
                    t_gps_off = switch_gps_off()
                if (source_set and t_gps_off is not None and t_back is None
                        and r.seq >= restore_wp and r.seq < last_seq):
                    t_back = give_gps_back()
                if r.seq >= last_seq:
                    why = "last waypoint reached"
                    break
            elif typ == "HEARTBEAT" and is_autopilot(m, r):
                mode = mavutil.mode_string_v10(r)
                if not modes or modes[-1][1] != mode:
                    modes.append((round(now - t_fly, 1), mode))
                    log(f"mode {mode}")
                if not r.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED and now - t_fly > 10:
                    why = "disarmed (landed)"
                    break
            elif typ == "GLOBAL_POSITION_INT":
                tr = truth.at(now)
                if tr is None:
                    continue
                agl = tr[2] - home[2]
                if t_gps_off is None and args.gps_off_alt is not None and agl > args.gps_off_alt:
                    t_gps_off = switch_gps_off()
                    continue
                score.add(now - t_fly, t_gps_off is not None, r.lat * 1e-7, r.lon * 1e-7,
                          r.alt * 1e-3, *tr)
    except SystemExit as e:
        if e.code not in (None, 0):
            error = str(e.code)
            log(f"error: {error}")
    except Exception as e:  # a bug or an I/O error: still stop the processes and report
        traceback.print_exc()
        error = f"{type(e).__name__}: {e}"
    finally:
        if source_set:
            # visnav flushes its .tlog when stopped; conclude scores what it sent.
            sitl_common.stop_processes(procs)
            report["switches"] = switches.summary()
            report["gps_back_after_s"] = None if t_back is None else round(t_back - t_fly, 1)
            if integ is not None and t_fly is not None:
                try:
                    external_nav_integrity(workdir, history, t_fly, t_gps_off, t_back, integ)
                except Exception as e:  # a damaged tlog: report, do not lose the run
                    log(f"cannot score visnav.tlog: {type(e).__name__}: {e}")
                    integ.skip("tlog_error")
        code, lines = conclude(args, report, score, integ, modes, texts, error, why, t_fly,
                               t_gps_off, reached, last_seq, bounds, workdir)
        finish_run(procs, workdir, report, log)
        for line in lines:
            print(line, flush=True)
        if held is not None:
            held.close()
    return code


def conclude(args, report, score, integ, modes, texts, error, why, t_fly, t_gps_off, reached,
             last_seq, bounds, workdir):
    """Fill the report (statistics, verdict) and save the samples; returns the exit code and the
    verdict's lines (module docstring)."""
    label = "control" if args.no_visnav else "visnav"
    if t_fly is None:
        # Never flew: nothing to score.
        v = {"pass": False, "reasons": [f"run_error: {error or 'did not fly'}"], "notes": [],
             "bounds": bounds.as_dict()}
        report["verdict"] = v
        return 2, sitl_common.verdict_lines(label, v)
    t_end = time.time() - t_fly
    ekf = score.summary(t_end)
    completed = last_seq is not None and reached >= last_seq
    report.update({
        "ended": why if error is None else f"error: {error}",
        "flight_s": round(t_end, 1),
        "gps_off_after_s": None if t_gps_off is None else round(t_gps_off - t_fly, 1),
        "last_waypoint_reached": reached,
        "mission_completed": completed,
        "modes": modes,
        "statustext": texts,
        "ekf3_error": ekf,
    })
    if integ is not None:
        report["injected_integrity"] = integ.summary()
        integ.save(workdir)
    score.save(workdir)
    v = sitl_common.verdict(
        estimator="EKF3", mission_completed=completed,
        mission_detail=f"reached item {reached} of {last_seq} (ended: {report['ended']})",
        modes=modes, allowed_modes={"AUTO"}, texts=texts, ekf=ekf,
        integrity=report.get("injected_integrity"), integrity_expected=not args.no_visnav,
        error=error, bounds=bounds)
    sw = report.get("switches")
    if sw is not None:
        # The source-set denials: every switch accepted, and the GPS given back in flight.
        bad = [f"{d['command']} {d['params']}: {d['result']}" for d in sw["commands"]
               if d["result"] != "MAV_RESULT_ACCEPTED"]
        if bad:
            v["reasons"].append("switch_refused: " + "; ".join(bad))
        if t_gps_off is not None and report.get("gps_back_after_s") is None:
            v["reasons"].append("gps_not_given_back: the run ended before source set 1 was "
                                "restored")
        v["pass"] = not v["reasons"]
    report["verdict"] = v
    if error is not None:
        return 2, sitl_common.verdict_lines(label, v)
    run_completed = t_gps_off is not None and not (why or "").startswith("stopped by signal")
    lines = sitl_common.verdict_lines(label, v)
    if args.no_visnav:
        lines.append(f"control: the control run {'completed' if run_completed else 'did NOT complete'}"
                     f" (exit {sitl_common.exit_code(v, True, run_completed)}); its verdict is "
                     f"the baseline for the visnav run")
    return sitl_common.exit_code(v, args.no_visnav, run_completed), lines


if __name__ == "__main__":
    sys.exit(main())
