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

/// A .tlog read back: its records and what was skipped between them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TlogContents {
    /// (timestamp µs, packet bytes) for each MAVLink 1/2 packet, in file order.
    pub records: Vec<(u64, Vec<u8>)>,
    /// Bytes that were not part of any record (corruption, junk, a truncated last record).
    pub skipped_bytes: u64,
    /// Places where bytes were skipped (each run of consecutive skipped bytes counts once).
    pub skipped_runs: u64,
}

/// MAVLink 2 incompatibility flag: the packet carries a 13-byte signature.
const MAVLINK2_SIGNED: u8 = 0x01;

/// What starts at some offset of a .tlog.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Candidate {
    /// A record of this length (timestamp + packet) whose MAVLink framing is complete and whose
    /// CRC checks with its message's CRC_EXTRA, as a MAVLink parser accepts a packet.
    Checked(usize),
    /// A complete packet of a message id this dialect does not know: its CRC cannot be checked.
    Unknown(usize),
    /// No record: no MAVLink start byte 8 bytes on, an incomplete packet, an unknown
    /// incompatibility flag or a wrong CRC.
    Nothing,
}

fn record_at(b: &[u8]) -> Candidate {
    use mavlink::Message;
    use mavlink::dialects::ardupilotmega::MavMessage;
    let framed = |p: &[u8]| -> Option<(usize, usize, u32)> {
        match *p.first()? {
            0xFD => {
                let hdr = p.get(..10)?;
                if hdr[2] & !MAVLINK2_SIGNED != 0 {
                    return None; // an incompatibility flag no MAVLink 2 parser knows
                }
                let crc_end = 10 + usize::from(hdr[1]);
                let signature = if hdr[2] & MAVLINK2_SIGNED != 0 { 13 } else { 0 };
                let msgid = u32::from_le_bytes([hdr[7], hdr[8], hdr[9], 0]);
                Some((crc_end + 2 + signature, crc_end, msgid))
            }
            0xFE => {
                let hdr = p.get(..6)?;
                Some((
                    6 + usize::from(hdr[1]) + 2,
                    6 + usize::from(hdr[1]),
                    u32::from(hdr[5]),
                ))
            }
            _ => None,
        }
    };
    let Some(p) = b.get(8..) else {
        return Candidate::Nothing;
    };
    let Some((len, crc_end, msgid)) = framed(p) else {
        return Candidate::Nothing;
    };
    let Some(packet) = p.get(..len) else {
        return Candidate::Nothing;
    };
    if MavMessage::default_message_from_id(msgid).is_none() {
        return Candidate::Unknown(8 + len);
    }
    let crc = mavlink::calculate_crc(&packet[1..crc_end], MavMessage::extra_crc(msgid));
    if crc == u16::from_le_bytes([packet[crc_end], packet[crc_end + 1]]) {
        Candidate::Checked(8 + len)
    } else {
        Candidate::Nothing
    }
}

/// Read a .tlog back, resynchronising after damage as MAVLink parsers do: a record is taken
/// where a MAVLink 1/2 packet of a known message starts 8 bytes on and its CRC checks; anything
/// else is skipped a byte at a time up to the next such record and counted. A packet of a
/// message this dialect does not know (its CRC cannot be checked) is taken when it is followed
/// by the end of the file or by a checked record, so a log with another dialect's messages still
/// reads whole.
pub fn scan_tlog(bytes: &[u8]) -> TlogContents {
    let mut out = TlogContents::default();
    let mut i = 0;
    let mut in_gap = false;
    while i < bytes.len() {
        let take = match record_at(&bytes[i..]) {
            Candidate::Checked(len) => Some(len),
            Candidate::Unknown(len) => {
                let next = i + len;
                (next == bytes.len() || matches!(record_at(&bytes[next..]), Candidate::Checked(_)))
                    .then_some(len)
            }
            Candidate::Nothing => None,
        };
        match take {
            Some(len) => {
                let mut ts = [0u8; 8];
                ts.copy_from_slice(&bytes[i..i + 8]);
                out.records
                    .push((u64::from_be_bytes(ts), bytes[i + 8..i + len].to_vec()));
                i += len;
                in_gap = false;
            }
            None => {
                if !in_gap {
                    out.skipped_runs += 1;
                    in_gap = true;
                }
                out.skipped_bytes += 1;
                i += 1;
            }
        }
    }
    out
}

