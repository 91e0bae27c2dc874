#!/usr/bin/env python3
"""visnav against a real PX4 SITL (SIH quadrotor, or Gazebo): fly a mission over the bundled NAIP
map with visnav's ODOMETRY (external vision) fused by EKF2, stop EKF2 from using the GPS after
take-off, and report EKF2's position error against the simulator's ground truth.

    python3 sitl/px4/run.py --px4-build /path/to/PX4-Autopilot/build/px4_sitl_default
    python3 sitl/px4/run.py --attach        # PX4 SITL already running (see docs/real-sitl.md)
    python3 sitl/px4/run.py --px4-build ... --no-visnav   # the GPS-off control run

NOT RUN in the project (PX4 was not built here): written and checked against the PX4
documentation only; see docs/real-sitl.md. It does not build PX4.

What runs (loopback):
* PX4 SITL with SIH (PX4_SIM_MODEL=sihsim_quadx, airframe 10040), home at the centre of
  sitl/maps (PX4_HOME_LAT/LON/ALT). PX4's onboard (API) MAVLink instance sends to UDP 14540 (visnav's link),
  its GCS instance to UDP 14550 (this script).
* `visnav sitl-run --kind px4 --config sitl/px4/visnav.toml --truth udpin:127.0.0.1:14552 ...`.
  PX4 has no spare MAVLink port for the truth, so this script relays the GROUND_TRUTH stream
  (HIL_STATE_QUATERNION) and ATTITUDE (for the time) it receives on 14550 to UDP 14552.
* This script: sets visnav-ev.params with PARAM_SET, waits for a global position, uploads
  ../ardupilot/mission.waypoints' twin (mission.waypoints), arms, starts the mission, sets
  EKF2_GPS_CTRL = 0 (EKF2 stops fusing GPS; visnav never uses it:
  [daemon] gps = "none") when the first corner of the loop is reached (--gps-off-wp; or
  --gps-off-alt metres up), and stops at the last waypoint.

Measured: GLOBAL_POSITION_INT (EKF2) against HIL_STATE_QUATERNION (truth) propagated over the
arrival gap with the true velocity: horizontal and vertical error, median / p90 / max, with the GPS
fused (airborne) and after EKF2_GPS_CTRL = 0.
"""

import argparse
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time

try:
    from pymavlink import mavutil
except ImportError:
    sys.exit("run.py needs pymavlink: python3 -m pip install pymavlink")

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
HOME_LAT, HOME_LON, HOME_ALT_M = 47.0203485, -99.1548094, 580.0
GCS_PORT, TRUTH_PORT = 14550, 14552


