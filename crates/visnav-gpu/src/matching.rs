//! Descriptor matching on the GPU: `visnav_core::vision::match_features` (Lowe's ratio test, the
//! Laplacian gate, the spatial gate around predicted positions, the mutual check) with its two
//! nearest neighbours found by `shaders/match.wgsl`, brute force, one invocation per query (and
//! per train keypoint for the mutual check). The distances sum the CPU's 8 lanes in its order, so
//! the nearest neighbours, the ratio test and the matches are the CPU's (a GPU that fuses a
//! multiply-add can move a distance by an ulp: a tie within that decides differently).

use visnav_core::vision::{Features, Match, MatchParams};
use wgpu::util::DeviceExt;

use crate::{GpuError, GpuSurf, frame, grid};

/// Below this many query x train pairs the CPU matches in well under a millisecond, less than
/// one round trip to a GPU costs: the CPU takes them (the same matches either way).
pub(crate) const GPU_MATCH_MIN_PAIRS: usize = 1 << 18;
/// Invocations per workgroup of the match pass.
const MATCH_WORKGROUP: u32 = 64;
/// Train rows per invocation (`shaders/match.wgsl`): chunks spread small query sets over more
/// invocations, and keep each invocation's loops far below llvmpipe's 65535 iterations (about
/// 18 per row for SURF-128).
const CHUNK_ROWS: u32 = 1024;

/// The uniform of `shaders/match.wgsl` (8 x 4 bytes).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct MatchUniform {
    n_a: u32,
    n_b: u32,
    stride8: u32,
    lap_gate: u32,
    spatial: u32,
    r2: f32,
    per_row: u32,
    chunk_rows: u32,
}

/// The inputs `match_features` accepts (anything else goes to the CPU, whose error is the
/// answer).
pub(crate) fn gpu_can_match(
    query: &Features,
    train: &Features,
    params: &MatchParams,
    pred: Option<&[[f32; 2]]>,
) -> bool {
    let ratio_ok = params.ratio.is_finite() && params.ratio > 0.0 && params.ratio <= 1.0;
    let gate_ok = match params.spatial_radius_px {
        None => true,
        Some(r) => r.is_finite() && r > 0.0 && pred.is_some_and(|p| p.len() == query.len()),
    };
    query.kind() == train.kind() && ratio_ok && gate_ok && !query.is_empty() && !train.is_empty()
}

/// Per keypoint: position (train) or prediction (query), Laplacian sign, usable.
fn info(f: &Features, pred: Option<&[[f32; 2]]>) -> Vec<[f32; 4]> {
    f.keypoints
        .iter()
        .enumerate()
        .map(|(i, k)| {
            let [x, y] = pred.and_then(|p| p.get(i).copied()).unwrap_or([k.x, k.y]);
            let usable = x.is_finite() && y.is_finite();
            let (x, y) = if usable { (x, y) } else { (0.0, 0.0) };
            [x, y, f32::from(k.laplacian), f32::from(u8::from(usable))]
        })
        .collect()
}

impl GpuSurf {
    /// A buffer of `bytes` within the adapter's storage binding size, else an error (the CPU
    /// takes the work).
    fn fits(&self, bytes: u64, what: &str) -> Result<(), GpuError> {
        let max = self.device.limits().max_storage_buffer_binding_size;
        if bytes > max {
            return Err(GpuError::Run(format!(
                "{what}: {bytes} bytes exceed the adapter's storage buffer size ({max})"
            )));
        }
        Ok(())
    }
}

/// The chunks' two nearest neighbours (`[chunk][row]`) merged in chunk order with the CPU's
/// update rule (strict comparisons, so the first of equal distances wins): the two nearest over
/// all rows, as one scan in index order gives.
fn merge_chunks(per_chunk: &[[u32; 4]], n: usize) -> Vec<[u32; 4]> {
    (0..n)
        .map(|i| {
            let (mut arg, mut b1, mut b2, mut seen) =
                (u32::MAX, f32::INFINITY, f32::INFINITY, 0u32);
            for c in per_chunk.iter().skip(i).step_by(n.max(1)) {
                let [ca, c1, c2, cseen] = *c;
                let values = [(f32::from_bits(c1), Some(ca)), (f32::from_bits(c2), None)];
                for (d, idx) in values.into_iter().take(cseen.min(2) as usize) {
                    if d < b1 {
                        b2 = b1;
                        b1 = d;
                        // The chunk's second value never displaces its own first.
                        arg = idx.unwrap_or(arg);
                    } else if d < b2 {
                        b2 = d;
                    }
                    seen = (seen + 1).min(2);
                }
            }
            [arg, b1.to_bits(), b2.to_bits(), seen]
        })
        .collect()
}

/// One side's buffers: descriptors (`stride` floats each) and keypoint info.
struct Side {
    desc: wgpu::Buffer,
    info: wgpu::Buffer,
    n: u32,
    stride: usize,
}

