#!/usr/bin/env python3
"""visnav against a real ArduPilot SITL (ArduCopter): fly an AUTO mission over the bundled NAIP
map, switch the simulated GPS off after take-off, and report EKF3's position error against the
simulator's truth.

    python3 sitl/ardupilot/run.py --arducopter /path/to/ardupilot/build/sitl/bin/arducopter
    python3 sitl/ardupilot/run.py --sim-vehicle /path/to/ardupilot/Tools/autotest/sim_vehicle.py
    python3 sitl/ardupilot/run.py --arducopter ... --no-visnav      # the GPS-off control run

It does not build ArduPilot (see docs/real-sitl.md). Needs pymavlink (`bash
scripts/interop/setup_venv.sh` prints a venv python that has it) and a built visnav
(`cargo build --release`, or give --visnav).

What runs (all on loopback):
* SITL, home at the centre of sitl/maps (47.0203485 N, 99.1548094 W, 580 m AMSL), parameters
  Tools/autotest/default_params/copter.parm + visnav-gps-input.parm (or control-no-visnav.parm);
  SERIAL0 tcp:5760 = this script, SERIAL1 udpclient 14551 = visnav's autopilot link, SERIAL2
  udpclient 14552 = visnav's truth connection (SIMSTATE + SIM_STATE for the simulated camera).
* `visnav sitl-run --config sitl/ardupilot/visnav.toml --truth udpin:127.0.0.1:14552 --ortho
  sitl/maps/naip_nd_2014.tif` (the camera sees the 2014 image; the map is the 2009 one).
* This script: waits for EKF3 to have a position (and, with visnav, for visnav's GPS_INPUT to be
  a 3D fix), uploads mission.waypoints, sets AUTO and arms (AUTO_OPTIONS = 3 takes off without
  throttle), sets SIM_GPS_DISABLE = 1 (4.6+: SIM_GPS1_ENABLE = 0) once the copter reaches the
  first corner of the loop at 1800 m (--gps-off-wp; or --gps-off-alt metres up), and stops at the last waypoint (or --timeout, or when the copter lands
  or disarms).

Measured: every GLOBAL_POSITION_INT (EKF3's output, 10 Hz) against the truth of the same instant
(SIMSTATE latitude/longitude degE7 and SIM_STATE altitude, 50 Hz, propagated over the arrival gap
with the true velocity): horizontal and vertical error, median / p90 / max, separately while the
GPS is on (airborne) and after it is switched off. Written to WORKDIR/report.json and printed.
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

try:
    from pymavlink import mavutil
except ImportError:
    sys.exit("run.py needs pymavlink: python3 -m pip install pymavlink "
             "(or use the venv python printed by scripts/interop/setup_venv.sh)")

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.dirname(HERE))
import sitl_common  # noqa: E402
from sitl_common import (HOME_ALT_M, HOME_LAT, HOME_LON, ErrorScore, finish_run,  # noqa: E402
                         metres_per_deg)
HOME_HDG = 0  # SITL start heading, deg
VISNAV_PORT, TRUTH_PORT, CONTROL_PORT = 14551, 14552, 5760
STOP = None  # set by SIGTERM/SIGINT/SIGHUP during the flight


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


def start_sitl(args, workdir):
    parms = [os.path.join(HERE, "control-no-visnav.parm" if args.no_visnav else "visnav-gps-input.parm")]
    serials = [f"--serial1=udpclient:127.0.0.1:{VISNAV_PORT}",
               f"--serial2=udpclient:127.0.0.1:{TRUTH_PORT}"]
    home = f"{HOME_LAT},{HOME_LON},{HOME_ALT_M},{HOME_HDG}"
    if args.arducopter:
        base = args.defaults or find_copter_parm(args.arducopter)
        if base is None:
            sys.exit("cannot find Tools/autotest/default_params/copter.parm beside the binary: give --defaults")
        # The control parameters go after visnav-gps-input.parm (same flight, GPS types changed).
        files = [base, os.path.join(HERE, "visnav-gps-input.parm")] + (parms if args.no_visnav else [])
        cmd = [args.arducopter, "-S", "--model", "+", "--speedup", "1", "--home", home, "-I0",
               "--wipe", "--defaults", ",".join(files)] + serials
    else:
        files = [os.path.join(HERE, "visnav-gps-input.parm")] + (parms if args.no_visnav else [])
        cmd = [sys.executable, args.sim_vehicle, "-v", "ArduCopter", "-f", "quad", "--no-rebuild",
               "--no-mavproxy", "-w", "-l", home, "-A", " ".join(serials)]
        for f in files:
            cmd += ["--add-param-file", f]
    log("SITL: " + " ".join(cmd))
    out = open(os.path.join(workdir, "sitl.log"), "w")
    return subprocess.Popen(cmd, cwd=workdir, stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


def start_visnav(args, workdir):
    return sitl_common.start_visnav(args.visnav, os.path.join(HERE, "visnav.toml"), workdir,
                                    "ardupilot", TRUTH_PORT, args.camera_hz, REPO, log)


def is_autopilot(m, hb):
    """The autopilot's own HEARTBEAT (ArduPilot forwards visnav's, same system id, to this link)."""
    return (hb.get_srcSystem() == m.target_system and hb.get_srcComponent() == 1
            and hb.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID)


def request_rates(m, rates):
    for msg_id, hz in rates.items():
        m.mav.command_long_send(m.target_system, m.target_component,
                                mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                msg_id, 1e6 / hz, 0, 0, 0, 0, 0)


def set_param(m, name, value, timeout=5.0):
    """PARAM_SET and wait for the PARAM_VALUE echo; False when the autopilot has no such name."""
    end = time.time() + timeout
    while time.time() < end:
        m.mav.param_set_send(m.target_system, m.target_component, name.encode(), float(value),
                             mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
        r = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
        if r is not None and r.param_id == name:
            return abs(r.param_value - value) < 1e-3
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


def gps_off(m):
    """Switch SITL's simulated GPS 1 off (4.5: SIM_GPS_DISABLE, 4.6+: SIM_GPS1_ENABLE)."""
    if not (set_param(m, "SIM_GPS_DISABLE", 1) or set_param(m, "SIM_GPS1_ENABLE", 0)):
        sys.exit("cannot switch the simulated GPS off (SIM_GPS_DISABLE / SIM_GPS1_ENABLE)")
    log("simulated GPS OFF")
    return time.time()


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


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--arducopter", help="path of the arducopter SITL binary (build/sitl/bin/arducopter)")
    g.add_argument("--sim-vehicle", help="path of Tools/autotest/sim_vehicle.py (copter already built)")
    ap.add_argument("--defaults", help="copter.parm (default: found beside --arducopter)")
    ap.add_argument("--visnav", help="visnav binary (default: target/release/visnav, else target/debug)")
    ap.add_argument("--no-visnav", action="store_true", help="the GPS-off control run (no visnav)")
    ap.add_argument("--mission", default=os.path.join(HERE, "mission.waypoints"))
    ap.add_argument("--gps-off-wp", type=int, default=2,
                    help="switch the simulated GPS off when this mission item is reached (2: the "
                         "first corner, after the climb; visnav's filter lags fast climbs)")
    ap.add_argument("--gps-off-alt", type=float, default=None,
                    help="instead, switch it off at this true height above home, m")
    ap.add_argument("--camera-hz", type=float, default=2.0)
    ap.add_argument("--after-gps-off", type=float, default=None,
                    help="stop this many seconds after the GPS is off (default: at the last waypoint)")
    ap.add_argument("--timeout", type=float, default=1500.0, help="whole run, s")
    ap.add_argument("--workdir", help="logs and report (default: a new temporary directory)")
    args = ap.parse_args()

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

    in_flight = False
    workdir = args.workdir or tempfile.mkdtemp(prefix="visnav-ardupilot-sitl-")
    os.makedirs(workdir, exist_ok=True)
    log(f"workdir {workdir}")
    procs = []
    report = {"run": "control (no visnav)" if args.no_visnav else "visnav GPS_INPUT",
              "home": [HOME_LAT, HOME_LON, HOME_ALT_M]}
    try:
        if not args.no_visnav:
            procs.append(("visnav", start_visnav(args, workdir)))
        procs.append(("sitl", start_sitl(args, workdir)))
        m = None
        end = time.time() + 60
        while m is None and time.time() < end:
            try:
                m = mavutil.mavlink_connection(f"tcp:127.0.0.1:{CONTROL_PORT}", source_system=255,
                                               autoreconnect=True)
            except OSError:
                time.sleep(0.5)
        if m is None:
            sys.exit("cannot connect to SITL on tcp 5760 (see sitl.log)")
        hb = m.wait_heartbeat(timeout=60)
        if hb is None:
            sys.exit("no HEARTBEAT from SITL within 60 s (see sitl.log)")
        log(f"SITL heartbeat: system {m.target_system}")
        rates = {33: 10, 164: 50, 108: 50, 24: 2, 124: 2, 193: 2, 42: 2}
        request_rates(m, rates)
        truth = Truth()
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
            need_gps = [0] if args.no_visnav else [0, 1]
            ready = (ekf_flags & 16 and ekf_flags & 512 and all(gps[i] >= 3 for i in need_gps)
                     and now - t0 > 30)
        log(f"ready: EKF flags {ekf_flags:#x}, GPS fix types {gps}")
        n_items = upload_mission(m, args.mission)
        last_seq = n_items - 1
        # 2. AUTO + arm (AUTO_OPTIONS = 3: arming in AUTO and take-off without throttle).
        m.set_mode("AUTO")
        armed = False
        t_arm = time.time()
        while not armed:
            if time.time() - t_arm > 60:
                sys.exit("could not arm within 60 s (pre-arm messages above)")
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
        score = ErrorScore("EKF3", log)
        t_gps_off = None
        reached = -1
        t_fly = time.time()
        modes = []
        why = "timeout"
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
            typ = r.get_type()
            truth.on(r, now)
            if typ == "STATUSTEXT":
                log(f"STATUSTEXT {r.text}")
            elif typ == "MISSION_ITEM_REACHED":
                reached = max(reached, r.seq)
                log(f"waypoint {r.seq} reached")
                if t_gps_off is None and args.gps_off_alt is None and r.seq >= args.gps_off_wp:
                    t_gps_off = gps_off(m)
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
                agl = tr[2] - HOME_ALT_M
                if t_gps_off is None and args.gps_off_alt is not None and agl > args.gps_off_alt:
                    t_gps_off = gps_off(m)
                    continue
                score.add(now - t_fly, t_gps_off is not None, r.lat * 1e-7, r.lon * 1e-7,
                          r.alt * 1e-3, *tr)
        report.update({
            "ended": why,
            "flight_s": round(time.time() - t_fly, 1),
            "gps_off_after_s": None if t_gps_off is None else round(t_gps_off - t_fly, 1),
            "last_waypoint_reached": reached,
            "modes": modes,
            "ekf3_error": score.summary(),
        })
        score.save(workdir)
    finally:
        finish_run(procs, workdir, report, log)


if __name__ == "__main__":
    main()
