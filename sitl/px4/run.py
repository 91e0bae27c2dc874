#!/usr/bin/env python3
"""visnav against a real PX4 SITL (SIH quadrotor, or jMAVSim): fly a mission over the bundled NAIP
map with visnav's ODOMETRY (external vision) fused by EKF2, stop EKF2 from using the GPS after
take-off, and report EKF2's position error against the simulator's ground truth.

    python3 sitl/px4/run.py --px4-build /path/to/PX4-Autopilot/build/px4_sitl_nolockstep
    python3 sitl/px4/run.py --px4-build ... --no-visnav   # the GPS-off control run
    python3 sitl/px4/run.py --attach        # PX4 SITL (SIH) already running, see docs/
    python3 sitl/px4/run.py --sim jmavsim --px4-build ... \
        --jmavsim-jar /path/to/jMAVSim/out/production/jmavsim_run.jar   # a realistic IMU

It does not build PX4 (docs/real-sitl.md (PX4 section) says how it was built and run). Needs pymavlink
(`bash scripts/interop/setup_venv.sh` prints a venv python that has it) and a built visnav
(`cargo build --release`, or give --visnav). Run with PX4 v1.14 (release/1.14, SIH as SITL),
built as px4_sitl_nolockstep: with the lockstep build PX4's clock is SIH's simulated time, which
falls behind real time on a loaded machine (1.6 % in irregular steps here) and visnav's TIMESYNC
filter, made for real clocks, then drops half the camera frames.

What runs (all on loopback):
* With --sim jmavsim: jMAVSim (the user's build of PX4/jMAVSim, docs/real-sitl.md, PX4 section)
  headless, real time (no lockstep), 250 Hz, home at the centre of sitl/maps (PX4_HOME_LAT/LON/
  ALT), listening on TCP 4560; then PX4 with PX4_SIM_MODEL=jmavsim_iris (airframe 10017) instead
  of SIH, whose private `px4-rc.simulator` no longer kills and starts jMAVSim itself
  (patch_rc_simulator_for_jmavsim); SIH_* parameters dropped, SYS_FAILURE_EN 1,
  EKF2_GPS_DELAY 200 and jMAVSim's magnetic declination (EKF2_DECL_TYPE 0, EKF2_MAG_DECL 2.72)
  added; visnav-jmavsim.toml. jMAVSim's HIL_STATE_QUATERNION carries its local
  z as the altitude: run.py turns it into the altitude AMSL before relaying and scoring it. GPS
  off is MAV_CMD_INJECT_FAILURE (GPS, off) + EKF2_GPS_CTRL 0.
* PX4 SITL with SIH (PX4_SIM_MODEL=sihsim_quadx, airframe 10040, 250 Hz, real time), as PX4's
  `sihsim_quadx` run target starts it, but in WORKDIR/px4 with a copy of the build's `etc` whose
  `init.d-posix/px4-rc.params` (PX4's hook for parameters, sourced by rcS before the modules
  start) sets the SIH home to the centre of sitl/maps (SIH_LOC_LAT0/LON0 degE7, SIH_LOC_H0
  580 m; PX4 v1.14 has no PX4_HOME_ALT for SIH and its PX4_HOME_LAT/LON path writes degrees
  into these integer degE7 parameters) and every parameter of visnav-ev.params. A fresh
  working directory: no parameters left from an earlier run.
  PX4's onboard (API) MAVLink instance sends to UDP LINK_PORT (visnav's link, visnav.toml), its
  GCS instance to UDP GCS_PORT (this script).
* Ports and instance (so that runs can share a host): PX4 runs as instance N (`px4 -i N`,
  --instance, by default the first N in 0-9 whose ports are free (bind test), whose
  /tmp/px4_lock-N no PX4 holds and whose lock (TMPDIR/visnav-sitl-px4-N.lock) no other run.py
  holds). `-i N` moves PX4's own local ports (UDP 18570 + N GCS link, 14580 + N onboard link,
  14280/13030/19450 + N, jMAVSim TCP 4560 + N) and its system id (rcS: MAV_SYS_ID = N + 1, set
  back to 1 here in px4-rc.params, the system visnav.toml expects). The ports PX4 sends *to* do
  not all move (every instance's GCS link sends to 14550): GCS_PORT (--gcs-port; 14550 on
  instance 0 when free, else a free port), LINK_PORT (--link-port; 14540 + N when free, else a
  free port) and TRUTH_PORT (--truth-port; 14562 on instance 0 when free, else a free port)
  are written into the work folder's copy of px4-rc.mavlink (`-o GCS_PORT` on the GCS link,
  udp_offboard_port_remote = LINK_PORT) and visnav.toml. Instance 0 with the default ports runs PX4's files unchanged. With --attach
  nothing is chosen: GCS_PORT 14550 (or --gcs-port), the link as in the configuration.
* `visnav sitl-run --kind px4 --config WORKDIR/visnav.toml --truth udpin:127.0.0.1:TRUTH_PORT
  --ortho sitl/maps/naip_nd_2014.tif` (the camera sees the 2014 image; the map is the 2009 one),
  started once PX4 is armed (--visnav-from: PX4 cannot arm while visnav's velocity wanders on the
  ground, docs/real-sitl.md (PX4 section)).
  PX4 has no spare MAVLink port for the truth, so this script asks for HIL_STATE_QUATERNION
  (PX4's ground truth stream) and ATTITUDE (for the time) at 50 Hz on the GCS link and relays both
  packets unchanged to UDP TRUTH_PORT (--truth-port, 14562 on instance 0: ArduPilot's recipe
  uses 14551 and 14552 on its instance 0).
* This script: waits for EKF2's global position, uploads mission.waypoints (without ArduPilot's
  home item), arms and starts the mission, sets EKF2_GPS_CTRL = 0 (EKF2 stops fusing GPS; visnav
  never uses it: [daemon] gps = "none") when the first corner of the loop is reached
  (--gps-off-wp; or --gps-off-alt metres up), and stops at the last waypoint (or --timeout, or
  --after-gps-off seconds, or --after-mode-change (60) seconds after PX4 first left MISSION, e.g.
  a failsafe's LAND, or when the copter lands / disarms).

Measured: every GLOBAL_POSITION_INT (EKF2's output) against HIL_STATE_QUATERNION (truth)
propagated over the arrival gap with the true velocity: horizontal and vertical error, median /
p90 / max, with the GPS fused (airborne), after EKF2_GPS_CTRL = 0 (all airborne samples), and
after it split by whether EKF2 was aiding (ESTIMATOR_STATUS flags: ESTIMATOR_POS_HORIZ_ABS set,
not ESTIMATOR_CONST_POS_MODE; sitl_common.py), with the time it was not aiding (first loss after
GPS off, total). PX4 stops GLOBAL_POSITION_INT while its global position is invalid: that time
shows as not aiding and as a sample gap. STATUSTEXT after arming (failsafes: "Failsafe
activated", any "failsafe") and the flight modes after arming. Written to WORKDIR/report.json
(with visnav's last metrics line and "verdict") and printed; every sample (with its aiding flag)
in WORKDIR/samples.json.

Injected-position integrity: PX4 does not send back the ODOMETRY it fuses (ArduPilot echoes
GPS_INPUT as GPS_RAW_INT; PX4's ODOMETRY stream sends its own estimate unless the MAV_ODOM_LP
loopback is set, which this recipe does not use), but it logs what it received
(`vehicle_visual_odometry`). After the flight, with PX4 stopped, run.py scores that against the
truth in the same log (ulog_error.injected_integrity: error over the claimed accuracy, as
ArduPilot's GPS_INPUT echo is scored) and the verdict uses it (WORKDIR/injected.json, report
"injected_integrity"). Needs pyulog; without it, with --attach or without a PX4 log the report says
it was not measured (a note in the verdict, not a failure).

Verdict (sitl_common.verdict, the same rules as sitl/ardupilot/run.py, mission mode MISSION;
bounds --max-p90-m 25, --max-error-m 50, --max-not-aiding-s 0, --max-sample-gap-s 2) and exit
code: 0 = a visnav run passed, 1 = it failed; the control run (--no-visnav) prints its verdict
as "control: ..." and exits 0 when the control run itself completed (the GPS went off and the
flight ended on its own), 1 when not; 2 = the run could not be made (PX4 did not start, no
position, could not arm, an error in flight).
"""

