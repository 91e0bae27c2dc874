//! libFuzzer target `config`: the body is `visnav_fuzz::config` (fuzz/src/lib.rs).
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| visnav_fuzz::run(visnav_fuzz::config, data));
