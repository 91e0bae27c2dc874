//! SURF on the GPU through wgpu compute shaders (Vulkan, Metal, DX12; Mesa's lavapipe gives a
//! software Vulkan adapter where there is no GPU), producing the same features as visnav-core's
//! CPU SURF, which stays the reference (`visnav_core::vision::surf`; Bay et al. 2008).
//!
//! What runs where (this is the first stage of the GPU path):
//! * GPU: the integral image (`shaders/integral.wgsl`: a row pass and a column pass, wrapping
//!   32-bit cells as the CPU's `IntegralImage`, so every box sum is the same integer) and every
//!   fast-Hessian response layer of [`Surf::layer_plan`] (`shaders/hessian.wgsl`: the box sums of
//!   `hessian_at`, the CPU's normalisation factors passed in, `det = Dxx Dyy - 0.81 Dxy^2`), in one
//!   submission per image;
//! * CPU (visnav-core): the 3x3x3 extrema and their interpolation ([`Surf::detect_with_layers`]),
//!   the orientation and the descriptors. The parameters are the one `SurfParams` of the CPU path,
//!   so the two cannot disagree on what to compute.
//!
//! The responses equal the CPU's up to the last bit of a float (a GPU may fuse a multiply-add);
//! `tests/gpu_surf.rs` holds the layers and the keypoints to the CPU's on real images.
//!
//! Adapter choice: a hardware adapter first; a software one (lavapipe, `DeviceType::Cpu`) only
//! when allowed ([`AdapterPolicy`]), and always reported as software so its times are never taken
//! for a GPU's.

use std::sync::mpsc;

use thiserror::Error;
use visnav_core::vision::surf::HESSIAN_DXY_WEIGHT_SQ;
use visnav_core::vision::{
    FeatureBackend, Features, GrayImage, IntegralImage, KeyPoint, LayerSpec, Surf,
};
use wgpu::util::DeviceExt;

/// Threads per workgroup of the integral passes (`shaders/integral.wgsl`).
const INTEGRAL_WORKGROUP: u32 = 64;
/// Workgroup side of the response pass (`shaders/hessian.wgsl`: 8 x 8).
const HESSIAN_WORKGROUP: u32 = 8;

