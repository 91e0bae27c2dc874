#![warn(missing_docs)]
//! SURF on the GPU through wgpu compute shaders (Vulkan, Metal, DX12; Mesa's lavapipe gives a
//! software Vulkan adapter where there is no GPU), producing the same features as visnav-core's
//! CPU SURF, which stays the reference (`visnav_core::vision::surf`; Bay et al. 2008).
//!
//! Every stage runs on the GPU, each shader a port of the CPU function it names:
//! * `shaders/integral.wgsl`: the integral image (a row pass, a workgroup scan per row, then a
//!   column pass; wrapping 32-bit cells as the CPU's `IntegralImage`, so every box sum is the same
//!   integer);
//! * `shaders/hessian.wgsl`: every fast-Hessian response layer of [`Surf::layer_plan`] (the box
//!   sums of `hessian_at`, the CPU's normalisation factors passed in);
//! * `shaders/extrema.wgsl`: the 3x3x3 maxima over the CPU's search window (`extrema_window`)
//!   and their quadratic interpolation (`find_maxima`, `interpolate`; f32 here, f64 there);
//! * `shaders/orientation.wgsl`: the dominant orientation (`orientation`, `best_window`; the
//!   CPU's sample table, weights and polynomial atan2);
//! * `shaders/descriptor.wgsl`: the descriptors by the CPU's three sampling paths
//!   (`describe_one`, `describe_rotated`), one workgroup per keypoint;
//! * `shaders/match.wgsl`: brute-force two-nearest-neighbour matching with the CPU matcher's
//!   gates and distance (`matching`; `visnav_core::vision::match_features`).
//!
//! The host sorts the maxima into the CPU's order, turns them into keypoints with the CPU's
//! formula (`keypoint_at`), applies `max_features` with the CPU's `select_spread`, and takes the
//! final `atan2` of each orientation (the GPU's trigonometry is not exact). A frame is three short
//! round trips: the layers and maxima (reading back their count), the maxima, then the
//! orientations and descriptors. Buffers are kept between frames of one size (`frame`).
//!
//! The parameters are the one `SurfParams` of the CPU path, so the two cannot disagree on what to
//! compute. They differ only where a GPU rounds differently (a fused multiply-add, a division
//! within 2.5 ulp, f32 interpolation): `tests/gpu_surf.rs` bounds that on real images.
//!
//! Errors: every operation runs inside wgpu error scopes (validation, out of memory, internal),
//! so a device error becomes a [`GpuError`], and the [`FeatureBackend`] computes that frame or
//! matching on the CPU instead (counted in [`GpuSurf::fallbacks`]).
//!
//! Adapter choice: a hardware adapter first; a software one (lavapipe, `DeviceType::Cpu`) only
//! when allowed ([`AdapterPolicy`]), and always reported as software so its times are never taken
//! for a GPU's.

mod frame;
mod matching;
mod pipelines;

use std::sync::{Mutex, mpsc};

use thiserror::Error;
use visnav_core::vision::surf::{
    Extremum as Maximum, ORIENTATION_BINS, ORIENTATION_WINDOW_BINS, descriptor_weights,
    keypoint_at, orientation_of_window, orientation_samples, select_spread,
};
use visnav_core::vision::{
    Detector, Family, FeatureBackend, Features, GrayImage, KeyPoint, LayerSpec, Match, MatchParams,
    Surf, match_features,
};
use wgpu::util::DeviceExt;

use frame::{DescribeBuffers, EXTREMUM_BYTES, Frame, FrameKey, MAX_EXTREMA};
use pipelines::Pipelines;

/// Threads per workgroup of the integral's column pass (`shaders/integral.wgsl`).
const INTEGRAL_WORKGROUP: u32 = 64;
/// Workgroup side of the response and extrema passes (8 x 8).
const TILE: u32 = 8;
/// Threads per workgroup of the orientation pass.
const ORIENTATION_WORKGROUP: u32 = 64;
/// Most workgroups along one dispatch dimension (WebGPU's limit); larger counts use rows.
const MAX_GROUPS_X: u32 = 65_535;

