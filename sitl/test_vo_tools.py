"""Unit tests of the visual odometry tools of the real-SITL recipes: the configuration sitl-run
gets (sitl_common.visnav_config_text: --vo, --map-ortho, the logs), the unmatchable map
(featureless_map.py) and the VO scoring against the truth (vo_check.py). Standard library only;
tests/sitl_scripts.rs runs them under `cargo test`.
"""

import contextlib
import io
import math
import os
import sys
import tempfile
import unittest
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import featureless_map as fm  # noqa: E402
import sitl_common as sc  # noqa: E402
import vo_check as vc  # noqa: E402

REPO = os.path.dirname(HERE)
MAP = os.path.join(HERE, "maps", "naip_nd_2009.tif")


class ConfigText(unittest.TestCase):
    BASE = ('[link]\nconnection = "udpin:127.0.0.1:14551"\n\n[map]\n'
            'ortho = ["../maps/naip_nd_2009.tif"]\nground_height_amsl_m = 580.0\n')

    def test_logs_and_paths(self):
        t = sc.visnav_config_text(self.BASE, "/repo")
        self.assertIn('ortho = ["/repo/sitl/maps/naip_nd_2009.tif"]', t)
        self.assertIn('tlog = "visnav.tlog"', t)
        self.assertIn('\n[daemon]\nfix_log = "fixes.jsonl"\nvo_log = "vo.jsonl"\n', t)
        self.assertNotIn("[vo]", t, "no --vo: the configuration's own setting")
        # An existing [daemon] section gets the logs, not a second section.
        t = sc.visnav_config_text(self.BASE + "\n[daemon]\nbaro = true\n", "/repo")
        self.assertEqual(t.count("[daemon]"), 1)
        self.assertIn('vo_log = "vo.jsonl"\nbaro = true', t)

    def test_vo_switch(self):
        t = sc.visnav_config_text(self.BASE, "/repo", vo="on")
        self.assertTrue(t.endswith("\n[vo]\nenabled = true\n"), t)
        t = sc.visnav_config_text(self.BASE + "\n[vo]\nmin_tracks = 30\n", "/repo", vo="off")
        self.assertEqual(t.count("[vo]"), 1)
        self.assertIn("[vo]\nenabled = false\nmin_tracks = 30\n", t)
        # A configuration that sets it already: its line replaced, never a duplicate key; a
        # later section's `enabled` untouched.
        base = self.BASE + "\n[vo]\nmin_tracks = 30\nenabled = true\n\n[x]\nenabled = true\n"
        t = sc.visnav_config_text(base, "/repo", vo="off")
        self.assertIn("[vo]\nmin_tracks = 30\nenabled = false\n\n[x]\nenabled = true\n", t)
        self.assertEqual(t.count("enabled = "), 2)

    def test_map_override_and_port(self):
        t = sc.visnav_config_text(self.BASE, "/repo", link_port=40001, map_ortho="/x/noise.tif")
        self.assertIn('ortho = ["/x/noise.tif"]', t)
        self.assertNotIn("naip_nd_2009", t)
        self.assertEqual(sc.connection_port(t), 40001)
        with self.assertRaises(SystemExit):
            sc.visnav_config_text('[map]\nfile = "m.vnm"\n', "/repo", map_ortho="/x/n.tif")

    def test_the_recipe_configs_take_the_overrides(self):
        for rel in ("ardupilot/visnav.toml", "px4/visnav.toml"):
            with open(os.path.join(HERE, rel)) as f:
                t = sc.visnav_config_text(f.read(), REPO, vo="on", map_ortho="/x/n.tif")
            self.assertIn('ortho = ["/x/n.tif"]', t, rel)
            self.assertEqual(t.count("enabled = true"), 1, rel)


