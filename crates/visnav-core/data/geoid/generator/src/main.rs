//! Generates visnav's bundled EGM96 geoid grid from the EGM96 spherical-harmonic model
//! (degree/order 360 plus the Rapp (1996) height-anomaly-to-undulation correction terms),
//! evaluated with the NGA F477 algorithm as ported by the `egm96` crate (Zlib licence).
//!
//! Output: little-endian i16, geoid undulation in centimetres (rounded), 721 rows from latitude
//! +90 to -90 in 0.25 deg steps, each of 1440 columns from longitude 0 to 359.75 deg in 0.25 deg
//! steps. Usage: `cargo run --release -- OUT.bin` (takes a few minutes on one core).
use std::io::Write;

fn main() -> std::process::ExitCode {
    let out = std::env::args().nth(1).unwrap_or_else(|| "egm96_15min_cm.i16le".to_string());
    let (rows, cols, step) = (721usize, 1440usize, 0.25f64);
    let mut bytes = Vec::with_capacity(rows * cols * 2);
    let mut scratch = egm96::Egm96Scratch::new();
    let (mut min, mut max) = (f64::MAX, f64::MIN);
    for r in 0..rows {
        let lat = 90.0 - step * r as f64;
        for c in 0..cols {
            let lon = step * c as f64;
            let n = egm96::egm96_compute_altitude_offset_with_scratch(lat, lon, &mut scratch);
            min = min.min(n);
            max = max.max(n);
            let cm = (n * 100.0).round();
            assert!(cm.abs() < 32000.0);
            bytes.extend_from_slice(&(cm as i16).to_le_bytes());
        }
        if r % 60 == 0 {
            eprintln!("row {r}/{rows}");
        }
    }
    if let Err(e) = std::fs::File::create(&out).and_then(|mut f| f.write_all(&bytes)) {
        eprintln!("{out}: cannot write: {e}");
        return std::process::ExitCode::FAILURE;
    }
    eprintln!("wrote {out}: {} bytes, N in [{min:.3}, {max:.3}] m", bytes.len());
    std::process::ExitCode::SUCCESS
}
