//! libFuzzer target `geotiff`: the body is `visnav_fuzz::geotiff` (fuzz/src/lib.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| visnav_fuzz::run(visnav_fuzz::geotiff, data));