// The orientation shader's bin arrays are sized for the CPU's 72 bins of 5 degrees.
const _: () = assert!(ORIENTATION_BINS == 72 && ORIENTATION_WINDOW_BINS <= ORIENTATION_BINS);

/// Why the GPU path is not available or failed.
#[derive(Debug, Error)]
pub enum GpuError {
    /// No adapter at all (the message says what to install).
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// Only a software adapter (named) where [`AdapterPolicy::HardwareOnly`] was asked for.
    #[error("only a software adapter ({0}) was found and software adapters are not allowed")]
    SoftwareOnly(String),
    /// The adapter refused the device or its shaders.
    #[error("GPU device: {0}")]
    Device(String),
    /// An operation on the device failed (an error scope, a read-back, a size the buffers cannot
    /// hold).
    #[error("GPU: {0}")]
    Run(String),
    /// The buffers for an image of this size could not be built.
    #[error("image of {width} x {height} px: {reason}")]
    Image {
        /// Image width, px.
        width: usize,
        /// Image height, px.
        height: usize,
        /// Why, in words.
        reason: String,
    },
    /// The CPU types refused the result (descriptors that do not fit the keypoints).
    #[error(transparent)]
    Vision(#[from] visnav_core::vision::VisionError),
}

/// Which adapters may be used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterPolicy {
    /// A hardware GPU only (integrated, discrete or virtual).
    HardwareOnly,
    /// A hardware GPU when there is one, else a software adapter (lavapipe: tests, CI).
    AllowSoftware,
}

/// The adapter in use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterInfo {
    /// The adapter's name as the driver reports it.
    pub name: String,
    /// `vulkan`, `metal`, `dx12`.
    pub backend: String,
    /// `discrete`, `integrated`, `virtual`, `cpu` (software), `other`.
    pub device_type: String,
    /// A software rasteriser (lavapipe, WARP, SwiftShader): its times are not a GPU's.
    pub software: bool,
}

impl std::fmt::Display for AdapterInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}, {}", self.name, self.backend, self.device_type)?;
        if self.software {
            write!(f, ", software: not a GPU")?;
        }
        write!(f, ")")
    }
}

fn adapter_info(a: &wgpu::Adapter) -> AdapterInfo {
    let i = a.get_info();
    let device_type = match i.device_type {
        wgpu::DeviceType::DiscreteGpu => "discrete",
        wgpu::DeviceType::IntegratedGpu => "integrated",
        wgpu::DeviceType::VirtualGpu => "virtual",
        wgpu::DeviceType::Cpu => "cpu",
        wgpu::DeviceType::Other => "other",
    };
    AdapterInfo {
        name: i.name.clone(),
        backend: i.backend.to_str().to_string(),
        device_type: device_type.to_string(),
        software: i.device_type == wgpu::DeviceType::Cpu,
    }
}

/// What one GPU submission computed for an image (for tests and diagnostics, [`GpuSurf::run`]).
#[derive(Debug, Clone, PartialEq)]
pub struct GpuLayers {
    /// The integral table, `(h + 1) x (w + 1)` (as `IntegralImage::data`).
    pub integral: Vec<i32>,
    /// The response layers of the plan, `[octave][layer]`, row-major on their grids.
    pub layers: Vec<Vec<Vec<f32>>>,
}

/// One maximum as `shaders/extrema.wgsl` writes it.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
struct Extremum {
    c: u32,
    r: u32,
    /// `octave << 8 | layer`, bit 16 for a negative Laplacian.
    tag: u32,
    response: f32,
    ox: f32,
    oy: f32,
    os: f32,
    pad: u32,
}

/// The uniform of `shaders/orientation.wgsl` (12 x 4 bytes).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
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
    pad: [u32; 3],
}

/// The uniform of `shaders/descriptor.wgsl` (16 x 4 bytes).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
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
    pad: [u32; 3],
}

