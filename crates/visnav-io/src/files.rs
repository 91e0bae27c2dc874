//! Reading a user-named file whole, within a size that fits its kind. A configuration, a
//! calibration, a `frames.csv`, a frame image or a telemetry log is read into memory in one
//! piece; a path naming `/dev/zero`, a pipe that never ends or a file far larger than its kind
//! ever is would otherwise grow the process until the system kills it. [`read_bytes`] and
//! [`read_text`] refuse anything that is not a regular file, refuse a file over its kind's limit
//! before reading it, and read at most the limit even when the file grows meanwhile.
//!
//! The errors are `std::io::Error`s (kind `InvalidInput` for a file that is not a regular file,
//! `FileTooLarge` for one over the limit, `InvalidData` for text that is not UTF-8) whose message
//! names the limit and the kind; the callers' error types add the path as they do for every other
//! read error.

use std::fs::File;
use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// What a file is, for its size limit and for messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FileKind {
    /// The kind in words ("a TOML configuration").
    pub what: &'static str,
    /// The largest file of this kind read, bytes.
    pub max_bytes: u64,
}

const MIB: u64 = 1 << 20;

/// A TOML configuration (`visnav run --config`, a `--camera` or `--settings` file of `visnav
/// fix`): the example configurations are a few KiB; 4 MiB leaves a thousand times that for
/// comments and long lists.
pub const CONFIG: FileKind = FileKind {
    what: "a TOML configuration",
    max_bytes: 4 * MIB,
};

/// A camera calibration (OpenCV / ROS / Kalibr YAML): a few KiB, a Kalibr camchain with its
/// transforms and many cameras well under 100 KiB.
pub const CALIBRATION: FileKind = FileKind {
    what: "a camera calibration",
    max_bytes: MIB,
};

/// A `frames.csv` timestamps file: a row is about 30 bytes, so 64 MiB holds two million frames
/// (ten hours at 50 Hz).
pub const FRAMES_CSV: FileKind = FileKind {
    what: "a frames.csv",
    max_bytes: 64 * MIB,
};

/// A camera frame or image file (PNG, JPEG, TIFF): the largest frame a source accepts is
/// 8192 x 8192 px (`frames::MAX_Y4M_PIXELS`); uncompressed as 16-bit RGBA that is 512 MiB, the
/// most such a file can honestly hold (and the image decoder's own allocation limit).
pub const IMAGE: FileKind = FileKind {
    what: "an image file",
    max_bytes: 512 * MIB,
};

/// A MAVLink telemetry log (`visnav replay --tlog`): replay holds it in memory twice (the bytes
/// and the records); a day of a full-rate 921600 baud link is under 8 GiB, a long flight's log a
/// few hundred MiB, so 2 GiB covers every flight log while bounding what a wrong path costs.
pub const TLOG: FileKind = FileKind {
    what: "a telemetry log (.tlog)",
    max_bytes: 2048 * MIB,
};

/// A tiled map's `index.json`, `plan.json` or square result: about 300 bytes per tile, so 256 MiB
/// lists close to a million tiles (a continent at 2 km tiles).
pub const TILED_INDEX: FileKind = FileKind {
    what: "a tiled map's index, plan or square result",
    max_bytes: 256 * MIB,
};

/// The daemon's fix or visual odometry log (JSON lines, `visnav replay --fixes / --vo-log`): a
/// line is under 1 KiB, so 512 MiB holds more than ten hours of 10 Hz fixes.
pub const JSON_LOG: FileKind = FileKind {
    what: "a fix or VO log",
    max_bytes: 512 * MIB,
};

/// A size in bytes in words: `4 MiB`, `512 KiB`, `37 bytes`.
pub fn size_words(bytes: u64) -> String {
    const GIB: u64 = 1 << 30;
    if bytes >= GIB && bytes.is_multiple_of(GIB) {
        format!("{} GiB", bytes / GIB)
    } else if bytes >= MIB && bytes.is_multiple_of(MIB) {
        format!("{} MiB", bytes / MIB)
    } else if bytes >= 1024 && bytes.is_multiple_of(1024) {
        format!("{} KiB", bytes / 1024)
    } else {
        format!("{bytes} bytes")
    }
}

