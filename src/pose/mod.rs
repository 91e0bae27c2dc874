//! Space resection ([`visnav_core::pose`], re-exported here) and its tooling: synthetic scenes
//! (`synth`) and the resection benchmark (`bench`, timed with the wall clock, so outside the
//! core).

pub use visnav_core::pose::*;

pub mod bench;
pub mod synth;
