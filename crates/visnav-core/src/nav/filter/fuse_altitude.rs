//! Altitude (barometer or another height source): the height at the capture time,
//! `h - v_d dt`, against the measured height above the ellipsoid.

use super::*;

/// Fuses an altitude, `dt` seconds after the filter's epoch.
pub(super) fn fuse(par: &Params, core: &mut Core, f: &AltitudeFix, dt: f64) -> Outcome {
    let st = &core.ins.state;
    let v = st.v_ned_m_s;
    let dz = SVector::<f64, 1>::new(st.h_m - v.z * dt - f.h_m);
    let mut h = SMatrix::<f64, 1, N_STATES>::zeros();
    h[(0, IP + 2)] = -1.0;
    core.update(
        par,
        dz,
        h,
        SMatrix::<f64, 1, 1>::new(f.var_m2),
        par.gate_alt,
    )
}
