#![warn(missing_docs)]
//! visnav-io: what visnav reads and writes besides the MAVLink link, on top of visnav-core's
//! pure types: GeoTIFF files and the terrain model built on them ([`geo`]), the reference map's
//! file format and build ([`map`]), image files ([`image_file`]) and camera frame sources
//! ([`frames`]: files, a capture command, GStreamer, V4L2), other tools' camera calibration files
//! ([`calibration`]). Errors name the file, key or field; every file read whole is read within a
//! size that fits its kind ([`files`]), and values quoted in errors are bounded (`visnav_core::text`).

pub mod calibration;
pub mod files;
pub mod frames;
pub mod geo;
pub mod image_file;
pub mod map;