impl GpuSurf {
    /// [`visnav_core::vision::match_features`] with the nearest neighbours found on the GPU
    /// (module doc). The inputs must be ones the CPU accepts.
    pub fn match_features(
        &self,
        query: &Features,
        train: &Features,
        params: &MatchParams,
        predicted_in_train: Option<&[[f32; 2]]>,
    ) -> Result<Vec<Match>, GpuError> {
        if !gpu_can_match(query, train, params, predicted_in_train) {
            return Err(GpuError::Run(
                "matching inputs the CPU matcher refuses".into(),
            ));
        }
        self.scoped(|| self.match_unscoped(query, train, params, predicted_in_train))
    }

    fn match_unscoped(
        &self,
        query: &Features,
        train: &Features,
        params: &MatchParams,
        predicted_in_train: Option<&[[f32; 2]]>,
    ) -> Result<Vec<Match>, GpuError> {
        let gate = params.spatial_radius_px.map(|r| r * r);
        let pred = gate.and(predicted_in_train);
        let q = self.side(query, pred)?;
        let t = self.side(train, None)?;
        let forward = self.two_nn(&q, &t, params, gate)?;
        let ratio2 = params.ratio * params.ratio;
        let mut out = Vec::new();
        for (qi, b) in forward.iter().enumerate() {
            let [arg, d1, d2, seen] = *b;
            if seen == 0 {
                continue;
            }
            let (d1, d2) = (f32::from_bits(d1), f32::from_bits(d2));
            let d2 = if seen >= 2 { d2 } else { f32::INFINITY };
            // A lone candidate (d2 infinite) gives no evidence of distinctiveness: rejected.
            if params.ratio < 1.0 && !(d2.is_finite() && d1 < ratio2 * d2) {
                continue;
            }
            out.push(Match {
                query: qi,
                train: arg as usize,
                distance: d1.max(0.0).sqrt(),
                second_distance: d2.max(0.0).sqrt(),
            });
        }
        if params.mutual && !out.is_empty() {
            // The gates are symmetric: a train keypoint's candidates are the queries whose
            // prediction lies within the radius of it.
            let reverse = self.two_nn(&t, &q, params, gate)?;
            out.retain(|m| {
                reverse
                    .get(m.train)
                    .is_some_and(|b| b[3] > 0 && b[0] as usize == m.query)
            });
        }
        Ok(out)
    }

    fn side(&self, f: &Features, pred: Option<&[[f32; 2]]>) -> Result<Side, GpuError> {
        let n = u32::try_from(f.len()).map_err(|_| GpuError::Run("too many features".into()))?;
        self.fits(
            std::mem::size_of_val(f.descriptors_padded()) as u64,
            "descriptors",
        )?;
        let init = |label: &str, contents: &[u8]| {
            self.device
                .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::STORAGE,
                })
        };
        let info = info(f, pred);
        Ok(Side {
            desc: init("descriptors", bytemuck::cast_slice(f.descriptors_padded())),
            info: init("keypoint info", bytemuck::cast_slice(&info)),
            n,
            stride: f.kind().stride(),
        })
    }

    /// Two nearest neighbours of every row of `a` among the rows of `b` (`[index, d1^2 bits,
    /// d2^2 bits, candidates]`).
    fn two_nn(
        &self,
        a: &Side,
        b: &Side,
        params: &MatchParams,
        gate_r2: Option<f32>,
    ) -> Result<Vec<[u32; 4]>, GpuError> {
        let (gx, gy) = grid(a.n.div_ceil(MATCH_WORKGROUP));
        let u = MatchUniform {
            n_a: a.n,
            n_b: b.n,
            stride8: (a.stride / 8) as u32,
            lap_gate: u32::from(params.laplacian_gate),
            spatial: u32::from(gate_r2.is_some()),
            r2: gate_r2.unwrap_or(0.0),
            per_row: gx * MATCH_WORKGROUP,
            chunk_rows: CHUNK_ROWS,
        };
        let chunks = b.n.div_ceil(CHUNK_ROWS).max(1);
        let dev = &self.device;
        let ub = frame::uniform(dev, "match", bytemuck::bytes_of(&u));
        let bytes = u64::from(a.n) * u64::from(chunks) * 16;
        self.fits(bytes, "nearest neighbours")?;
        let out = frame::storage(dev, "nearest", bytes, wgpu::BufferUsages::COPY_SRC);
        let rb = frame::readback(dev, bytes);
        let bg = frame::bind_group(
            dev,
            &self.pipelines.matcher,
            &[
                (0, &a.desc),
                (1, &b.desc),
                (2, &a.info),
                (3, &b.info),
                (4, &out),
                (5, &ub),
            ],
        );
        let mut enc = self.encoder();
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.pipelines.matcher);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, chunks);
        }
        enc.copy_buffer_to_buffer(&out, 0, &rb, 0, bytes);
        self.queue.submit([enc.finish()]);
        let per_chunk: Vec<[u32; 4]> = self.read(&rb, bytes)?;
        Ok(merge_chunks(&per_chunk, a.n as usize))
    }
}
