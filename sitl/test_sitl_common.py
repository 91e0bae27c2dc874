"""Unit tests of the real-SITL scoring and verdict layer (sitl/sitl_common.py), standard library
only (no pymavlink, no autopilot):

    python3 -m unittest discover -s sitl -p 'test_*.py'      # from the repository root

tests/sitl_scripts.rs runs them under `cargo test`.
"""

import argparse
import math
import os
import socket
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import sitl_common as sc  # noqa: E402

HOME = (sc.HOME_LAT, sc.HOME_LON)
AIDING = sc.EKF_POS_HORIZ_ABS | 0x200 | 0x1 | 0x2 | 0x4 | 0x8 | 0x20  # 0x23f: all good
STOPPED = sc.EKF_CONST_POS_MODE | 0x1 | 0x4 | 0x20                   # EKF3 after "stopped aiding"


def offset(lat, lon, north_m, east_m):
    m_lat, m_lon = sc.metres_per_deg(lat)
    return lat + north_m / m_lat, lon + east_m / m_lon


def quiet(_msg):
    pass


class Flight:
    """A synthetic flight at 10 Hz: the copter flies east at 15 m/s, 1800 m up; the GPS goes off
    at t_off. `est(t)` gives the estimator's (north, east) error in metres at t, `flags(t)` its
    status flags (reported at 2 Hz), `frozen_after`: from then on the estimator reports its last
    position (EKF3's constant position mode) while the copter descends almost in place."""

    def __init__(self, t_off=100.0, t_end=300.0, est=lambda t: (1.0, 0.5),
                 flags=lambda t: AIDING, frozen_after=None, drop=lambda t: False):
        self.score = sc.ErrorScore("EKF3", quiet)
        self.t_end = t_end
        frozen = None
        for i in range(int(t_end * 10)):
            t = i / 10.0
            if i % 5 == 0:
                self.score.status(t, flags(t))
            if t >= t_off and i == int(t_off * 10):
                self.score.gps_switched_off(t)
            if frozen_after is not None and t >= frozen_after:
                # LAND: the copter barely moves; the EKF's position stays where it stopped.
                east = 15.0 * frozen_after + 0.02 * (t - frozen_after)
            else:
                east = 15.0 * t
            lat_t, lon_t = offset(*HOME, 0.0, east)
            alt_t = sc.HOME_ALT_M + min(1800.0, 10.0 + 8.0 * t)
            if frozen_after is not None and t >= frozen_after:
                if frozen is None:
                    frozen = offset(lat_t, lon_t, *est(t))
                lat, lon = frozen
            else:
                lat, lon = offset(lat_t, lon_t, *est(t))
            if drop(t):
                continue
            self.score.add(t, t >= t_off, lat, lon, alt_t + 2.0, lat_t, lon_t, alt_t)
        self.summary = self.score.summary(t_end)


def good_verdict(**over):
    f = Flight()
    integ = sc.IntegrityScore()
    for i in range(200):
        lat_t, lon_t = offset(*HOME, 10.0 * i, 0.0)
        lat, lon = offset(lat_t, lon_t, 3.0, -4.0)  # 5 m off, claimed 4 m: ratio 1.25
        integ.add(i * 0.2, "gps_off", lat, lon, 4.0, lat_t, lon_t)
    facts = dict(estimator="EKF3", mission_completed=True, mission_detail="item 7 of 7",
                 modes=[(0.0, "AUTO")], allowed_modes={"AUTO"},
                 texts=[(0.5, "Mission: 1 Takeoff"), (120.0, "Reached command #7")],
                 ekf=f.summary, integrity=integ.summary(), integrity_expected=True)
    facts.update(over)
    return sc.verdict(**facts)


def reason_names(v):
    return [r.split(":", 1)[0] for r in v["reasons"]]


