#!/usr/bin/env python3
"""MAVLink interop check for visnav: a pymavlink "autopilot" that decodes everything visnav sends
and checks every field against the expected values written by the Rust test (tests/link_interop.rs).

Usage: fake_autopilot.py EXPECTED.json REPORT.json

The script listens on UDP (expected["port"]), behaves like ArduPilot (HEARTBEAT, answers TIMESYNC,
COMMAND_LONG with COMMAND_ACK, SYSTEM_TIME, GPS_GLOBAL_ORIGIN), signs its own messages and
requires valid signatures when expected["signing_key_hex"] is set, and checks:
  framing (MAVLink 2 magic 0xFD, signed flag), CRC (pymavlink rejects bad CRCs -> BAD_DATA),
  HEARTBEAT type/autopilot/ids, SET_MESSAGE_INTERVAL requests, TIMESYNC requests, and every field of
  GPS_INPUT, VISION_POSITION_ESTIMATE, ODOMETRY, GLOBAL_POSITION_SENSOR and STATUSTEXT with
  units and scaling computed here independently (flat-earth NED, ArduPilot's own local projection
  for the local positions, own quaternion maths).
It prints one line per failed check and a closing 'interop: N passed, M failed' line, writes the
report JSON, and exits 0 only when nothing failed.
"""
import json
import math
import os
import sys
import time

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

GPS_EPOCH_UNIX_S = 315964800
LEAP_S = 18


class Checks:
    def __init__(self):
        self.passed = 0
        self.failed = []

    def ok(self, cond, what):
        if cond:
            self.passed += 1
        else:
            self.failed.append(what)
            print("FAIL:", what, flush=True)
        return cond

    def close(self, got, want, tol, what):
        return self.ok(
            isinstance(got, (int, float)) and math.isfinite(got) and abs(got - want) <= tol,
            f"{what}: got {got!r}, want {want!r} +- {tol}",
        )


