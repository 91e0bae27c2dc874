//! Telemetry log (.tlog) recording, the format QGroundControl, MAVProxy and MAVExplorer read:
//! a plain concatenation of records, each an 8-byte big-endian Unix timestamp in microseconds
//! followed by one complete MAVLink packet (header, payload, CRC and signature as on the wire).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// An open .tlog file.
#[derive(Debug)]
pub struct Tlog {
    path: PathBuf,
    out: BufWriter<File>,
    /// Packets written.
    pub packets: u64,
}

/// Replace `{t}` in a configured file name by the Unix time in seconds.
pub fn expand_name(path: &Path, unix_s: u64) -> PathBuf {
    PathBuf::from(path.to_string_lossy().replace("{t}", &unix_s.to_string()))
}

/// Current Unix time in µs (0 if the system clock is before 1970).
pub fn unix_now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

impl Tlog {
    /// Create (truncate) the file.
    pub fn create(path: &Path) -> std::io::Result<Self> {
        let f = File::create(path)?;
        Ok(Self {
            path: path.to_path_buf(),
            out: BufWriter::new(f),
            packets: 0,
        })
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Append one packet with its timestamp.
    pub fn write(&mut self, unix_us: u64, packet: &[u8]) -> std::io::Result<()> {
        self.out.write_all(&unix_us.to_be_bytes())?;
        self.out.write_all(packet)?;
        self.packets += 1;
        Ok(())
    }

    /// Flush buffered records to the file.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

impl Drop for Tlog {
    fn drop(&mut self) {
        let _ = self.out.flush();
    }
}

/// Read a .tlog back: (timestamp µs, packet bytes) for each MAVLink 1/2 packet. Stops at the first
/// record that is not a complete packet.
pub fn read_tlog(bytes: &[u8]) -> Vec<(u64, Vec<u8>)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i + 8 + 3 <= bytes.len() {
        let mut ts = [0u8; 8];
        ts.copy_from_slice(&bytes[i..i + 8]);
        let p = &bytes[i + 8..];
        let len = match p[0] {
            0xFD if p.len() >= 10 => {
                let signed = p[2] & 0x01 != 0;
                12 + p[1] as usize + if signed { 13 } else { 0 }
            }
            0xFE => 8 + p[1] as usize,
            _ => break,
        };
        if p.len() < len {
            break;
        }
        out.push((u64::from_be_bytes(ts), p[..len].to_vec()));
        i += 8 + len;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let d = tempfile::tempdir().unwrap();
        let f = expand_name(&d.path().join("x-{t}.tlog"), 42);
        assert!(f.ends_with("x-42.tlog"));
        let mut t = Tlog::create(&f).unwrap();
        let p1 = [0xFD, 1, 0, 0, 5, 1, 1, 0, 0, 0, 7, 0xAA, 0xBB];
        let p2 = [0xFE, 0, 3, 1, 1, 0, 0x11, 0x22];
        t.write(1_000, &p1).unwrap();
        t.write(2_000, &p2).unwrap();
        drop(t);
        let got = read_tlog(&std::fs::read(&f).unwrap());
        assert_eq!(got, vec![(1_000, p1.to_vec()), (2_000, p2.to_vec())]);
    }
}
