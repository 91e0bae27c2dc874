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
                format!("{v} is outside the accepted range [{lo}, {hi}]"),
            );
        }
    }

    /// Require a finite value strictly greater than zero.
    pub fn positive(&mut self, key: &str, v: f64) {
        if !v.is_finite() || v <= 0.0 {
            self.push(key, format!("{v} must be a finite number greater than 0"));
        }
    }

    /// Require a finite value.
    pub fn finite(&mut self, key: &str, v: f64) {
        if !v.is_finite() {
            self.push(key, format!("{v} must be a finite number"));
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