class Basics(unittest.TestCase):
    def test_metres_per_degree_at_home(self):
        m_lat, m_lon = sc.metres_per_deg(sc.HOME_LAT)
        self.assertAlmostEqual(m_lat, 111195, delta=30)
        self.assertAlmostEqual(m_lon, 111412.84 * math.cos(math.radians(sc.HOME_LAT)), delta=100)

    def test_stats_nearest_rank(self):
        s = sc.stats([float(i) for i in range(1, 11)])
        self.assertEqual(s, {"n": 10, "median_m": 5.5, "p90_m": 9.0, "max_m": 10.0})
        self.assertIsNone(sc.stats([]))

    def test_aiding_flags(self):
        self.assertTrue(sc.ekf_aiding(AIDING))
        self.assertFalse(sc.ekf_aiding(STOPPED))
        # Horizontal absolute position but constant position mode or uninitialised: not aiding.
        self.assertFalse(sc.ekf_aiding(AIDING | sc.EKF_CONST_POS_MODE))
        self.assertFalse(sc.ekf_aiding(AIDING | sc.EKF_UNINITIALIZED))
        self.assertFalse(sc.ekf_aiding(AIDING & ~sc.EKF_POS_HORIZ_ABS))
        # PX4's ESTIMATOR_STATUS uses the same bits (0x80 alone: constant position mode).
        self.assertFalse(sc.ekf_aiding(0x80))


class AutopilotProjections(unittest.TestCase):
    """The autopilots' local frames, against numbers their own formulas give by hand."""

    def test_ardupilot(self):
        # 0.01 deg on ArduPilot's 6378.1 km sphere is 1113.188 m (LOCATION_SCALING_FACTOR 1e5);
        # east at 60 deg scales by the cosine of the mean latitude (0.5 here).
        lat, lon = sc.ardupilot_from_ned(60.0, 10.0, 1113.1884502145034, 0.0)
        self.assertAlmostEqual(lat, 60.01, places=10)
        self.assertEqual(lon, 10.0)
        lat, lon = sc.ardupilot_from_ned(60.0, 10.0, 0.0, 556.5942251072517)
        self.assertEqual(lat, 60.0)
        self.assertAlmostEqual(lon, 10.01, places=10)

    def test_px4(self):
        # PX4's 6371 km sphere: 1111.949 m along a meridian is 0.01 deg; the origin maps to itself.
        lat, lon = sc.px4_from_ned(-35.0, 149.0, 1111.9492664455872, 0.0)
        self.assertAlmostEqual(lat, -34.99, places=10)
        self.assertAlmostEqual(lon, 149.0, places=12)
        self.assertEqual(sc.px4_from_ned(-35.0, 149.0, 0.0, 0.0), (-35.0, 149.0))
        # 1 km east at the equator: a great circle along it, 1000 / R radians.
        lat, lon = sc.px4_from_ned(0.0, 0.0, 0.0, 1000.0)
        self.assertAlmostEqual(lat, 0.0, places=12)
        self.assertAlmostEqual(lon, math.degrees(1000.0 / sc.PX4_EARTH_RADIUS_M), places=12)

    def test_they_differ_from_the_ellipsoid(self):
        # At 47 deg 1 km north is 0.13 % shorter on ArduPilot's sphere than on WGS84, as the
        # projection's scale: read back, it lands 1.3 m short of the ellipsoid's kilometre.
        m_lat, _ = sc.metres_per_deg(47.0)
        lat, _ = sc.ardupilot_from_ned(47.0, 0.0, 1000.0, 0.0)
        self.assertAlmostEqual((lat - 47.0) * m_lat, 998.7, delta=0.1)


class Aiding(unittest.TestCase):
    def test_tracker_periods(self):
        a = sc.AidingTracker(max_age_s=2.0)
        self.assertIsNone(a.aiding_at(0.0))
        a.status(0.0, AIDING)
        a.gps_off(1.0)
        a.status(1.5, AIDING)
        a.status(2.0, STOPPED)        # loses it at +1 s
        a.status(2.5, STOPPED)
        a.status(5.0, AIDING)         # back at +4 s
        a.status(5.5, AIDING)
        # Reports stop: stale 2 s after the last one (7.5), open until the end.
        s = a.summary(10.0)
        self.assertEqual(s["first_loss_after_gps_off_s"], 1.0)
        self.assertEqual(s["periods_after_gps_off_s"], [[1.0, 4.0], [6.5, 9.0]])
        self.assertAlmostEqual(s["total_s"], 5.5)
        self.assertFalse(s["aiding_at_end"])

    def test_no_loss(self):
        a = sc.AidingTracker()
        for i in range(20):
            a.status(i * 0.5, AIDING)
            if i == 4:
                a.gps_off(2.0)
        s = a.summary(9.6)
        self.assertEqual(s["total_s"], 0)
        self.assertIsNone(s["first_loss_after_gps_off_s"])
        self.assertTrue(s["aiding_at_end"])

    def test_never_off(self):
        a = sc.AidingTracker()
        a.status(0.0, STOPPED)
        self.assertIsNone(a.summary(10.0))

    def test_not_aiding_when_gps_goes_off(self):
        a = sc.AidingTracker()
        a.status(0.0, STOPPED)
        a.gps_off(1.0)
        a.status(3.0, AIDING)
        self.assertEqual(a.summary(4.0)["periods_after_gps_off_s"], [[0.0, 2.0]])


