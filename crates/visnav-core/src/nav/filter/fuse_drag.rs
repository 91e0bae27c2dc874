//! The multirotor drag law as a measurement of the body velocity (`nav::drag`).

use super::*;

/// The drag law as a measurement of the body velocity (`nav::drag`): per fused axis `k`,
/// `z = f_k` (bias-corrected specific force), `h(x) = law_k((C_n^b v)_k)`. With
/// `C_est = (I + [psi x]) C_true`, `v_b,est = v_b + C_n^b [v x] psi`; the accelerometer bias error
/// enters with +1 (the measured force is corrected by the estimate).
pub(super) fn fuse(par: &Params, core: &mut Core, d: &DragFix) -> Outcome {
    let st = &core.ins.state;
    let c_nb = st.q_nb.inverse().to_rotation_matrix().into_inner();
    let v_b = c_nb * st.v_ned_m_s;
    let d_vb_d_psi = c_nb * skew_matrix(&st.v_ned_m_s);
    let rows: Vec<(usize, crate::nav::drag::AxisModel)> = d
        .model
        .iter()
        .enumerate()
        .filter_map(|(k, m)| m.map(|m| (k, m)))
        .collect();
    let v_xy = v_b.xy();
    let row = |k: usize, m: &crate::nav::drag::AxisModel| {
        // d f_k / d (v_x, v_y) of the body velocity, then through v_b = C_nb v_n.
        let g = m.gradient(&v_xy, k);
        let mut h = SMatrix::<f64, 1, N_STATES>::zeros();
        for j in 0..3 {
            h[(0, IV + j)] = g[0] * c_nb[(0, j)] + g[1] * c_nb[(1, j)];
            h[(0, IA + j)] = g[0] * d_vb_d_psi[(0, j)] + g[1] * d_vb_d_psi[(1, j)];
        }
        h[(0, IBA + k)] = 1.0;
        if par.drift {
            h[(0, IDA + k)] = 1.0;
        }
        let dz = m.force_at(&v_xy, k) - d.f_body_xy_m_s2[k];
        (
            h,
            dz,
            m.variance_at(&v_xy, k, d.wind_sigma_m_s, d.f_body_xy_m_s2[k]),
        )
    };
    // The law's error and the wind persist: one independent measurement per correlation time.
    let corr = correlation_factor(
        crate::nav::drag::ERROR_CORR_TIME_S,
        core.last_drag_us,
        d.t_capture_us,
        1e4,
    );
    let out = match rows.as_slice() {
        [(k, m)] => {
            let (h, dz, var) = row(*k, m);
            core.update(
                par,
                SVector::<f64, 1>::new(dz),
                h,
                SMatrix::<f64, 1, 1>::new(var * corr),
                par.gate_drag1,
            )
        }
        [(k0, m0), (k1, m1)] => {
            let (h0, dz0, var0) = row(*k0, m0);
            let (h1, dz1, var1) = row(*k1, m1);
            let mut h = SMatrix::<f64, 2, N_STATES>::zeros();
            h.set_row(0, &h0);
            h.set_row(1, &h1);
            core.update(
                par,
                SVector::<f64, 2>::new(dz0, dz1),
                h,
                SMatrix::<f64, 2, 2>::new(var0 * corr, 0.0, 0.0, var1 * corr),
                par.gate_drag2,
            )
        }
        _ => Outcome::Ignored,
    };
    if matches!(out, Outcome::Accepted { .. }) {
        core.last_drag_us = Some(d.t_capture_us);
    }
    out
}