class UnmatchableMap(unittest.TestCase):
    def tiles(self, data):
        bo, tags = fm.ifd_tags(data)
        offs, _ = fm.long_array(data, bo, tags[fm.TILE_OFFSETS])
        lens, _ = fm.long_array(data, bo, tags[fm.TILE_BYTE_COUNTS])
        return tags, [zlib.decompress(data[o:o + n]) for o, n in zip(offs, lens)]

    def test_noise_keeps_the_georeferencing_and_replaces_every_pixel(self):
        with open(MAP, "rb") as f:
            src = f.read()
        out = fm.featureless(src, None, seed=3)
        tags_a, tiles_a = self.tiles(src)
        tags_b, tiles_b = self.tiles(out)
        geo = (33550, 33922, 34735, 34737, 256, 257, 258, 277, 322, 323)
        for t in geo:
            self.assertEqual(tags_a[t], tags_b[t], t)
        # Georeferencing values (stored at their offsets) are the same bytes.
        for t in (33550, 33922, 34735):
            typ, cnt, at = tags_a[t]
            size = {3: 2, 12: 8}[typ] * cnt
            self.assertEqual(src[at:at + size], out[at:at + size], t)
        self.assertEqual([len(t) for t in tiles_a], [len(t) for t in tiles_b])
        for a, b in zip(tiles_a, tiles_b):
            self.assertNotEqual(a, b)
            self.assertGreater(len(set(b)), 200, "noise uses the whole grey range")
        self.assertEqual(out, fm.featureless(src, None, seed=3), "seeded")
        self.assertNotEqual(out, fm.featureless(src, None, seed=4))
        uniform = self.tiles(fm.featureless(src, 200))[1]
        self.assertTrue(all(set(t) == {200} for t in uniform))

    def test_not_a_tiff_is_refused(self):
        with self.assertRaises(ValueError):
            fm.featureless(b"GIF89a" + bytes(100), None)
        with tempfile.TemporaryDirectory() as d:
            bad = os.path.join(d, "bad.tif")
            with open(bad, "wb") as f:
                f.write(b"II*\0" + bytes(4))
            with self.assertRaises(SystemExit):
                fm.main([bad, os.path.join(d, "out.tif")])


def truth_row(seq, t_us, north_m, east_m, alt=0.0):
    m_lat, m_lon = sc.metres_per_deg(47.0)
    return {"seq": seq, "t_capture_us": t_us, "lat_deg": 47.0 + north_m / m_lat,
            "lon_deg": -99.0 + east_m / m_lon, "alt_amsl_m": alt}


def motion(seq, t_prev, t_next, dp, sigma, agl=1400.0, outcome="fused"):
    s2 = sigma * sigma
    return {"seq": seq, "t_capture_us": t_next, "step": "motion", "outcome": outcome,
            "t_prev_us": t_prev, "dp_ned_m": dp, "agl_m": agl,
            "cov_ned_m2": [[s2, 0, 0], [0, s2, 0], [0, 0, 4 * s2]]}


