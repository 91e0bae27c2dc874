//! The fuzz targets' bodies: one function per target taking the fuzzer's bytes, feeding them to
//! the code that reads untrusted input in the daemon. The libFuzzer binaries in `fuzz_targets/`
//! call these, and so does `tests/fuzz_corpus.rs` (on stable, `cargo test`), which replays every
//! committed corpus file through them: one harness, two drivers.
//!
//! A target passes an input when it returns; any panic that escapes is a crash (the daemon would
//! have gone down). Errors are the expected outcome for most inputs, and each error's message is
//! rendered (its `Display` walks the paths and values the message names).
//!
//! This file is compiled twice: as the `visnav_fuzz` library (fuzz/Cargo.toml) and as a module of
//! the root package's `tests/fuzz_corpus.rs`; so it names only crates both depend on
//! (visnav-core, -io, -link, -daemon, mavlink) and nothing else (no tempfile, no crc crate).

use std::io::Cursor;
use std::path::{Path, PathBuf};

use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{MavHeader, MavlinkVersion, Message};
use visnav_core::fix::reference::Reference;
use visnav_core::geo::dem::Dem;
use visnav_core::nav::{NavConfig, NavFilter};
use visnav_core::vision::GrayImage;
use visnav_daemon::config::Config;
use visnav_daemon::inputs::{Inputs, NavInput, estimate_from_output};
use visnav_daemon::{DaemonConfig, GpsSource, ImuBiasRestore};
use visnav_io::frames::{DirectorySource, FrameSource, PixelFormat, Y4mSource, v4l2_luma};
use visnav_io::geo::geotiff::read_geotiff;
use visnav_io::geo::window::GeoTiffWindowReader;
use visnav_io::image_file::GrayImageFile;
use visnav_io::map::{HeightInfo, MapReference, ReferenceMap};
use visnav_link::Telemetry;

/// A target's body: one input.
pub type Target = fn(&[u8]);

/// Every target: its name (the directory under `fuzz/corpus/`, the binary in `fuzz_targets/`)
/// and its body.
pub const TARGETS: &[(&str, Target)] = &[
    ("config", config),
    ("map_file", map_file),
    ("geotiff", geotiff),
    ("frame", frame),
    ("mavlink", mavlink),
];

/// Upper bound of the work one input may ask for (messages, frames, map levels, windows), so a
/// run's executions stay fast; the readers' own limits are what is tested, not these.
const MAX_ITEMS: usize = 64;

/// Runs one input of `target` under libFuzzer. A panic caught inside the code under test is
/// its own business, as in the daemon (the GeoTIFF reader turns a panic of the `tiff` crate into
/// an error), so libFuzzer's panic hook, which aborts on any panic, is replaced by one that only
/// keeps the message; a panic that escapes the target prints that message and aborts (libFuzzer
/// then saves the input as a crash). `FUZZ_STRICT_PANICS=1` keeps libFuzzer's hook: every panic,
/// caught or not, is a crash (to find the dependencies' panics behind our guards).
pub fn run(target: Target, data: &[u8]) {
    use std::sync::{Mutex, Once};
    static HOOK: Once = Once::new();
    static LAST: Mutex<String> = Mutex::new(String::new());
    HOOK.call_once(|| {
        if std::env::var_os("FUZZ_STRICT_PANICS").is_none_or(|v| v != "1") {
            std::panic::set_hook(Box::new(|info| {
                *LAST.lock().unwrap_or_else(|e| e.into_inner()) = info.to_string();
            }));
        }
    });
    if std::panic::catch_unwind(|| target(data)).is_err() {
        let msg = LAST.lock().unwrap_or_else(|e| e.into_inner()).clone();
        eprintln!("visnav-fuzz: a panic escaped the target: {msg}");
        std::process::abort();
    }
}

// ------------------------------------------------------------------------------------------------
// Scratch files (the map reader memory-maps a path; image and frame-directory sources open paths)

