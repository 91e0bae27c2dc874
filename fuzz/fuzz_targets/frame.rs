//! libFuzzer target `frame`: the body is `visnav_fuzz::frame` (fuzz/src/lib.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| visnav_fuzz::run(visnav_fuzz::frame, data));
