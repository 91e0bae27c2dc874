//! The core's end-to-end tests, one module per file of this folder, built as one test binary
//! (one link instead of four): the navigation filter on synthetic flights (`nav_ekf`, `nav_drag`,
//! `nav_ins`, on `visnav_core::nav::synth`) and the resection on synthetic scenes
//! (`pose_resection`, on `visnav_core::pose::synth`). `cargo test -p visnav-core` runs them.

mod nav_drag;
mod nav_ekf;
mod nav_ins;
mod pose_resection;
