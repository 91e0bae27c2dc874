//! Built-in software-in-the-loop simulator (issue 5 starts it): truth trajectories, IMU and
//! sensor synthesis, scenario files and the runner that scores the navigation filter.
//!
//! * [`trajectory`]: lines, coordinated turns, climbs; exact ideal IMU increments.
//! * [`imu`]: IMU error synthesis (white noise, turn-on bias, bias instability, random walk,
//!   scale factor, sample rate).
//! * [`scenario`]: `sitl/scenarios/*.toml` schema and validation.
//! * [`run`]: scenario runner, INS-only control, Monte Carlo NEES consistency.
//! * [`rng`]: deterministic random numbers.

pub mod imu;
pub mod rng;
pub mod run;
pub mod scenario;
pub mod trajectory;

pub use scenario::Scenario;
