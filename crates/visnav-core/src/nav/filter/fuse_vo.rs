//! Visual odometry (`crate::vo`): the camera's displacement between two frames, fused as the mean
//! camera velocity over the frame interval, applied at its middle (exact for constant
//! acceleration; the history replays it there like a late fix).
//!
//! Measurement (`VoFix`): `z = dp_true + psi_z e_D x dp + dp dh / agl + e` (the displacement was
//! computed from this filter's pose at the previous frame: its yaw error rotates it, its height
//! error scales it, its horizontal position error does not reach it). Prediction
//! `h(x) = (v + C_b^n (w x l_cam)) dt`. With `dz = h(x_est) - z`, `dh = -dD` and
//! `C_est = (I + [psi x]) C_true`:
//! ```text
//! dz = dt dv - dt [(C (w x l)) x] psi + [dp x] e_D psi_z + (dp / agl) dD - e
//! ```
//! and, for the gyro bias error `dbg = bg_est - bg_true`: the odometer turned the next frame by
//! the rotation integrated from the rates this filter compensated with its bias estimate, wrong
//! by `Exp(-C dbg dt)` (NED, `C = C_b^n`), which moves the displacement by `G (-C dbg dt)`, `G`
//! the resection's own dependence on that rotation (`VoFix::gyro_rotation_sensitivity`: at most
//! the rays' lever arm `[look x]`, a tenth of it at 100 m with a wide view); in `dz` with the
//! other sign:
//! ```text
//! dz += dt G C dbg
//! ```
//! where `dbg` is every gyro error the filter carries: the turn-on bias, its Gauss-Markov drift
//! (`bias_drift_states`: with an autopilot's rates most of the bias variance is there) and, with
//! `scale_factor_states`, the scale factor error times the rate.
//! At 1800 m above ground a residual bias of 60 deg/h (ArduPilot's bias-compensated rates in
//! SITL) is 0.5 m/s of displacement error, steady for minutes: as white noise it drifted the
//! track 10 % of the distance flown; as a column it makes the bias observable from VO.
//!
//! With the gyros' rotation given, the odometer also measures what the images saw of the rotation
//! beyond it about the mean line of sight `u` (`VoRotation`: a turn of the whole image, which no
//! shift imitates): `z = u . C dbg dt + e_img + e_arw` (`R_images = Exp(z u) R_gyros`, and
//! `R_gyros = Exp(-C dbg dt) R_true`), predicted 0, so `dz = -u^T C dbg dt - e`, fused with the
//! displacement as one 4-dof measurement (noise: the images' sigma with the gyros' sampling
//! error, and the gyros' white noise over the interval). For a nadir camera it is the yaw-rate
//! bias: without it VO carries the heading only as well as the gyros do, and every degree of
//! heading error is 1.7 % of the distance flown as cross-track error (with an autopilot's rates,
//! 170 deg/h of residual bias, 3 deg a minute). When the 4-dof gate refuses the pair, the
//! displacement alone is tried against its own 3-dof gate: a rotation the gyros contradict does
//! not throw away a displacement that agrees with the filter.
//!
//! The motion's covariance is fused scaled by what the recent VO innovations showed
//! (`vo_noise`: at least the claim, more when the motions prove noisier).
//!
//! The yaw column is what makes the heading observable from VO whenever the velocity is known
//! otherwise (a manoeuvre seen by the accelerometers, a fix): VO alone measures the motion in the
//! heading frame the filter believes in. The height column makes the scale error a correlated
//! error of the filter's own (the next height measurement corrects the VO it already fused),
//! rather than white noise averaged away over hundreds of frames. No position column: VO never
//! reduces the position uncertainty directly, so the accuracy the filter reports (and sends to the
//! autopilot) grows as it really does without absolute fixes, and `lost_no_fix_s` (health) keeps
//! counting, as it counts only position fixes.

use super::*;

