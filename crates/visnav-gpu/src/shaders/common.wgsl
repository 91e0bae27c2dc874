// Shared by orientation.wgsl and descriptor.wgsl (the host prepends this file): the integral
// table and the Haar wavelet sums of visnav-core's SURF, with the CPU's index rules.

@group(0) @binding(0) var<storage, read> table: array<u32>;

// f32::round (half away from zero), exact for any float.
fn round_away(x: f32) -> f32 {
    let t = trunc(x);
    if (abs(x - t) >= 0.5) {
        return t + sign(x);
    }
    return t;
}

// visnav-core's boundary_index: floor(f + 1) clamped to [half, n - half] (truncation, saturating).
fn boundary_index(f: f32, half: u32, n: u32) -> u32 {
    let v = i32(clamp(f + 1.0, -2147483648.0, 2147483520.0));
    return u32(clamp(v, i32(half), i32(n - half)));
}

// Haar responses (dx, dy) of side 2 half centred at table corner (x, y): visnav-core's
// haar_from_corners, wrapping 32-bit arithmetic.
fn haar_at(x: u32, y: u32, half: u32, stride: u32) -> vec2<f32> {
    let r0 = (y - half) * stride;
    let r1 = y * stride;
    let r2 = (y + half) * stride;
    let x0 = x - half;
    let x2 = x + half;
    let a00 = table[r0 + x0];
    let a01 = table[r0 + x];
    let a02 = table[r0 + x2];
    let a10 = table[r1 + x0];
    let a12 = table[r1 + x2];
    let a20 = table[r2 + x0];
    let a21 = table[r2 + x];
    let a22 = table[r2 + x2];
    let dx = a22 - a02 - 2u * a21 + 2u * a01 + a20 - a00;
    let dy = a22 - 2u * a12 - a20 + 2u * a10 + a02 - a00;
    return vec2<f32>(f32(bitcast<i32>(dx)), f32(bitcast<i32>(dy)));
}

// visnav-core's haar(): the box shifted inside the image, shrunk for tiny images.
fn haar_clamped(fx: f32, fy: f32, half_in: u32, w: u32, h: u32, stride: u32) -> vec2<f32> {
    let half = max(min(min(half_in, w / 2u), h / 2u), 1u);
    if (2u * half > w || 2u * half > h) {
        return vec2<f32>(0.0);
    }
    return haar_at(boundary_index(fx, half, w), boundary_index(fy, half, h), half, stride);
}
