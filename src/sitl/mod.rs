//! Software-in-the-loop simulation: the simulated camera (`render`) and, later, the vehicle and link.
pub mod render;