class VoScoring(unittest.TestCase):
    def flight(self, bias_e_m, sigma):
        """Eastward at 10 m per frame, 0.5 s apart; every motion bias_e_m too far east."""
        truth = [truth_row(i, 1_000_000 + 500_000 * i, 0.0, 10.0 * i) for i in range(21)]
        vo = [{"seq": 0, "t_capture_us": 1_000_000, "step": "started"}]
        for i in range(1, 21):
            vo.append(motion(i, truth[i - 1]["t_capture_us"], truth[i]["t_capture_us"],
                             [0.0, 10.0 + bias_e_m, 0.0], sigma))
        vo.append({"seq": 21, "t_capture_us": 11_500_000, "step": "refused", "reason": "blank"})
        return vo, truth

    def test_errors_nees_scale_and_drift(self):
        vo, truth = self.flight(0.2, 0.1)
        steps, outcomes, reasons, rows = vc.score(vo, truth)
        self.assertEqual(steps, {"started": 1, "motion": 20, "refused": 1})
        self.assertEqual(dict(reasons), {"blank": 1})
        self.assertEqual(len(rows), 20)
        s = vc.summary(steps, outcomes, reasons, rows)
        self.assertAlmostEqual(s["err_h_m"]["p50"], 0.2, places=2)
        # (0.2 / 0.1)^2; the truth's metres are at the aircraft's height (R + h), the test's
        # offsets at the ground's: 0.03 % of 10 m apart.
        self.assertAlmostEqual(s["nees_h"]["p50"], 4.0, delta=0.15)
        self.assertEqual(s["nees_h_over_95pct"], 0.0)
        self.assertAlmostEqual(s["scale_err_pct"]["p50"], 2.0, places=1)
        self.assertAlmostEqual(s["dir_err_deg"]["p50"], 0.0, places=2)
        run = s["longest_run"]
        self.assertEqual(run["motions"], 20)
        self.assertAlmostEqual(run["flown_m"], 200.0, places=0)
        self.assertAlmostEqual(run["drift_ned_m"][1], 4.0, places=1)
        self.assertAlmostEqual(run["drift_h_pct"], 2.0, places=1)
        self.assertAlmostEqual(s["mean_err_rate_ne_m_s"][1], 0.4, places=2)
        self.assertIn("1000-1500", s["by_agl_m"])

    def test_the_rotation_beyond_the_gyros_is_a_rate(self):
        vo, truth = self.flight(0.0, 0.1)
        for i, r in enumerate(r for r in vo if r["step"] == "motion"):
            # 0.5 s frames, 0.01 deg each: 72 deg/h, scattered +-0.001 deg.
            r["rot_los_deg"] = 0.01 + (0.001 if i % 2 else -0.001)
            r["rot_los_sigma_deg"] = 0.004
        s = vc.summary(*vc.score(vo, truth))
        self.assertEqual(s["rot_los"]["n"], 20)
        self.assertAlmostEqual(s["rot_los"]["mean_deg_h"], 72.0, places=1)
        self.assertAlmostEqual(s["rot_los"]["sd_deg"], 0.001, places=5)
        self.assertAlmostEqual(s["rot_los"]["sigma_p50_deg"], 0.004)
        self.assertNotIn("rot_los", vc.summary(*vc.score(*self.flight(0.0, 0.1))))

    def test_an_overconfident_claim_shows(self):
        vo, truth = self.flight(0.5, 0.1)
        s = vc.summary(*vc.score(vo, truth))
        self.assertAlmostEqual(s["nees_h"]["p50"], 25.0, places=0)
        self.assertEqual(s["nees_h_over_95pct"], 1.0)
        self.assertEqual(s["nees_h_over_99_9pct"], 1.0)

    def test_gaps_split_runs_and_missing_truth_is_skipped(self):
        vo, truth = self.flight(0.0, 0.1)
        del truth[10]  # motions 10 and 11 have no truth at one end
        steps, outcomes, reasons, rows = vc.score(vo, truth)
        self.assertEqual(len(rows), 18)
        run = vc.drift(rows)
        self.assertEqual(run["n"], 9, "two runs of 9 (1-9, 12-20): the later")
        self.assertAlmostEqual(run["t0_s"], 5.5)

    def test_main_on_files(self):
        vo, truth = self.flight(0.1, 0.1)
        with tempfile.TemporaryDirectory() as d:
            for name, rows in (("vo.jsonl", vo), ("frames_truth.jsonl", truth)):
                with open(os.path.join(d, name), "w") as f:
                    for r in rows:
                        f.write(vc.json.dumps(r) + "\n")
                    if name == "vo.jsonl":
                        f.write('{"seq": 99, "t_capt')  # cut by a kill: skipped
            buf = io.StringIO()
            with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
                vc.main([d, "--json"])
            self.assertEqual(vc.json.loads(buf.getvalue())["scored_motions"], 20)
            with self.assertRaises(SystemExit):
                vc.main([os.path.join(d, "nope")])


if __name__ == "__main__":
    unittest.main()