import argparse
import glob
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback

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
from sitl_common import (HOME_ALT_M, HOME_LAT, HOME_LON, ErrorScore, ekf_aiding,  # noqa: E402
                         finish_run, metres_per_deg)
# PX4's defaults for instance 0: the GCS link's remote port, the onboard link's (+ N), the truth
# relay (this recipe's), jMAVSim's TCP port (+ N).
GCS_PORT, LINK_PORT, TRUTH_PORT, JMAVSIM_PORT = 14550, 14540, 14562, 4560
MAX_INSTANCE = 9  # px4-rc.mavlink sends every instance above 9 to the same onboard port
INTEGRITY_NOTE = ("injected position integrity not measured: PX4 does not echo the ODOMETRY it "
                  "receives, and its log (vehicle_visual_odometry) could not be read")
# Declination of jMAVSim's fixed magnetic field (Simulator.DEFAULT_MAG_FIELD, N / E / D gauss
# 0.21506 / 0.01021 / 0.42974), deg.
JMAVSIM_MAG_DECL_DEG = 2.718
STOP = None  # set by SIGTERM/SIGINT/SIGHUP during the flight


def log(msg):
    print(f"[px4 run.py {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def read_params(path):
    """(name, value text) pairs of a `NAME VALUE` file (# comments)."""
    out = []
    with open(path) as f:
        for line in f:
            line = line.split("#", 1)[0].strip()
            if line:
                name, value = line.split()
                float(value)  # a number, or stop here
                out.append((name, value))
    return out


def sih_params():
    return [("SIH_LOC_LAT0", str(int(round(HOME_LAT * 1e7)))),
            ("SIH_LOC_LON0", str(int(round(HOME_LON * 1e7)))),
            ("SIH_LOC_H0", f"{HOME_ALT_M:.2f}")]


# PX4 v1.14's px4-rc.simulator, jMAVSim branch (PX4_SIM_MODEL=jmavsim_iris): it kills every
# running jMAVSim (`jps`) and starts its own from ./jmavsim_run.sh in lockstep (`-l`), which this
# script's real-time (nolockstep) PX4 cannot serve. The private copy keeps only IMU_INTEG_RATE and
# `simulator_mavlink start -h localhost 4560` (PX4 connects to jMAVSim, the TCP server).
RC_JMAVSIM_START = """	if jps | grep -i jmavsim; then
		kill "$(jps | grep -i jmavsim | awk '{print $1}')" || true
		sleep 1
	fi

	param set IMU_INTEG_RATE 250
	./jmavsim_run.sh -l -r 250 &
"""


def patch_rc_simulator_for_jmavsim(path):
    with open(path) as f:
        text = f.read()
    if RC_JMAVSIM_START not in text:
        sys.exit(f"{path}: not PX4 v1.14's jMAVSim start (this script patches it, see run.py)")
    with open(path, "w") as f:
        f.write(text.replace(RC_JMAVSIM_START, "\tparam set IMU_INTEG_RATE 250\n", 1))


def start_jmavsim(args, workdir, port):
    """jMAVSim (jmavsim_run.jar, built by the user: docs/real-sitl.md, PX4 section) headless, real
    time (no -lockstep), 250 Hz, TCP server on 127.0.0.1:PORT (4560 + PX4's instance) for PX4's
    simulator_mavlink, with
    home at the centre of sitl/maps (PX4_HOME_LAT/LON/ALT, which jMAVSim reads). It runs in the
    jar's folder, which must hold the jar's resources (`ant copy_res`: mavlink/, models/,
    environment/)."""
    jar = os.path.abspath(args.jmavsim_jar)
    here = os.path.dirname(jar)
    schema = os.path.join(here, "mavlink", "message_definitions", "common.xml")
    if not os.path.exists(jar) or not os.path.exists(schema):
        sys.exit(f"{jar}: no jMAVSim jar with its resources ({schema}) beside it")
    if tcp_listening(port):
        sys.exit(f"TCP port {port} is in use (another jMAVSim or simulator?)")
    env = dict(os.environ, PX4_HOME_LAT=f"{HOME_LAT:.7f}", PX4_HOME_LON=f"{HOME_LON:.7f}",
               PX4_HOME_ALT=f"{HOME_ALT_M:.2f}")
    env.pop("PX4_SIM_SPEED_FACTOR", None)
    cmd = ["java", "--add-exports", "java.base/java.lang=ALL-UNNAMED",
           "--add-exports", "java.desktop/sun.awt=ALL-UNNAMED",
           "--add-exports", "java.desktop/sun.java2d=ALL-UNNAMED",
           "-XX:GCTimeRatio=20", "-Djava.ext.dirs=", "-jar", jar,
           "-tcp", f"127.0.0.1:{port}", "-r", "250", "-no-gui"]
    log(f"jMAVSim (in {here}): PX4_HOME_LAT={env['PX4_HOME_LAT']} PX4_HOME_LON="
        f"{env['PX4_HOME_LON']} PX4_HOME_ALT={env['PX4_HOME_ALT']} " + " ".join(cmd))
    out = os.path.join(workdir, "jmavsim.log")
    p = subprocess.Popen(cmd, env=env, cwd=here, stdin=subprocess.DEVNULL, stdout=open(out, "w"),
                         stderr=subprocess.STDOUT, start_new_session=True)
    end = time.time() + 30
    while time.time() < end:
        with open(out) as f:
            text = f.read()
        if p.poll() is not None or "Failed to open MAV port" in text:
            break
        if tcp_listening(port):
            return p
        time.sleep(0.5)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)
    sys.exit(f"jMAVSim did not open TCP {port} (see {out})")


