//! Navigation: strapdown INS in a local-level NED frame and an error-state EKF fusing vision
//! fixes, GPS, altitude and autopilot attitude (docs/nav.md).
//!
//! * [`earth`]: WGS84 radii of curvature, Somigliana normal gravity, earth and transport rates.
//! * [`ins`]: strapdown mechanization with coning and sculling corrections (Sheta 2012 ch. 2).
//! * [`filter`]: 15/21-state closed-loop error-state EKF with delayed-measurement handling,
//!   chi-square gates, divergence detection and health (Sheta 2012 ch. 5, Chan 2022);
//!   one file per measurement model (`filter/fuse_*.rs`).
//! * [`divergence`]: whether a run of rejected position fixes agree with each other enough to
//!   reset the filter onto them.
//! * [`drag`]: a multirotor's horizontal body velocity from its accelerometer (drag law learned
//!   while the GPS aids).
//! * [`measurement`]: the filter's inputs; [`config`]: the `[nav]` configuration section;
//!
//! Conventions: NED local-level frame; body frame FRD; `q_nb` rotates body vectors into NED;
//! ZYX Euler angles; heights above the WGS84 ellipsoid; times in microseconds (`t_us`) on the
//! autopilot clock. Error states are "estimate minus truth".

pub mod config;
pub mod divergence;
pub mod drag;
pub mod earth;
pub mod filter;
pub mod ins;
pub mod measurement;
pub mod synth;

pub use config::NavConfig;
pub use filter::{Counters, Health, NavFilter, NavOutput, Outcome};
pub use ins::{InsState, Strapdown};
pub use measurement::{
    AltitudeFix, AttitudeFix, ImuSample, Measurement, PoseFix, PositionFix, VO_MAX_SPAN_S,
    VelocityFix, VoFix, VoRotation,
};
