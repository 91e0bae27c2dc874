// 3x3x3 non-maximum suppression of a middle response layer and the quadratic interpolation of
// each maximum (Brown & Lowe 2002; visnav-core's find_maxima and interpolate), one invocation per
// grid cell of the search window (visnav_core::vision::surf::extrema_window). A maximum is above
// the threshold and strictly above its 26 neighbours; its offset solves the 3x3 system of the
// fitted quadratic (partial pivoting, as nalgebra's LU) and must stay within one sample. Maxima
// are appended in any order; the host sorts them (response, then octave, layer, row, column: the
// CPU's order) and turns them into keypoints with visnav_core's keypoint_at.

struct Triple {
    lo_off: u32,
    mid_off: u32,
    hi_off: u32,
    cols: u32,
    c_lo: u32,
    r_lo: u32,
    c_n: u32,
    r_n: u32,
    step: u32,
    mid_size: u32,
    stride: u32,
    tag: u32,
    threshold: f32,
    inv_a: f32,
    capacity: u32,
    pad: u32,
}

// c, r: grid cell; tag: octave << 8 | layer, bit 16 set for a negative Laplacian (bright blob).
struct Extremum {
    c: u32,
    r: u32,
    tag: u32,
    response: f32,
    ox: f32,
    oy: f32,
    os: f32,
    pad: u32,
}

@group(0) @binding(0) var<storage, read> det: array<f32>;
@group(0) @binding(1) var<storage, read> table: array<u32>;
@group(0) @binding(2) var<storage, read_write> found: array<Extremum>;
@group(0) @binding(3) var<storage, read_write> count: atomic<u32>;
@group(0) @binding(4) var<uniform> p: Triple;

// Sample (dr, dc) of layer s (-1 lo, 0 mid, 1 hi) around (r, c).
fn v(s: i32, r: u32, c: u32, dr: i32, dc: i32) -> f32 {
    var off = p.mid_off;
    if (s < 0) {
        off = p.lo_off;
    } else if (s > 0) {
        off = p.hi_off;
    }
    let rr = u32(i32(r) + dr);
    let cc = u32(i32(c) + dc);
    return det[off + rr * p.cols + cc];
}

fn box_sum(x0: u32, y0: u32, x1: u32, y1: u32) -> u32 {
    return table[y1 * p.stride + x1] - table[y0 * p.stride + x1] - table[y1 * p.stride + x0]
        + table[y0 * p.stride + x0];
}

// Sign of Dxx + Dyy of the filter of size mid_size at pixel (x, y) (visnav-core's hessian_at).
fn laplacian_negative(x: u32, y: u32) -> bool {
    let size = p.mid_size;
    let l = size / 3u;
    let hs = (size - 1u) / 2u;
    let m = (l - 1u) / 2u;
    let dyy = box_sum(x + 1u - l, y - hs, x + l, y + hs + 1u)
        - 3u * box_sum(x + 1u - l, y - m, x + l, y + m + 1u);
    let dxx = box_sum(x - hs, y + 1u - l, x + hs + 1u, y + l)
        - 3u * box_sum(x - m, y + 1u - l, x + m + 1u, y + l);
    let fxx = f32(bitcast<i32>(dxx)) * p.inv_a;
    let fyy = f32(bitcast<i32>(dyy)) * p.inv_a;
    return fxx + fyy < 0.0;
}

// Solve A o = b (3x3, partial pivoting); w = 0 when singular.
fn solve3(a_in: mat3x3<f32>, b_in: vec3<f32>) -> vec4<f32> {
    var m = array<vec4<f32>, 3>(
        vec4<f32>(a_in[0][0], a_in[1][0], a_in[2][0], b_in.x),
        vec4<f32>(a_in[0][1], a_in[1][1], a_in[2][1], b_in.y),
        vec4<f32>(a_in[0][2], a_in[1][2], a_in[2][2], b_in.z),
    );
    for (var col = 0u; col < 3u; col = col + 1u) {
        var piv = col;
        for (var r = col + 1u; r < 3u; r = r + 1u) {
            if (abs(m[r][col]) > abs(m[piv][col])) {
                piv = r;
            }
        }
        let t = m[col];
        m[col] = m[piv];
        m[piv] = t;
        if (m[col][col] == 0.0) {
            return vec4<f32>(0.0);
        }
        for (var r = col + 1u; r < 3u; r = r + 1u) {
            let f = m[r][col] / m[col][col];
            m[r] = m[r] - f * m[col];
        }
    }
    let z = m[2][3] / m[2][2];
    let y = (m[1][3] - m[1][2] * z) / m[1][1];
    let x = (m[0][3] - m[0][1] * y - m[0][2] * z) / m[0][0];
    return vec4<f32>(x, y, z, 1.0);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= p.c_n || gid.y >= p.r_n) {
        return;
    }
    let c = p.c_lo + gid.x;
    let r = p.r_lo + gid.y;
    let v0 = v(0, r, c, 0, 0);
    if (!(v0 > p.threshold)) {
        return;
    }
    for (var s = -1; s <= 1; s = s + 1) {
        for (var dr = -1; dr <= 1; dr = dr + 1) {
            for (var dc = -1; dc <= 1; dc = dc + 1) {
                if (s == 0 && dr == 0 && dc == 0) {
                    continue;
                }
                if (v(s, r, c, dr, dc) >= v0) {
                    return;
                }
            }
        }
    }
    let gx = (v(0, r, c, 0, 1) - v(0, r, c, 0, -1)) / 2.0;
    let gy = (v(0, r, c, 1, 0) - v(0, r, c, -1, 0)) / 2.0;
    let gs = (v(1, r, c, 0, 0) - v(-1, r, c, 0, 0)) / 2.0;
    let dxx = v(0, r, c, 0, 1) - 2.0 * v0 + v(0, r, c, 0, -1);
    let dyy = v(0, r, c, 1, 0) - 2.0 * v0 + v(0, r, c, -1, 0);
    let dss = v(1, r, c, 0, 0) - 2.0 * v0 + v(-1, r, c, 0, 0);
    let dxy = (v(0, r, c, 1, 1) - v(0, r, c, 1, -1) - v(0, r, c, -1, 1) + v(0, r, c, -1, -1)) / 4.0;
    let dxs = (v(1, r, c, 0, 1) - v(1, r, c, 0, -1) - v(-1, r, c, 0, 1) + v(-1, r, c, 0, -1)) / 4.0;
    let dys = (v(1, r, c, 1, 0) - v(1, r, c, -1, 0) - v(-1, r, c, 1, 0) + v(-1, r, c, -1, 0)) / 4.0;
    // Columns of the symmetric matrix.
    let a = mat3x3<f32>(
        vec3<f32>(dxx, dxy, dxs),
        vec3<f32>(dxy, dyy, dys),
        vec3<f32>(dxs, dys, dss),
    );
    let o = solve3(a, vec3<f32>(-gx, -gy, -gs));
    if (o.w == 0.0 || !(abs(o.x) <= 1.0) || !(abs(o.y) <= 1.0) || !(abs(o.z) <= 1.0)) {
        return;
    }
    var tag = p.tag;
    if (laplacian_negative(c * p.step, r * p.step)) {
        tag = tag | 0x10000u;
    }
    let slot = atomicAdd(&count, 1u);
    if (slot < p.capacity) {
        found[slot] = Extremum(c, r, tag, v0, o.x, o.y, o.z, 0u);
    }
}
