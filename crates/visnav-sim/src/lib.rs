#![warn(missing_docs)]
//! visnav-sim: the built-in software-in-the-loop simulator and the evaluation tooling (see
//! docs/architecture.md): flights of the core's truth trajectories, sensor synthesis, scenario files, the runner
//! that scores the navigation filter, a MAVLink autopilot emulator, the camera renderer, the
//! closed loop of `visnav sim`, its report and plots; the resection bench and the SURF
//! repeatability evaluation behind `visnav bench`. A flight build (`--no-default-features` on the
//! `visnav` package) leaves this crate out.
//!
//! * Truth trajectories and IMU error synthesis live in the core
//!   (`visnav_core::nav::synth`), where the filter's own tests fly them too.
//! * [`scenario`]: `sitl/scenarios/*.toml` schema and validation.
//! * [`run`]: scenario runner, INS-only control, Monte Carlo NEES consistency.
//! * [`autopilot`]: a MAVLink 2 autopilot emulator speaking like ArduPilot over real sockets.
//! * [`real_sitl`]: truth (SIMSTATE/SIM_STATE, HIL_STATE_QUATERNION) from a real ArduPilot/PX4
//!   SITL as a [`camera_sim::TruthFeed`].
//! * [`camera_sim`]: the simulated camera as a frame source, rendering at the truth pose.
//! * [`faults`]: scripted fault events of a closed-loop scenario and their scoring.
//! * [`closed_loop`]: `visnav sim`'s closed loop (emulator + daemon + camera) and its scoring;
//!   [`report`] writes its report folder.
//! * [`plot`]: the report folder's PNG plots (errors, track over the map, fix residuals), drawn
//!   with plotters and a compiled-in font.
//! * [`render`]: the simulated camera (perspective view of an orthophoto on a DEM, lens
//!   distortion, exposure, blur, noise).
//! * [`pose_bench`]: the resection timings (on the core's synthetic scenes, `pose::synth`).
//! * [`surf_eval`]: SURF repeatability and matching scores on image pairs with known geometry.

pub mod autopilot;
pub mod camera_sim;
pub mod closed_loop;
pub mod dtm_eval;
pub mod faults;
pub mod fixeval;
pub mod plot;
pub mod pose_bench;
pub mod real_sitl;
pub mod render;
pub mod report;
pub mod run;
pub mod scenario;
pub mod surf_eval;
pub mod vo_eval;

pub use scenario::Scenario;
