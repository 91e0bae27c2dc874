// Fast-Hessian response layer (Bay et al. 2008 sec. 3.2-3.3), as visnav-core's compute_layer:
// det(H) = Dxx Dyy - 0.81 Dxy^2 of the lobe-area normalised box filters of size `size` at the
// pixels (c * step, r * step); 0 where the filter does not fit. The box sums are exact integers
// (wrapping u32, read as i32), the normalisation factors come from the CPU (bit-identical).

struct Layer {
    w: u32,
    h: u32,
    stride: u32,
    size: u32,
    step: u32,
    rows: u32,
    cols: u32,
    out_offset: u32,
    inv_a: f32,
    inv_d: f32,
    dxy_weight_sq: f32,
    pad: u32,
}

@group(0) @binding(0) var<storage, read> table: array<u32>;
@group(0) @binding(1) var<storage, read_write> det: array<f32>;
@group(0) @binding(2) var<uniform> p: Layer;

fn at(x: u32, y: u32) -> u32 {
    return table[y * p.stride + x];
}

// Sum over columns x0..x1, rows y0..y1 (half-open), modulo 2^32.
fn box_sum(x0: u32, y0: u32, x1: u32, y1: u32) -> u32 {
    return at(x1, y1) - at(x1, y0) - at(x0, y1) + at(x0, y0);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let c = gid.x;
    let r = gid.y;
    if (c >= p.cols || r >= p.rows) {
        return;
    }
    let idx = p.out_offset + r * p.cols + c;
    let hs = (p.size - 1u) / 2u;
    let x = c * p.step;
    let y = r * p.step;
    if (p.size > p.w || p.size > p.h || x < hs || y < hs || x + hs > p.w - 1u || y + hs > p.h - 1u) {
        det[idx] = 0.0;
        return;
    }
    let l = p.size / 3u;
    let m = (l - 1u) / 2u;
    let dyy = box_sum(x + 1u - l, y - hs, x + l, y + hs + 1u)
        - 3u * box_sum(x + 1u - l, y - m, x + l, y + m + 1u);
    let dxx = box_sum(x - hs, y + 1u - l, x + hs + 1u, y + l)
        - 3u * box_sum(x - m, y + 1u - l, x + m + 1u, y + l);
    let dxy = box_sum(x - l, y - l, x, y)
        + box_sum(x + 1u, y + 1u, x + l + 1u, y + l + 1u)
        - box_sum(x + 1u, y - l, x + l + 1u, y)
        - box_sum(x - l, y + 1u, x, y + l + 1u);
    let fxx = f32(bitcast<i32>(dxx)) * p.inv_a;
    let fyy = f32(bitcast<i32>(dyy)) * p.inv_a;
    let fxy = f32(bitcast<i32>(dxy)) * p.inv_d;
    det[idx] = fxx * fyy - p.dxy_weight_sq * fxy * fxy;
}
