//! MAVLink 2 message signing (<https://mavlink.io/en/guide/message_signing.html>): loading the
//! 32-byte secret key and building the mavlink crate's signing configuration.
//!
//! Key file format: either exactly 32 raw bytes, or 64 hexadecimal characters (surrounding
//! whitespace ignored) — the form `openssl rand -hex 32 > key` produces.

use std::path::{Path, PathBuf};

/// Why a key file cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum KeyError {
    /// The file cannot be read.
    #[error("{path}: cannot read: {cause}")]
    Read {
        /// The key file.
        path: PathBuf,
        /// The operating system's error.
        cause: std::io::Error,
    },
    /// Neither 32 raw bytes nor 64 hexadecimal characters.
    #[error("{path}: expected 32 raw bytes or 64 hexadecimal characters, found {len} bytes")]
    Format {
        /// The key file.
        path: PathBuf,
        /// Its length, bytes.
        len: usize,
    },
    /// An all-zero key (no key at all).
    #[error("{path}: the key is all zeros")]
    Zero {
        /// The key file.
        path: PathBuf,
    },
}

/// Parse key bytes (see module docs).
pub fn parse_key(bytes: &[u8]) -> Option<[u8; 32]> {
    if bytes.len() == 32 && std::str::from_utf8(bytes).map_or(true, |s| s.trim().len() != 64) {
        let mut k = [0u8; 32];
        k.copy_from_slice(bytes);
        return Some(k);
    }
    let s = std::str::from_utf8(bytes).ok()?.trim();
    if s.len() != 64 || !s.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    let mut k = [0u8; 32];
    for (i, out) in k.iter_mut().enumerate() {
        *out = u8::from_str_radix(&s[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(k)
}

/// The most bytes of a key file read: more than any key form (64 hex digits, a line end, some
/// spaces), so a longer file fails the format check by its length.
const MAX_KEY_FILE_BYTES: u64 = 4096;

/// Read and parse a key file.
pub fn load_key(path: &Path) -> Result<[u8; 32], KeyError> {
    // A key file is 32 bytes (64 hex digits and a newline at most as text): read a little more
    // than the longest form so an oversized file is refused by its length, never read whole.
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| {
            use std::io::Read;
            f.take(MAX_KEY_FILE_BYTES).read_to_end(&mut bytes)
        })
        .map_err(|source| KeyError::Read {
            path: path.to_path_buf(),
            cause: source,
        })?;
    let key = parse_key(&bytes).ok_or_else(|| KeyError::Format {
        path: path.to_path_buf(),
        len: bytes.len(),
    })?;
    if key == [0u8; 32] {
        return Err(KeyError::Zero {
            path: path.to_path_buf(),
        });
    }
    Ok(key)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_and_raw_keys() {
        let hex = "00112233445566778899aabbccddeeff00112233445566778899AABBCCDDEEFF\n";
        let k = parse_key(hex.as_bytes()).unwrap();
        assert_eq!(k[0], 0x00);
        assert_eq!(k[1], 0x11);
        assert_eq!(k[31], 0xff);
        let raw: Vec<u8> = (1..=32).collect();
        assert_eq!(parse_key(&raw).unwrap()[31], 32);
        assert!(parse_key(b"too short").is_none());
        assert!(parse_key(&[b'g'; 64]).is_none());
    }

    #[test]
    fn load_rejects_missing_and_zero() {
        let d = tempfile::tempdir().unwrap();
        assert!(load_key(&d.path().join("absent")).is_err());
        let f = d.path().join("zero");
        std::fs::write(&f, [0u8; 32]).unwrap();
        assert!(matches!(load_key(&f), Err(KeyError::Zero { .. })));
    }
}
