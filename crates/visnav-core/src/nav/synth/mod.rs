//! Synthetic truth for the navigation filter: trajectories with their exact IMU increments
//! ([`trajectory`]) and the IMU's errors laid over them ([`imu`]). The built-in simulator flies
//! them, and the filter's own tests (`cargo test -p visnav-core`) run on them without the
//! simulator. Pure: seeded, no I/O.

pub mod imu;
pub mod trajectory;
