//! Camera model: pinhole intrinsics, Brown-Conrady distortion, camera-to-body mount, frame sources.