def log(msg):
    print(f"[px4 run.py {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def metres_per_deg(lat_deg):
    p = math.radians(lat_deg)
    return (111132.954 - 559.822 * math.cos(2 * p) + 1.175 * math.cos(4 * p),
            111412.84 * math.cos(p) - 93.5 * math.cos(3 * p))


def stats(v):
    if not v:
        return None
    s = sorted(v)
    p90 = s[min(len(s) - 1, int(math.ceil(0.9 * len(s))) - 1)]
    return {"n": len(s), "median_m": round(statistics.median(s), 2), "p90_m": round(p90, 2),
            "max_m": round(s[-1], 2)}


def read_params(path):
    out = []
    with open(path) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if line:
                name, value = line.split()
                out.append((name, float(value)))
    return out


def set_param(m, name, value, timeout=5.0):
    end = time.time() + timeout
    while time.time() < end:
        m.mav.param_set_send(m.target_system, m.target_component, name.encode(), float(value),
                             mavutil.mavlink.MAV_PARAM_TYPE_REAL32)
        r = m.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
        if r is not None and r.param_id == name:
            return True
    return False


def upload_mission(m, path):
    items = []
    with open(path) as f:
        if not f.readline().startswith("QGC WPL 110"):
            sys.exit(f"{path}: not a QGC WPL 110 file")
        for line in f:
            v = line.strip().split("\t")
            if len(v) == 12 and int(v[0]) > 0:  # PX4 missions have no home item
                items.append(v)
    m.mav.mission_count_send(m.target_system, m.target_component, len(items),
                             mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
    end = time.time() + 30
    while time.time() < end:
        r = m.recv_match(type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"],
                         blocking=True, timeout=2.0)
        if r is None:
            continue
        if r.get_type() == "MISSION_ACK":
            if r.type == mavutil.mavlink.MAV_MISSION_ACCEPTED:
                return len(items)
            sys.exit(f"mission upload refused: MISSION_ACK type {r.type}")
        v = items[r.seq]
        m.mav.mission_item_int_send(m.target_system, m.target_component, r.seq, int(v[2]),
                                    int(v[3]), 1 if r.seq == 0 else 0, 1, float(v[4]), float(v[5]),
                                    float(v[6]), float(v[7]), int(round(float(v[8]) * 1e7)),
                                    int(round(float(v[9]) * 1e7)), float(v[10]),
                                    mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
    sys.exit("mission upload timed out")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--px4-build", help="PX4 SITL build directory (build/px4_sitl_default)")
    g.add_argument("--attach", action="store_true", help="PX4 SITL is already running")
    ap.add_argument("--visnav", help="visnav binary (default: target/release/visnav)")
    ap.add_argument("--no-visnav", action="store_true", help="the GPS-off control run")
    ap.add_argument("--mission", default=os.path.join(HERE, "mission.waypoints"))
    ap.add_argument("--gps-off-wp", type=int, default=1,
                    help="EKF2_GPS_CTRL = 0 when this mission item (0-based, no home item) is "
                         "reached: 1 = the first corner, after the climb")
    ap.add_argument("--gps-off-alt", type=float, default=None,
                    help="instead, at this true height above home, m")
    ap.add_argument("--camera-hz", type=float, default=2.0)
    ap.add_argument("--timeout", type=float, default=1500.0)
    ap.add_argument("--workdir")
    args = ap.parse_args()

    def stop(signum, _frame):
        # Also when started in the background (SIGINT ignored): clean up in `finally`.
        raise SystemExit(f"stopped by signal {signum}")

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, stop)

    workdir = args.workdir or tempfile.mkdtemp(prefix="visnav-px4-sitl-")
    os.makedirs(workdir, exist_ok=True)
    log(f"workdir {workdir}")
    procs = []
    report = {"run": "control (no visnav)" if args.no_visnav else "visnav ODOMETRY"}
    try:
        if args.px4_build:
            # As PX4's sihsim_quadx run target does
            # (src/modules/simulation/simulator_sih/CMakeLists.txt): the px4 binary in the build's
            # rootfs with PX4_SIM_MODEL / PX4_SIMULATOR; -d: no interactive shell.
            env = dict(os.environ, PX4_SIMULATOR="sihsim", PX4_SIM_MODEL="sihsim_quadx",
                       PX4_HOME_LAT=str(HOME_LAT), PX4_HOME_LON=str(HOME_LON),
                       PX4_HOME_ALT=str(HOME_ALT_M))
            rootfs = os.path.join(args.px4_build, "rootfs")
            if not os.path.isdir(rootfs):
                sys.exit(f"{rootfs}: not a PX4 SITL build directory")
            cmd = [os.path.join(args.px4_build, "bin", "px4"), "-d"]
            log("PX4: " + " ".join(cmd))
            procs.append(("px4", subprocess.Popen(cmd, env=env, cwd=rootfs, stdin=subprocess.DEVNULL,
                                                  stdout=open(os.path.join(workdir, "px4.log"), "w"),
                                                  stderr=subprocess.STDOUT, start_new_session=True)))
        if not args.no_visnav:
            exe = os.path.abspath(args.visnav or os.path.join(REPO, "target", "release", "visnav"))
            cmd = [exe, "sitl-run", "--kind", "px4", "--config", os.path.join(HERE, "visnav.toml"),
                   "--truth", f"udpin:127.0.0.1:{TRUTH_PORT}",
                   "--ortho", os.path.join(REPO, "sitl", "maps", "naip_nd_2014.tif"),
                   "--rate-hz", str(args.camera_hz)]
            log("visnav: " + " ".join(cmd))
            procs.append(("visnav", subprocess.Popen(
                cmd, stdout=open(os.path.join(workdir, "visnav.json"), "w"),
                stderr=open(os.path.join(workdir, "visnav.log"), "w"), start_new_session=True)))
        m = mavutil.mavlink_connection(f"udpin:0.0.0.0:{GCS_PORT}", source_system=255)
        relay = mavutil.mavlink_connection(f"udpout:127.0.0.1:{TRUTH_PORT}", source_system=1)
        if m.wait_heartbeat(timeout=120) is None:
            sys.exit("no HEARTBEAT from PX4 on UDP 14550")
        log(f"PX4 heartbeat: system {m.target_system}")
        for name, value in read_params(os.path.join(HERE, "visnav-ev.params")):
            if args.no_visnav and name.startswith("EKF2_EV"):
                continue
            if not set_param(m, name, value):
                log(f"parameter {name} not acknowledged (absent in this PX4 version?)")
        rates = {115: 50, 30: 50, 33: 10}

        def ask():
            for msg_id, hz in rates.items():
                m.mav.command_long_send(m.target_system, m.target_component,
                                        mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                        msg_id, 1e6 / hz, 0, 0, 0, 0, 0)

        ask()
        truth = None  # (t_arrival, lat, lon, alt, vn, ve, vd)

        def on(r, now):
            nonlocal truth
            typ = r.get_type()
            if typ in ("HIL_STATE_QUATERNION", "ATTITUDE"):
                relay.write(r.get_msgbuf())
            if typ == "HIL_STATE_QUATERNION":
                truth = (now, r.lat * 1e-7, r.lon * 1e-7, r.alt * 1e-3, r.vx * 0.01, r.vy * 0.01,
                         r.vz * 0.01)
            elif typ == "STATUSTEXT":
                log(f"STATUSTEXT {r.text}")

        t0 = time.time()
        last_ask = t0
        while True:
            r = m.recv_match(blocking=True, timeout=1.0)
            now = time.time()
            if now - last_ask > 5:
                ask()
                last_ask = now
            if now - t0 > 240:
                sys.exit("no global position within 240 s")
            if r is None:
                continue
            on(r, now)
            if r.get_type() == "GLOBAL_POSITION_INT" and r.lat != 0 and now - t0 > 20:
                break
        n = upload_mission(m, args.mission)
        log(f"mission: {n} items")
        m.mav.command_long_send(m.target_system, m.target_component,
                                mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        time.sleep(1)
        m.mav.command_long_send(m.target_system, m.target_component,
                                mavutil.mavlink.MAV_CMD_MISSION_START, 0, 0, n - 1, 0, 0, 0, 0, 0)
        errs = {"gps_on": ([], []), "gps_off": ([], [])}
        t_fly = time.time()
        t_gps_off = None
        why = "timeout"
        while time.time() - t_fly < args.timeout:
            r = m.recv_match(blocking=True, timeout=1.0)
            now = time.time()
            if now - last_ask > 5:
                ask()
                last_ask = now
            if r is None:
                continue
            on(r, now)
            typ = r.get_type()
            if typ == "MISSION_ITEM_REACHED":
                log(f"mission item {r.seq} reached")
                if t_gps_off is None and args.gps_off_alt is None and r.seq >= args.gps_off_wp:
                    if not set_param(m, "EKF2_GPS_CTRL", 0):
                        sys.exit("cannot set EKF2_GPS_CTRL = 0")
                    t_gps_off = time.time()
                    log("EKF2_GPS_CTRL = 0")
                if r.seq >= n - 1:
                    why = "last waypoint reached"
                    break
            elif typ == "GLOBAL_POSITION_INT" and truth is not None and now - truth[0] < 0.1:
                tt, lat, lon, alt, vn, ve, vd = truth
                dt = now - tt
                m_lat, m_lon = metres_per_deg(lat)
                lat, lon, alt = lat + vn * dt / m_lat, lon + ve * dt / m_lon, alt - vd * dt
                eh = math.hypot((r.lat * 1e-7 - lat) * m_lat, (r.lon * 1e-7 - lon) * m_lon)
                ev = r.alt * 1e-3 - alt
                agl = alt - HOME_ALT_M
                if t_gps_off is None and args.gps_off_alt is not None and agl > args.gps_off_alt:
                    if not set_param(m, "EKF2_GPS_CTRL", 0):
                        sys.exit("cannot set EKF2_GPS_CTRL = 0")
                    t_gps_off = time.time()
                    log(f"EKF2_GPS_CTRL = 0 at {agl:.0f} m above home")
                    continue
                if agl > 5:
                    ph = "gps_off" if t_gps_off else "gps_on"
                    errs[ph][0].append(eh)
                    errs[ph][1].append(abs(ev))
        report.update({
            "ended": why,
            "ekf2_error": {ph: {"horizontal": stats(h), "vertical": stats(v)}
                           for ph, (h, v) in errs.items()},
        })
    finally:
        for name, p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT if name == "visnav" else signal.SIGTERM)
        for name, p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
        with open(os.path.join(workdir, "report.json"), "w") as f:
            json.dump(report, f, indent=1)
        print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