def tcp_listening(port):
    """Something listens on TCP `port` (Linux /proc/net/tcp*, state 0A), without connecting: a
    connection would be jMAVSim's one autopilot link."""
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(name) as f:
                next(f)
                for line in f:
                    v = line.split()
                    if v[3] == "0A" and int(v[1].rsplit(":", 1)[1], 16) == port:
                        return True
        except OSError:
            pass
    return False


def choose_ports(args):
    """PX4's instance N and the GCS / onboard-link / truth ports (module docstring). Returns a
    namespace (instance, gcs, link, truth, jmavsim, held lock file)."""
    net = argparse.Namespace(instance=None, gcs=args.gcs_port, link=args.link_port,
                             truth=args.truth_port, jmavsim=None, held=None)
    if args.attach:
        net.gcs = GCS_PORT if net.gcs is None else net.gcs
        net.truth = TRUTH_PORT if net.truth is None else net.truth
        return net

    def lock(n):
        if sitl_common.px4_instance_running(n):
            return None
        return sitl_common.try_lock(sitl_common.instance_lock_path("px4", n))

    if args.instance is None:
        n, held = sitl_common.choose_instance(sitl_common.px4_ports, range(MAX_INSTANCE + 1),
                                              lock=lock)
        if n is None:
            sys.exit(f"no free PX4 SITL instance in 0-{MAX_INSTANCE}")
    else:
        n = args.instance
        if n > MAX_INSTANCE:
            sys.exit(f"--instance {n}: PX4 shares its onboard port above {MAX_INSTANCE}")
        busy = [f"{proto} {port}" for proto, port in sitl_common.px4_ports(n)
                if not sitl_common.port_free(port, proto)]
        if busy:
            sys.exit(f"instance {n}: ports in use ({', '.join(busy)}); another PX4? "
                     f"(--instance auto picks a free one)")
        held = lock(n)
        if held is None:
            sys.exit(f"instance {n} is used by another PX4 or run.py")
    net.instance, net.held, net.jmavsim = n, held, JMAVSIM_PORT + n
    taken = set()
    # Instance 0 keeps PX4's and this recipe's usual ports when free; another instance never
    # takes instance 0's (its run may start later).
    defaults = (("gcs", GCS_PORT if n == 0 else None), ("link", LINK_PORT + n),
                ("truth", TRUTH_PORT if n == 0 else None))
    for name, default in defaults:
        given = getattr(net, name)
        if given is not None:
            if given in taken or not sitl_common.port_free(given, "udp"):
                sys.exit(f"UDP port {given} (--{name}-port) is in use")
            port = given
        else:
            port = sitl_common.pick_port(default, "udp", taken=taken)
        setattr(net, name, port)
        taken.add(port)
    return net


