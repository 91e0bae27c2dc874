//! The GPU buffers of one image size and layer plan, kept between frames (a camera's frames all
//! have one size): pixels, integral table, response layers, the maxima's append buffer, the
//! keypoints and descriptors, and their readback buffers. Built on the first frame of a size,
//! rebuilt when the size or the plan changes; the keypoint buffers grow to the largest count
//! seen.

use visnav_core::vision::LayerSpec;
use visnav_core::vision::surf::{ExtremaWindow, HESSIAN_DXY_WEIGHT_SQ, extrema_window};
use wgpu::util::DeviceExt;

use crate::pipelines::Pipelines;

/// Most maxima one image may have on the GPU (32 bytes each: 4 MiB); an image with more is
/// computed on the CPU (no realistic threshold gets near: an HD frame at OpenCV's default
/// threshold has a few thousand).
pub(crate) const MAX_EXTREMA: usize = 1 << 17;
/// Bytes of one maximum in `shaders/extrema.wgsl` (`Extremum`).
pub(crate) const EXTREMUM_BYTES: u64 = 32;
/// Largest image side: the descriptor's 16.16 fixed-point cell origins hold coordinates below
/// 32768 px with room for the window.
pub(crate) const MAX_SIDE_PX: usize = 16_384;

/// The layer uniform of `shaders/hessian.wgsl` (12 x 4 bytes).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct LayerUniform {
    pub w: u32,
    pub h: u32,
    pub stride: u32,
    pub size: u32,
    pub step: u32,
    pub rows: u32,
    pub cols: u32,
    pub out_offset: u32,
    pub inv_a: f32,
    pub inv_d: f32,
    pub dxy_weight_sq: f32,
    pub pad: u32,
}

/// The triple uniform of `shaders/extrema.wgsl` (16 x 4 bytes).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct TripleUniform {
    pub lo_off: u32,
    pub mid_off: u32,
    pub hi_off: u32,
    pub cols: u32,
    pub c_lo: u32,
    pub r_lo: u32,
    pub c_n: u32,
    pub r_n: u32,
    pub step: u32,
    pub mid_size: u32,
    pub stride: u32,
    pub tag: u32,
    pub threshold: f32,
    pub inv_a: f32,
    pub capacity: u32,
    pub pad: u32,
}

/// What a frame's buffers were built for.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct FrameKey {
    pub width: usize,
    pub height: usize,
    pub plan: Vec<Vec<LayerSpec>>,
}

/// One middle layer's extrema dispatch.
pub(crate) struct TripleSlot {
    pub data: TripleUniform,
    pub uniform: wgpu::Buffer,
    pub bind_group: wgpu::BindGroup,
    /// The layers' sizes: the lower one's for the scale step of the interpolation.
    pub mid: LayerSpec,
    pub lo_size: usize,
    pub octave: usize,
}

/// The buffers of one image size and plan (module doc).
pub(crate) struct Frame {
    pub key: FrameKey,
    pub dims: [u32; 4],
    pub px: wgpu::Buffer,
    pub table: wgpu::Buffer,
    pub table_bytes: u64,
    pub det: wgpu::Buffer,
    pub det_bytes: u64,
    pub rows_bg: wgpu::BindGroup,
    pub cols_bg: wgpu::BindGroup,
    pub layers: Vec<(wgpu::BindGroup, LayerUniform)>,
    pub triples: Vec<TripleSlot>,
    pub found: wgpu::Buffer,
    pub count: wgpu::Buffer,
    pub count_rb: wgpu::Buffer,
    pub found_rb: wgpu::Buffer,
    pub describe: Option<DescribeBuffers>,
}

/// The keypoint, orientation and descriptor buffers, for up to `capacity` keypoints of
/// `stride` floats, with the descriptor weights of `samples` per side.
pub(crate) struct DescribeBuffers {
    pub capacity: usize,
    pub stride: usize,
    pub samples: usize,
    pub kps: wgpu::Buffer,
    pub ori: wgpu::Buffer,
    pub desc: wgpu::Buffer,
    pub ori_rb: wgpu::Buffer,
    pub desc_rb: wgpu::Buffer,
    pub ori_params: wgpu::Buffer,
    pub desc_params: wgpu::Buffer,
    pub ori_bg: wgpu::BindGroup,
    pub desc_bg: wgpu::BindGroup,
}

/// Why a frame cannot be built (the caller names the image).
pub(crate) type BuildError = String;

pub(crate) fn storage(
    dev: &wgpu::Device,
    label: &str,
    bytes: u64,
    extra: wgpu::BufferUsages,
) -> wgpu::Buffer {
    dev.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(16),
        usage: wgpu::BufferUsages::STORAGE | extra,
        mapped_at_creation: false,
    })
}