/// The records of a .tlog ([`scan_tlog`] without the count of what was skipped).
pub fn read_tlog(bytes: &[u8]) -> Vec<(u64, Vec<u8>)> {
    scan_tlog(bytes).records
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{self as ap, MavMessage};

    /// A real packet (CRC and all) of message `seq`-numbered HEARTBEAT or ATTITUDE.
    fn packet(v2: bool, seq: u8) -> Vec<u8> {
        let header = mavlink::MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: seq,
        };
        let msg = if seq.is_multiple_of(2) {
            MavMessage::HEARTBEAT(ap::HEARTBEAT_DATA::default())
        } else {
            MavMessage::ATTITUDE(ap::ATTITUDE_DATA {
                time_boot_ms: u32::from(seq) * 20,
                roll: 0.1,
                ..Default::default()
            })
        };
        let mut out = Vec::new();
        if v2 {
            mavlink::write_v2_msg(&mut out, header, &msg).unwrap();
        } else {
            mavlink::write_v1_msg(&mut out, header, &msg).unwrap();
        }
        out
    }

    fn log(n: usize) -> (Vec<u8>, Vec<(u64, Vec<u8>)>) {
        let mut bytes = Vec::new();
        let mut recs = Vec::new();
        for i in 0..n {
            let p = packet(i % 3 != 0, i as u8);
            let t = 1_700_000_000_000_000 + i as u64 * 10_000;
            bytes.extend_from_slice(&t.to_be_bytes());
            bytes.extend_from_slice(&p);
            recs.push((t, p));
        }
        (bytes, recs)
    }

    #[test]
    fn round_trip() {
        let d = tempfile::tempdir().unwrap();
        let f = expand_name(&d.path().join("x-{t}.tlog"), 42);
        assert!(f.ends_with("x-42.tlog"));
        let mut t = Tlog::create(&f).unwrap();
        let (p1, p2) = (packet(true, 0), packet(false, 1));
        t.write(1_000, &p1).unwrap();
        t.write(2_000, &p2).unwrap();
        drop(t);
        let got = scan_tlog(&std::fs::read(&f).unwrap());
        assert_eq!(got.records, vec![(1_000, p1), (2_000, p2)]);
        assert_eq!((got.skipped_bytes, got.skipped_runs), (0, 0));
    }

    /// One flipped length byte or three junk bytes used to end the reading there (101 of
    /// 22,141 packets read, and nothing said): the records after the damage are read, and the
    /// damage is counted.
    #[test]
    fn damage_is_skipped_and_counted_and_the_rest_is_read() {
        let (clean, recs) = log(300);
        let start_of = |k: usize| -> usize { recs[..k].iter().map(|(_, p)| 8 + p.len()).sum() };

        // Three junk bytes between records 100 and 101.
        let mut junk = clean.clone();
        let at = start_of(101);
        junk.splice(at..at, [0x00, 0xFD, 0x42]);
        let got = scan_tlog(&junk);
        assert_eq!(got.records, recs);
        assert_eq!((got.skipped_bytes, got.skipped_runs), (3, 1));

        // Record 100's length byte flipped: that record is lost, every other one read.
        let mut flipped = clean.clone();
        flipped[start_of(100) + 8 + 1] ^= 0x40;
        let got = scan_tlog(&flipped);
        let mut want = recs.clone();
        want.remove(100);
        assert_eq!(got.records, want);
        assert_eq!(got.skipped_runs, 1);
        assert_eq!(got.skipped_bytes, (8 + recs[100].1.len()) as u64);

        // A payload bit flipped (the CRC fails): the packet is dropped, as a parser drops it.
        let mut payload = clean.clone();
        payload[start_of(7) + 8 + 12] ^= 0x01;
        let got = scan_tlog(&payload);
        assert_eq!(got.records.len(), 299);
        assert_eq!(got.skipped_runs, 1);

        // A truncated last record is counted, not taken.
        let cut = &clean[..clean.len() - 5];
        let got = scan_tlog(cut);
        assert_eq!(got.records.len(), 299);
        assert_eq!(got.skipped_bytes, (8 + recs[299].1.len() - 5) as u64);
        assert_eq!(read_tlog(cut), got.records);
    }

    #[test]
    fn another_dialects_message_is_kept_between_checked_records() {
        let (clean, recs) = log(3);
        // A MAVLink 2 packet of message id 60000 (not in this dialect), CRC unknowable.
        let mut unknown = vec![
            0xFD, 2, 0, 0, 9, 1, 1, 0x60, 0xEA, 0x00, 0xAB, 0xCD, 0x12, 0x34,
        ];
        let first = 8 + recs[0].1.len();
        let mut bytes = clean[..first].to_vec();
        bytes.extend_from_slice(&5u64.to_be_bytes());
        bytes.append(&mut unknown.clone());
        bytes.extend_from_slice(&clean[first..]);
        let got = scan_tlog(&bytes);
        assert_eq!(got.records.len(), 4);
        assert_eq!(got.records[1], (5, unknown.clone()));
        assert_eq!(got.skipped_bytes, 0);
        // At the end of the file, too.
        let mut tail = clean.clone();
        tail.extend_from_slice(&6u64.to_be_bytes());
        tail.append(&mut unknown);
        assert_eq!(scan_tlog(&tail).records.len(), 4);
    }
}