def start_px4(args, workdir, params, net):
    """PX4 SITL (with SIH, or for the running jMAVSim) as instance net.instance in WORKDIR/px4
    with the parameters in a private copy of `etc`, whose px4-rc.mavlink sends to net.gcs and
    net.link when they are not PX4's defaults."""
    build = os.path.abspath(args.px4_build)
    exe = os.path.join(build, "bin", "px4")
    etc_src = os.path.join(build, "etc")
    if not (os.path.exists(exe) and os.path.isdir(os.path.join(etc_src, "init.d-posix"))):
        sys.exit(f"{build}: not a PX4 SITL build directory (no bin/px4, etc/init.d-posix)")
    etc = os.path.join(workdir, "px4-etc")
    shutil.rmtree(etc, ignore_errors=True)
    shutil.copytree(etc_src, etc, symlinks=True)
    with open(os.path.join(etc, "init.d-posix", "px4-rc.params"), "w") as f:
        f.write("#!/bin/sh\n# Written by sitl/px4/run.py: SIH home and visnav-ev.params.\n")
        for name, value in params:
            f.write(f"param set {name} {value}\n")
        if net.instance:
            # rcS set MAV_SYS_ID = instance + 1 before sourcing this file; visnav.toml expects 1
            # (each instance has its own ports).
            f.write("param set MAV_SYS_ID 1\n")
    if (net.gcs, net.link) != (GCS_PORT, LINK_PORT + net.instance):
        rc = os.path.join(etc, "init.d-posix", "px4-rc.mavlink")
        with open(rc) as f:
            text = f.read()
        try:
            text = sitl_common.px4_rc_mavlink_with_ports(text, net.gcs, net.link)
        except ValueError as e:
            sys.exit(f"{rc}: {e}; run with --instance 0 --gcs-port {GCS_PORT} "
                     f"--link-port {LINK_PORT}")
        with open(rc, "w") as f:
            f.write(text)
    if args.sim == "jmavsim" and net.instance:
        with open(os.path.join(etc, "init.d-posix", "px4-rc.simulator")) as f:
            if "4560+px4_instance" not in f.read().replace(" ", ""):
                sys.exit("this PX4's px4-rc.simulator connects jMAVSim on a fixed port: "
                         "run with --instance 0")
    wd = os.path.join(workdir, "px4")
    os.makedirs(wd, exist_ok=True)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("PX4_HOME_") and k not in ("PX4_SIMULATOR", "PX4_SIM_MODEL")}
    if args.sim == "jmavsim":
        patch_rc_simulator_for_jmavsim(os.path.join(etc, "init.d-posix", "px4-rc.simulator"))
        env.update(PX4_SIM_MODEL="jmavsim_iris")
        shown = "PX4_SIM_MODEL=jmavsim_iris "
    else:
        env.update(PX4_SIMULATOR="sihsim", PX4_SIM_MODEL="sihsim_quadx")
        shown = "PX4_SIMULATOR=sihsim PX4_SIM_MODEL=sihsim_quadx "
    cmd = [exe, "-d", "-i", str(net.instance), "-w", wd, etc]
    log("PX4: " + shown + " ".join(cmd))
    return subprocess.Popen(cmd, env=env, cwd=wd, stdin=subprocess.DEVNULL,
                            stdout=open(os.path.join(workdir, "px4.log"), "w"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def start_visnav(args, workdir, net):
    return sitl_common.start_visnav(args.visnav, args.config, workdir, "px4", net.truth,
                                    args.camera_hz, REPO, log, link_port=net.link,
                                    vo=args.vo, map_ortho=args.map_ortho,
                                    map_tile_m=args.map_tile_m,
                                    map_memory_mb=args.map_memory_mb)


def is_autopilot(m, hb):
    return (hb.get_srcSystem() == m.target_system and hb.get_srcComponent() == 1
            and hb.autopilot != mavutil.mavlink.MAV_AUTOPILOT_INVALID)


def recv(m, typ, timeout, on):
    """The next `typ` message within `timeout` s; every other message goes to `on(msg, t)`."""
    end = time.time() + timeout
    while time.time() < end:
        r = m.recv_match(blocking=True, timeout=max(0.01, end - time.time()))
        if r is None:
            continue
        if r.get_type() == typ:
            return r
        if on is not None:
            on(r, time.time())
    return None


def get_param(m, name, timeout=5.0, on=None):
    """(value as float or int, MAV_PARAM_TYPE) or None. PX4 sends INT32 bytewise in the float."""
    end = time.time() + timeout
    while time.time() < end:
        m.mav.param_request_read_send(m.target_system, m.target_component, name.encode(), -1)
        r = recv(m, "PARAM_VALUE", 1.0, on)
        if r is not None and r.param_id == name:
            if r.param_type == mavutil.mavlink.MAV_PARAM_TYPE_INT32:
                return struct.unpack("<i", struct.pack("<f", r.param_value))[0], r.param_type
            return r.param_value, r.param_type
    return None


def set_param(m, name, value, timeout=5.0, on=None):
    """PARAM_SET with PX4's bytewise encoding of integers; True when echoed with the value."""
    cur = get_param(m, name, on=on)
    if cur is None:
        return False
    ptype = cur[1]
    if ptype == mavutil.mavlink.MAV_PARAM_TYPE_INT32:
        wire = struct.unpack("<f", struct.pack("<i", int(float(value))))[0]
    else:
        wire = float(value)
    end = time.time() + timeout
    while time.time() < end:
        m.mav.param_set_send(m.target_system, m.target_component, name.encode(), wire, ptype)
        r = recv(m, "PARAM_VALUE", 1.0, on)
        if r is not None and r.param_id == name:
            got = get_param(m, name, on=on)
            return got is not None and abs(float(got[0]) - float(value)) < 1e-3
    return False


def inject_gps_off(m, on, timeout=5.0):
    """MAV_CMD_INJECT_FAILURE (FAILURE_UNIT_SENSOR_GPS, FAILURE_TYPE_OFF); True when acknowledged
    as accepted (needs SYS_FAILURE_EN = 1)."""
    cmd = mavutil.mavlink.MAV_CMD_INJECT_FAILURE
    end = time.time() + timeout
    while time.time() < end:
        m.mav.command_long_send(m.target_system, m.target_component, cmd, 0,
                                mavutil.mavlink.FAILURE_UNIT_SENSOR_GPS,
                                mavutil.mavlink.FAILURE_TYPE_OFF, 0, 0, 0, 0, 0)
        # Several modules see the command (simulator_mavlink, battery_simulator): any accepted.
        results = []
        t_end = time.time() + 1.5
        while time.time() < t_end:
            r = recv(m, "COMMAND_ACK", t_end - time.time(), on)
            if r is not None and r.command == cmd:
                results.append(r.result)
        if mavutil.mavlink.MAV_RESULT_ACCEPTED in results:
            return True
        if results:
            log(f"MAV_CMD_INJECT_FAILURE acknowledged with {results}")
            return False
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
    sent = set()
    end = time.time() + 30
    while time.time() < end:
        r = m.recv_match(type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"],
                         blocking=True, timeout=2.0)
        if r is None:
            continue
        if r.get_type() == "MISSION_ACK":
            if r.type == mavutil.mavlink.MAV_MISSION_ACCEPTED and len(sent) == len(items):
                return len(items)
            sys.exit(f"mission upload refused: MISSION_ACK type {r.type}")
        v = items[r.seq]
        m.mav.mission_item_int_send(m.target_system, m.target_component, r.seq, int(v[2]),
                                    int(v[3]), 1 if r.seq == 0 else 0, 1, float(v[4]), float(v[5]),
                                    float(v[6]), float(v[7]), int(round(float(v[8]) * 1e7)),
                                    int(round(float(v[9]) * 1e7)), float(v[10]),
                                    mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
        sent.add(r.seq)
    sys.exit("mission upload timed out")


def jmavsim_truth_alt(r):
    """jMAVSim (66b764a, MAVLinkHILSystem.java) fills HIL_STATE_QUATERNION.alt with its local z
    (NED down, metres from the home ground, in mm) instead of the altitude AMSL, and PX4 passes it
    on unchanged: the truth's altitude AMSL is home altitude - z. Rewrites `r` in place."""
    r.alt = int(round(HOME_ALT_M * 1000.0)) - r.alt


class Truth:
    """Latest HIL_STATE_QUATERNION (PX4's ground truth) with its arrival time."""

    def __init__(self):
        self.s = None  # (t_arrival, lat, lon, alt, vn, ve, vd)

    def on(self, r, t):
        if r.get_type() == "HIL_STATE_QUATERNION":
            self.s = (t, r.lat * 1e-7, r.lon * 1e-7, r.alt * 1e-3, r.vx * 0.01, r.vy * 0.01,
                      r.vz * 0.01)

    def at(self, t):
        """(lat, lon, alt) propagated to arrival time `t`, or None when older than 0.1 s."""
        if self.s is None or t - self.s[0] > 0.1:
            return None
        ts, lat, lon, alt, vn, ve, vd = self.s
        dt = t - ts
        m_lat, m_lon = metres_per_deg(lat)
        return lat + vn * dt / m_lat, lon + ve * dt / m_lon, alt - vd * dt


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--px4-build", help="PX4 SITL build directory (build/px4_sitl_default)")
    g.add_argument("--attach", action="store_true",
                   help="PX4 SITL (SIH, home as above) is already running: parameters are set "
                        "with PARAM_SET")
    ap.add_argument("--sim", choices=["sih", "jmavsim"], default="sih",
                    help="PX4's simulator: SIH (built in, default) or jMAVSim (--jmavsim-jar)")
    ap.add_argument("--jmavsim-jar",
                    help="jMAVSim's jmavsim_run.jar with its resources beside it (not built here: "
                         "docs/real-sitl.md, PX4 section)")
    ap.add_argument("--visnav", help="visnav binary (default: target/release/visnav)")
    ap.add_argument("--config",
                    help="visnav configuration (default: sitl/px4/visnav.toml for SIH, "
                         "sitl/px4/visnav-jmavsim.toml for jMAVSim)")
    ap.add_argument("--no-visnav", action="store_true", help="the GPS-off control run")
    ap.add_argument("--params", default=os.path.join(HERE, "visnav-ev.params"))
    ap.add_argument("--mission", default=os.path.join(HERE, "mission.waypoints"))
    ap.add_argument("--instance", type=sitl_common.instance_arg, default=None, metavar="N|auto",
                    help="PX4 instance (px4 -i N); default auto: the first free one in 0-9")
    ap.add_argument("--gcs-port", type=int, default=None,
                    help="UDP port PX4's GCS link sends to (this script); default 14550 on "
                         "instance 0 if free, else a free port")
    ap.add_argument("--link-port", type=int, default=None,
                    help="UDP port PX4's onboard link sends to (visnav's link); default 14540 + N "
                         "if free, else a free port (with --attach: the configuration's)")
    ap.add_argument("--truth-port", type=int, default=None,
                    help="UDP port the truth is relayed to (visnav sitl-run --truth); default "
                         "14562 on instance 0 if free, else a free port")
    ap.add_argument("--gps-off-wp", type=int, default=1,
                    help="EKF2_GPS_CTRL = 0 when this mission item (0-based, no home item) is "
                         "reached: 1 = the first corner, after the climb")
    ap.add_argument("--gps-off-alt", type=float, default=None,
                    help="instead, at this true height above home, m")
    ap.add_argument("--visnav-from", choices=["armed", "boot"], default="armed",
                    help="start visnav once the copter is armed (default), or with PX4")
    ap.add_argument("--ev-from", choices=["armed", "boot"], default="boot",
                    help="EKF2 fuses visnav from arming (EKF2_EV_CTRL 0 at boot, the file's value "
                         "once armed) or from boot")
    ap.add_argument("--camera-hz", type=float, default=2.0)
    sitl_common.add_visnav_args(ap)
    ap.add_argument("--after-gps-off", type=float, default=None,
                    help="stop this many seconds after the GPS is off (default: last waypoint); "
                         "a run stopped so has not completed its mission: it fails")
    ap.add_argument("--timeout", type=float, default=1500.0, help="flight, s")
    ap.add_argument("--after-mode-change", type=float, default=60.0,
                    help="stop this many seconds after PX4 first leaves MISSION in flight (a "
                         "failsafe's LAND; the verdict fails on it anyway), default %(default)s; "
                         "a negative value: never")
    ap.add_argument("--workdir")
    sitl_common.add_bounds_args(ap)
    args = ap.parse_args()
    bounds = sitl_common.bounds_from_args(args)
    if args.config is None:
        args.config = os.path.join(HERE, "visnav-jmavsim.toml" if args.sim == "jmavsim"
                                   else "visnav.toml")
    if args.sim == "jmavsim" and args.px4_build and not args.jmavsim_jar:
        ap.error("--sim jmavsim needs --jmavsim-jar (or --attach with jMAVSim running)")
    jmavsim = args.sim == "jmavsim"

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

    workdir = os.path.abspath(args.workdir or tempfile.mkdtemp(prefix="visnav-px4-sitl-"))
    os.makedirs(workdir, exist_ok=True)
    log(f"workdir {workdir}")
    params = read_params(args.params)
    if jmavsim:
        # SIH's parameters do not apply; the GPS is switched off by failure injection
        # (gps_off below), which PX4 accepts only with SYS_FAILURE_EN = 1; jMAVSim's GPS is
        # 200 ms late (imu_check.py; EKF2's default delay is 110 ms). jMAVSim's magnetic field
        # is a constant (Simulator.DEFAULT_MAG_FIELD, Zurich's: declination atan2(0.01021,
        # 0.21506) = 2.72 deg) wherever home is, and EKF2 would take the declination of home
        # from its tables (WMM): EKF2's heading was then 1.5-1.8 deg off the truth before
        # take-off and drifted to 2-3 deg off once the GPS was off (flight jm-v1), which visnav
        # follows ([nav] use_autopilot_attitude). EKF2_DECL_TYPE 0: EKF2 uses EKF2_MAG_DECL.
        params = [(n, v) for n, v in params if not n.startswith("SIH_")]
        params += [("SYS_FAILURE_EN", "1"), ("EKF2_GPS_DELAY", "200"),
                   ("EKF2_DECL_TYPE", "0"), ("EKF2_MAG_DECL", f"{JMAVSIM_MAG_DECL_DEG:.2f}")]
    sim_params = [] if jmavsim else sih_params()
    procs = []
    report = {"run": "control (no visnav)" if args.no_visnav else "visnav ODOMETRY",
              "sim": args.sim, "home": [HOME_LAT, HOME_LON, HOME_ALT_M]}
    # What the verdict needs, filled in as the run goes.
    score = ErrorScore("EKF2", log)
    modes, texts = [], []
    error = why = None
    t_fly = t_gps_off = None
    reached, last_seq = -1, None
    t_left = None  # (time, mode) when PX4 first left MISSION in flight
    net = None
    try:
        net = choose_ports(args)
        report.update({"instance": net.instance,
                       "ports": {"gcs_udp": net.gcs, "visnav_link_udp": net.link,
                                 "truth_udp": net.truth, "jmavsim_tcp": net.jmavsim}})
        log(f"PX4 instance {net.instance}: GCS link udp {net.gcs}, visnav link udp "
            f"{'(configuration)' if net.link is None else net.link}, truth udp {net.truth}")
        ev_ctrl = dict(params).get("EKF2_EV_CTRL", "0")
        if args.ev_from == "armed":
            # EKF2 may fuse visnav only once the copter is armed (this alone does not let PX4 arm
            # with visnav running from boot: see --visnav-from).
            params = [(n, "0" if n == "EKF2_EV_CTRL" else v) for n, v in params]
        if args.px4_build:
            if jmavsim:
                procs.append(("jmavsim", start_jmavsim(args, workdir, net.jmavsim)))
            procs.append(("px4", start_px4(args, workdir, sim_params + params, net)))
        if not args.no_visnav and args.visnav_from == "boot":
            procs.append(("visnav", start_visnav(args, workdir, net)))
        host = "0.0.0.0" if args.attach else "127.0.0.1"
        m = mavutil.mavlink_connection(f"udpin:{host}:{net.gcs}", source_system=255)
        relay = mavutil.mavlink_connection(f"udpout:127.0.0.1:{net.truth}", source_system=255)
        hb = None
        end = time.time() + 120
        while hb is None and time.time() < end:
            r = m.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
            if r is not None and r.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4:
                hb = r
        if hb is None:
            sys.exit(f"no PX4 HEARTBEAT on UDP {net.gcs} within 120 s (see px4.log)")
        m.target_system, m.target_component = hb.get_srcSystem(), hb.get_srcComponent()
        log(f"PX4 heartbeat: system {m.target_system}")
        # A GCS heartbeat: PX4 answers to this socket from now on.
        m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID,
                             0, 0, 0)
        todo = (sim_params + params) if args.attach else (
            [] if jmavsim else [("SIH_LOC_H0", f"{HOME_ALT_M:.2f}")]) + [
            ("EKF2_EV_CTRL", None), ("EKF2_GPS_CTRL", None)]
        for name, value in todo:
            if value is None:
                value = dict(params).get(name)
                got = get_param(m, name)
                log(f"parameter {name} = {None if got is None else got[0]} (file: {value})")
                if got is None or value is None or abs(float(got[0]) - float(value)) > 1e-3:
                    sys.exit(f"parameter {name} is not as px4-rc.params set it: see px4.log")
            elif not set_param(m, name, value):
                log(f"parameter {name} not set (absent in this PX4 version?)")
        # 115 HIL_STATE_QUATERNION, 30 ATTITUDE (truth for visnav), 33 GLOBAL_POSITION_INT
        # (EKF2), 230 ESTIMATOR_STATUS.
        rates = {115: 50, 30: 50, 33: 10, 230: 5}

        def ask():
            for msg_id, hz in rates.items():
                m.mav.command_long_send(m.target_system, m.target_component,
                                        mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                        msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
            m.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                 mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

        ask()
        truth = Truth()
        est_flags = [None]

        # Re-encodes a rewritten truth message as PX4's (visnav listens to PX4's system id).
        enc = mavutil.mavlink.MAVLink(None)

        def on(r, now):
            typ = r.get_type()
            if typ in ("HIL_STATE_QUATERNION", "ATTITUDE") and r.get_srcSystem() == m.target_system:
                if jmavsim and typ == "HIL_STATE_QUATERNION":
                    jmavsim_truth_alt(r)
                    enc.srcSystem, enc.srcComponent = r.get_srcSystem(), r.get_srcComponent()
                    enc.seq = r.get_seq()
                    relay.write(r.pack(enc))
                else:
                    relay.write(r.get_msgbuf())
            truth.on(r, now)
            if typ == "STATUSTEXT":
                log(f"STATUSTEXT {r.text}")
                if t_fly is not None:
                    texts.append((round(now - t_fly, 1), r.text))
            elif typ == "ESTIMATOR_STATUS" and r.get_srcSystem() == m.target_system:
                if t_fly is not None:
                    score.status(now - t_fly, r.flags)
                if (r.flags & ~0x40) != est_flags[0]:
                    # Bit 0x40 (terrain height) toggles all the time in SIH: not logged.
                    when = "" if t_gps_off is None else f", {now - t_gps_off:+.1f} s after GPS off"
                    log(f"ESTIMATOR_STATUS flags {r.flags & ~0x40:#06x} (EKF2 "
                        f"{'aiding' if ekf_aiding(r.flags) else 'NOT aiding'}{when})")
                    est_flags[0] = r.flags & ~0x40

        t0 = time.time()
        last_ask = t0
        while True:
            r = m.recv_match(blocking=True, timeout=1.0)
            now = time.time()
            if now - last_ask > 2:
                ask()
                last_ask = now
            if now - t0 > 240:
                sys.exit("no global position within 240 s")
            if r is None:
                continue
            on(r, now)
            if (r.get_type() == "GLOBAL_POSITION_INT" and r.lat != 0 and now - t0 > 30
                    and truth.at(now) is not None):
                break
        n = upload_mission(m, args.mission)
        log(f"mission: {n} items")
        last_seq = n - 1
        # Arm and start until PX4 is armed *in* MISSION mode: PX4 checks an uploaded mission
        # asynchronously, and a start that comes first is denied ("Mission start denied! No valid
        # mission") while the copter stays armed in LOITER (and then disarms): start again.
        armed = in_mission = False
        t_arm = time.time()
        while not (armed and in_mission):
            if time.time() - t_arm > 60:
                sys.exit("could not arm and start the mission within 60 s")
            m.mav.command_long_send(m.target_system, m.target_component,
                                    mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0,
                                    0, 0, 0)
            m.mav.command_long_send(m.target_system, m.target_component,
                                    mavutil.mavlink.MAV_CMD_MISSION_START, 0, 0, last_seq, 0, 0,
                                    0, 0, 0)
            end = time.time() + 3
            while time.time() < end:
                r = m.recv_match(blocking=True, timeout=0.5)
                if r is None:
                    continue
                on(r, time.time())
                if r.get_type() == "HEARTBEAT" and is_autopilot(m, r):
                    armed = bool(r.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    in_mission = mavutil.mode_string_v10(r) == "MISSION"
                    if armed and in_mission:
                        break
        log("armed, mission started")
        if not args.no_visnav and args.visnav_from == "armed":
            # visnav's ODOMETRY velocity wanders by 0.5-3 m/s while the copter stands on the
            # ground; EKF2 computes the vision velocity innovation even while not fusing it and
            # its pre-flight check (0.5 m/s, PreFlightChecker.cpp) then refuses to arm.
            procs.append(("visnav", start_visnav(args, workdir, net)))
        if args.ev_from == "armed" and not args.no_visnav:
            if not set_param(m, "EKF2_EV_CTRL", ev_ctrl, on=on):
                sys.exit(f"cannot set EKF2_EV_CTRL = {ev_ctrl}")
            log(f"EKF2_EV_CTRL = {ev_ctrl}: EKF2 fuses visnav's ODOMETRY from now on")
        in_flight = True
        t_fly = time.time()
        why = "timeout"

        def gps_off(where):
            # SIH: the simulated receiver reports no fix (SIM_GPS_USED < 4: fix_type 0, eph
            # 100 m, PX4 v1.14 sensor_gps_sim), as ArduPilot's SIM_GPS_DISABLE does: GPS_RAW_INT
            # has no fix, so visnav ([daemon] gps = "gps1") stops using it too.
            # jMAVSim: MAV_CMD_INJECT_FAILURE GPS off (simulator_mavlink drops jMAVSim's HIL_GPS:
            # no GPS sample at all, so GPS_RAW_INT stops).
            # Both: EKF2 stops fusing GPS at once (EKF2_GPS_CTRL = 0) rather than after its GPS
            # checks time out.
            if jmavsim:
                if not inject_gps_off(m, on):
                    sys.exit("MAV_CMD_INJECT_FAILURE (GPS off) not accepted")
                what = "MAV_CMD_INJECT_FAILURE GPS off"
            else:
                if not set_param(m, "SIM_GPS_USED", 0, on=on):
                    sys.exit("cannot set SIM_GPS_USED = 0")
                what = "SIM_GPS_USED = 0"
            if not set_param(m, "EKF2_GPS_CTRL", 0, on=on):
                sys.exit("cannot set EKF2_GPS_CTRL = 0")
            log(f"GPS off: {what}, EKF2_GPS_CTRL = 0 ({where})")
            t = time.time()
            score.gps_switched_off(t - t_fly)
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
            if (t_left is not None and args.after_mode_change >= 0
                    and now - t_left[0] > args.after_mode_change):
                # PX4 left its mission (a failsafe's LAND from 1800 m takes about 20 min at
                # 1.5 m/s): the verdict cannot change any more.
                why = f"{args.after_mode_change:.0f} s after leaving MISSION (for {t_left[1]})"
                break
            if now - last_ask > 2:
                ask()
                last_ask = now
            r = m.recv_match(blocking=True, timeout=1.0)
            if r is None:
                continue
            on(r, now)
            typ = r.get_type()
            if typ == "MISSION_ITEM_REACHED":
                if r.seq > reached:
                    log(f"mission item {r.seq} reached")
                reached = max(reached, r.seq)
                if t_gps_off is None and args.gps_off_alt is None and r.seq >= args.gps_off_wp:
                    t_gps_off = gps_off(f"mission item {r.seq}")
                if r.seq >= last_seq:
                    why = "last waypoint reached"
                    break
            elif typ == "HEARTBEAT" and is_autopilot(m, r):
                mode = mavutil.mode_string_v10(r)
                if not modes or modes[-1][1] != mode:
                    modes.append((round(now - t_fly, 1), mode))
                    log(f"mode {mode}")
                if mode != "MISSION" and t_left is None:
                    t_left = (now, mode)
                if not r.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED and now - t_fly > 10:
                    why = "disarmed (landed)"
                    break
            elif typ == "GLOBAL_POSITION_INT":
                tr = truth.at(now)
                if tr is None:
                    continue
                agl = tr[2] - HOME_ALT_M
                if t_gps_off is None and args.gps_off_alt is not None and agl > args.gps_off_alt:
                    t_gps_off = gps_off(f"{agl:.0f} m above home")
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
        # The flight ends now (the scoring's end time), not once the processes have stopped.
        t_end_abs = time.time()
        # PX4 first (its log is complete once it stopped), then the log's injected positions.
        sitl_common.stop_processes(procs)
        integ, note = (None, None) if args.no_visnav or t_fly is None else \
            injected_from_log(args, workdir, bounds)
        code, lines = conclude(args, report, score, modes, texts, error, why, t_fly, t_gps_off,
                               reached, last_seq, bounds, workdir, integ, note, t_end_abs)
        finish_run(procs, workdir, report, log)
        for line in lines:
            print(line, flush=True)
        if net is not None and net.held is not None:
            net.held.close()
    return code


def injected_from_log(args, workdir, bounds):
    """(IntegrityScore of visnav's ODOMETRY as PX4 logged it, None) after a visnav run, or (None,
    why not) (module docstring). Integrity counts as expected whenever PX4's log could be read: a
    log without vehicle_visual_odometry gives an empty score, which fails the verdict."""
    if args.attach:
        return None, INTEGRITY_NOTE.split(",")[0] + " (--attach: PX4's log is not here)"
    try:
        import pyulog  # noqa: F401
    except ImportError:
        return None, INTEGRITY_NOTE.split(",")[0] + " (pyulog is not installed)"
    logs = sorted(glob.glob(os.path.join(workdir, "px4", "log", "*", "*.ulg")), key=os.path.getmtime)
    if not logs:
        return None, INTEGRITY_NOTE.split(",")[0] + " (no PX4 log in WORKDIR/px4/log)"
    if HERE not in sys.path:
        sys.path.insert(0, HERE)
    import ulog_error
    try:
        u, gt, _, t_off = ulog_error.load(logs[-1])
        integ = ulog_error.injected_integrity(u, gt, t_off, bounds.ratio)
    except (Exception, SystemExit) as e:  # a truncated log or a missing topic
        return None, f"{INTEGRITY_NOTE} ({logs[-1]}: {e})"
    if integ is None:
        integ = sitl_common.IntegrityScore(bounds.ratio)
        integ.skip("no vehicle_visual_odometry in PX4's log")
    log(f"injected integrity from {logs[-1]}: {len(integ.samples)} ODOMETRY samples")
    return integ, None


def conclude(args, report, score, modes, texts, error, why, t_fly, t_gps_off, reached, last_seq,
             bounds, workdir, integ=None, integ_note=None, t_end_abs=None):
    """Fill the report (statistics, verdict) and save the samples; returns the exit code and the
    verdict's lines (module docstring). integ: the injected positions' IntegrityScore
    (injected_from_log) or None with integ_note saying why. t_end_abs: when the flight ended
    (time.time(); default now): the aiding and sample-gap scores end there, not after the
    processes were stopped and the log read."""
    label = "control" if args.no_visnav else "visnav"
    if t_fly is None:
        v = {"pass": False, "reasons": [f"run_error: {error or 'did not fly'}"], "notes": [],
             "bounds": bounds.as_dict()}
        report["verdict"] = v
        return 2, sitl_common.verdict_lines(label, v)
    t_end = (time.time() if t_end_abs is None else t_end_abs) - t_fly
    ekf = score.summary(t_end)
    completed = last_seq is not None and reached >= last_seq
    report.update({
        "ended": why if error is None else f"error: {error}",
        "flight_s": round(t_end, 1),
        "gps_off_after_s": None if t_gps_off is None else round(t_gps_off - t_fly, 1),
        "last_mission_item_reached": reached,
        "mission_completed": completed,
        "modes": modes,
        "statustext": texts,
        "ekf2_error": ekf,
        "injected_integrity": None if args.no_visnav else (
            integ.summary() if integ is not None else {"measured": False, "why": integ_note}),
    })
    score.save(workdir)
    if integ is not None:
        integ.save(workdir)
    v = sitl_common.verdict(
        estimator="EKF2", mission_completed=completed,
        mission_detail=f"reached item {reached} of {last_seq} (ended: {report['ended']})",
        modes=modes, allowed_modes={"MISSION"}, texts=texts, ekf=ekf,
        integrity=None if integ is None else integ.summary(), integrity_expected=integ is not None,
        integrity_note=None if args.no_visnav else integ_note,
        error=error, bounds=bounds)
    report["verdict"] = v
    lines = sitl_common.verdict_lines(label, v)
    if error is not None:
        return 2, lines
    run_completed = t_gps_off is not None and not (why or "").startswith("stopped by signal")
    if args.no_visnav:
        lines.append(f"control: the control run {'completed' if run_completed else 'did NOT complete'}"
                     f" (exit {sitl_common.exit_code(v, True, run_completed)}); its verdict is "
                     f"the baseline for the visnav run")
    return sitl_common.exit_code(v, args.no_visnav, run_completed), lines


if __name__ == "__main__":
    sys.exit(main())