pub(crate) fn readback(dev: &wgpu::Device, bytes: u64) -> wgpu::Buffer {
    dev.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: bytes.max(16),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

pub(crate) fn uniform(dev: &wgpu::Device, label: &str, contents: &[u8]) -> wgpu::Buffer {
    dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}

pub(crate) fn bind_group(
    dev: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    entries: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = entries
        .iter()
        .map(|(binding, buf)| wgpu::BindGroupEntry {
            binding: *binding,
            resource: buf.as_entire_binding(),
        })
        .collect();
    dev.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

impl Frame {
    /// Build the buffers for `key` (sizes checked against the device's limits).
    pub fn new(dev: &wgpu::Device, p: &Pipelines, key: FrameKey) -> Result<Self, BuildError> {
        let (w, h) = (key.width, key.height);
        if w == 0 || h == 0 {
            return Err("empty".into());
        }
        if w > MAX_SIDE_PX || h > MAX_SIDE_PX {
            return Err(format!("a side beyond {MAX_SIDE_PX} px"));
        }
        let max_binding = dev.limits().max_storage_buffer_binding_size;
        let stride = w + 1;
        let table_bytes = (stride * (h + 1) * 4) as u64;
        if table_bytes > max_binding {
            return Err("its integral table exceeds the adapter's storage buffer size".into());
        }
        let dims = [w as u32, h as u32, stride as u32, 0];
        let (layer_data, n_det) = layer_uniforms(&key.plan, dims).ok_or("too large")?;
        let det_bytes = (n_det.max(1) * 4) as u64;
        if det_bytes > max_binding {
            return Err("its response layers exceed the adapter's storage buffer size".into());
        }
        let px = storage(
            dev,
            "pixels",
            (w * h * 4) as u64,
            wgpu::BufferUsages::COPY_DST,
        );
        let copy = wgpu::BufferUsages::COPY_SRC;
        let table = storage(dev, "integral", table_bytes, copy);
        let det = storage(dev, "responses", det_bytes, copy);
        let dims_buf = uniform(dev, "dims", bytemuck::cast_slice(&dims));
        // Each pass's layout is derived from what its entry point uses: the column pass does
        // not read the pixels.
        let rows_bg = bind_group(
            dev,
            &p.integral_rows,
            &[(0, &dims_buf), (1, &px), (2, &table)],
        );
        let cols_bg = bind_group(dev, &p.integral_cols, &[(0, &dims_buf), (2, &table)]);
        let layers = layer_data
            .iter()
            .map(|u| {
                let ub = uniform(dev, "layer", bytemuck::bytes_of(u));
                let bg = bind_group(dev, &p.hessian, &[(0, &table), (1, &det), (2, &ub)]);
                (bg, *u)
            })
            .collect();
        let found = storage(dev, "maxima", MAX_EXTREMA as u64 * EXTREMUM_BYTES, copy);
        let count = storage(dev, "count", 4, copy | wgpu::BufferUsages::COPY_DST);
        let triples = triple_slots(
            dev,
            p,
            &key,
            dims,
            &layer_data,
            [&det, &table, &found, &count],
        );
        Ok(Self {
            count_rb: readback(dev, 4),
            found_rb: readback(dev, MAX_EXTREMA as u64 * EXTREMUM_BYTES),
            key,
            dims,
            px,
            table,
            table_bytes,
            det,
            det_bytes,
            rows_bg,
            cols_bg,
            layers,
            triples,
            found,
            count,
            describe: None,
        })
    }

    /// Record the integral passes and the response layers.
    pub fn encode_layers(&self, p: &Pipelines, enc: &mut wgpu::CommandEncoder) {
        // Separate passes order the writes of one before the reads of the next.
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&p.integral_rows);
            pass.set_bind_group(0, &self.rows_bg, &[]);
            // One workgroup per row (at most MAX_SIDE_PX + 1, within the dispatch limit).
            pass.dispatch_workgroups(self.dims[1] + 1, 1, 1);
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&p.integral_cols);
            pass.set_bind_group(0, &self.cols_bg, &[]);
            pass.dispatch_workgroups((self.dims[0] + 1).div_ceil(crate::INTEGRAL_WORKGROUP), 1, 1);
        }
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
        pass.set_pipeline(&p.hessian);
        for (bg, u) in &self.layers {
            pass.set_bind_group(0, bg, &[]);
            pass.dispatch_workgroups(
                u.cols.div_ceil(crate::TILE),
                u.rows.div_ceil(crate::TILE),
                1,
            );
        }
    }

    /// Record the extrema passes (the count cleared first) and the count's copy to its readback.
    pub fn encode_extrema(&self, p: &Pipelines, enc: &mut wgpu::CommandEncoder) {
        enc.clear_buffer(&self.count, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&p.extrema);
            for t in &self.triples {
                pass.set_bind_group(0, &t.bind_group, &[]);
                pass.dispatch_workgroups(
                    t.data.c_n.div_ceil(crate::TILE),
                    t.data.r_n.div_ceil(crate::TILE),
                    1,
                );
            }
        }
        enc.copy_buffer_to_buffer(&self.count, 0, &self.count_rb, 0, 4);
    }
}

