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

// Pass 1: one workgroup per table row, its running sum as a scan of 256-pixel tiles (each tile a
// Hillis-Steele inclusive scan in workgroup memory, plus the carry of the tiles before it): the
// pixels are read by neighbouring invocations at neighbouring addresses. Wrapping addition is
// associative, so the sums are the sequential ones exactly.
const SCAN: u32 = 256u;
var<workgroup> part: array<u32, 256>;

@compute @workgroup_size(256)
fn rows(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let y = wg.x;
    if (y > dims.h) {
        return;
    }
    let base = y * dims.stride;
    if (lid == 0u) {
        table[base] = 0u;
    }
    var carry = 0u;
    let tiles = (dims.w + SCAN - 1u) / SCAN;
    for (var t = 0u; t < tiles; t = t + 1u) {
        let x = t * SCAN + lid;
        var v = 0u;
        if (y > 0u && x < dims.w) {
            v = px[(y - 1u) * dims.w + x];
        }
        part[lid] = v;
        workgroupBarrier();
        for (var off = 1u; off < SCAN; off = off * 2u) {
            var add = 0u;
            if (lid >= off) {
                add = part[lid - off];
            }
            workgroupBarrier();
            part[lid] = part[lid] + add;
            workgroupBarrier();
        }
        if (x < dims.w) {
            table[base + x + 1u] = carry + part[lid];
        }
        carry = carry + part[SCAN - 1u];
        workgroupBarrier();
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
