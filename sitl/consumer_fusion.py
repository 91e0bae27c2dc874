"""What an autopilot's EKF makes of visnav's injected stream: a model of its horizontal fusion.

ArduPilot's EKF3 (GPS_INPUT) and PX4's EKF2 (ODOMETRY) fuse every injected message as an
independent measurement with the variance visnav claims (EKF3: `R = h_acc^2` for the position,
`s_acc^2` for the velocity, AP_NavEKF3_PosVelFusion.cpp), and predict between messages with
their own IMU. When visnav's velocity error persists for tens of seconds (a drag law or an
attitude error does) the EKF integrates it and trusts the integral over the position for about
`h_acc / s_acc` seconds: its position error grows beyond the injected one.

The model: per horizontal axis a position / velocity Kalman filter whose prediction is the true
acceleration (the autopilot's IMU, good over seconds) plus white acceleration noise `q_acc`
(EKF3's `EK3_ACC_P_NSE` default 0.35 m/s^2), updated by each injected message. With the
injected stream and the truth of four ArduCopter SITL flights it reproduces EKF3's horizontal
error within 0.4 m at median, p90 and max (docs/real-sitl.md, "EKF3 fuses visnav's position
only"). Standard library only.
"""

import math

from sitl_common import stats

# The check scripts score every sample from this long after the GPS went off while the copter
# flies faster than SCORE_MIN_SPEED_M_S (the turns' hover-like moments say nothing of fusion).
SCORE_AFTER_GPS_OFF_S = 5.0
SCORE_MIN_SPEED_M_S = 5.0

# EKF3's default accelerometer process noise, m/s^2 (EK3_ACC_P_NSE).
DEFAULT_Q_ACC_M_S2 = 0.35
# EKF3 floors the claimed accuracies at its own noise parameters (EK3_POSNE_M_NSE 0.5 m,
# EK3_VELNE_M_NSE 0.3 m/s, the defaults).
POS_FLOOR_M = 0.5
VEL_FLOOR_M_S = 0.3


def fuse_axis(msgs, acc_of, fuse_velocity=True, q_acc=DEFAULT_Q_ACC_M_S2):
    """One axis: `msgs` are (t_s, pos_m, vel_m_s, h_acc_m, s_acc_m_s) in time order, `acc_of(t0,
    t1)` the true mean acceleration between two message times (m/s^2). Returns [(t_s, pos_m)]
    after each update (the first message initialises the state)."""
    out = []
    x = p = None
    t_last = None
    for t, z_p, z_v, h_acc, s_acc in msgs:
        if x is None:
            x = [z_p, z_v]
            p = [[max(h_acc, POS_FLOOR_M) ** 2, 0.0], [0.0, max(s_acc, VEL_FLOOR_M_S) ** 2]]
            t_last = t
            out.append((t, x[0]))
            continue
        dt = t - t_last
        t_last = t
        a = acc_of(t - dt, t)
        # Predict: x' = F x + (a dt^2/2, a dt); P' = F P F^T + diag(0, (q dt)^2).
        x = [x[0] + x[1] * dt + 0.5 * a * dt * dt, x[1] + a * dt]
        p00 = p[0][0] + dt * (p[1][0] + p[0][1]) + dt * dt * p[1][1]
        p01 = p[0][1] + dt * p[1][1]
        p11 = p[1][1] + (q_acc * dt) ** 2
        p = [[p00, p01], [p01, p11]]
        x, p = _update(x, p, 0, z_p, max(h_acc, POS_FLOOR_M) ** 2)
        if fuse_velocity:
            x, p = _update(x, p, 1, z_v, max(s_acc, VEL_FLOOR_M_S) ** 2)
        out.append((t, x[0]))
    return out


def _update(x, p, i, z, r):
    """Scalar update of state component i (sequential fusion, as EKF3 does)."""
    s = p[i][i] + r
    k = [p[0][i] / s, p[1][i] / s]
    innov = z - x[i]
    x = [x[0] + k[0] * innov, x[1] + k[1] * innov]
    p = [[p[r_][c] - k[r_] * p[i][c] for c in range(2)] for r_ in range(2)]
    return x, p


def fused_errors(msgs_ne, truth_pos, truth_acc, fuse_velocity=True, q_acc=DEFAULT_Q_ACC_M_S2,
                 keep=lambda t: True):
    """Horizontal error of the modelled EKF: `msgs_ne` are (t, n, e, vn, ve, h_acc, s_acc),
    `truth_pos(t)` -> (n, e), `truth_acc(t0, t1)` -> (an, ae). Returns the errors (m) at the
    message times `keep` selects."""
    axes = []
    for k in range(2):
        msgs = [(m[0], m[1 + k], m[3 + k], m[5], m[6]) for m in msgs_ne]
        axes.append(fuse_axis(msgs, lambda t0, t1, k=k: truth_acc(t0, t1)[k], fuse_velocity,
                              q_acc))
    errs = []
    for (t, n), (_, e) in zip(axes[0], axes[1]):
        if keep(t):
            tn, te = truth_pos(t)
            errs.append(math.hypot(n - tn, e - te))
    return errs


def print_comparison(autopilot, injected, msgs_ne, truth_pos, truth_acc, keep, as_flown=None):
    """The check scripts' table: `autopilot` and `injected` are (label, errors); then the model of
    the same injected stream (`fused_errors` arguments) as flown (`as_flown`: whether the flight
    fused the velocity; None: not printed), with the velocity, and position only."""
    def row(label, errs):
        s = stats(errs)
        if s is None:
            print(f"{label:34s} no samples")
        else:
            print(f"{label:34s} {s['median_m']:6.1f} {s['p90_m']:6.1f} {s['max_m']:6.1f}   n {s['n']}")

    print(f"{'horizontal error after GPS off, m':34s} {'median':>6s} {'p90':>6s} {'max':>6s}")
    row(*autopilot)
    row(*injected)
    if as_flown is not None:
        row("model, as flown", fused_errors(msgs_ne, truth_pos, truth_acc, as_flown, keep=keep))
    row("model, position and velocity", fused_errors(msgs_ne, truth_pos, truth_acc, True, keep=keep))
    row("model, position only", fused_errors(msgs_ne, truth_pos, truth_acc, False, keep=keep))