/// What a file type is, in words, for one that is not a regular file.
fn type_words(t: std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_dir() {
        "a directory"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_fifo() {
        "a pipe"
    } else if t.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

fn too_large(kind: FileKind, size: Option<u64>) -> Error {
    let size = size.map_or("more".to_string(), |s| format!("{s} bytes,"));
    Error::new(
        ErrorKind::FileTooLarge,
        format!(
            "{size} larger than the {} {} may have",
            size_words(kind.max_bytes),
            kind.what
        ),
    )
}

/// Refuse `path` unless it is a regular file (named `what` in the message, e.g. "a GeoTIFF"):
/// for files that are read in parts rather than whole (maps, GeoTIFFs), where a device or a
/// pipe would make the reader wait for ever or read without end. Examined before opening,
/// because opening a pipe waits for a writer.
pub fn require_regular(path: &Path, what: &str) -> std::io::Result<()> {
    let t = std::fs::metadata(path)?.file_type();
    if t.is_file() {
        return Ok(());
    }
    Err(Error::new(
        ErrorKind::InvalidInput,
        format!(
            "{}, not a regular file; {what} must be a file",
            type_words(t)
        ),
    ))
}

/// Opens `path` for reading in parts, refusing anything but a regular file (a device or a pipe
/// would never end); `what` names its kind in the error.
pub fn open_regular(path: &Path, what: &str) -> std::io::Result<std::fs::File> {
    require_regular(path, what)?;
    std::fs::File::open(path)
}

/// The whole of the regular file `path`, at most `kind.max_bytes` of it (see the module docs).
pub fn read_bytes(path: &Path, kind: FileKind) -> std::io::Result<Vec<u8>> {
    require_regular(path, kind.what)?;
    let file = File::open(path)?;
    let len = file.metadata()?.len();
    if len > kind.max_bytes {
        return Err(too_large(kind, Some(len)));
    }
    let mut out = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    // One byte past the limit tells a file that grew since from one that is exactly at it.
    file.take(kind.max_bytes + 1).read_to_end(&mut out)?;
    if out.len() as u64 > kind.max_bytes {
        return Err(too_large(kind, None));
    }
    Ok(out)
}

/// [`read_bytes`] as UTF-8 text, without a leading byte order mark (Windows editors write one;
/// it is not part of the content).
pub fn read_text(path: &Path, kind: FileKind) -> std::io::Result<String> {
    let bytes = read_bytes(path, kind)?;
    let text = String::from_utf8(bytes).map_err(|e| {
        Error::new(
            ErrorKind::InvalidData,
            format!(
                "not UTF-8 text (byte {}); {} is text",
                e.utf8_error().valid_up_to(),
                kind.what
            ),
        )
    })?;
    Ok(match text.strip_prefix(BOM) {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// The UTF-8 byte order mark.
pub const BOM: char = '\u{feff}';

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: FileKind = FileKind {
        what: "a test file",
        max_bytes: 16,
    };

    #[test]
    fn devices_pipes_and_folders_are_refused_without_reading() {
        for (p, words) in [("/dev/zero", "character device"), ("/tmp", "directory")] {
            let e = read_bytes(Path::new(p), CONFIG).unwrap_err();
            assert_eq!(e.kind(), ErrorKind::InvalidInput, "{p}");
            let m = e.to_string();
            assert!(
                m.contains(words) && m.contains("a TOML configuration"),
                "{m}"
            );
        }
        let e = read_text(Path::new("/nonexistent/x.toml"), CONFIG).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::NotFound);
        // Maps and GeoTIFFs are read in parts, not whole: a device is refused all the same.
        let e = crate::map::ReferenceMap::open(Path::new("/dev/zero"))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("/dev/zero") && e.contains("a reference map must be a file"),
            "{e}"
        );
        let e = crate::geo::geotiff::load_geotiff(Path::new("/dev/zero"), None)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("a GeoTIFF must be a file"), "{e}");
    }

    #[test]
    fn a_file_over_its_limit_is_refused_naming_the_limit() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("f");
        std::fs::write(&f, [b'a'; 16]).unwrap();
        assert_eq!(read_bytes(&f, SMALL).unwrap().len(), 16);
        std::fs::write(&f, [b'a'; 17]).unwrap();
        let e = read_bytes(&f, SMALL).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::FileTooLarge);
        assert_eq!(
            e.to_string(),
            "17 bytes, larger than the 16 bytes a test file may have"
        );
        assert_eq!(size_words(CONFIG.max_bytes), "4 MiB");
        assert_eq!(size_words(TLOG.max_bytes), "2 GiB");
    }

    #[test]
    fn text_loses_its_byte_order_mark_and_must_be_utf8() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("f");
        std::fs::write(&f, "\u{feff}a,b\n").unwrap();
        assert_eq!(read_text(&f, SMALL).unwrap(), "a,b\n");
        std::fs::write(&f, b"ab\xff").unwrap();
        let e = read_text(&f, SMALL).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::InvalidData);
        assert!(e.to_string().contains("byte 2"), "{e}");
    }
}