/// Why the GPU path is not available or failed.
#[derive(Debug, Error)]
pub enum GpuError {
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    #[error("only a software adapter ({0}) was found and software adapters are not allowed")]
    SoftwareOnly(String),
    #[error("GPU device: {0}")]
    Device(String),
    #[error("GPU: {0}")]
    Run(String),
    #[error("image of {width} x {height} px: {reason}")]
    Image {
        width: usize,
        height: usize,
        reason: String,
    },
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

/// What one GPU submission computed for an image.
#[derive(Debug, Clone, PartialEq)]
pub struct GpuLayers {
    /// The integral table, `(h + 1) x (w + 1)` (as `IntegralImage::data`).
    pub integral: Vec<i32>,
    /// The response layers of the plan, `[octave][layer]`, row-major on their grids.
    pub layers: Vec<Vec<Vec<f32>>>,
}

/// SURF's GPU stages on one device (module doc).
pub struct GpuSurf {
    /// Frames computed on the CPU because the GPU failed ([`FeatureBackend`]).
    fallbacks: std::sync::atomic::AtomicU64,
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: AdapterInfo,
    integral_rows: wgpu::ComputePipeline,
    integral_cols: wgpu::ComputePipeline,
    hessian: wgpu::ComputePipeline,
}

/// The layer uniform of `shaders/hessian.wgsl` (12 x 4 bytes, std140-compatible).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct LayerUniform {
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

impl GpuSurf {
    /// Open an adapter by `policy` (hardware first) and build the pipelines.
    pub fn new(policy: AdapterPolicy) -> Result<Self, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12;
        let instance = wgpu::Instance::new(desc);
        let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        let hardware = adapters
            .iter()
            .filter(|a| a.get_info().device_type != wgpu::DeviceType::Cpu)
            .max_by_key(|a| match a.get_info().device_type {
                wgpu::DeviceType::DiscreteGpu => 3,
                wgpu::DeviceType::IntegratedGpu => 2,
                wgpu::DeviceType::VirtualGpu => 1,
                _ => 0,
            });
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
        let info = adapter_info(adapter);
        let limits = wgpu::Limits {
            // HD frames: a 1921 x 1081 table and the layers of four octaves.
            max_storage_buffer_binding_size: adapter.limits().max_storage_buffer_binding_size,
            max_buffer_size: adapter.limits().max_buffer_size,
            ..wgpu::Limits::downlevel_defaults()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("visnav-gpu"),
            required_features: wgpu::Features::empty(),
            required_limits: limits,
            ..wgpu::DeviceDescriptor::default()
        }))
        .map_err(|e| GpuError::Device(format!("{}: {e}", info.name)))?;
        let integral = device.create_shader_module(wgpu::include_wgsl!("shaders/integral.wgsl"));
        let hessian = device.create_shader_module(wgpu::include_wgsl!("shaders/hessian.wgsl"));
        let pipeline = |module: &wgpu::ShaderModule, entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                cache: None,
            })
        };
        Ok(Self {
            fallbacks: std::sync::atomic::AtomicU64::new(0),
            integral_rows: pipeline(&integral, "rows"),
            integral_cols: pipeline(&integral, "cols"),
            hessian: pipeline(&hessian, "main"),
            device,
            queue,
            info,
        })
    }

    /// The adapter in use.
    pub fn adapter(&self) -> &AdapterInfo {
        &self.info
    }

    /// Frames the [`FeatureBackend`] computed on the CPU because the GPU failed.
    pub fn fallbacks(&self) -> u64 {
        self.fallbacks.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Detect on the GPU path (module doc); the same keypoints as `surf.detect` on the CPU. `ii`
    /// is the CPU's integral image of `img` (the extrema's interpolation reads it).
    pub fn detect(
        &self,
        surf: &Surf,
        img: &GrayImage,
        ii: &IntegralImage,
    ) -> Result<Vec<KeyPoint>, GpuError> {
        let plan = surf.layer_plan(img.width(), img.height());
        let out = self.run(img, &plan)?;
        Ok(surf.detect_with_layers(ii, out.layers)?)
    }

    /// Detect and describe: [`Self::detect`], then the CPU's orientation and descriptors.
    pub fn detect_and_describe(&self, surf: &Surf, img: &GrayImage) -> Result<Features, GpuError> {
        let ii = IntegralImage::new(img);
        let kps = self.detect(surf, img, &ii)?;
        Ok(surf.describe(&ii, kps))
    }

    /// The GPU's integral table of `img` (`(h + 1) x (w + 1)`, as `IntegralImage::data`) and the
    /// response layers of `plan` (`[octave][layer]`, row-major), in one submission.
    pub fn run(&self, img: &GrayImage, plan: &[Vec<LayerSpec>]) -> Result<GpuLayers, GpuError> {
        let (w, h) = (img.width(), img.height());
        let bad = |reason: &str| GpuError::Image {
            width: w,
            height: h,
            reason: reason.to_string(),
        };
        if w == 0 || h == 0 {
            return Err(bad("empty"));
        }
        let stride = w + 1;
        let cells = stride * (h + 1);
        let table_bytes = (cells * 4) as u64;
        if table_bytes > self.device.limits().max_storage_buffer_binding_size {
            return Err(bad(
                "its integral table exceeds the adapter's storage buffer size",
            ));
        }
        let u32_of = |v: usize| u32::try_from(v).map_err(|_| bad("too large"));
        // Quantised as IntegralImage::new does: rounded, clamped to 0..=255, NaN as 0.
        let px: Vec<u32> = img
            .data()
            .iter()
            .map(|v| (v + 0.5).clamp(0.0, 255.0) as u32)
            .collect();
        let dev = &self.device;
        let px_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("pixels"),
            contents: bytemuck::cast_slice(&px),
            usage: wgpu::BufferUsages::STORAGE,
        });
        let table = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("integral"),
            size: table_bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let dims: [u32; 4] = [u32_of(w)?, u32_of(h)?, u32_of(stride)?, 0];
        let dims_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("dims"),
            contents: bytemuck::cast_slice(&dims),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let (uniforms, offset) = layer_uniforms(plan, dims).ok_or_else(|| bad("too large"))?;
        let det_bytes = (offset.max(1) * 4) as u64;
        if det_bytes > dev.limits().max_storage_buffer_binding_size {
            return Err(bad(
                "its response layers exceed the adapter's storage buffer size",
            ));
        }
        let det = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("responses"),
            size: det_bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        // Each pass's layout is derived from what its entry point uses: the column pass does
        // not read the pixels.
        let integral_bg = |pipeline: &wgpu::ComputePipeline, with_pixels: bool| {
            let mut entries = vec![wgpu::BindGroupEntry {
                binding: 0,
                resource: dims_buf.as_entire_binding(),
            }];
            if with_pixels {
                entries.push(wgpu::BindGroupEntry {
                    binding: 1,
                    resource: px_buf.as_entire_binding(),
                });
            }
            entries.push(wgpu::BindGroupEntry {
                binding: 2,
                resource: table.as_entire_binding(),
            });
            dev.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("integral"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        };
        let rows_bg = integral_bg(&self.integral_rows, true);
        let cols_bg = integral_bg(&self.integral_cols, false);
        let layer_bgs: Vec<(wgpu::BindGroup, &LayerUniform)> = uniforms
            .iter()
            .map(|u| {
                let ub = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("layer"),
                    contents: bytemuck::bytes_of(u),
                    usage: wgpu::BufferUsages::UNIFORM,
                });
                let bg = dev.create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("layer"),
                    layout: &self.hessian.get_bind_group_layout(0),
                    entries: &[
                        wgpu::BindGroupEntry {
                            binding: 0,
                            resource: table.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 1,
                            resource: det.as_entire_binding(),
                        },
                        wgpu::BindGroupEntry {
                            binding: 2,
                            resource: ub.as_entire_binding(),
                        },
                    ],
                });
                (bg, u)
            })
            .collect();
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("surf"),
        });
        {
            // Separate passes order the writes of one before the reads of the next.
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.integral_rows);
            pass.set_bind_group(0, &rows_bg, &[]);
            pass.dispatch_workgroups((dims[1] + 1).div_ceil(INTEGRAL_WORKGROUP), 1, 1);
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.integral_cols);
            pass.set_bind_group(0, &cols_bg, &[]);
            pass.dispatch_workgroups((dims[0] + 1).div_ceil(INTEGRAL_WORKGROUP), 1, 1);
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&self.hessian);
            for (bg, u) in &layer_bgs {
                pass.set_bind_group(0, bg, &[]);
                pass.dispatch_workgroups(
                    u.cols.div_ceil(HESSIAN_WORKGROUP),
                    u.rows.div_ceil(HESSIAN_WORKGROUP),
                    1,
                );
            }
        }
        let table_rb = self.readback_buffer(table_bytes);
        let det_rb = self.readback_buffer(det_bytes);
        enc.copy_buffer_to_buffer(&table, 0, &table_rb, 0, table_bytes);
        enc.copy_buffer_to_buffer(&det, 0, &det_rb, 0, det_bytes);
        self.queue.submit([enc.finish()]);
        let integral: Vec<i32> = self.read(&table_rb)?;
        let det_all: Vec<f32> = self.read(&det_rb)?;
        Ok(GpuLayers {
            integral,
            layers: split_layers(&det_all, plan),
        })
    }

    fn readback_buffer(&self, size: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Map a readback buffer, wait for the GPU, copy it out.
    fn read<T: bytemuck::Pod>(&self, buf: &wgpu::Buffer) -> Result<Vec<T>, GpuError> {
        let slice = buf.slice(..);
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
        let out = bytemuck::cast_slice::<u8, T>(&view).to_vec();
        drop(view);
        buf.unmap();
        Ok(out)
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

/// The GPU path as the fix engine's feature backend: a frame the GPU fails on is computed on the
/// CPU (counted in [`GpuSurf::fallbacks`]).
impl FeatureBackend for GpuSurf {
    fn detect_and_describe(&self, surf: &Surf, img: &GrayImage) -> Features {
        match GpuSurf::detect_and_describe(self, surf, img) {
            Ok(f) => f,
            Err(_) => {
                self.fallbacks
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                surf.detect_and_describe(img)
            }
        }
    }

    fn name(&self) -> String {
        format!("gpu: {}", self.info)
    }
}