class Scoring(unittest.TestCase):
    def test_good_flight(self):
        f = Flight()
        s = f.summary
        off = s["gps_off"]["horizontal"]
        self.assertAlmostEqual(off["max_m"], math.hypot(1.0, 0.5), places=1)
        self.assertEqual(s["gps_off_aiding"]["horizontal"]["n"], off["n"])
        self.assertIsNone(s["gps_off_not_aiding"]["horizontal"])
        self.assertEqual(s["not_aiding"]["total_s"], 0)
        self.assertLess(s["gps_off_max_sample_gap_s"], 0.2)
        self.assertAlmostEqual(s["gps_off"]["vertical"]["median_m"], 2.0, places=1)
        # samples.json rows carry the aiding flag.
        row = f.score.samples[-1]
        self.assertEqual(row[1], "gps_off")
        self.assertIs(row[6], True)

    def test_ground_not_scored(self):
        score = sc.ErrorScore("EKF3", quiet)
        score.add(0.0, False, *HOME, sc.HOME_ALT_M, *HOME, sc.HOME_ALT_M + 1.0)
        self.assertIsNone(score.summary()["gps_on"]["horizontal"])
        self.assertEqual(len(score.samples), 1)
        self.assertIsNone(score.samples[0][6])  # no status yet

    def test_frozen_position_after_aiding_stops_is_not_accuracy(self):
        # The control run: GPS off at 100 s, EKF3 drifts to 10 m and stops aiding at
        # +15 s; its position is frozen there while the copter descends in place (LAND). The
        # frozen samples' small error (~10 m) must not count as the aiding accuracy.
        def est(t):
            return (0.0, min(10.0, 0.7 * max(0.0, t - 100.0)))

        f = Flight(est=est, flags=lambda t: AIDING if t < 115.0 else STOPPED, frozen_after=115.0)
        s = f.summary
        aiding = s["gps_off_aiding"]["horizontal"]
        stale = s["gps_off_not_aiding"]["horizontal"]
        self.assertEqual(aiding["n"], 150)          # only the 15 s while it aided
        self.assertGreater(stale["n"], 1800)        # the frozen rest
        self.assertEqual(s["gps_off"]["horizontal"]["n"], aiding["n"] + stale["n"])
        na = s["not_aiding"]
        self.assertEqual(na["first_loss_after_gps_off_s"], 15.0)
        self.assertAlmostEqual(na["total_s"], 185.0, delta=0.01)
        # Every frozen sample is marked not aiding in samples.json.
        frozen_rows = [r for r in f.score.samples if r[0] >= 115.0]
        self.assertTrue(all(r[6] is False for r in frozen_rows))
        # The verdict fails on it even though the error stays within the bounds.
        self.assertLess(s["gps_off"]["horizontal"]["max_m"], 25.0)
        v = sc.verdict(estimator="EKF3", mission_completed=True, mission_detail="",
                       modes=[(0.0, "AUTO")], allowed_modes={"AUTO"}, texts=[], ekf=s)
        self.assertFalse(v["pass"])
        self.assertEqual(reason_names(v), ["not_aiding"])
        self.assertIn("first at +15.0 s", v["reasons"][0])

    def test_stale_status_counts_as_not_aiding(self):
        # Status reports stop at 150 s (estimator silent): not aiding from 152 s (2 s max age).
        score = sc.ErrorScore("EKF3", quiet)
        for i in range(3000):
            t = i / 10.0
            if i % 5 == 0 and t < 150.0:
                score.status(t, AIDING)
            if i == 1000:
                score.gps_switched_off(t)
        na = score.summary(300.0)["not_aiding"]
        self.assertEqual(na["periods_after_gps_off_s"], [[51.5, 200.0]])

    def test_sample_gap(self):
        # PX4 stops GLOBAL_POSITION_INT when its position is invalid: a 30 s hole after GPS off.
        f = Flight(drop=lambda t: 150.0 <= t < 180.0)
        self.assertAlmostEqual(f.summary["gps_off_max_sample_gap_s"], 30.1, places=1)
        v = good_verdict(ekf=f.summary)
        self.assertEqual(reason_names(v), ["sample_gap"])

    def test_gap_at_the_end_counts(self):
        f = Flight(drop=lambda t: t >= 290.0)
        self.assertAlmostEqual(f.summary["gps_off_max_sample_gap_s"], 10.1, places=1)


