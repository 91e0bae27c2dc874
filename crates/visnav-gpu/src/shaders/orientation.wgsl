// Dominant orientation (Bay et al. 2008 sec. 4.1; visnav-core's orientation and best_window), one
// invocation per keypoint: Haar responses of side 4s at the 113 samples (i s, j s), i^2 + j^2 <= 36
// (the CPU's table and Gaussian weights), binned into 72 bins by the CPU's polynomial atan2 and
// summed in its order (two interleaved bin arrays), then the pi/3 window with the longest sum.
// Writes that sum vector (bx, by); the host takes atan2 (bit for bit the CPU's), the descriptor
// pass normalises it (no trigonometry on the GPU, whose sin/cos/atan2 are not exact).

struct OriParams {
    w: u32,
    h: u32,
    stride: u32,
    n: u32,
    n_samples: u32,
    bins: u32,
    window: u32,
    per_row: u32,
    bin_scale: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(1) var<storage, read> kps: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> samples: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> ori: array<vec4<f32>>;
@group(0) @binding(4) var<uniform> q: OriParams;

const PI: f32 = 3.14159265358979;
const FRAC_PI_2: f32 = 1.57079632679490;

// visnav-core's fast_atan2.
fn fast_atan2(y: f32, x: f32) -> f32 {
    let ax = abs(x);
    let ay = abs(y);
    let mn = min(ax, ay);
    let mx = max(ax, ay);
    let a = mn / max(mx, 1.17549435e-38);
    let t = a * a;
    var r = ((((-0.01348047 * t + 0.05747731) * t - 0.12123907) * t + 0.19563593) * t
        - 0.3329946) * t * a + 0.9999956 * a;
    r = select(r, FRAC_PI_2 - r, ay > ax);
    r = select(r, PI - r, x < 0.0);
    return select(r, -r, y < 0.0);
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.y * q.per_row + gid.x;
    if (gid.x >= q.per_row || i >= q.n) {
        return;
    }
    let kp = kps[i];
    let s = kp.z;
    var half = max(u32(round_away(2.0 * s)), 1u);
    half = max(min(min(half, q.w / 2u), q.h / 2u), 1u);
    if (2u * half > q.w || 2u * half > q.h) {
        ori[i] = vec4<f32>(0.0);
        return;
    }
    var cols: array<u32, 13>;
    var rows: array<u32, 13>;
    for (var k = 0u; k < 13u; k = k + 1u) {
        let o = (f32(k) - 6.0) * s;
        cols[k] = boundary_index(kp.x + o, half, q.w);
        rows[k] = boundary_index(kp.y + o, half, q.h);
    }
    // [parity * 72 + bin]
    var bins: array<vec2<f32>, 144>;
    for (var k = 0u; k < 144u; k = k + 1u) {
        bins[k] = vec2<f32>(0.0);
    }
    for (var j = 0u; j < q.n_samples; j = j + 1u) {
        let sm = samples[j];
        let g = haar_at(cols[u32(sm.x)], rows[u32(sm.y)], half, q.stride);
        let a = fast_atan2(g.y, g.x);
        let b = min(u32(floor((a + PI) * q.bin_scale)), q.bins - 1u);
        let at = (j & 1u) * 72u + b;
        bins[at] = vec2<f32>(bins[at].x + sm.z * g.x, bins[at].y + sm.z * g.y);
    }
    for (var k = 0u; k < 72u; k = k + 1u) {
        bins[k] = bins[k] + bins[72u + k];
    }
    var sx = 0.0;
    var sy = 0.0;
    for (var k = 0u; k < q.window; k = k + 1u) {
        sx = sx + bins[k].x;
    }
    for (var k = 0u; k < q.window; k = k + 1u) {
        sy = sy + bins[k].y;
    }
    var best = sx * sx + sy * sy;
    var bx = sx;
    var by = sy;
    for (var start = 1u; start < q.bins; start = start + 1u) {
        let out_b = bins[start - 1u];
        let in_b = bins[(start + q.window - 1u) % q.bins];
        sx = sx + (in_b.x - out_b.x);
        sy = sy + (in_b.y - out_b.y);
        let m = sx * sx + sy * sy;
        if (m > best) {
            best = m;
            bx = sx;
            by = sy;
        }
    }
    ori[i] = vec4<f32>(bx, by, 0.0, 0.0);
}