/// Fuses a VO displacement.
pub(super) fn fuse(par: &Params, core: &mut Core, f: &VoFix) -> Outcome {
    let st = &core.ins.state;
    let dt = f.span_s();
    let dp = f.dp_ned_m;
    // The camera's velocity: the body's plus the rotation of the lever arm.
    let lv_n = st.q_nb * core.w_b.cross(&par.l_cam);
    let dz = (st.v_ned_m_s + lv_n) * dt - dp;
    let mut h = SMatrix::<f64, 3, N_STATES>::zeros();
    h.fixed_view_mut::<3, 3>(0, IV)
        .copy_from(&(Matrix3::identity() * dt));
    h.fixed_view_mut::<3, 3>(0, IA)
        .copy_from(&(lever_arm_jacobian(&lv_n) * dt));
    // Yaw used by the VO: `z` contains `psi_z e_D x dp = psi_z (-dp_E, dp_N, 0)`; its negative
    // goes into `dz`.
    h[(0, IA + 2)] += dp.y;
    h[(1, IA + 2)] -= dp.x;
    // Height used by the VO: `z` contains `dp dh / agl = -dp dD / agl`.
    for i in 0..3 {
        h[(i, IP + 2)] += dp[i] / f.agl_m;
    }
    // Gyro errors in the VO's rotation: `z` contains `S (-C dbg dt)`, `dbg` every gyro error
    // state the filter removes from the rates (the turn-on bias, its drift, the scale factor).
    let cols = gyro_error_columns(par, core);
    for (i, col) in &cols {
        h.fixed_view_mut::<3, 3>(0, *i)
            .copy_from(&(f.gyro_rotation_sensitivity() * col * dt));
    }
    // The motion's covariance as claimed, scaled by what the recent innovations showed
    // (`vo_noise`); this innovation joins the window after, so it does not set its own scale.
    let r_claimed = covariance(f);
    let r = r_claimed * core.vo_noise.scale();
    let hph = h * core.p * h.transpose();
    core.vo_noise.push(dz, hph, r_claimed);
    let Some(rot) = f.rotation else {
        return core.update(par, dz, h, r, par.gate_vo);
    };
    // The images' rotation against the gyros' about the line of sight `u`: `z = u . C dbg dt`
    // (module doc), predicted 0.
    let u = f.look_ned_m / f.look_ned_m.norm();
    let mut h4 = SMatrix::<f64, 4, N_STATES>::zeros();
    h4.fixed_rows_mut::<3>(0).copy_from(&h);
    for (i, col) in &cols {
        let row = -(u.transpose() * col) * dt;
        h4.fixed_view_mut::<1, 3>(3, *i).copy_from(&row);
    }
    let mut r4 = SMatrix::<f64, 4, 4>::zeros();
    r4.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    r4[(3, 3)] = rot.sigma_rad.powi(2) + par.q_arw * dt;
    let dz4 = SVector::<f64, 4>::new(dz.x, dz.y, dz.z, -rot.about_los_rad);
    match core.update(par, dz4, h4, r4, par.gate_vo4) {
        // The rotation contradicts the gyros beyond the gate (a sampling error at a sharp
        // manoeuvre, a rolling-shutter skew the tracks took for a turn): the displacement is
        // still a measurement of its own, gated as it would be without the rotation. A gross
        // displacement fails this gate too. An update refused leaves the filter unchanged.
        Outcome::Rejected { .. } => core.update(par, dz, h, r, par.gate_vo),
        outcome => outcome,
    }
}

/// How each gyro error state moves the rotation rate in NED (`C_b^n d(w_b)/d(state)`): the
/// constant bias and its Gauss-Markov drift both add to the rates (`C_b^n`), a scale factor error
/// with the rate itself (`C_b^n diag(w_b)`), as in the filter's propagation.
fn gyro_error_columns(par: &Params, core: &Core) -> Vec<(usize, Matrix3<f64>)> {
    let c_bn = core.ins.state.q_nb.to_rotation_matrix().into_inner();
    let mut cols = vec![(IBG, c_bn)];
    if par.drift {
        cols.push((IDG, c_bn));
    }
    if par.scale {
        cols.push((ISG, c_bn * Matrix3::from_diagonal(&core.w_b)));
    }
    cols
}

/// The measurement covariance: the VO's own plus the terrain model's height error, correlated
/// over `terrain_corr_dist_m` (`VoFix`): `k (sigma_t / agl)^2 dp dp^T`, `k = L / |dp|` (at least
/// 1, at most `MAX_TERRAIN_CORR_FACTOR`). Over a distance `D < L` flown, `D / |dp|` such steps
/// sum to the variance `(sigma_t D / agl)^2` of one scale error over `D`.
fn covariance(f: &VoFix) -> Matrix3<f64> {
    let dp = f.dp_ned_m;
    let eps = f.terrain_sigma_m / f.agl_m;
    let k = (f.terrain_corr_dist_m / dp.norm().max(1e-3)).clamp(1.0, MAX_TERRAIN_CORR_FACTOR);
    f.cov_ned_m2 + dp * dp.transpose() * (k * eps * eps)
}

/// Cap of the terrain error's correlation factor: a hovering aircraft (dp near zero) would
/// otherwise divide by zero; at the cap the term is negligible against the images' noise.
const MAX_TERRAIN_CORR_FACTOR: f64 = 1e6;
