//! Validation of configuration values: each section type checks its own values through
//! [`Validate`] and reports every problem into [`Problems`] as an [`Invalid`] naming the dotted key
//! path (`camera.fx_px`), the value and the reason; the application reports them all at once,
//! prefixed with the file name. A leaf module: every configurable module uses it, it uses none.

use std::fmt;
use std::path::{Path, PathBuf};

/// One invalid configuration value.
#[derive(Debug, Clone, PartialEq)]
pub struct Invalid {
    /// Dotted key path, e.g. `camera.distortion.k1`.
    pub key: String,
    /// Why the value is rejected (include the value and the accepted range).
    pub reason: String,
}

impl fmt::Display for Invalid {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.reason)
    }
}

/// Collects validation problems under a key prefix.
#[derive(Debug, Default)]
pub struct Problems {
    prefix: Vec<String>,
    /// Problems found so far.
    pub list: Vec<Invalid>,
}

impl Problems {
    /// Run `f` with `name` appended to the key prefix (for nested sections).
    pub fn section(&mut self, name: &str, f: impl FnOnce(&mut Problems)) {
        self.prefix.push(name.to_string());
        f(self);
        self.prefix.pop();
    }

    /// Record that `key` (relative to the current section) is invalid.
    pub fn push(&mut self, key: &str, reason: impl Into<String>) {
        let mut full = self.prefix.join(".");
        if !key.is_empty() {
            if !full.is_empty() {
                full.push('.');
            }
            full.push_str(key);
        }
        self.list.push(Invalid {
            key: full,
            reason: reason.into(),
        });
    }

    /// Require `lo <= v <= hi` and finite.
    pub fn range(&mut self, key: &str, v: f64, lo: f64, hi: f64) {
        if !v.is_finite() || v < lo || v > hi {
            self.push(
                key,
                format!(
                    "{} is outside the accepted range [{lo}, {hi}]",
                    crate::text::num(v)
                ),
            );
        }
    }

    /// Require a finite value strictly greater than zero.
    pub fn positive(&mut self, key: &str, v: f64) {
        if !v.is_finite() || v <= 0.0 {
            self.push(
                key,
                format!(
                    "{} must be a finite number greater than 0",
                    crate::text::num(v)
                ),
            );
        }
    }

    /// Require a finite value.
    pub fn finite(&mut self, key: &str, v: f64) {
        if !v.is_finite() {
            self.push(
                key,
                format!("{} must be a finite number", crate::text::num(v)),
            );
        }
    }
}

/// A configuration section that can check its own values.
pub trait Validate {
    /// Push every invalid value into `p` (keys relative to this section).
    fn validate(&self, p: &mut Problems);
}

/// Resolve `f` against `base` (the configuration file's folder: relative paths in a configuration are relative to it) unless it is absolute.
pub fn resolve(base: &Path, f: &Path) -> PathBuf {
    if f.is_absolute() {
        f.to_path_buf()
    } else {
        base.join(f)
    }
}

/// The rule for paths written in a configuration file, as messages state it.
pub const FILE_PATH_RULE: &str = "paths in the config are relative to the config file's folder";

/// The rule for paths given by a command-line option or an environment variable.
pub const OVERRIDE_PATH_RULE: &str =
    "paths on the command line and in the environment are relative to the current directory";

/// The folder a configuration's relative paths are resolved against, and the rule that chose it
/// (named in messages): the configuration file's folder for what the file says, the current
/// directory for a command-line or environment override.
#[derive(Debug, Clone, PartialEq)]
pub struct Base {
    dir: PathBuf,
    rule: &'static str,
}

impl Base {
    /// Paths written in the configuration file `config`: relative to its folder.
    pub fn config_file(config: &Path) -> Base {
        Self::config_folder(config.parent().unwrap_or(Path::new("")))
    }

    /// Paths written in a configuration file in the folder `dir`.
    pub fn config_folder(dir: &Path) -> Base {
        Base {
            dir: absolute(dir),
            rule: FILE_PATH_RULE,
        }
    }

    /// Paths from the command line or the environment: relative to the current directory.
    pub fn current_dir() -> Base {
        Base {
            dir: absolute(Path::new("")),
            rule: OVERRIDE_PATH_RULE,
        }
    }