def quat_from_euler(roll, pitch, yaw):
    """Hamilton (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def rot_ned_body(roll, pitch, yaw):
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]


def flat_ned(origin, lat, lon, alt):
    """Small-offset NED from geodetic differences with WGS84 radii of curvature."""
    a, e2 = 6378137.0, 6.69437999014e-3
    phi = math.radians(origin["lat_deg"])
    w = math.sqrt(1 - e2 * math.sin(phi) ** 2)
    rn = a / w
    rm = a * (1 - e2) / w**3
    dn = math.radians(lat - origin["lat_deg"]) * (rm + origin["alt_amsl_m"])
    de = math.radians(lon - origin["lon_deg"]) * (rn + origin["alt_amsl_m"]) * math.cos(phi)
    return dn, de, -(alt - origin["alt_amsl_m"])


def ardupilot_ned(origin, lat, lon, alt):
    """NED about the origin as ArduPilot computes it (this fake announces ArduPilot):
    Location::get_distance_NE on integer 1e-7 degrees, LOCATION_SCALING_FACTOR metres per unit
    (a 6378.1 km sphere), the longitude scaled by the cosine of the mean latitude; down is the
    altitude difference."""
    lsf = 0.011131884502145034
    lat0, lon0 = round(origin["lat_deg"] * 1e7), round(origin["lon_deg"] * 1e7)
    lat1, lon1 = round(lat * 1e7), round(lon * 1e7)
    mid = int((lat0 + lat1) / 2)  # C integer division truncates toward zero
    scale = max(math.cos(math.radians(mid * 1e-7)), 0.01)
    dn = (lat1 - lat0) * lsf
    de = (lon1 - lon0) * lsf * scale
    return dn, de, -(alt - origin["alt_amsl_m"])


def lambda_max_2(p):
    a, b, d = p[0][0], p[0][1], p[1][1]
    m = (a + d) / 2
    return m + math.sqrt(((a - d) / 2) ** 2 + b * b)


def main():
    exp = json.load(open(sys.argv[1]))
    report_path = sys.argv[2]
    c = Checks()
    est = exp["estimate"]
    origin = exp["origin"]
    ap_sys, ap_comp = exp["autopilot_system_id"], 1
    conn = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{exp['port']}", source_system=ap_sys, source_component=ap_comp,
        dialect="ardupilotmega", robust_parsing=True,
    )
    key = bytes.fromhex(exp["signing_key_hex"]) if exp.get("signing_key_hex") else None
    if key:
        conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None)
    mav = conn.mav
    t_boot = time.monotonic()

    def boot_us():
        return int((time.monotonic() - t_boot) * 1e6)

    seen = {}
    bad_data = 0
    unsigned = 0
    intervals = {}
    timesync_requests = 0
    statustexts = []
    last_hb = 0.0
    last_st = 0.0
    deadline = time.monotonic() + exp["duration_s"]
    while time.monotonic() < deadline:
        now = time.monotonic()
        if now - last_hb >= 1.0:
            last_hb = now
            try:
                mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_QUADROTOR,
                                   mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3)
            except Exception:
                pass  # no peer yet (udpin learns it from the first packet)
        if now - last_st >= 0.5 and seen:
            last_st = now
            mav.system_time_send(int(time.time() * 1e6), boot_us() // 1000)
        m = conn.recv_msg()
        if m is None:
            time.sleep(0.002)
            continue
        t = m.get_type()
        if t == "BAD_DATA":
            bad_data += 1
            print("BAD_DATA:", m, flush=True)
            continue
        if m.get_srcSystem() == ap_sys and m.get_srcComponent() == ap_comp:
            continue  # our own echo cannot happen on UDP, but be safe
        buf = m.get_msgbuf()
        c.ok(buf[0] == 0xFD, f"{t}: MAVLink 2 framing (magic 0x{buf[0]:02X})")
        if key:
            signed = bool(buf[2] & 0x01) and m._signed
            if not signed:
                unsigned += 1
            c.ok(signed, f"{t}: signed with the shared key")
        c.ok(m.get_srcSystem() == exp["our_system_id"], f"{t}: source system {m.get_srcSystem()}")
        c.ok(m.get_srcComponent() == exp["our_component_id"], f"{t}: source component {m.get_srcComponent()}")
        seen.setdefault(t, []).append(m)

        if t == "HEARTBEAT":
            c.ok(m.type == mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER, f"HEARTBEAT.type {m.type}")
            c.ok(m.autopilot == mavutil.mavlink.MAV_AUTOPILOT_INVALID, f"HEARTBEAT.autopilot {m.autopilot}")
            c.ok(m.mavlink_version == 3, "HEARTBEAT.mavlink_version")
        elif t == "TIMESYNC":
            timesync_requests += 1
            c.ok(m.tc1 == 0 and m.ts1 > 0, f"TIMESYNC request tc1={m.tc1} ts1={m.ts1}")
            mav.timesync_send(boot_us() * 1000, m.ts1)
        elif t == "COMMAND_LONG":
            c.ok(m.target_system == ap_sys and m.target_component == ap_comp, "COMMAND_LONG target")
            if m.command == mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                intervals[int(m.param1)] = m.param2
            if m.command == mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE and int(m.param1) == 49:
                mav.gps_global_origin_send(round(origin["lat_deg"] * 1e7), round(origin["lon_deg"] * 1e7),
                                           round(origin["alt_amsl_m"] * 1000), boot_us())
            mav.command_ack_send(m.command, 0, 0, 0, m.get_srcSystem(), m.get_srcComponent())
        elif t == "STATUSTEXT":
            statustexts.append(m.text)
        elif t == "GPS_INPUT":
            check_gps_input(c, m, est, exp)
        elif t == "VISION_POSITION_ESTIMATE":
            check_vpe(c, m, est, origin)
        elif t == "ODOMETRY":
            check_odometry(c, m, est, origin)
        elif t == "GLOBAL_POSITION_SENSOR":
            check_gps_sensor(c, m, est, exp)

    # Whole-session checks.
    c.ok(bad_data == 0, f"{bad_data} undecodable packets (CRC/length/signature)")
    for needed in ["HEARTBEAT", "TIMESYNC", "COMMAND_LONG", "STATUSTEXT"] + exp["injected"]:
        c.ok(needed in seen, f"{needed} received")
    for mid, hz in exp["streams"].items():
        got = intervals.get(int(mid))
        c.ok(got is not None and abs(got - 1e6 / hz) < 1.0,
             f"SET_MESSAGE_INTERVAL for message {mid}: got {got} us, want {1e6 / hz}")
    c.ok(any(s.startswith("visnav:") for s in statustexts), f"STATUSTEXT from visnav: {statustexts}")
    report = {
        "passed": c.passed,
        "failed": c.failed,
        "counts": {k: len(v) for k, v in seen.items()},
        "statustexts": statustexts,
        "bad_data": bad_data,
        "unsigned": unsigned,
        "timesync_requests": timesync_requests,
    }
    json.dump(report, open(report_path, "w"), indent=1)
    print(f"interop: {c.passed} passed, {len(c.failed)} failed", flush=True)
    sys.exit(0 if not c.failed else 1)


def check_gps_input(c, m, est, exp):
    c.ok(m.gps_id == exp["gps_id"], f"GPS_INPUT.gps_id {m.gps_id}")
    c.ok(m.fix_type == 3, f"GPS_INPUT.fix_type {m.fix_type}")
    c.ok(m.ignore_flags == 0, f"GPS_INPUT.ignore_flags {m.ignore_flags}")
    c.ok(m.satellites_visible == exp["gps_satellites"], f"GPS_INPUT.satellites_visible {m.satellites_visible}")
    # GPS time from the UNIX time_usec: week and time of week in ms with 18 leap seconds.
    gps_us = m.time_usec - GPS_EPOCH_UNIX_S * 1_000_000 + LEAP_S * 1_000_000
    c.ok(m.time_week == gps_us // (604800 * 10**6), f"GPS_INPUT.time_week {m.time_week}")
    c.ok(m.time_week_ms == (gps_us % (604800 * 10**6)) // 1000, f"GPS_INPUT.time_week_ms {m.time_week_ms}")
    c.close(m.time_usec / 1e6, time.time(), 2.0, "GPS_INPUT.time_usec vs wall clock (s)")
    # Propagated to send time by at most max_age_s: allow |v| * max_age.
    speed = math.sqrt(sum(v * v for v in est["vel_ned_m_s"]))
    tol_m = speed * exp["max_age_s"] + 0.05
    dn, de, dd = flat_ned(est, m.lat * 1e-7, m.lon * 1e-7, m.alt)
    c.ok(math.hypot(dn, de) <= tol_m, f"GPS_INPUT lat/lon within {tol_m} m of the estimate ({dn:.3f}, {de:.3f})")
    c.ok(abs(dd) <= abs(est["vel_ned_m_s"][2]) * exp["max_age_s"] + 0.01, f"GPS_INPUT.alt {m.alt}")
    for f, v in zip(["vn", "ve", "vd"], est["vel_ned_m_s"]):
        c.close(getattr(m, f), v, 1e-5, f"GPS_INPUT.{f}")
    p = est["pos_cov_ned_m2"]
    h0 = math.sqrt(lambda_max_2(p))
    vvar = max(est["vel_cov_ned_m2_s2"][i][i] for i in range(3))
    h1 = math.sqrt(lambda_max_2(p) + vvar * exp["max_age_s"] ** 2)
    c.ok(h0 - 1e-4 <= m.horiz_accuracy <= h1 + 1e-4, f"GPS_INPUT.horiz_accuracy {m.horiz_accuracy} in [{h0}, {h1}]")
    c.ok(math.sqrt(p[2][2]) - 1e-4 <= m.vert_accuracy <= math.sqrt(p[2][2] + vvar * exp["max_age_s"] ** 2) + 1e-4,
         f"GPS_INPUT.vert_accuracy {m.vert_accuracy}")
    c.close(m.speed_accuracy, math.sqrt(vvar), 1e-4, "GPS_INPUT.speed_accuracy")
    c.close(m.hdop, m.horiz_accuracy / exp["dop_uere_m"], 1e-3, "GPS_INPUT.hdop")
    c.close(m.vdop, m.vert_accuracy / exp["dop_uere_m"], 1e-3, "GPS_INPUT.vdop")
    yaw_cd = round((math.degrees(est["rpy_rad"][2]) % 360.0) * 100) or 36000
    c.ok(m.yaw == yaw_cd, f"GPS_INPUT.yaw {m.yaw} cdeg, want {yaw_cd}")


def cov_checks(c, name, cov, p3, att_sigma):
    # Row-major upper triangle of the 6x6 (x, y, z, roll, pitch, yaw).
    c.close(cov[0], p3[0][0], 1e-4, f"{name} cov[0] (xx)")
    c.close(cov[1], p3[0][1], 1e-4, f"{name} cov[1] (xy)")
    c.close(cov[6], p3[1][1], 1e-4, f"{name} cov[6] (yy)")
    c.close(cov[11], p3[2][2], 1e-4, f"{name} cov[11] (zz)")
    c.close(cov[15], att_sigma[0] ** 2, 1e-7, f"{name} cov[15] (roll)")
    c.close(cov[18], att_sigma[1] ** 2, 1e-7, f"{name} cov[18] (pitch)")
    c.close(cov[20], att_sigma[2] ** 2, 1e-7, f"{name} cov[20] (yaw)")


def check_vpe(c, m, est, origin):
    n, e, d = ardupilot_ned(origin, est["lat_deg"], est["lon_deg"], est["alt_amsl_m"])
    # 1e-7 degrees is 1.1 cm; the message's f32 keeps 1e-5 m at these distances.
    c.close(m.x, n, 0.03, "VISION_POSITION_ESTIMATE.x (north m)")
    c.close(m.y, e, 0.03, "VISION_POSITION_ESTIMATE.y (east m)")
    c.close(m.z, d, 0.05, "VISION_POSITION_ESTIMATE.z (down m)")
    for f, v in zip(["roll", "pitch", "yaw"], est["rpy_rad"]):
        c.close(getattr(m, f), v, 1e-5, f"VISION_POSITION_ESTIMATE.{f}")
    cov_checks(c, "VISION_POSITION_ESTIMATE", m.covariance, est["pos_cov_ned_m2"], est["att_sigma_rad"])
    c.ok(m.reset_counter == est["reset_counter"], f"VISION_POSITION_ESTIMATE.reset_counter {m.reset_counter}")
    c.ok(m.usec > 0, "VISION_POSITION_ESTIMATE.usec set")


def check_odometry(c, m, est, origin):
    c.ok(m.frame_id == mavutil.mavlink.MAV_FRAME_LOCAL_FRD, f"ODOMETRY.frame_id {m.frame_id}")
    c.ok(m.child_frame_id == mavutil.mavlink.MAV_FRAME_BODY_FRD, f"ODOMETRY.child_frame_id {m.child_frame_id}")
    c.ok(m.estimator_type == mavutil.mavlink.MAV_ESTIMATOR_TYPE_VIO, f"ODOMETRY.estimator_type {m.estimator_type}")
    c.ok(m.quality == 100, f"ODOMETRY.quality {m.quality}")
    c.ok(m.reset_counter == est["reset_counter"], f"ODOMETRY.reset_counter {m.reset_counter}")
    n, e, d = ardupilot_ned(origin, est["lat_deg"], est["lon_deg"], est["alt_amsl_m"])
    c.close(m.x, n, 0.03, "ODOMETRY.x")
    c.close(m.y, e, 0.03, "ODOMETRY.y")
    c.close(m.z, d, 0.05, "ODOMETRY.z")
    q = quat_from_euler(*est["rpy_rad"])
    sign = 1 if sum(a * b for a, b in zip(q, m.q)) >= 0 else -1
    for i in range(4):
        c.close(m.q[i], sign * q[i], 1e-5, f"ODOMETRY.q[{i}] (w, x, y, z)")
    r = rot_ned_body(*est["rpy_rad"])
    v = est["vel_ned_m_s"]
    vb = [sum(r[j][i] * v[j] for j in range(3)) for i in range(3)]  # R^T v
    for f, want in zip(["vx", "vy", "vz"], vb):
        c.close(getattr(m, f), want, 1e-4, f"ODOMETRY.{f} (body FRD)")
    for f in ["rollspeed", "pitchspeed", "yawspeed"]:
        c.ok(math.isfinite(getattr(m, f)), f"ODOMETRY.{f} finite")
    cov_checks(c, "ODOMETRY pose", m.pose_covariance, est["pos_cov_ned_m2"], est["att_sigma_rad"])
    c.ok(all(math.isfinite(x) for x in m.velocity_covariance), "ODOMETRY.velocity_covariance finite")


def check_gps_sensor(c, m, est, exp):
    c.ok(m.lat == round(est["lat_deg"] * 1e7), f"GLOBAL_POSITION_SENSOR.lat {m.lat}")
    c.ok(m.lon == round(est["lon_deg"] * 1e7), f"GLOBAL_POSITION_SENSOR.lon {m.lon}")
    c.close(m.alt, est["alt_amsl_m"], 1e-3, "GLOBAL_POSITION_SENSOR.alt (AMSL m)")
    c.close(m.alt_ellipsoid, est["alt_amsl_m"] + est["geoid_undulation_m"], 1e-3, "GLOBAL_POSITION_SENSOR.alt_ellipsoid")
    c.close(m.eph, math.sqrt(lambda_max_2(est["pos_cov_ned_m2"])), 1e-4, "GLOBAL_POSITION_SENSOR.eph")
    c.close(m.epv, math.sqrt(est["pos_cov_ned_m2"][2][2]), 1e-4, "GLOBAL_POSITION_SENSOR.epv")
    c.ok(m.source == 2, f"GLOBAL_POSITION_SENSOR.source {m.source} (VISION)")
    c.ok(m.flags == 0, f"GLOBAL_POSITION_SENSOR.flags {m.flags}")
    c.ok(m.target_system == exp["autopilot_system_id"], "GLOBAL_POSITION_SENSOR.target_system")
    c.ok(0 <= m.processing_time <= exp["max_age_s"] * 1e6, f"GLOBAL_POSITION_SENSOR.processing_time {m.processing_time}")


if __name__ == "__main__":
    main()
