//! The `[vision]` section: where the fix engine computes the frames' features (the CPU, a GPU,
//! or a hardware GPU when there is one). `wiring` turns it into the engine's feature backend.

/// `[vision]`: where the fix engine computes the frames' SURF features.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VisionConfig {
    /// `cpu` (default), `gpu` or `auto`.
    pub backend: VisionBackend,
}

/// `[vision] backend`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VisionBackend {
    /// The CPU reference.
    #[default]
    Cpu,
    /// The GPU path (crates/visnav-gpu; a binary built with the `gpu` feature): any adapter,
    /// a software one with a warning; none, or a binary without the path: the CPU, with a
    /// warning.
    Gpu,
    /// A hardware GPU when there is one (and the binary has the path), else the CPU.
    Auto,
}
