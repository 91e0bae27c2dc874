//! Attitude from the autopilot's AHRS: all three angles (tilt and heading) or the heading alone
//! (`NavConfig`'s tilt switch), inflated for correlated AHRS errors.

use super::*;

/// Fuses an attitude.
pub(super) fn fuse(par: &Params, core: &mut Core, f: &AttitudeFix) -> Outcome {
    let st = &core.ins.state;
    let t_c = f.t_capture_us;
    // Correlated AHRS errors (NavConfig::attitude_error_corr_time_s).
    let k = correlation_factor(par.att_corr_s, core.last_att_us, t_c, 1e5);
    // Attitude error (estimate relative to the measurement), NED small-angle vector.
    let dz = (st.q_nb * f.q_nb.inverse()).scaled_axis();
    let out = if par.att_tilt {
        let mut h = SMatrix::<f64, 3, N_STATES>::zeros();
        h.fixed_view_mut::<3, 3>(0, IA)
            .copy_from(&Matrix3::identity());
        core.update(par, dz, h, par.r_att * k, par.gate_att)
    } else {
        // Heading only: the rotation about the down axis.
        let mut h = SMatrix::<f64, 1, N_STATES>::zeros();
        h[(0, IA + 2)] = 1.0;
        core.update(
            par,
            SVector::<f64, 1>::new(dz.z),
            h,
            SMatrix::<f64, 1, 1>::new(par.r_att[(2, 2)] * k),
            par.gate_att1,
        )
    };
    if matches!(out, Outcome::Accepted { .. }) {
        core.last_att_us = Some(t_c);
    }
    out
}