    /// The folder (absolute when the current directory is known).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The rule, as messages state it.
    pub fn rule(&self) -> &'static str {
        self.rule
    }

    /// `f` resolved against the folder unless it is absolute.
    pub fn resolve(&self, f: &Path) -> PathBuf {
        resolve(&self.dir, f)
    }

    /// A problem with the path `f` as written: `"maps/x.vnm": /home/pi/config/maps/x.vnm does not
    /// exist (paths in the config are relative to the config file's folder)`, where `what` is
    /// what is wrong with the resolved path (`does not exist`, `is not a directory`). An
    /// absolute path is its own resolution: neither repeated nor followed by the rule, which
    /// would wrongly suggest it was taken as relative.
    pub fn problem(&self, f: &Path, what: &str) -> String {
        if f.is_absolute() {
            return format!("\"{}\" {what}", f.display());
        }
        format!(
            "\"{}\": {} {what} ({})",
            f.display(),
            self.resolve(f).display(),
            self.rule
        )
    }

    /// What is wrong with the file `f` (relative to this base), if anything, given what
    /// examining its resolved path found (`is_file`: whether it is a regular file; the caller
    /// does the I/O, e.g. `std::fs::metadata(base.resolve(f)).map(|m| m.is_file())`): it does
    /// not exist, is not a regular file or cannot be examined.
    pub fn file_problem(&self, f: &Path, is_file: std::io::Result<bool>) -> Option<String> {
        match is_file {
            Ok(true) => None,
            Ok(false) => Some(self.problem(f, "is not a regular file")),
            Err(e) => Some(self.io_problem(f, &e)),
        }
    }

    /// A problem from examining `f`: "does not exist" for a missing file, else the OS error.
    pub fn io_problem(&self, f: &Path, e: &std::io::Error) -> String {
        if e.kind() == std::io::ErrorKind::NotFound {
            self.problem(f, "does not exist")
        } else {
            self.problem(f, &format!("cannot be examined: {e}"))
        }
    }
}

/// `f` made absolute against the current directory (without resolving links or `..`); `f`
/// itself when the current directory is unknown.
fn absolute(f: &Path) -> PathBuf {
    let f = if f.as_os_str().is_empty() {
        Path::new(".")
    } else {
        f
    };
    std::path::absolute(f).unwrap_or_else(|_| f.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn examine(base: &Base, f: &str) -> std::io::Result<bool> {
        std::fs::metadata(base.resolve(Path::new(f))).map(|m| m.is_file())
    }

    #[test]
    fn a_path_problem_names_the_value_the_resolved_path_and_the_rule() {
        let base = Base::config_file(Path::new("/home/pi/visnav/config/visnav.toml"));
        assert_eq!(base.dir(), Path::new("/home/pi/visnav/config"));
        assert_eq!(
            base.file_problem(Path::new("maps/x.vnm"), examine(&base, "maps/x.vnm"))
                .as_deref(),
            Some(
                "\"maps/x.vnm\": /home/pi/visnav/config/maps/x.vnm does not exist (paths in the \
                 config are relative to the config file's folder)"
            )
        );
        assert_eq!(base.resolve(Path::new("/abs.vnm")), Path::new("/abs.vnm"));
        let dir = base
            .file_problem(Path::new("/"), examine(&base, "/"))
            .unwrap_or_default();
        assert_eq!(dir, "\"/\" is not a regular file");
        // An absolute path is not said to be relative to anything.
        assert_eq!(
            base.file_problem(
                Path::new("/var/log/visnav-none/a.tlog"),
                examine(&base, "/var/log/visnav-none/a.tlog")
            )
            .as_deref(),
            Some("\"/var/log/visnav-none/a.tlog\" does not exist")
        );
    }

    #[test]
    fn relative_bases_become_absolute() {
        let cwd = std::env::current_dir().unwrap();
        for base in [
            Base::config_file(Path::new("visnav.toml")),
            Base::config_file(Path::new("./visnav.toml")),
            Base::current_dir(),
        ] {
            assert_eq!(base.dir(), cwd, "{base:?}");
        }
        assert_eq!(
            Base::config_file(Path::new("config/v.toml")).dir(),
            cwd.join("config")
        );
        assert_eq!(Base::current_dir().rule(), OVERRIDE_PATH_RULE);
    }
}
