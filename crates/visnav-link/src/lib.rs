//! MAVLink link to the autopilot (async, tokio): connection with reconnect and backoff, heartbeat,
//! autopilot lock-on, telemetry stream requests and rate checks, TIMESYNC clock mapping, reboot
//! detection, injection of the navigation solution, STATUSTEXT, signing, .tlog recording and
//! Prometheus metrics.
//!
//! * [`config`]: the `[link]` and `[output]` configuration sections.
//! * [`time`]: TIMESYNC filter, UTC and GPS week/time of week (pure).
//! * [`inject`]: estimate -> GPS_INPUT / VISION_POSITION_ESTIMATE / ODOMETRY /
//!   GLOBAL_POSITION_SENSOR / SET_GPS_GLOBAL_ORIGIN (pure, validated).
//! * [`streams`]: wanted telemetry and rate monitoring (pure).
//! * [`session`]: the running link ([`Link`]).
//! * [`signing`], [`tlog`], [`metrics`]: operations; [`LogLimiter`]: repeated warnings
//!   rate-limited with counts (the link's and the daemon's).
//!
//! Clocks: the companion clock is `std::time::Instant` (CLOCK_MONOTONIC on Linux) expressed in ns
//! since the link started plus 1 s ([`Link::companion_ns`]); the autopilot clock is its boot time
//! `t_boot_us`. Camera frames are stamped by [`Link::to_autopilot_us`] of their capture instant.
//!
//! How the daemon uses it:
//!
//! ```text
//! let mut link = Link::start(cfg.link, cfg.output).await?;      // connects, locks, syncs time
//! let clock = link.clock();                                      // camera task: frame Instant -> t_boot_us
//! let mut tel = link.telemetry();                                // IMU, attitude, baro, GPS for the EKF
//! let (est_tx, est_rx) = watch::channel(None);                   // EKF publishes Some(NavEstimate)
//! link.spawn_injector(est_rx);                                   // sends at output.rate_hz
//! shutdown_signal().await?; link.shutdown().await;               // SIGINT/SIGTERM, .tlog flushed
//! ```
//!
//! Never hold a `watch::Ref` from [`Link::status`] across an `.await`: it blocks the link's
//! status updates (clone the value out instead).

#![warn(missing_docs)]

pub mod config;
pub mod inject;
pub mod metrics;
pub mod sensors;
pub mod session;
pub mod signing;
pub mod streams;
pub mod time;
pub mod tlog;
mod transport;

pub use inject::{Health, InjectError, NavEstimate};
pub use metrics::{LogLimiter, LogLine};
pub use session::{
    AutopilotInfo, Clock, Link, LinkError, LinkStatus, Telemetry, boot_time_us, decode,
    is_lock_candidate, shutdown_signal,
};
