//! The compute pipelines of the GPU path, one per shader entry point; each pipeline's bind group
//! layout is derived from what its entry point uses.

/// The pipelines (module doc).
pub(crate) struct Pipelines {
    pub integral_rows: wgpu::ComputePipeline,
    pub integral_cols: wgpu::ComputePipeline,
    pub hessian: wgpu::ComputePipeline,
    pub extrema: wgpu::ComputePipeline,
    pub orientation: wgpu::ComputePipeline,
    pub descriptor: wgpu::ComputePipeline,
    pub matcher: wgpu::ComputePipeline,
}

/// `shaders/common.wgsl` (the integral table and the Haar sums) prepended to a shader.
fn with_common(body: &str) -> String {
    format!("{}\n{body}", include_str!("shaders/common.wgsl"))
}

impl Pipelines {
    pub fn new(device: &wgpu::Device) -> Self {
        let module = |label: &str, source: String| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            })
        };
        let integral = module("integral", include_str!("shaders/integral.wgsl").into());
        let hessian = module("hessian", include_str!("shaders/hessian.wgsl").into());
        let extrema = module("extrema", include_str!("shaders/extrema.wgsl").into());
        let orientation = module(
            "orientation",
            with_common(include_str!("shaders/orientation.wgsl")),
        );
        let descriptor = module(
            "descriptor",
            with_common(include_str!("shaders/descriptor.wgsl")),
        );
        let matcher = module("match", include_str!("shaders/match.wgsl").into());
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
        Self {
            integral_rows: pipeline(&integral, "rows"),
            integral_cols: pipeline(&integral, "cols"),
            hessian: pipeline(&hessian, "main"),
            extrema: pipeline(&extrema, "main"),
            orientation: pipeline(&orientation, "main"),
            descriptor: pipeline(&descriptor, "main"),
            matcher: pipeline(&matcher, "main"),
        }
    }
}
