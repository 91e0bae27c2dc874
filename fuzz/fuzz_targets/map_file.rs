//! libFuzzer target `map_file`: the body is `visnav_fuzz::map_file` (fuzz/src/lib.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| visnav_fuzz::run(visnav_fuzz::map_file, data));
