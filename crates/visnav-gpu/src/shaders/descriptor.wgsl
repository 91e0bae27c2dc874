// SURF descriptors (Bay et al. 2008 sec. 4.2; visnav-core's describe_one), one workgroup per
// keypoint and one invocation per subregion, each summing its samples in the CPU's order, then
// the L2 normalisation over the whole descriptor. The CPU's three sampling paths, chosen by the
// CPU's rules:
// * upright grid: Haar responses of side 2s at the axis-aligned sample grid (boundary_index);
// * rotated cells (SURF-36/64 with orientation): the (n+1)^2 cells of side round(s) along the
//   keypoint axes, box origins in 16.16 fixed point (the CPU's 48.16, the same integers for any
//   image below 32768 px; windows beyond that take the per-sample path), responses as differences
//   of neighbouring cells (describe_rotated);
// * per sample (SURF-128 with orientation, tiny images): the wavelet at each rotated sample point,
//   its response rotated into the keypoint frame.
// The orientation enters as the unit vector of the orientation pass's window sum.

struct DescParams {
    w: u32,
    h: u32,
    stride: u32,
    n_kp: u32,
    samples: u32,
    nsub: u32,
    vals: u32,
    len: u32,
    out_stride: u32,
    upright: u32,
    extended: u32,
    per_row: u32,
    sp_unit: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(1) var<storage, read> kps: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> ori: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read_write> desc: array<f32>;
@group(0) @binding(5) var<uniform> d: DescParams;

var<workgroup> acc: array<f32, 128>;
var<workgroup> inv_norm: f32;

// Add one weighted, rotated response to a subregion's sums (4 or 8 values, OpenCV's order).
fn accumulate(a: ptr<function, array<f32, 8>>, rx: f32, ry: f32) {
    if (d.extended == 1u) {
        if (ry >= 0.0) {
            (*a)[0] = (*a)[0] + rx;
            (*a)[1] = (*a)[1] + abs(rx);
        } else {
            (*a)[2] = (*a)[2] + rx;
            (*a)[3] = (*a)[3] + abs(rx);
        }
        if (rx >= 0.0) {
            (*a)[4] = (*a)[4] + ry;
            (*a)[5] = (*a)[5] + abs(ry);
        } else {
            (*a)[6] = (*a)[6] + ry;
            (*a)[7] = (*a)[7] + abs(ry);
        }
    } else {
        (*a)[0] = (*a)[0] + rx;
        (*a)[1] = (*a)[1] + ry;
        (*a)[2] = (*a)[2] + abs(rx);
        (*a)[3] = (*a)[3] + abs(ry);
    }
}

// Add a row's subregion sums (SURF-36/64 grid paths: the CPU sums a row in registers first).
fn add_row(a: ptr<function, array<f32, 8>>, s: vec4<f32>) {
    (*a)[0] = (*a)[0] + s.x;
    (*a)[1] = (*a)[1] + s.y;
    (*a)[2] = (*a)[2] + s.z;
    (*a)[3] = (*a)[3] + s.w;
}

fn fix16(v: f32) -> i32 {
    return i32(round_away(v * 65536.0));
}

fn upright_grid(kp: vec4<f32>, half: u32, sr: u32, sc: u32) -> array<f32, 8> {
    var a: array<f32, 8>;
    let n = d.samples;
    let per = n / d.nsub;
    let c = f32(n - 1u) / 2.0;
    let sp = d.sp_unit * kp.z;
    for (var jj = 0u; jj < per; jj = jj + 1u) {
        let j = sr * per + jj;
        let y = boundary_index(kp.y + (f32(j) - c) * sp, half, d.h);
        var s = vec4<f32>(0.0);
        for (var ii = 0u; ii < per; ii = ii + 1u) {
            let i = sc * per + ii;
            let x = boundary_index(kp.x + (f32(i) - c) * sp, half, d.w);
            let g = haar_at(x, y, half, d.stride);
            let wt = weights[j * n + i];
            let rx = wt * g.x;
            let ry = wt * g.y;
            if (d.extended == 1u) {
                accumulate(&a, rx, ry);
            } else {
                s = s + vec4<f32>(rx, ry, abs(rx), abs(ry));
            }
        }
        if (d.extended == 0u) {
            add_row(&a, s);
        }
    }
    return a;
}

fn rotated_cells(kp: vec4<f32>, cs: vec2<f32>, sr: u32, sc: u32) -> array<f32, 8> {
    var a: array<f32, 8>;
    let n = d.samples;
    let per = n / d.nsub;
    let s = kp.z;
    let sp = d.sp_unit * s;
    let cb = max(u32(round_away(s)), 1u);
    let co = cs.x;
    let si = cs.y;
    let ux = sp * co;
    let uy = sp * si;
    let vx = -sp * si;
    let vy = sp * co;
    let half_n = f32(n) / 2.0;
    let off = 1.0 - f32(cb) / 2.0;
    let oxf = kp.x + off - half_n * (ux + vx);
    let oyf = kp.y + off - half_n * (uy + vy);
    let ox = fix16(oxf);
    let oy = fix16(oyf);
    let iux = fix16(ux);
    let iuy = fix16(uy);
    let ivx = fix16(vx);
    let ivy = fix16(vy);
    let xm = i32(d.w - cb);
    let ym = i32(d.h - cb);
    let ni = i32(n);
    var inside = true;
    for (var q = 0; q < 4; q = q + 1) {
        let k = (q & 1) * ni;
        let l = (q >> 1u) * ni;
        let x = (ox + k * iux + l * ivx) >> 16u;
        let y = (oy + k * iuy + l * ivy) >> 16u;
        inside = inside && x >= 0 && x <= xm && y >= 0 && y <= ym;
    }
    let st = d.stride;
    // This subregion's cells: rows l0..=l0+per, columns k0..=k0+per.
    let k0 = sc * per;
    let l0 = sr * per;
    let m = per + 1u;
    var cells: array<f32, 49>;
    for (var dl = 0u; dl < m; dl = dl + 1u) {
        let li = i32(l0 + dl);
        let rx = ox + li * ivx;
        let ry = oy + li * ivy;
        for (var dk = 0u; dk < m; dk = dk + 1u) {
            let ki = i32(k0 + dk);
            var x = (rx + ki * iux) >> 16u;
            var y = (ry + ki * iuy) >> 16u;
            if (!inside) {
                x = clamp(x, 0, xm);
                y = clamp(y, 0, ym);
            }
            let i0 = u32(y) * st + u32(x);
            let v = table[i0 + cb * st + cb] - table[i0 + cb * st] - table[i0 + cb] + table[i0];
            cells[dl * m + dk] = f32(bitcast<i32>(v));
        }
    }
    for (var jj = 0u; jj < per; jj = jj + 1u) {
        let j = l0 + jj;
        var sm = vec4<f32>(0.0);
        for (var ii = 0u; ii < per; ii = ii + 1u) {
            let i = k0 + ii;
            let ca = cells[jj * m + ii];
            let cbv = cells[jj * m + ii + 1u];
            let cp = cells[(jj + 1u) * m + ii];
            let cq = cells[(jj + 1u) * m + ii + 1u];
            let wt = weights[j * n + i];
            let rx = wt * ((cbv + cq) - (ca + cp));
            let ry = wt * ((cp + cq) - (ca + cbv));
            sm = sm + vec4<f32>(rx, ry, abs(rx), abs(ry));
        }
        add_row(&a, sm);
    }
    return a;
}

fn per_sample(kp: vec4<f32>, cs: vec2<f32>, half: u32, sr: u32, sc: u32) -> array<f32, 8> {
    var a: array<f32, 8>;
    let n = d.samples;
    let per = n / d.nsub;
    let c = f32(n - 1u) / 2.0;
    let sp = d.sp_unit * kp.z;
    let co = cs.x;
    let si = cs.y;
    for (var jj = 0u; jj < per; jj = jj + 1u) {
        let j = sr * per + jj;
        let v = (f32(j) - c) * sp;
        for (var ii = 0u; ii < per; ii = ii + 1u) {
            let i = sc * per + ii;
            let u = (f32(i) - c) * sp;
            let wt = weights[j * n + i];
            var fx = kp.x + u;
            var fy = kp.y + v;
            if (d.upright == 0u) {
                fx = kp.x + co * u - si * v;
                fy = kp.y + si * u + co * v;
            }
            let g = haar_clamped(fx, fy, half, d.w, d.h, d.stride);
            let rx = wt * (co * g.x + si * g.y);
            let ry = wt * (co * g.y - si * g.x);
            accumulate(&a, rx, ry);
        }
    }
    return a;
}

// One subregion's sums by the CPU's choice of path.
fn subregion(k: u32, b: u32) -> array<f32, 8> {
    let kp = kps[k];
    let s = kp.z;
    let half = max(u32(round_away(s)), 1u);
    let sr = b / d.nsub;
    let sc = b % d.nsub;
    var cs = vec2<f32>(1.0, 0.0);
    if (d.upright == 0u) {
        let o = ori[k];
        let r2 = o.x * o.x + o.y * o.y;
        if (r2 > 0.0) {
            let r = sqrt(r2);
            cs = vec2<f32>(o.x / r, o.y / r);
        }
    }
    if (d.upright == 1u && 2u * half <= d.w && 2u * half <= d.h) {
        return upright_grid(kp, half, sr, sc);
    }
    // 16.16 fixed point holds the window's corners (at most 14.2 s from the keypoint).
    let fits = max(abs(kp.x), abs(kp.y)) + 16.0 * s < 30000.0;
    if (d.upright == 0u && d.extended == 0u && half <= d.w && half <= d.h && fits) {
        return rotated_cells(kp, cs, sr, sc);
    }
    return per_sample(kp, cs, half, sr, sc);
}

@compute @workgroup_size(16)
fn main(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(local_invocation_index) b: u32,
) {
    let k = wg.y * d.per_row + wg.x;
    if (wg.x >= d.per_row || k >= d.n_kp) {
        return;
    }
    let in_use = b < d.nsub * d.nsub;
    var mine: array<f32, 8>;
    if (in_use) {
        mine = subregion(k, b);
        for (var v = 0u; v < d.vals; v = v + 1u) {
            acc[b * d.vals + v] = mine[v];
        }
    }
    workgroupBarrier();
    if (b == 0u) {
        var norm2 = 0.0;
        for (var i = 0u; i < d.len; i = i + 1u) {
            norm2 = norm2 + acc[i] * acc[i];
        }
        var inv = 0.0;
        if (norm2 > 0.0) {
            inv = 1.0 / sqrt(norm2);
        }
        inv_norm = inv;
        for (var i = d.len; i < d.out_stride; i = i + 1u) {
            desc[k * d.out_stride + i] = 0.0;
        }
    }
    workgroupBarrier();
    if (in_use) {
        let inv = inv_norm;
        for (var v = 0u; v < d.vals; v = v + 1u) {
            desc[k * d.out_stride + b * d.vals + v] = acc[b * d.vals + v] * inv;
        }
    }
}