class Integrity(unittest.TestCase):
    def test_ratio(self):
        g = sc.IntegrityScore()
        lat_t, lon_t = HOME
        for i, (err, acc) in enumerate([(3.0, 3.0), (6.0, 3.0), (10.0, 3.0), (5.0, 0.0)]):
            lat, lon = offset(lat_t, lon_t, 0.0, err)
            g.add(float(i), "gps_off", lat, lon, acc, lat_t, lon_t)
        g.skip("no_fix")
        s = g.summary()
        self.assertEqual(s["n"], 4)
        self.assertEqual(s["no_accuracy"], 1)
        self.assertAlmostEqual(s["ratio_max"], 10.0 / 3.0, places=2)
        self.assertEqual(s["over_limit"], 1)
        self.assertEqual(s["skipped"], {"no_fix": 1})
        self.assertEqual(s["h_acc"]["max_m"], 3.0)
        self.assertEqual(s["gps_off"]["n"], 4)


class Timing(unittest.TestCase):
    def test_truth_history_interpolates(self):
        h = sc.TruthHistory()
        for i in range(100):
            t = i * 0.02
            h.add(t, 47.0 + t * 1e-4, -99.0, 1000.0 + t)
        lat, lon, alt = h.at(1.011)
        self.assertAlmostEqual(lat, 47.0 + 1.011e-4, places=9)
        self.assertAlmostEqual(alt, 1001.011, places=6)
        self.assertIsNone(h.at(5.0))
        self.assertIsNone(h.at(-1.0))
        self.assertEqual(h.at(1.98 + 0.1)[2], 1001.98)  # nearest within max gap at the end

    def test_truth_history_gap(self):
        h = sc.TruthHistory(max_gap_s=0.2)
        h.add(0.0, 1.0, 1.0, 1.0)
        h.add(1.0, 2.0, 2.0, 2.0)
        self.assertIsNone(h.at(0.5))

    def test_boot_clock_uses_least_delay(self):
        c = sc.BootClock()
        self.assertIsNone(c.local(1.0))
        for i, delay in enumerate([0.030, 0.005, 0.050, 0.012]):
            boot_ms = 1000 + 100 * i
            c.on(boot_ms, 500.0 + boot_ms * 1e-3 + delay)
        self.assertAlmostEqual(c.local(2.0), 502.005, places=6)


