#![warn(missing_docs)]
//! visnav-core: the pure algorithms of visnav, with no file or device I/O, no async and no wall
//! clock (budgets count work), so the same inputs give the same outputs on any machine.
//!
//! The modules in the order of the data flow (docs/architecture.md): [`validate`] (the
//! configuration values' checks, a leaf), [`geo`] (geodesy, projections, rasters in memory),
//! [`camera`] (sensor model), [`vision`] (SURF and matching), [`pose`] (space resection and its
//! integrity), [`fix`] (the absolute fix: frame against reference map, prior to pose), [`nav`]
//! (strapdown INS and error-state EKF), with [`stats`] (chi-square quantiles), [`rng`] (the
//! seeded generator of RANSAC and of the simulator) and [`reasons`] (refusals counted by class)
//! beside them. Every frame and rotation
//! convention is defined once in docs/conventions.md.

pub mod camera;
pub mod dtm_nav;
pub mod fix;
pub mod geo;
pub mod nav;
pub mod pose;
pub mod reasons;
pub mod rng;
pub mod stats;
pub mod text;
pub mod validate;
pub mod vision;
pub mod vo;
