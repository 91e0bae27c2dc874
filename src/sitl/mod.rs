//! Built-in simulator code (see docs/architecture.md).
//!
//! * `autopilot`: a MAVLink 2 autopilot emulator speaking like ArduPilot over real sockets.

pub mod autopilot;