class Verdict(unittest.TestCase):
    def test_passes_a_good_flight(self):
        v = good_verdict()
        self.assertTrue(v["pass"], v["reasons"])
        self.assertEqual(v["reasons"], [])
        self.assertEqual(v["bounds"]["gps_off_p90_m"], 25.0)
        self.assertEqual(sc.verdict_lines("visnav", v), ["visnav: PASS"])

    def test_fails_on_land_mode(self):
        v = good_verdict(modes=[(0.0, "AUTO"), (317.2, "LAND")])
        self.assertEqual(reason_names(v), ["mode_change"])
        self.assertIn("LAND at +317.2 s", v["reasons"][0])

    def test_fails_on_failsafe_text(self):
        for text in ("EKF Failsafe: changed to LAND Mode", "EKF variance",
                     "GPS Glitch or Compass error", "Failsafe activated"):
            v = good_verdict(texts=[(10.0, "Mission: 2 WP"), (317.0, text)])
            self.assertEqual(reason_names(v), ["failsafe"], text)

    def test_fails_when_mission_not_completed(self):
        v = good_verdict(mission_completed=False, mission_detail="reached item 3 of 7")
        self.assertEqual(reason_names(v), ["mission_not_completed"])
        self.assertIn("3 of 7", v["reasons"][0])

    def test_fails_on_p90(self):
        # 20 % of the GPS-off samples 30 m off: p90 over 25 m, max under 50 m.
        f = Flight(est=lambda t: (30.0, 0.0) if t >= 260.0 else (1.0, 0.0))
        v = good_verdict(ekf=f.summary)
        self.assertEqual(reason_names(v), ["gps_off_error_p90"])

    def test_fails_on_max(self):
        f = Flight(est=lambda t: (60.0, 0.0) if 200.0 <= t < 201.0 else (1.0, 0.0))
        v = good_verdict(ekf=f.summary)
        self.assertEqual(reason_names(v), ["gps_off_error_max"])

    def test_fails_on_integrity_ratio(self):
        g = sc.IntegrityScore()
        lat, lon = offset(*HOME, 0.0, 13.0)
        g.add(1.0, "gps_off", lat, lon, 4.0, *HOME)  # 13 m off, claimed 4 m: 3.25
        v = good_verdict(integrity=g.summary())
        self.assertEqual(reason_names(v), ["integrity_ratio"])
        self.assertIn("3.25 x", v["reasons"][0])

    def test_integrity_not_measured(self):
        v = good_verdict(integrity=None)
        self.assertEqual(reason_names(v), ["integrity_not_measured"])
        # PX4 (no echo): a note, not a failure.
        v = good_verdict(integrity=None, integrity_expected=False,
                         integrity_note="not measured on PX4")
        self.assertTrue(v["pass"])
        self.assertEqual(v["notes"], ["not measured on PX4"])

    def test_gps_never_off(self):
        score = sc.ErrorScore("EKF3", quiet)
        score.status(0.0, AIDING)
        lat_t, lon_t = HOME
        score.add(1.0, False, lat_t, lon_t, 2000.0, lat_t, lon_t, 2000.0)
        v = good_verdict(ekf=score.summary(10.0))
        self.assertEqual(reason_names(v), ["gps_not_off"])

    def test_run_error(self):
        v = good_verdict(error="cannot switch the simulated GPS off")
        self.assertEqual(reason_names(v), ["run_error"])

    def test_control_run_fails_honestly(self):
        # The control: EKF failsafe (LAND) 8 s after GPS off, stopped aiding at +15 s,
        # frozen position, the mission abandoned. Every reason shows; its exit code is 0 (the
        # control run itself completed) while a visnav run with this verdict exits 1.
        f = Flight(est=lambda t: (0.0, min(10.0, 0.7 * max(0.0, t - 100.0))),
                   flags=lambda t: AIDING if t < 115.0 else STOPPED, frozen_after=115.0)
        v = sc.verdict(estimator="EKF3", mission_completed=False,
                       mission_detail="reached item 2 of 7 (ended: disarmed (landed))",
                       modes=[(0.0, "AUTO"), (108.0, "LAND")], allowed_modes={"AUTO"},
                       texts=[(108.0, "EKF variance"),
                              (108.0, "EKF Failsafe: changed to LAND Mode"),
                              (115.0, "EKF3 IMU0 stopped aiding")],
                       ekf=f.summary)
        self.assertEqual(reason_names(v), ["mission_not_completed", "mode_change", "failsafe",
                                           "not_aiding"])
        lines = sc.verdict_lines("control", v)
        self.assertEqual(lines[0], "control: FAIL")
        self.assertEqual(len(lines), 5)
        self.assertEqual(sc.exit_code(v, control=True, run_completed=True), 0)
        self.assertEqual(sc.exit_code(v, control=True, run_completed=False), 1)
        self.assertEqual(sc.exit_code(v, control=False, run_completed=True), 1)
        self.assertEqual(sc.exit_code(good_verdict(), control=False, run_completed=True), 0)

    def test_bounds_options(self):
        ap = argparse.ArgumentParser()
        sc.add_bounds_args(ap)
        b = sc.bounds_from_args(ap.parse_args(["--max-p90-m", "40", "--max-ratio", "5"]))
        self.assertEqual((b.p90_m, b.max_m, b.ratio, b.not_aiding_s), (40.0, 50.0, 5.0, 0.0))
        f = Flight(est=lambda t: (30.0, 0.0) if t >= 260.0 else (1.0, 0.0))
        self.assertTrue(good_verdict(ekf=f.summary, bounds=b)["pass"])


