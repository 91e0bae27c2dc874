//! Position fixes: a vision fix (camera position, with the vision bias and its dependence on
//! this filter's attitude), a GPS position (antenna), and a vision pose (position and attitude
//! jointly against the image-only pose's 6x6 covariance). The fix is of the camera / antenna,
//! `r + C_b^n l`; with `C_est = (I + [psi x]) C_true`: `dz = dr + [psi x] C l = dr - [(C l) x] psi`.

use super::*;

/// Predicted minus measured position of a fix's point (camera or antenna, lever arm `l`): the
/// state moved to the capture time by its velocity, plus `C_b^n l`, minus the fix (NED, m).
pub(super) fn position_innovation(
    par: &Params,
    core: &Core,
    f: &PositionFix,
    is_vision: bool,
) -> Vector3<f64> {
    let st = &core.ins.state;
    let l = if is_vision { par.l_cam } else { par.l_gps };
    earth::ned_offset_m(
        (st.lat_rad, st.lon_rad, st.h_m),
        (f.lat_rad, f.lon_rad, f.h_m),
    ) + st.v_ned_m_s * dt_s(core.t_us, f.t_capture_us)
        + st.q_nb * l
}

/// Fuses a position fix or a vision pose (`m`: `Vision`, `GpsPosition` or `VisionPose`).
pub(super) fn fuse(par: &Params, core: &mut Core, m: &Measurement) -> Outcome {
    let t_c = m.t_capture_us();
    let st = &core.ins.state;
    let Some((f, is_vision)) = m.position_fix() else {
        return Outcome::Ignored;
    };
    // The fix is the position of the camera / antenna, `r + C_b^n l`; with
    // `C_est = (I + [psi x]) C_true`: `dz = dr + [psi x] C l = dr - [(C l) x] psi`.
    let l_n = st.q_nb * if is_vision { par.l_cam } else { par.l_gps };
    let mut dz = position_innovation(par, core, f, is_vision);
    let mut h = SMatrix::<f64, 3, N_STATES>::zeros();
    h.fixed_view_mut::<3, 3>(0, IP)
        .copy_from(&Matrix3::identity());
    h.fixed_view_mut::<3, 3>(0, IA)
        .copy_from(&lever_arm_jacobian(&l_n));
    // A vision fix also measures the bias: `z = r_cam + b + e`.
    if is_vision && par.vbias {
        dz += core.vb;
        h.fixed_view_mut::<3, 3>(0, IVB)
            .copy_from(&Matrix3::identity());
    }
    // A fix solved with this filter's attitude as its prior: `z = p + D psi + e`, so
    // `dz = dp - D psi - e` (PositionFix::att_dependence_ned).
    if let (Some(d), false) = (
        f.att_dependence_ned,
        matches!(m, Measurement::VisionPose(_)),
    ) {
        let mut ha = h.fixed_view_mut::<3, 3>(0, IA);
        ha -= d;
    }
    // Correlated fix errors (NavConfig::vision_error_corr_time_s).
    let corr = if is_vision {
        correlation_factor(par.vision_corr_s, core.last_vision_us, t_c, 1e4)
    } else {
        1.0
    };
    let out = if let Measurement::VisionPose(p) = m {
        // Position and attitude jointly: `[dz_pos; psi_est - psi_meas]` against the
        // image-only pose's 6x6 covariance (position/tilt correlation included).
        let dz_att = (st.q_nb * p.q_nb.inverse()).scaled_axis();
        let dz6 = SVector::<f64, 6>::new(dz.x, dz.y, dz.z, dz_att.x, dz_att.y, dz_att.z);
        let mut h6 = SMatrix::<f64, 6, N_STATES>::zeros();
        h6.fixed_view_mut::<3, N_STATES>(0, 0).copy_from(&h);
        h6.fixed_view_mut::<3, 3>(3, IA)
            .copy_from(&Matrix3::identity());
        core.update(par, dz6, h6, p.cov6 * corr, par.gate_vision6)
    } else {
        let gate = if is_vision {
            par.gate_vision
        } else {
            par.gate_gps3
        };
        core.update(par, dz, h, f.cov_ned_m2 * corr, gate)
    };
    if is_vision && matches!(out, Outcome::Accepted { .. }) {
        core.last_vision_us = Some(t_c);
    }
    out
}