/// The uniforms of the plan's layers, packed one after the other in the response buffer, and the
/// number of responses (`None`: a figure beyond 32 bits).
fn layer_uniforms(plan: &[Vec<LayerSpec>], dims: [u32; 4]) -> Option<(Vec<LayerUniform>, usize)> {
    let mut uniforms = Vec::new();
    let mut offset = 0usize;
    for s in plan.iter().flatten() {
        let l = s.size / 3;
        uniforms.push(LayerUniform {
            w: dims[0],
            h: dims[1],
            stride: dims[2],
            size: u32::try_from(s.size).ok()?,
            step: u32::try_from(s.step).ok()?,
            rows: u32::try_from(s.rows).ok()?,
            cols: u32::try_from(s.cols).ok()?,
            out_offset: u32::try_from(offset).ok()?,
            // The CPU's factors, bit for bit (a GPU's division need not be correctly rounded).
            inv_a: 1.0 / (l * (2 * l - 1)) as f32,
            inv_d: 1.0 / (l * l) as f32,
            dxy_weight_sq: HESSIAN_DXY_WEIGHT_SQ,
            pad: 0,
        });
        offset += s.rows * s.cols;
    }
    Some((uniforms, offset))
}

/// One extrema dispatch per middle layer of every octave, over the CPU's search window
/// (`extrema_window`); the threshold is written per frame.
fn triple_slots(
    dev: &wgpu::Device,
    p: &Pipelines,
    key: &FrameKey,
    dims: [u32; 4],
    layers: &[LayerUniform],
    [det, table, found, count]: [&wgpu::Buffer; 4],
) -> Vec<TripleSlot> {
    let mut out = Vec::new();
    let mut first = 0usize;
    for (o, specs) in key.plan.iter().enumerate() {
        for k in 1..specs.len().saturating_sub(1) {
            let (lo, mid, hi) = (
                &layers[first + k - 1],
                &layers[first + k],
                &layers[first + k + 1],
            );
            let Some(ExtremaWindow {
                c_lo,
                c_hi,
                r_lo,
                r_hi,
            }) = extrema_window(key.width, key.height, &specs[k], &specs[k + 1])
            else {
                continue;
            };
            let data = TripleUniform {
                lo_off: lo.out_offset,
                mid_off: mid.out_offset,
                hi_off: hi.out_offset,
                cols: mid.cols,
                c_lo: c_lo as u32,
                r_lo: r_lo as u32,
                c_n: (c_hi + 1 - c_lo) as u32,
                r_n: (r_hi + 1 - r_lo) as u32,
                step: mid.step,
                mid_size: mid.size,
                stride: dims[2],
                tag: ((o as u32) << 8) | k as u32,
                threshold: 0.0,
                inv_a: mid.inv_a,
                capacity: MAX_EXTREMA as u32,
                pad: 0,
            };
            let ub = uniform(dev, "triple", bytemuck::bytes_of(&data));
            let bg = bind_group(
                dev,
                &p.extrema,
                &[(0, det), (1, table), (2, found), (3, count), (4, &ub)],
            );
            out.push(TripleSlot {
                data,
                uniform: ub,
                bind_group: bg,
                mid: specs[k],
                lo_size: specs[k - 1].size,
                octave: o,
            });
        }
        first += specs.len();
    }
    out
}

impl DescribeBuffers {
    /// Buffers for `capacity` keypoints of `kind`; `[table, samples, weights]` are bound as the
    /// shaders expect.
    pub fn new(
        dev: &wgpu::Device,
        p: &Pipelines,
        [table, samples, weights]: [&wgpu::Buffer; 3],
        capacity: usize,
        kind: visnav_core::vision::DescriptorKind,
    ) -> Self {
        let copy = wgpu::BufferUsages::COPY_SRC;
        let kps = storage(
            dev,
            "keypoints",
            capacity as u64 * 16,
            wgpu::BufferUsages::COPY_DST,
        );
        let ori = storage(dev, "orientations", capacity as u64 * 16, copy);
        let desc_bytes = (capacity * kind.stride() * 4) as u64;
        let desc = storage(dev, "descriptors", desc_bytes, copy);
        let ori_params = uniform(dev, "orientation params", &[0u8; 48]);
        let desc_params = uniform(dev, "descriptor params", &[0u8; 64]);
        let ori_bg = bind_group(
            dev,
            &p.orientation,
            &[
                (0, table),
                (1, &kps),
                (2, samples),
                (3, &ori),
                (4, &ori_params),
            ],
        );
        let desc_bg = bind_group(
            dev,
            &p.descriptor,
            &[
                (0, table),
                (1, &kps),
                (2, &ori),
                (3, weights),
                (4, &desc),
                (5, &desc_params),
            ],
        );
        Self {
            capacity,
            stride: kind.stride(),
            samples: kind.samples(),
            ori_rb: readback(dev, capacity as u64 * 16),
            desc_rb: readback(dev, desc_bytes),
            kps,
            ori,
            desc,
            ori_params,
            desc_params,
            ori_bg,
            desc_bg,
        }
    }
}