/// SURF on one GPU device (module doc).
pub struct GpuSurf {
    /// Frames computed on the CPU because the GPU failed ([`FeatureBackend`]).
    fallbacks: std::sync::atomic::AtomicU64,
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: AdapterInfo,
    pipelines: Pipelines,
    /// The orientation samples `(i + 6, j + 6, weight, 0)` of the CPU's table.
    ori_samples: wgpu::Buffer,
    /// The descriptor weights of the 20 x 20 and 18 x 18 grids.
    weights20: wgpu::Buffer,
    weights18: wgpu::Buffer,
    /// The buffers of the last frame's size (one frame at a time on the device).
    frame: Mutex<Option<Frame>>,
}

impl GpuSurf {
    /// Open an adapter by `policy` (hardware first) and build the pipelines.
    pub fn new(policy: AdapterPolicy) -> Result<Self, GpuError> {
        let (adapter, info) = choose_adapter(policy)?;
        let limits = wgpu::Limits {
            // HD frames: a 1921 x 1081 table and the layers of four octaves.
            max_storage_buffer_binding_size: adapter.limits().max_storage_buffer_binding_size,
            max_buffer_size: adapter.limits().max_buffer_size,
            // The extrema and descriptor passes bind 5 storage buffers (WebGPU's default is 8;
            // an adapter with fewer fails at pipeline creation, reported as a device error).
            max_storage_buffers_per_shader_stage: adapter
                .limits()
                .max_storage_buffers_per_shader_stage
                .min(8),
            ..wgpu::Limits::downlevel_defaults()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("visnav-gpu"),
            required_features: wgpu::Features::empty(),
            required_limits: limits,
            ..wgpu::DeviceDescriptor::default()
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", info.name)))?;
        // A driver that rejects a shader is an adapter we cannot use, not a crash.
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let pipelines = Pipelines::new(&device);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Device(format!("{}: {e}", info.name)));
        }
        // Every operation after this runs inside error scopes (`scoped`), so its errors become a
        // `GpuError` and the CPU takes the frame; this handler replaces wgpu's default, which
        // panics, for anything a driver reports outside them.
        device.on_uncaptured_error(std::sync::Arc::new(|_| {}));
        let init = |label: &str, contents: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let samples: Vec<[f32; 4]> = orientation_samples()
            .iter()
            .map(|&(i, j, w)| [f32::from(i), f32::from(j), w, 0.0])
            .collect();
        let ori_samples = init("orientation samples", bytemuck::cast_slice(&samples));
        let weights20 = init(
            "weights 20",
            bytemuck::cast_slice(descriptor_weights(
                visnav_core::vision::DescriptorKind::Surf64,
            )),
        );
        let weights18 = init(
            "weights 18",
            bytemuck::cast_slice(descriptor_weights(
                visnav_core::vision::DescriptorKind::Surf36,
            )),
        );
        Ok(Self {
            fallbacks: std::sync::atomic::AtomicU64::new(0),
            device,
            queue,
            info,
            pipelines,
            ori_samples,
            weights20,
            weights18,
            frame: Mutex::new(None),
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterInfo {
        &self.info
    }

    /// Frames (and matchings) the [`FeatureBackend`] computed on the CPU because the GPU failed.
    pub fn fallbacks(&self) -> u64 {
        self.fallbacks.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Fast-Hessian detection on the GPU: the keypoints of `surf.detect` (strongest first,
    /// orientation not yet assigned, capped to `max_features` with the CPU's spread).
    pub fn detect(&self, surf: &Surf, img: &GrayImage) -> Result<Vec<KeyPoint>, GpuError> {
        self.with_frame(surf, img, |frame| self.detect_on(frame, surf, img))
    }

    /// Detect, assign orientations (unless upright) and describe, all on the GPU: the features of
    /// `surf.detect_and_describe`.
    pub fn detect_and_describe(&self, surf: &Surf, img: &GrayImage) -> Result<Features, GpuError> {
        self.with_frame(surf, img, |frame| {
            let kps = self.detect_on(frame, surf, img)?;
            self.describe_on(frame, surf, kps)
        })
    }

    /// The GPU's integral table of `img` (`(h + 1) x (w + 1)`, as `IntegralImage::data`) and the
    /// response layers of `plan` (`[octave][layer]`, row-major): the first stages' output, read
    /// back for tests and diagnostics.
    pub fn run(&self, img: &GrayImage, plan: &[Vec<LayerSpec>]) -> Result<GpuLayers, GpuError> {
        let key = FrameKey {
            width: img.width(),
            height: img.height(),
            plan: plan.to_vec(),
        };
        self.with_key(key, |frame| {
            self.upload(frame, img);
            let mut enc = self.encoder();
            frame.encode_layers(&self.pipelines, &mut enc);
            let table_rb = frame::readback(&self.device, frame.table_bytes);
            let det_rb = frame::readback(&self.device, frame.det_bytes);
            enc.copy_buffer_to_buffer(&frame.table, 0, &table_rb, 0, frame.table_bytes);
            enc.copy_buffer_to_buffer(&frame.det, 0, &det_rb, 0, frame.det_bytes);
            self.queue.submit([enc.finish()]);
            let integral: Vec<i32> = self.read(&table_rb, frame.table_bytes)?;
            let det_all: Vec<f32> = self.read(&det_rb, frame.det_bytes)?;
            Ok(GpuLayers {
                integral,
                layers: split_layers(&det_all, plan),
            })
        })
    }

    /// Run `f` on the buffers of `img`'s size and `surf`'s plan.
    fn with_frame<T>(
        &self,
        surf: &Surf,
        img: &GrayImage,
        f: impl FnOnce(&mut Frame) -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        let key = FrameKey {
            width: img.width(),
            height: img.height(),
            plan: surf.layer_plan(img.width(), img.height()),
        };
        self.with_key(key, f)
    }

    /// Run `f` with the device's validation, out-of-memory and internal errors caught: any of
    /// them makes the result an error (wgpu reports them apart from the calls that caused them).
    fn scoped<T>(&self, f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        // Popped innermost first.
        let caught = [validation.pop(), memory.pop(), internal.pop()]
            .into_iter()
            .find_map(pollster::block_on);
        match (out, caught) {
            (Err(e), _) => Err(e),
            (Ok(_), Some(e)) => Err(GpuError::Run(e.to_string())),
            (Ok(v), None) => Ok(v),
        }
    }

    /// Run `f` on the frame buffers of `key`, built when the last frame's differ.
    fn with_key<T>(
        &self,
        key: FrameKey,
        f: impl FnOnce(&mut Frame) -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        self.scoped(|| self.with_key_unscoped(key, f))
    }

    fn with_key_unscoped<T>(
        &self,
        key: FrameKey,
        f: impl FnOnce(&mut Frame) -> Result<T, GpuError>,
    ) -> Result<T, GpuError> {
        let mut guard = self
            .frame
            .lock()
            .map_err(|_| GpuError::Run("an earlier frame panicked on this device".into()))?;
        if guard.as_ref().is_none_or(|fr| fr.key != key) {
            *guard = None;
            let (width, height) = (key.width, key.height);
            let built = Frame::new(&self.device, &self.pipelines, key).map_err(|reason| {
                GpuError::Image {
                    width,
                    height,
                    reason,
                }
            })?;
            *guard = Some(built);
        }
        match guard.as_mut() {
            Some(frame) => f(frame),
            None => Err(GpuError::Run("no frame buffers".into())),
        }
    }

    /// The image's pixels into the frame, quantised as `IntegralImage::new` does: rounded,
    /// clamped to 0..=255, NaN as 0.
    fn upload(&self, frame: &Frame, img: &GrayImage) {
        let px: Vec<u32> = img
            .data()
            .iter()
            .map(|v| (v + 0.5).clamp(0.0, 255.0) as u32)
            .collect();
        self.queue
            .write_buffer(&frame.px, 0, bytemuck::cast_slice(&px));
    }

    fn encoder(&self) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("surf"),
            })
    }

    /// Layers and maxima on the GPU; the keypoints in the CPU's order and selection.
    fn detect_on(
        &self,
        frame: &mut Frame,
        surf: &Surf,
        img: &GrayImage,
    ) -> Result<Vec<KeyPoint>, GpuError> {
        if frame.triples.is_empty() {
            return Ok(Vec::new());
        }
        let p = surf.params();
        for t in &mut frame.triples {
            t.data.threshold = p.hessian_threshold;
            self.queue
                .write_buffer(&t.uniform, 0, bytemuck::bytes_of(&t.data));
        }
        self.upload(frame, img);
        let mut enc = self.encoder();
        frame.encode_layers(&self.pipelines, &mut enc);
        frame.encode_extrema(&self.pipelines, &mut enc);
        self.queue.submit([enc.finish()]);
        let n = self
            .read::<u32>(&frame.count_rb, 4)?
            .first()
            .copied()
            .unwrap_or(0) as usize;
        if n > MAX_EXTREMA {
            return Err(GpuError::Run(format!(
                "{n} maxima, more than the GPU path holds ({MAX_EXTREMA})"
            )));
        }
        if n == 0 {
            return Ok(Vec::new());
        }
        let bytes = n as u64 * EXTREMUM_BYTES;
        let mut enc = self.encoder();
        enc.copy_buffer_to_buffer(&frame.found, 0, &frame.found_rb, 0, bytes);
        self.queue.submit([enc.finish()]);
        let mut found: Vec<Extremum> = self.read(&frame.found_rb, bytes)?;
        // The CPU's order: strongest first, ties by octave, layer, row, column.
        found.sort_by(|a, b| {
            b.response
                .total_cmp(&a.response)
                .then((a.tag & 0xffff).cmp(&(b.tag & 0xffff)))
                .then(a.r.cmp(&b.r))
                .then(a.c.cmp(&b.c))
        });
        let mut kps = Vec::with_capacity(found.len());
        for e in &found {
            let tag = e.tag & 0xffff;
            let Some(t) = frame.triples.iter().find(|t| t.data.tag == tag) else {
                return Err(GpuError::Run(format!("a maximum of unknown layer {tag}")));
            };
            let offset = [f64::from(e.ox), f64::from(e.oy), f64::from(e.os)];
            let laplacian = if e.tag & 0x10000 != 0 { -1 } else { 1 };
            let found = Maximum {
                cell: [e.c as usize, e.r as usize],
                offset,
                response: e.response,
                laplacian,
            };
            kps.push(keypoint_at(&found, &t.mid, t.lo_size, t.octave));
        }
        if let Some(cap) = p.max_features {
            kps = select_spread(kps, cap, img.width(), img.height());
        }
        Ok(kps)
    }

    /// Orientations and descriptors of `kps` on the frame's integral table.
    fn describe_on(
        &self,
        frame: &mut Frame,
        surf: &Surf,
        mut kps: Vec<KeyPoint>,
    ) -> Result<Features, GpuError> {
        let p = surf.params();
        let kind = p.descriptor;
        if kps.is_empty() {
            return Ok(Features::new(kps, Vec::new(), kind)?);
        }
        let n = kps.len();
        self.ensure_describe_buffers(frame, n, kind);
        let Some(b) = frame.describe.as_ref() else {
            return Err(GpuError::Run("no descriptor buffers".into()));
        };
        let n32 = u32::try_from(n).map_err(|_| GpuError::Run(format!("{n} keypoints")))?;
        let kp_data: Vec<[f32; 4]> = kps.iter().map(|k| [k.x, k.y, k.scale, 0.0]).collect();
        self.queue
            .write_buffer(&b.kps, 0, bytemuck::cast_slice(&kp_data));
        let [w, h, stride, _] = frame.dims;
        let ori_groups = n32.div_ceil(ORIENTATION_WORKGROUP);
        let ori_grid = grid(ori_groups);
        let ori_params = OriParams {
            w,
            h,
            stride,
            n: n32,
            n_samples: orientation_samples().len() as u32,
            bins: ORIENTATION_BINS as u32,
            window: ORIENTATION_WINDOW_BINS as u32,
            per_row: ori_grid.0 * ORIENTATION_WORKGROUP,
            // The CPU's bin scale, bit for bit.
            bin_scale: ORIENTATION_BINS as f32 / std::f32::consts::TAU,
            pad: [0; 3],
        };
        let desc_grid = grid(n32);
        let desc_params = DescParams {
            w,
            h,
            stride,
            n_kp: n32,
            samples: kind.samples() as u32,
            nsub: kind.subregions() as u32,
            vals: (kind.len() / (kind.subregions() * kind.subregions())) as u32,
            len: kind.len() as u32,
            out_stride: kind.stride() as u32,
            upright: u32::from(p.upright),
            extended: u32::from(kind == visnav_core::vision::DescriptorKind::Surf128),
            per_row: desc_grid.0,
            // The CPU's `20 / n` (its sample spacing is this times the scale).
            sp_unit: 20.0 / kind.samples() as f32,
            pad: [0; 3],
        };
        self.queue
            .write_buffer(&b.ori_params, 0, bytemuck::bytes_of(&ori_params));
        self.queue
            .write_buffer(&b.desc_params, 0, bytemuck::bytes_of(&desc_params));
        let mut enc = self.encoder();
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            if !p.upright {
                pass.set_pipeline(&self.pipelines.orientation);
                pass.set_bind_group(0, &b.ori_bg, &[]);
                pass.dispatch_workgroups(ori_grid.0, ori_grid.1, 1);
            }
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.pipelines.descriptor);
            pass.set_bind_group(0, &b.desc_bg, &[]);
            pass.dispatch_workgroups(desc_grid.0, desc_grid.1, 1);
        }
        let ori_bytes = n as u64 * 16;
        let desc_bytes = (n * kind.stride() * 4) as u64;
        if !p.upright {
            enc.copy_buffer_to_buffer(&b.ori, 0, &b.ori_rb, 0, ori_bytes);
        }
        enc.copy_buffer_to_buffer(&b.desc, 0, &b.desc_rb, 0, desc_bytes);
        self.queue.submit([enc.finish()]);
        if !p.upright {
            let ori: Vec<[f32; 4]> = self.read(&b.ori_rb, ori_bytes)?;
            for (k, o) in kps.iter_mut().zip(&ori) {
                k.orientation_rad = orientation_of_window(o[0], o[1]);
            }
        }
        let desc: Vec<f32> = self.read(&b.desc_rb, desc_bytes)?;
        Ok(Features::new(kps, desc, kind)?)
    }

    /// The frame's keypoint and descriptor buffers for at least `n` keypoints of `kind`.
    fn ensure_describe_buffers(
        &self,
        frame: &mut Frame,
        n: usize,
        kind: visnav_core::vision::DescriptorKind,
    ) {
        let fits = frame.describe.as_ref().is_some_and(|b| {
            b.capacity >= n && b.stride == kind.stride() && b.samples == kind.samples()
        });
        if fits {
            return;
        }
        let weights = if kind.samples() == 18 {
            &self.weights18
        } else {
            &self.weights20
        };
        frame.describe = Some(DescribeBuffers::new(
            &self.device,
            &self.pipelines,
            [&frame.table, &self.ori_samples, weights],
            n.next_power_of_two().max(256),
            kind,
        ));
    }

    /// Map the first `bytes` of a readback buffer, wait for the GPU, copy them out.
    fn read<T: bytemuck::Pod>(&self, buf: &wgpu::Buffer, bytes: u64) -> Result<Vec<T>, GpuError> {
        let slice = buf.slice(..bytes);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Run(format!("waiting for the device: {e}")))?;
        rx.recv()
            .map_err(|_| GpuError::Run("the buffer map callback never ran".into()))?
            .map_err(|e| GpuError::Run(format!("reading back: {e}")))?;
        let view = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Run(format!("reading back: {e}")))?;
        let out = bytemuck::pod_collect_to_vec::<u8, T>(&view);
        drop(view);
        buf.unmap();
        Ok(out)
    }
}