class Ports(unittest.TestCase):
    def test_bound_port_is_not_free(self):
        for proto, kind in (("udp", socket.SOCK_DGRAM), ("tcp", socket.SOCK_STREAM)):
            s = socket.socket(socket.AF_INET, kind)
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
            try:
                self.assertFalse(sc.port_free(port, proto))
                other = sc.pick_port(port, proto)
                self.assertNotEqual(other, port)
                self.assertTrue(sc.port_free(other, proto))
            finally:
                s.close()
            self.assertTrue(sc.port_free(port, proto))

    def test_pick_port_prefers_the_default(self):
        self.assertEqual(sc.pick_port(14551, "udp", is_free=lambda p, k: True), 14551)
        self.assertNotEqual(sc.pick_port(14551, "udp", is_free=lambda p, k: True,
                                         taken={14551}), 14551)

    def test_choose_instance(self):
        busy = {("tcp", 5760), ("udp", 5511)}  # instance 0's SERIAL0, instance 1's RC input

        def free(port, proto):
            return (proto, port) not in busy

        self.assertEqual(sc.ardupilot_ports(2)[0], ("tcp", 5780))
        self.assertEqual(sc.choose_instance(sc.ardupilot_ports, range(5), free), (2, None))
        # An instance whose lock another run holds is skipped.
        n, _ = sc.choose_instance(sc.ardupilot_ports, range(5), free,
                                  lock=lambda n: None if n == 2 else "held")
        self.assertEqual(n, 3)
        self.assertEqual(sc.choose_instance(sc.ardupilot_ports, [0], free), (None, None))
        self.assertIn(("udp", 18573), sc.px4_ports(3))
        self.assertIn(("tcp", 4563), sc.px4_ports(3))

    def test_instance_lock_is_exclusive(self):
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "x.lock")
            first = sc.try_lock(path)
            self.assertIsNotNone(first)
            # flock locks belong to the open file: a second open (as another run) is refused.
            self.assertIsNone(sc.try_lock(path))
            first.close()
            again = sc.try_lock(path)
            self.assertIsNotNone(again)
            again.close()

    def test_connection_port_rewrite(self):
        text = ('[link]\nconnection = "udpin:127.0.0.1:14551"\ncomponent_id = 197\n'
                '# connection = "udpin:127.0.0.1:1"\n')
        new = sc.set_connection_port(text, 40123)
        self.assertIn('connection = "udpin:127.0.0.1:40123"', new)
        self.assertEqual(sc.connection_port(new), 40123)
        self.assertIn('# connection = "udpin:127.0.0.1:1"', new)
        with self.assertRaises(ValueError):
            sc.set_connection_port("[link]\n", 1)

    def test_repo_configs_have_a_replaceable_connection(self):
        here = os.path.dirname(os.path.abspath(__file__))
        for rel, port in (("ardupilot/visnav.toml", 14551), ("px4/visnav.toml", 14540),
                          ("px4/visnav-jmavsim.toml", 14540), ("ardupilot/drone/visnav.toml", 14551)):
            with open(os.path.join(here, rel)) as f:
                self.assertEqual(sc.connection_port(f.read()), port, rel)

    def test_px4_rc_mavlink_ports(self):
        rc = ("#!/bin/sh\n"
              "udp_offboard_port_local=$((14580+px4_instance))\n"
              "udp_offboard_port_remote=$((14540+px4_instance))\n"
              "[ $px4_instance -gt 9 ] && udp_offboard_port_remote=14549\n"
              "udp_gcs_port_local=$((18570+px4_instance))\n\n"
              "# GCS link\n"
              "mavlink start -x -u $udp_gcs_port_local -r 4000000 -f\n"
              "mavlink stream -r 50 -s ATTITUDE -u $udp_gcs_port_local\n\n"
              "# API/Offboard link\n"
              "mavlink start -x -u $udp_offboard_port_local -r 4000000 -f -m onboard "
              "-o $udp_offboard_port_remote\n")
        out = sc.px4_rc_mavlink_with_ports(rc, 40001, 40002).split("\n")
        self.assertIn("mavlink start -x -u $udp_gcs_port_local -r 4000000 -f -o 40001", out)
        i = out.index("udp_offboard_port_remote=40002  # sitl/px4/run.py")
        # After PX4's own assignments (also the > 9 one), before the first mavlink start.
        self.assertGreater(i, out.index("[ $px4_instance -gt 9 ] && udp_offboard_port_remote=14549"))
        self.assertLess(i, out.index("mavlink start -x -u $udp_gcs_port_local -r 4000000 -f -o 40001"))
        with self.assertRaises(ValueError):
            sc.px4_rc_mavlink_with_ports("mavlink start -u 14556\n", 1, 2)
        with self.assertRaises(ValueError):  # already has a remote port
            sc.px4_rc_mavlink_with_ports("\n".join(out), 1, 2)

    def test_the_drone_config_reads_the_shared_data_beside_the_repository(self):
        here = os.path.dirname(os.path.abspath(__file__))
        with open(os.path.join(here, "ardupilot", "drone", "visnav.toml")) as f:
            t = sc.visnav_config_text(f.read(), "/w/repo")
        self.assertIn('ortho = ["/w/shared/data/autzen/autzen_ortho_0p3m_utm10n.tif"]', t)
        self.assertIn('dem = "/w/shared/data/autzen/autzen_dsm_1m_utm10n.tif"', t)
        self.assertNotIn("../", t.split("[map]")[1].split("[nav]")[0])

    def test_the_tiled_map_replaces_the_ortho_line(self):
        here = os.path.dirname(os.path.abspath(__file__))
        with open(os.path.join(here, "ardupilot", "visnav.toml")) as f:
            t = sc.visnav_config_text(f.read(), "/w/repo")
        out, ortho, ground = sc.tiled_map_config(t, "/w/run/map", 24)
        self.assertEqual(ortho, "/w/repo/sitl/maps/naip_nd_2009.tif")
        self.assertEqual(ground, 580.0)
        section = out.split("[map]")[1].split("[nav]")[0]
        self.assertIn('file = "/w/run/map"\nmemory_mb = 24\n', section)
        self.assertNotIn("ortho =", section)
        self.assertIn("ground_height_amsl_m = 580.0", section)
        # Everything else is unchanged.
        self.assertEqual(out.replace('file = "/w/run/map"\nmemory_mb = 24', ""),
                         t.replace('ortho = ["/w/repo/sitl/maps/naip_nd_2009.tif"]', ""))
        with self.assertRaises(SystemExit):
            sc.tiled_map_config("[map]\nfile = \"x.vnm\"\n", "/w/run/map", 16)

    def test_heights_above_ground_count_from_the_given_home(self):
        score = sc.ErrorScore("EKF3", lambda _m: None, home_alt_m=132.0)
        home = (44.05, -123.07)
        score.add(0.0, False, *home, 134.0, *home, 134.0)  # 2 m up: on the ground
        score.add(1.0, False, *home, 232.0, *home, 232.0)  # 100 m up: airborne
        self.assertEqual([s[2] for s in score.samples], [2.0, 100.0])
        self.assertEqual(len(score.errs["gps_on"][0]), 1)

    def test_instance_arg(self):
        self.assertIsNone(sc.instance_arg("auto"))
        self.assertEqual(sc.instance_arg("3"), 3)
        with self.assertRaises(argparse.ArgumentTypeError):
            sc.instance_arg("-1")



class Processes(unittest.TestCase):
    def test_stop_processes_ends_every_group_and_a_second_call_does_nothing(self):
        import subprocess
        stubborn = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                    "print('ready', flush=True); time.sleep(60)")
        procs = [("visnav", subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"],
                                             start_new_session=True)),
                 ("px4", subprocess.Popen([sys.executable, "-c", stubborn], stdout=subprocess.PIPE,
                                          start_new_session=True))]
        self.assertEqual(procs[1][1].stdout.readline().strip(), b"ready")
        procs[1][1].stdout.close()
        sc.stop_processes(procs, timeout_s=1.0)
        self.assertTrue(all(p.poll() is not None for _, p in procs))
        self.assertNotEqual(procs[0][1].returncode, 0)  # SIGINT: KeyboardInterrupt
        self.assertEqual(procs[1][1].returncode, -9)     # ignored SIGTERM, then SIGKILL
        sc.stop_processes(procs, timeout_s=1.0)          # already ended: no signal, no error


if __name__ == "__main__":
    unittest.main()
