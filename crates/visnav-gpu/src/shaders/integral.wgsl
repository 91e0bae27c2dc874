// Summed-area table with wrapping 32-bit cells, as visnav-core's IntegralImage:
// table[y * stride + x] = sum of px[v * w + u] for u < x, v < y; (h + 1) x (w + 1), first row and
// column zero. u32 addition wraps (WGSL), so every box sum is exact modulo 2^32.

struct Dims {
    w: u32,
    h: u32,
    stride: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> dims: Dims;
@group(0) @binding(1) var<storage, read> px: array<u32>;
@group(0) @binding(2) var<storage, read_write> table: array<u32>;

// Pass 1: one invocation per table row, the running sum along it.
@compute @workgroup_size(64)
fn rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let y = gid.x;
    if (y > dims.h) {
        return;
    }
    let base = y * dims.stride;
    table[base] = 0u;
    var acc = 0u;
    for (var x = 0u; x < dims.w; x = x + 1u) {
        if (y > 0u) {
            acc = acc + px[(y - 1u) * dims.w + x];
        }
        table[base + x + 1u] = acc;
    }
}

// Pass 2: one invocation per table column, the running sum down it.
@compute @workgroup_size(64)
fn cols(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x = gid.x;
    if (x > dims.w) {
        return;
    }
    var acc = 0u;
    for (var y = 1u; y <= dims.h; y = y + 1u) {
        let i = y * dims.stride + x;
        acc = acc + table[i];
        table[i] = acc;
    }
}
