// Two nearest neighbours in L2 descriptor distance (visnav-core's matcher: two_nn, dist2,
// match_features' gates), one invocation per row of set A against every row of set B in index
// order. Forward: A = query, B = train; reverse (the mutual check): A = train, B = query. A pair
// is compared when the Laplacian signs agree (if gated) and, with the spatial gate, when the train
// keypoint lies within the radius of the query's prediction (a query without a finite
// prediction has none). The squared distance sums 8 lanes in the CPU's order. Writes, per chunk
// of train rows, (best index, d1^2 bits, d2^2 bits, candidates seen, at most 2).

struct MatchParams {
    n_a: u32,
    n_b: u32,
    stride8: u32,
    lap_gate: u32,
    spatial: u32,
    r2: f32,
    per_row: u32,
    chunk_rows: u32,
}

// Per keypoint: x, y (train: its position; query: its prediction), Laplacian sign, usable (1: the
// position or prediction is finite).
@group(0) @binding(0) var<storage, read> a_desc: array<vec4<f32>>;
@group(0) @binding(1) var<storage, read> b_desc: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> a_info: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read> b_info: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> best: array<vec4<u32>>;
@group(0) @binding(5) var<uniform> m: MatchParams;

fn compatible(a: vec4<f32>, b: vec4<f32>) -> bool {
    if (m.lap_gate == 1u && a.z != b.z) {
        return false;
    }
    if (m.spatial == 1u) {
        if (a.w == 0.0 || b.w == 0.0) {
            return false;
        }
        // (train - prediction) either way round: the square is the same.
        let d = b.xy - a.xy;
        return d.x * d.x + d.y * d.y <= m.r2;
    }
    return true;
}

// Train rows staged through workgroup memory, TILE_ROWS at a time (a row is at most 32 vec4:
// SURF-128), each loaded once per workgroup instead of once per invocation.
const TILE_ROWS: u32 = 16u;
var<workgroup> tile_desc: array<vec4<f32>, 512>;
var<workgroup> tile_info: array<vec4<f32>, 16>;

// Invocation (x, y) takes query row i against train rows chunk_rows * z .. of chunk z (the
// dispatch's third dimension); the host merges the chunks' two nearest in chunk order, which is
// the CPU's scan in index order. Bounded chunks also keep every invocation's loop short (Mesa's
// llvmpipe stops an invocation's loops after 65535 iterations).
@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let i = gid.y * m.per_row + gid.x;
    let valid = gid.x < m.per_row && i < m.n_a;
    let row_v4 = m.stride8 * 2u;
    var ai = vec4<f32>(0.0);
    if (valid) {
        ai = a_info[i];
    }
    let abase = i * row_v4;
    var b1 = 0.0;
    var b2 = 0.0;
    var seen = 0u;
    var arg = 0xffffffffu;
    let first = gid.z * m.chunk_rows;
    let end = min(first + m.chunk_rows, m.n_b);
    for (var j0 = first; j0 < end; j0 = j0 + TILE_ROWS) {
        let rows = min(TILE_ROWS, end - j0);
        for (var k = lid; k < rows * row_v4; k = k + 64u) {
            tile_desc[k] = b_desc[j0 * row_v4 + k];
        }
        if (lid < rows) {
            tile_info[lid] = b_info[j0 + lid];
        }
        workgroupBarrier();
        if (valid) {
            for (var r = 0u; r < rows; r = r + 1u) {
                if (!compatible(ai, tile_info[r])) {
                    continue;
                }
                let tb = r * row_v4;
                var lo = vec4<f32>(0.0);
                var hi = vec4<f32>(0.0);
                for (var c = 0u; c < m.stride8; c = c + 1u) {
                    let dl = a_desc[abase + 2u * c] - tile_desc[tb + 2u * c];
                    let dh = a_desc[abase + 2u * c + 1u] - tile_desc[tb + 2u * c + 1u];
                    lo = lo + dl * dl;
                    hi = hi + dh * dh;
                }
                let d = ((lo.x + hi.x) + (lo.y + hi.y)) + ((lo.z + hi.z) + (lo.w + hi.w));
                if (seen == 0u || d < b1) {
                    b2 = b1;
                    b1 = d;
                    arg = j0 + r;
                    seen = min(seen + 1u, 2u);
                } else if (seen == 1u || d < b2) {
                    b2 = d;
                    seen = 2u;
                }
            }
        }
        workgroupBarrier();
    }
    if (valid) {
        best[gid.z * m.n_a + i] = vec4<u32>(arg, bitcast<u32>(b1), bitcast<u32>(b2), seen);
    }
}
