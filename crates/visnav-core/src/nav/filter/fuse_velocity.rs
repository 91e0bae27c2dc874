//! GPS velocity: the antenna velocity `v + C_b^n (w x l)` (the earth/transport rate part of `w`
//! is below 1e-4 rad/s and neglected); Jacobian with respect to psi as for the position.

use super::*;

/// Fuses a GPS velocity.
pub(super) fn fuse(par: &Params, core: &mut Core, f: &VelocityFix) -> Outcome {
    let st = &core.ins.state;
    let v = st.v_ned_m_s;
    // Antenna velocity `v + C_b^n (w x l)` (the earth/transport rate part of `w` is
    // below 1e-4 rad/s and neglected); Jacobian wrt psi as for the position.
    let lv_n = st.q_nb * core.w_b.cross(&par.l_gps);
    let dz = v + lv_n - f.v_ned_m_s;
    let mut h = SMatrix::<f64, 3, N_STATES>::zeros();
    h.fixed_view_mut::<3, 3>(0, IV)
        .copy_from(&Matrix3::identity());
    h.fixed_view_mut::<3, 3>(0, IA)
        .copy_from(&lever_arm_jacobian(&lv_n));
    core.update(par, dz, h, f.cov_ned_m2_s2, par.gate_gps3)
}
