"""Unit tests of the autopilot-fusion model (sitl/consumer_fusion.py), standard library only.

    python3 -m unittest discover -s sitl -p 'test_*.py'      # from the repository root
"""

import math
import os
import random
import statistics
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import consumer_fusion as cf  # noqa: E402

RATE_HZ = 5.0
H_ACC_M = 8.0
S_ACC_M_S = 0.7


def flight(vel_err_of, pos_sigma_m=5.0, seconds=600.0, seed=7):
    """A copter flying north at 12 m/s; the injected position is the truth plus white noise of
    pos_sigma_m, the injected velocity the truth plus vel_err_of(t, rng). Returns (msgs, truth_pos,
    truth_acc)."""
    rng = random.Random(seed)
    msgs = []
    for i in range(int(seconds * RATE_HZ)):
        t = i / RATE_HZ
        err_v = vel_err_of(t, rng)
        msgs.append((t, 12.0 * t + rng.gauss(0.0, pos_sigma_m), rng.gauss(0.0, pos_sigma_m),
                     12.0 + err_v[0], err_v[1], H_ACC_M, S_ACC_M_S))
    return msgs, (lambda t: (12.0 * t, 0.0)), (lambda t0, t1: (0.0, 0.0))


def median_error(msgs, truth_pos, truth_acc, fuse_velocity):
    errs = cf.fused_errors(msgs, truth_pos, truth_acc, fuse_velocity, keep=lambda t: t > 60.0)
    return statistics.median(errs)


class ConsumerFusionTest(unittest.TestCase):
    def test_a_persistent_velocity_error_is_integrated_when_the_velocity_is_fused(self):
        # 0.8 m/s along one axis, changing sign every 90 s (a drag law learned on one leg,
        # flown on another), well inside the claimed 0.7 m/s's 2 sigma.
        def vel_err(t, rng):
            s = 1.0 if int(t / 90.0) % 2 == 0 else -1.0
            return (0.8 * s + rng.gauss(0.0, 0.1), rng.gauss(0.0, 0.1))

        msgs, tp, ta = flight(vel_err)
        with_vel = median_error(msgs, tp, ta, True)
        pos_only = median_error(msgs, tp, ta, False)
        # Integrated over the ~h_acc / s_acc = 11 s the filter trusts it: about 9 m.
        self.assertGreater(with_vel, 6.0)
        self.assertLess(pos_only, 0.6 * with_vel)

    def test_a_white_velocity_error_helps_when_fused(self):
        # The EKF's assumption holds: fusing the velocity must not be worse than position alone.
        msgs, tp, ta = flight(lambda t, rng: (rng.gauss(0.0, 0.7), rng.gauss(0.0, 0.7)))
        self.assertLess(median_error(msgs, tp, ta, True), median_error(msgs, tp, ta, False))

    def test_the_filter_follows_a_manoeuvre_through_the_true_acceleration(self):
        # Exact measurements of a circle: the model's error stays at the claimed floor's scale.
        def pos(t):
            return (100.0 * math.sin(0.1 * t), 100.0 * (1.0 - math.cos(0.1 * t)))

        def vel(t):
            return (10.0 * math.cos(0.1 * t), 10.0 * math.sin(0.1 * t))

        msgs = [(i / RATE_HZ, *pos(i / RATE_HZ), *vel(i / RATE_HZ), 1.0, 0.3)
                for i in range(1500)]

        def acc(t0, t1):
            a, b = vel(t0), vel(t1)
            return ((b[0] - a[0]) / (t1 - t0), (b[1] - a[1]) / (t1 - t0))

        errs = cf.fused_errors(msgs, pos, acc, True)
        self.assertLess(max(errs), 0.05)


if __name__ == "__main__":
    unittest.main()
