//! The integration tests, one module per file of this folder, built as one test binary: each
//! test binary links the whole workspace and its dependencies again, so fifty of them spent most
//! of a clean build linking and instantiating the same generic code fifty times. cargo-nextest
//! still runs every test in a process of its own (scripts/test.sh); `cargo test --test
//! integration MODULE::` runs one file's tests.

mod common;

mod architecture;
mod closed_loop;
mod closed_loop_copter;
mod closed_loop_drone;
mod closed_loop_paged;
mod config_check;
mod config_overrides;
mod config_reference;
mod config_run_agree;
mod daemon;
mod daemon_frames_faults;
mod deb_package;
mod dtm_ngi;
mod dtm_replica;
mod first_run;
mod fix_autzen;
mod fix_bench_cli;
mod fix_cli;
mod fix_naip;
mod fix_ngi;
mod fuzz_corpus;
mod heap_count;
mod hostile_files;
mod install;
mod link_connection_forms;
mod link_emulator;
mod link_faults;
mod link_interop;
mod link_mavproxy;
mod link_origin;
mod link_shutdown;
mod live_capture;
mod map_build;
mod map_compare;
mod map_paged;
mod nav_sitl;
mod ngi_camera;
mod pose_bench;
mod prometheus;
mod px4_imu_bias;
mod real_sitl_truth;
mod render_geometry;
mod render_naip;
mod render_timing;
mod replay;
mod sim_faults;
mod sitl_scripts;
mod surf_bench_cli;
mod surf_quality;
mod vo_closed_loop;
mod vo_ngi;