/// Open the adapter `policy` allows: hardware first (discrete, integrated, virtual), software
/// only when allowed.
fn choose_adapter(policy: AdapterPolicy) -> Result<(wgpu::Adapter, AdapterInfo), GpuError> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
    let instance = wgpu::Instance::new(desc);
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
    let rank = |a: &wgpu::Adapter| match a.get_info().device_type {
        wgpu::DeviceType::DiscreteGpu => 3,
        wgpu::DeviceType::IntegratedGpu => 2,
        wgpu::DeviceType::VirtualGpu => 1,
        _ => 0,
    };
    let hardware = adapters
        .iter()
        .filter(|a| a.get_info().device_type != wgpu::DeviceType::Cpu)
        .max_by_key(|a| rank(a));
    let software = adapters
        .iter()
        .find(|a| a.get_info().device_type == wgpu::DeviceType::Cpu);
    let adapter = match (hardware, software, policy) {
        (Some(a), _, _) => a,
        (None, Some(a), AdapterPolicy::AllowSoftware) => a,
        (None, Some(a), AdapterPolicy::HardwareOnly) => {
            return Err(GpuError::SoftwareOnly(adapter_info(a).name));
        }
        (None, None, _) => {
            return Err(GpuError::NoAdapter(
                "no Vulkan, Metal or DX12 adapter (on Linux: a Vulkan driver and libvulkan1; \
                 Mesa's mesa-vulkan-drivers has the lavapipe software adapter)"
                    .into(),
            ));
        }
    };
    Ok((adapter.clone(), adapter_info(adapter)))
}