/// A file path private to this process and thread, in a directory created on first use.
fn scratch(name: &str) -> PathBuf {
    let thread = format!("{:?}", std::thread::current().id())
        .chars()
        .filter(char::is_ascii_alphanumeric)
        .collect::<String>();
    let dir = std::env::temp_dir().join(format!("visnav-fuzz-{}-{thread}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    dir.join(name)
}

/// Removes this thread's scratch directory (the corpus test calls it at the end).
pub fn remove_scratch() {
    if let Some(dir) = scratch("x").parent() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// Writes `bytes` to the scratch file `name`; `None` when the file system refuses (not a finding).
fn write_scratch(name: &str, bytes: &[u8]) -> Option<PathBuf> {
    let p = scratch(name);
    std::fs::write(&p, bytes).ok().map(|()| p)
}

// ------------------------------------------------------------------------------------------------
// config: the daemon's TOML configuration (`visnav run`, `visnav check-config`)

/// Parses and validates the text as the configuration file `config/fuzz.toml` (relative to the
/// working directory, the repository's root under `scripts/fuzz.sh` and `cargo test`: so the
/// examples' file names resolve and their configurations pass; the files named are only
/// `stat`ed, never read). A configuration
/// the validation accepts must then build its camera model and navigation filter, as the daemon
/// does at start: a validated value that a constructor rejects or panics on is a finding.
pub fn config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let path = Path::new("config/fuzz.toml");
    match Config::from_toml_str(text, path) {
        Ok(cfg) => {
            if let Err(e) = cfg.camera.build() {
                panic!("[camera] passed validation but does not build: {e}");
            }
            let _ = NavFilter::new(cfg.nav.clone());
            let _ = cfg.daemon.gps_source(&cfg.output);
            let _ = cfg.daemon.metrics_addr();
            let _ = format!("{cfg:?}");
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
}

// ------------------------------------------------------------------------------------------------
// map_file: the .vnm reference map (`ReferenceMap::open`, `MapReference`)

/// CRC-32 (IEEE, reflected, the `crc32fast` polynomial) of `parts` in sequence.
fn crc32(parts: &[&[u8]]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for part in parts {
        for &b in *part {
            c ^= u32::from(b);
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    (c >> 1) ^ 0xEDB8_8320
                } else {
                    c >> 1
                };
            }
        }
    }
    !c
}

/// The bytes with the preamble's `file_len` and checksum made consistent with them (the map
/// format's offsets 32 and 56), so mutations reach the header and the tables behind the checksum.
fn with_valid_checksum(data: &[u8]) -> Option<Vec<u8>> {
    if data.len() < 64 {
        return None;
    }
    let mut b = data.to_vec();
    let len = b.len() as u64;
    b[32..40].copy_from_slice(&len.to_le_bytes());
    let crc = crc32(&[&b[..56], &b[60..]]);
    b[56..60].copy_from_slice(&crc.to_le_bytes());
    Some(b)
}

/// Opens the bytes as a map file twice: as given (magic, version, sizes and checksum checks) and
/// with the length and checksum fields repaired (everything behind them); an opened map is then
/// queried as the fix engine queries it.
pub fn map_file(data: &[u8]) {
    open_map(data);
    if let Some(fixed) = with_valid_checksum(data)
        && fixed != data
    {
        open_map(&fixed);
    }
}

fn open_map(bytes: &[u8]) {
    let Some(path) = write_scratch("map.vnm", bytes) else {
        return;
    };
    let height = match ReferenceMap::open(&path) {
        Ok(map) => {
            query_map(&map);
            map.header().height.clone()
        }
        Err(e) => {
            let _ = e.to_string();
            return;
        }
    };
    // The fix engine's view: with the header's constant height, or a flat DEM standing in for
    // the DEM file a header names (the fuzzer's file names are not opened).
    let dem = match height {
        HeightInfo::Constant { .. } => None,
        HeightInfo::Dem { .. } => Dem::flat(0.0).ok(),
    };
    match MapReference::open(&path, dem) {
        Ok(r) => query_reference(&r),
        Err(e) => {
            let _ = e.to_string();
        }
    }
}

fn query_map(map: &ReferenceMap) {
    let h = map.header();
    let _ = format!("{h:?}");
    for (level, info) in h.levels.iter().enumerate().take(MAX_ITEMS) {
        let g = &info.grid;
        let (w, n) = (g.cols as f64 * g.cell_m, g.rows as f64 * g.cell_m);
        // The whole grid, a corner cell, the header's bounds, an inverted and a NaN rectangle.
        let rects = [
            [
                g.origin_x_m,
                g.origin_y_m - n,
                g.origin_x_m + w,
                g.origin_y_m,
            ],
            [
                g.origin_x_m,
                g.origin_y_m - g.cell_m,
                g.origin_x_m + g.cell_m,
                g.origin_y_m,
            ],
            [
                h.bounds.min_x_m,
                h.bounds.min_y_m,
                h.bounds.max_x_m,
                h.bounds.max_y_m,
            ],
            [1.0, 1.0, 0.0, 0.0],
            [f64::NAN, 0.0, f64::INFINITY, 1.0],
        ];
        for r in rects {
            let s = map.select(level, r[0], r[1], r[2], r[3]);
            assert_eq!(
                s.descriptors.len(),
                s.features.len() * s.kind.stride(),
                "level {level}: selection descriptors do not match its features"
            );
        }
        let _ = map.level_image(level);
        let _ = map.all_features(level);
    }
    let _ = map.select(usize::MAX, 0.0, 0.0, 1.0, 1.0);
}

fn query_reference(r: &MapReference) {
    let _ = (
        r.crs(),
        r.level_gsd_m(),
        r.ortho_pixel_m(),
        r.feature_spec(),
    );
    let [x0, y0, x1, y1] = r.bounds_m();
    let (cx, cy) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
    let _ = r.height_amsl_m(cx, cy);
    let _ = r.height_sigma_m();
    for level in 0..r.level_gsd_m().len().min(MAX_ITEMS) {
        let _ = r.select(level, [x0, y0, x1, y1]);
        if let Some(img) = r.level_image(level) {
            let [px, py] = img.to_px(cx, cy);
            let _ = img.to_map([px, py]);
            if px.is_finite() && py.is_finite() {
                let _ = img.crop(px as i64 - 8, py as i64 - 8, 16, 16);
            }
            let _ = img.crop(-4, -4, 8, 8);
            let _ = img.crop(i64::MAX - 1, i64::MIN, 3, 3);
        }
    }
}

// ------------------------------------------------------------------------------------------------
// geotiff: orthophotos and DEMs (`load_geotiff`, the windowed reader, DEM loading)

/// Reads the bytes as a GeoTIFF: whole (as the map build, `check-config` and DEM loading do,
/// then as a DEM) and through the windowed reader (two corners, the cache, a window outside).
pub fn geotiff(data: &[u8]) {
    let path = Path::new("fuzz.tif");
    match read_geotiff(Cursor::new(data), path, None) {
        Ok(r) => {
            let _ = (r.bounds(), r.crs(), r.nodata(), r.source_type());
            let (w, h) = (r.width(), r.height());
            let _ = r.sample(w / 2, h / 2, 0);
            let _ = r.sample(w, h, r.bands());
            match Dem::from_raster(&r) {
                Ok(dem) => {
                    let (x, y) = r.pixel_centre_to_map(w / 2, h / 2);
                    let _ = dem.height_at(x, y);
                }
                Err(e) => {
                    let _ = e.to_string();
                }
            }
            // A level-1 window inside the level image (its precondition: not empty).
            let (lw, lh) = ((w / 2).min(32), (h / 2).min(32));
            if lw > 0 && lh > 0 {
                let _ = visnav_io::map::build::level_window(&r, 1, 0, 0, lw, lh);
            }
        }
        Err(e) => {
            let _ = e.to_string();
        }
    }
    let mut win = match GeoTiffWindowReader::new(Cursor::new(data), path, None) {
        Ok(w) => w,
        Err(e) => {
            let _ = e.to_string();
            return;
        }
    };
    let info = win.info().clone();
    let (w, h) = (info.width.min(64), info.height.min(64));
    if w > 0 && h > 0 {
        for (c, r) in [(0, 0), (info.width - w, info.height - h), (0, 0)] {
            if let Err(e) = win.read_window(c, r, w, h) {
                let _ = e.to_string();
            }
        }
    }
    let _ = win.read_window(info.width, 0, 1, 1);
    let _ = win.read_window(0, 0, 0, 0);
}

// ------------------------------------------------------------------------------------------------
// frame: camera frames (image files, YUV4MPEG2 streams, V4L2 buffers, frames.csv)

/// The first byte picks the decoder, the rest is its input: `% 4` = 0 a y4m stream (file or
/// capture process), 1 an image file (`/ 4 % 3`: .png, .jpg, .tif) as `GrayImage::load` reads
/// it, 2 a V4L2 buffer (`/ 4 % 3`: GREY, YUYV, MJPG; the next 3 bytes give width, height and
/// row stride), 3 a `frames.csv` of an image directory.
pub fn frame(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let sub = usize::from(mode / 4) % 3;
    match mode % 4 {
        0 => y4m(rest),
        1 => {
            let name = ["frame.png", "frame.jpg", "frame.tif"][sub];
            if let Some(p) = write_scratch(name, rest) {
                match GrayImage::load(&p) {
                    Ok(g) => assert_eq!(g.data().len(), g.width() * g.height()),
                    Err(e) => {
                        let _ = e.to_string();
                    }
                }
            }
        }
        2 => {
            let [w, h, stride, buf @ ..] = rest else {
                return;
            };
            let fmt = [PixelFormat::Grey, PixelFormat::Yuyv, PixelFormat::Mjpg][sub];
            let (w, h) = (usize::from(*w) + 1, usize::from(*h) + 1);
            match v4l2_luma(fmt, buf, w, h, usize::from(*stride) * 2) {
                Ok(g) => assert_eq!((g.width(), g.height()), (w, h)),
                Err(e) => {
                    let _ = e.to_string();
                }
            }
        }
        _ => {
            let Some(csv) = write_scratch(visnav_io::frames::FRAMES_CSV, rest) else {
                return;
            };
            let Some(dir) = csv.parent() else {
                return;
            };
            match DirectorySource::open(dir) {
                Ok(s) => {
                    let _ = (s.len(), s.rate_hz(), s.describe());
                    // The images it names are not read: a fuzzed name may be any path.
                }
                Err(e) => {
                    let _ = e.to_string();
                }
            }
            let _ = std::fs::remove_file(&csv);
        }
    }
}

fn y4m(bytes: &[u8]) {
    let r = Box::new(Cursor::new(bytes.to_vec()));
    let mut src = match Y4mSource::from_reader(r, Path::new("fuzz.y4m")) {
        Ok(s) => s,
        Err(e) => {
            let _ = e.to_string();
            return;
        }
    };
    let _ = (
        src.size(),
        src.fps(),
        src.colour(),
        src.describe(),
        src.rate_hz(),
    );
    for _ in 0..4 {
        match src.next_frame() {
            Ok(Some(f)) => {
                assert_eq!((f.image.width(), f.image.height()), src.size());
            }
            Ok(None) => break,
            Err(e) => {
                let _ = e.to_string();
                break;
            }
        }
    }
}

// ------------------------------------------------------------------------------------------------
// mavlink: the autopilot link's intake (frames -> messages -> filter inputs -> filter -> output)

/// The first byte picks the input form, the rest is the input: `% 3` = 0 a byte stream as read
/// from the serial/TCP/UDP link (frame sync, CRC, with signature checking when `mode & 4`), 1
/// message payloads without the frame (`[id u16 LE, length u8, payload]` records: what reaches
/// `MavMessage::parse` once a frame's CRC matched, so the fuzzer need not find CRCs), 2 a `.tlog`
/// through `visnav replay`. The messages go through the daemon's conversion (`Inputs::convert`,
/// `mode & 8`: GPS2, `mode & 16`: IMU bias restoring) into a navigation filter, and its outputs
/// into the injector's estimate, as in the daemon's navigation task.
pub fn mavlink(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let mut nav = NavTask::new(mode);
    match mode % 3 {
        0 => {
            let signing = (mode & 4 != 0).then(|| {
                mavlink::SigningData::from_config(mavlink::SigningConfig::new(
                    [7; 32], 1, false, true,
                ))
            });
            let mut reader = mavlink::MavlinkReader::new(rest);
            for _ in 0..4 * MAX_ITEMS {
                let raw = match reader.read_any_raw_message_signed::<MavMessage>(signing.as_ref()) {
                    Ok(raw) => raw,
                    Err(MessageReadError::Io(_)) => break,
                    Err(e) => {
                        let _ = e.to_string();
                        continue;
                    }
                };
                // The link's own decoding of a received frame.
                let Some((header, msg)) = visnav_link::decode(&raw) else {
                    continue;
                };
                nav.telemetry(header, msg);
            }
        }
        1 => {
            let mut b = rest;
            for _ in 0..4 * MAX_ITEMS {
                let [lo, hi, len, tail @ ..] = b else {
                    break;
                };
                let n = usize::from(*len).min(tail.len());
                let (payload, next) = tail.split_at(n);
                b = next;
                let id = u32::from(u16::from_le_bytes([*lo, *hi]));
                let version = if id > 255 || *len & 0x80 != 0 {
                    MavlinkVersion::V2
                } else {
                    MavlinkVersion::V1
                };
                if let Ok(msg) = MavMessage::parse(version, id, payload) {
                    nav.telemetry(MavHeader::default(), msg);
                }
            }
        }
        _ => {
            let records = visnav_link::tlog::read_tlog(rest);
            let records = &records[..records.len().min(4 * MAX_ITEMS)];
            let opts = visnav_daemon::replay::ReplayOptions {
                daemon: nav.daemon_cfg.clone(),
                gps: nav.gps,
                nav: NavConfig::default(),
                autopilot_system_id: None,
                autopilot_component_id: 1,
                state_interval_s: 0.1,
            };
            let rep = visnav_daemon::replay::replay(records, &[], &[], &opts);
            let _ = visnav_daemon::replay::meas_csv(&rep);
            let _ = visnav_daemon::replay::states_csv(&rep);
        }
    }
}

/// The daemon's navigation task without its clocks and channels.
struct NavTask {
    daemon_cfg: DaemonConfig,
    gps: GpsSource,
    inputs: Inputs,
    filter: NavFilter,
    n: u64,
    /// The link's stale-message and reboot rule, as in front of the real navigation task.
    boot: visnav_link::time::BootClock,
    epoch: u32,
}

impl NavTask {
    fn new(mode: u8) -> Self {
        let daemon_cfg = DaemonConfig {
            imu_bias_restore: if mode & 16 != 0 {
                ImuBiasRestore::ScaledImu
            } else {
                ImuBiasRestore::Auto
            },
            ..DaemonConfig::default()
        };
        let gps = if mode & 8 != 0 {
            GpsSource::Gps2
        } else {
            GpsSource::Gps1
        };
        Self {
            inputs: Inputs::new(daemon_cfg.clone(), gps),
            daemon_cfg,
            gps,
            filter: NavFilter::new(NavConfig::default()),
            n: 0,
            boot: visnav_link::time::BootClock::default(),
            epoch: 0,
        }
    }

    fn telemetry(&mut self, header: MavHeader, msg: MavMessage) {
        self.n += 1;
        // Arrival every 10 ms; the boot-time mapping converged after the first few messages.
        let t_companion_ns = (self.n * 10_000_000) as i64;
        if let Some(b) = visnav_link::boot_time_us(&msg) {
            use mavlink::Message;
            match self.boot.observe(msg.message_id(), b, t_companion_ns) {
                visnav_link::time::BootVerdict::Current => {}
                visnav_link::time::BootVerdict::Stale => return,
                visnav_link::time::BootVerdict::Reboot => self.epoch += 1,
            }
        }
        let tel = Telemetry {
            t_companion_ns,
            t_boot_us: (self.n > 3).then_some(self.n * 10_000),
            boot_epoch: self.epoch,
            header,
            msg,
        };
        for input in self.inputs.convert(&tel) {
            match input {
                NavInput::Imu(s) => {
                    if let Some(o) = self.filter.imu(&s) {
                        let health = visnav_link::Health::Ok;
                        if let Some(e) = estimate_from_output(&o, health, 0) {
                            let _ = visnav_link::inject::check_estimate(&e);
                        }
                    }
                }
                NavInput::Meas(m) => {
                    let _ = self.filter.measure(m);
                }
                NavInput::Vehicle { multirotor } => self.filter.set_multirotor(multirotor),
                NavInput::Reboot => {
                    self.filter = NavFilter::new(NavConfig::default());
                    self.filter.set_multirotor(self.inputs.multirotor());
                }
            }
        }
    }
}
