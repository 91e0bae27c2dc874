#![warn(missing_docs)]
//! The service behind `visnav run`: talks to the autopilot, runs the navigation pipeline and
//! injects the solution. An async shell around the pure modules: [`daemon`] starts and stops the
//! tasks (its module doc draws them), [`fixer`] is the frame path's view of the fix engine, the
//! navigation task owns the filter; the other modules are the configuration, the inputs, the
//! frame path, the logs, the metrics and replay.

pub mod config;
pub mod daemon;
pub mod fixer;
pub mod fixlog;
pub mod frames;
pub mod handoff;
pub mod heap;
pub mod imu_bias;
pub mod inputs;
pub mod metrics;
mod nav_task;
pub mod paging;
mod priors;
pub mod prometheus;
pub mod replay;
pub mod vo_path;
pub mod volog;
pub mod wiring;

pub use config::{DaemonConfig, GpsSource, ImuBiasRestore};
pub use daemon::{
    Daemon, DaemonError, DaemonSetup, FramePipeline, THREAD_STOP_DEADLINE, final_counters, run,
};
pub use fixer::FrameFixer;
pub use frames::{FixResult, Slot};
pub use metrics::{DaemonMetrics, MetricsSnapshot};
pub use wiring::{engine_from_config, fixer_from_config};