/// A dispatch of `groups` workgroups as `(x, y)` within the per-dimension limit.
fn grid(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, MAX_GROUPS_X);
    (x, groups.div_ceil(x).max(1))
}

/// The response buffer cut into the plan's layers.
fn split_layers(det_all: &[f32], plan: &[Vec<LayerSpec>]) -> Vec<Vec<Vec<f32>>> {
    let mut at = 0usize;
    plan.iter()
        .map(|specs| {
            specs
                .iter()
                .map(|s| {
                    let n = s.rows * s.cols;
                    let layer = det_all
                        .get(at..at + n)
                        .map_or_else(Vec::new, <[f32]>::to_vec);
                    at += n;
                    layer
                })
                .collect()
        })
        .collect()
}

/// The GPU path as the fix engine's feature backend: a frame (or a matching) the GPU fails on is
/// computed on the CPU (counted in [`GpuSurf::fallbacks`]).
impl FeatureBackend for GpuSurf {
    fn detect_and_describe(&self, detector: &dyn Detector, img: &GrayImage) -> Features {
        let Some(surf) = detector.as_surf() else {
            return detector.detect_and_describe(img);
        };
        match GpuSurf::detect_and_describe(self, surf, img) {
            Ok(f) => f,
            Err(_) => {
                self.fallbacks
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                surf.detect_and_describe(img)
            }
        }
    }

    fn match_features(
        &self,
        query: &Features,
        train: &Features,
        params: &MatchParams,
        predicted_in_train: Option<&[[f32; 2]]>,
    ) -> Result<Vec<Match>, visnav_core::vision::VisionError> {
        // Small sets, and inputs the CPU refuses (its error is the answer), stay on the CPU.
        let worth = query.len().saturating_mul(train.len()) >= matching::GPU_MATCH_MIN_PAIRS;
        // The GPU kernel computes L2 distances: binary descriptors are matched on the CPU.
        let float = query.kind().family() == Family::Float;
        if !worth || !float || !matching::gpu_can_match(query, train, params, predicted_in_train) {
            return match_features(query, train, params, predicted_in_train);
        }
        match GpuSurf::match_features(self, query, train, params, predicted_in_train) {
            Ok(m) => Ok(m),
            Err(_) => {
                self.fallbacks
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                match_features(query, train, params, predicted_in_train)
            }
        }
    }

    fn name(&self) -> String {
        format!("gpu: {}", self.info)
    }
}
