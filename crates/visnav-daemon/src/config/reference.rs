//! The configuration's key reference and its default file, generated from the configuration
//! types so that neither can go stale (`visnav config reference`, `visnav config default`,
//! docs/config-reference.md).
//!
//! What is written by hand is only what the types cannot say: one line of meaning per key
//! ([`KEYS`], in the order the reference and the default file show them), an example for a key
//! without a default, and a range in words where the validation's message has no bounds to read.
//! Everything else is asked of the types themselves:
//!
//! * the keys: serde's "unknown field, expected one of ..." answer to a probe key in every
//!   table ([`accepted_keys`]); a test holds [`KEYS`] to exactly that set;
//! * the defaults: the `Default` impls (or the serde defaults of a section without one),
//!   serialised ([`defaults`]);
//! * the type: serde's answer to a value of the wrong type (`expected f64`, `unknown variant,
//!   expected one of ...`), so the choices of an enum are the enum's own;
//! * whether a key is required: serde's "missing field" for a file without it;
//! * the range: the validation's message for a value far outside it (`[lo, hi]`, `> 0`);
//! * the unit: the key's suffix (`_m`, `_s`, `_hz`, `_deg_h`, ...), the project's naming rule.

use std::collections::BTreeSet;
use std::path::Path;

use crate::config::{Config, Overrides, PLACEHOLDER_MARK};
use visnav_core::validate::Base;

mod keys;
mod values;
pub use keys::KEYS;

/// One key the reference documents, written by hand beside the types.
#[derive(Debug, Clone, Copy)]
pub struct KeyDoc {
    /// Dotted path (`link.streams.imu_hz`).
    pub path: &'static str,
    /// One line of meaning.
    pub meaning: &'static str,
    /// TOML value shown for a key without a default (`""`: none): in the default file as a
    /// commented-out line.
    pub example: &'static str,
    /// The example is a value every installation must replace (the map, the camera's
    /// calibration, the connection): the default file has it active, marked as a placeholder
    /// that `check-config` warns about.
    pub placeholder: bool,
    /// The accepted values in words, where the validation's message gives no bounds (`""`:
    /// read from the validation).
    pub range: &'static str,
}

/// One row of the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// Dotted path.
    pub path: String,
    /// The value's type in words (`number`, `integer 0-255`, `"auto" | "gps1" | ...`).
    pub ty: String,
    /// The default as TOML, `required`, or `none` (absent: off / not used).
    pub default: String,
    /// The unit, from the key's suffix (empty: none).
    pub unit: String,
    /// The accepted values.
    pub range: String,
    /// One line of meaning.
    pub meaning: String,
}

/// The probe key: no configuration type has it.
const PROBE: &str = "__probe__";

/// The sections whose keys only apply when the section is present, with the minimal content
/// that makes it parse (for the probes; the default file shows them commented out).
const OPTIONAL_SECTIONS: [(&str, &str); 2] = [
    ("frames", "source = \"directory\"\npath = \"frames\"\n"),
    ("link.signing", "key_file = \"signing.key\"\n"),
];

/// Every key the configuration accepts, as dotted paths (tables are not listed, their keys
/// are), found by asking serde for the fields of every table.
pub fn accepted_keys() -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let defaults = defaults();
    let mut todo: Vec<Vec<String>> = vec![Vec::new()];
    while let Some(path) = todo.pop() {
        // An internally tagged enum (`{ kind = "huber", k_sigma = 3.0 }`) is one value, whose
        // other keys depend on its kind.
        let tagged = get(&defaults, &path.join(".")).is_some_and(|v| v.get("kind").is_some());
        let fields = if tagged { None } else { fields_of(&path) };
        let Some(fields) = fields else {
            out.insert(path.join("."));
            continue;
        };
        for f in fields {
            let mut child = path.clone();
            child.push(f);
            todo.push(child);
        }
    }
    out
}

/// The fields of the table at `path`, or `None` when the value there is not a struct table.
fn fields_of(path: &[String]) -> Option<Vec<String>> {
    let mut doc = toml::Table::new();
    let mut probe = toml::Table::new();
    probe.insert(PROBE.into(), toml::Value::Integer(0));
    set(&mut doc, path, toml::Value::Table(probe));
    let text = toml::to_string(&doc).ok()?;
    let e = toml::from_str::<Config>(&text).err()?;
    let message = e.message();
    let at = message.find(&format!("unknown field `{PROBE}`"))?;
    let rest = &message[at..];
    let expected = rest.split_once("expected")?.1;
    let expected = expected.lines().next().unwrap_or_default();
    Some(
        expected
            .split('`')
            .skip(1)
            .step_by(2)
            .map(str::to_string)
            .collect(),
    )
}

/// Put `value` at the dotted `path` of `doc`, creating the tables on the way.
fn set(doc: &mut toml::Table, path: &[String], value: toml::Value) {
    let Some((last, parents)) = path.split_last() else {
        if let toml::Value::Table(t) = value {
            doc.extend(t);
        }
        return;
    };
    let mut t = doc;
    for p in parents {
        let slot = t
            .entry(p.clone())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if !slot.is_table() {
            *slot = toml::Value::Table(toml::Table::new());
        }
        let toml::Value::Table(inner) = slot else {
            return;
        };
        t = inner;
    }
    t.insert(last.clone(), value);
}

/// The value at the dotted `path` of `doc`.
fn get<'a>(doc: &'a toml::Table, path: &str) -> Option<&'a toml::Value> {
    let mut parts = path.split('.');
    let first = parts.next()?;
    parts.try_fold(doc.get(first)?, |v, p| v.get(p))
}

/// Remove the value at the dotted `path` of `doc`.
fn remove(doc: &mut toml::Table, path: &str) {
    let parts: Vec<&str> = path.split('.').collect();
    let Some((last, parents)) = parts.split_last() else {
        return;
    };
    let mut t = doc;
    for p in parents {
        let Some(toml::Value::Table(inner)) = t.get_mut(*p) else {
            return;
        };
        t = inner;
    }
    t.remove(*last);
}

fn path_of(dotted: &str) -> Vec<String> {
    dotted.split('.').map(str::to_string).collect()
}

/// Serialise a section's value; the configuration types serialise to TOML tables.
fn value_of<T: serde::Serialize>(v: &T) -> toml::Value {
    toml::Value::try_from(v).unwrap_or_else(|_| toml::Value::Table(toml::Table::new()))
}

/// The defaults of every key that has one, as the `Default` impls (and serde's defaults for
/// the sections that have none) give them. Required keys and keys whose absence means "off"
/// are not in it.
pub fn defaults() -> toml::Table {
    use visnav_core::camera::{DistortionConfig, MountConfig};
    let mut t = toml::Table::new();
    // LinkConfig's defaults, with the serde defaults of a [link.signing] (it has no Default).
    let mut link = visnav_link::config::LinkConfig::new("");
    link.signing = toml::from_str("key_file = \"\"").ok();
    t.insert("link".into(), values::link(&link));
    let mut camera = toml::Table::new();
    camera.insert("distortion".into(), value_of(&DistortionConfig::default()));
    camera.insert("mount".into(), value_of(&MountConfig::default()));
    t.insert("camera".into(), toml::Value::Table(camera));
    t.insert("map".into(), value_of(&crate::config::MapConfig::default()));
    t.insert(
        "output".into(),
        values::output(&visnav_link::config::OutputConfig::default()),
    );
    t.insert(
        "nav".into(),
        value_of(&visnav_core::nav::config::NavConfig::default()),
    );
    t.insert(
        "fix".into(),
        value_of(&visnav_core::fix::FixParams::default()),
    );
    t.insert(
        "frames".into(),
        values::frames(&visnav_io::frames::FramesConfig::new(
            visnav_io::frames::SourceKind::Directory,
            "",
        )),
    );
    t.insert("vo".into(), value_of(&visnav_core::vo::VoConfig::default()));
    t.insert(
        "dtm_nav".into(),
        value_of(&visnav_core::dtm_nav::DtmNavConfig::default()),
    );
    t.insert(
        "daemon".into(),
        value_of(&crate::config::DaemonConfig::default()),
    );
    t.insert(
        "vision".into(),
        values::vision(&crate::config::vision::VisionConfig::default()),
    );
    // The empty strings of an absent [frames] source and connection are not defaults.
    for required in [
        "link.connection",
        "link.signing.key_file",
        "frames.source",
        "frames.path",
    ] {
        remove(&mut t, required);
    }
    t
}

/// A document that parses as a configuration: the defaults, the placeholders of the required
/// keys, and the optional sections present with their required keys.
fn complete_document() -> toml::Table {
    let mut doc = defaults();
    for k in KEYS.iter().filter(|k| k.placeholder) {
        if let Ok(v) = parse_value(k.example) {
            set(&mut doc, &path_of(k.path), v);
        }
    }
    for (section, text) in OPTIONAL_SECTIONS {
        if let Ok(t) = toml::from_str::<toml::Table>(text) {
            for (k, v) in t {
                let mut p = path_of(section);
                p.push(k);
                set(&mut doc, &p, v);
            }
        }
    }
    doc
}

/// A TOML value written alone (`1.5`, `"text"`, `[1, 2]`, `{ kind = "utm" }`).
fn parse_value(text: &str) -> Result<toml::Value, toml::de::Error> {
    let t: toml::Table = toml::from_str(&format!("v = {text}"))?;
    Ok(t.get("v").cloned().unwrap_or(toml::Value::Boolean(false)))
}

/// What serde says of the whole document with `value` at `path` (`None`: it parses).
fn serde_error(doc: &toml::Table, path: &str, value: Option<toml::Value>) -> Option<String> {
    let mut doc = doc.clone();
    match value {
        Some(v) => set(&mut doc, &path_of(path), v),
        None => remove(&mut doc, path),
    }
    let text = toml::to_string(&doc).ok()?;
    toml::from_str::<Config>(&text)
        .err()
        .map(|e| e.message().to_string())
}

/// The key's type in words, from serde's refusal of a value of the wrong type.
fn type_words(doc: &toml::Table, path: &str) -> String {
    let probe = toml::Value::String(PROBE.into());
    let Some(message) = serde_error(doc, path, Some(probe)) else {
        return "string".into();
    };
    if let Some(choices) = message.split("unknown variant").nth(1) {
        let names: Vec<String> = choices
            .split_once("expected")
            .map_or("", |(_, e)| e)
            .lines()
            .next()
            .unwrap_or_default()
            .split('`')
            .skip(1)
            .step_by(2)
            .map(|c| format!("\"{c}\""))
            .collect();
        return names.join(" | ");
    }
    let expected = message
        .split_once("expected ")
        .map_or("", |(_, e)| e)
        .lines()
        .next()
        .unwrap_or_default()
        .trim();
    match expected {
        "f64" | "f32" => "number".into(),
        "u8" => "integer 0-255".into(),
        "u16" | "u32" | "u64" | "usize" => "integer >= 0".into(),
        "i32" | "i64" => "integer".into(),
        "a boolean" => "bool".into(),
        "an array of length 3" => "[x, y, z] numbers".into(),
        "a sequence" => {
            let element = serde_error(
                doc,
                path,
                Some(toml::Value::Array(vec![toml::Value::Integer(-1)])),
            );
            match element {
                None => "list".into(),
                Some(m) if m.contains("unknown variant") || m.contains("expected a string") => {
                    "list of strings".into()
                }
                Some(m) if m.contains("path") => "list of paths".into(),
                Some(_) => "list of strings".into(),
            }
        }
        e if e.contains("enum") || e.contains("map") || e.contains("struct") => "table".into(),
        _ => "value".into(),
    }
}

/// The key's unit, from its suffix (the project names keys with their units).
pub fn unit_of(path: &str) -> &'static str {
    const SUFFIXES: [(&str, &str); 25] = [
        ("_deg_h_sqrt_h", "deg/h/sqrt(h)"),
        ("_deg_sqrt_h", "deg/sqrt(h)"),
        ("_m_s_sqrt_h", "m/s/sqrt(h)"),
        ("_ug_sqrt_h", "ug/sqrt(h)"),
        ("_body_frd_m", "m, body FRD"),
        ("_deg_h", "deg/h"),
        ("_deg_s", "deg/s"),
        ("_m_s2", "m/s^2"),
        ("_m_s", "m/s"),
        ("_rtt_ms", "ms"),
        ("_ug", "ug (1e-6 g)"),
        ("_ppm", "ppm"),
        ("_deg", "deg"),
        ("_hz", "Hz"),
        ("_px", "px"),
        ("_mm", "mm"),
        ("_amsl_m", "m AMSL"),
        ("_m", "m"),
        ("_s", "s"),
        ("_range_g", "g"),
        ("_mwork", "million work units"),
        ("_cells", "DEM cells"),
        ("_fraction", "fraction"),
        ("_prob", "probability"),
        ("_ms", "ms"),
    ];
    let key = path.rsplit('.').next().unwrap_or(path);
    SUFFIXES
        .iter()
        .find(|(s, _)| key.ends_with(s))
        .map_or("", |(_, u)| u)
}

/// The accepted range from the validation: the problems it reports for values far outside
/// any range (`[lo, hi]`, `> 0`), `any` when it refuses none, empty when its message has no
/// bounds to read.
fn probed_range(doc: &toml::Table, path: &str, ty: &str) -> String {
    let probes: Vec<toml::Value> = match ty {
        "number" => vec![toml::Value::Float(1e300), toml::Value::Float(-1e300)],
        "integer 0-255" => vec![toml::Value::Integer(0), toml::Value::Integer(255)],
        t if t.starts_with("integer") => vec![
            toml::Value::Integer(0),
            toml::Value::Integer(i64::from(u32::MAX)),
        ],
        _ => return String::new(),
    };
    let mut reasons = Vec::new();
    for v in probes {
        let mut d = doc.clone();
        set(&mut d, &path_of(path), v);
        let Ok(text) = toml::to_string(&d) else {
            continue;
        };
        let Ok(cfg) = toml::from_str::<Config>(&text) else {
            continue;
        };
        let base = Base::config_file(Path::new("probe.toml"));
        reasons.extend(
            cfg.problems(&base, &Overrides::default())
                .into_iter()
                .filter(|p| p.key == path)
                .map(|p| p.reason),
        );
    }
    if reasons.is_empty() {
        return "any".into();
    }
    let words: Vec<String> = reasons.iter().map(|r| range_words(r)).collect();
    words
        .iter()
        .find(|w| w.starts_with(['[', '(', '>']))
        .or(words.first())
        .cloned()
        .unwrap_or_default()
}

/// A validation message about a value far out of range as the range in words: the value it
/// starts with dropped, the bounds of `[lo, hi]` / `lo..=hi` as `lo to hi`.
fn range_words(reason: &str) -> String {
    let r = reason.trim();
    let r = match r.split_once(' ') {
        Some((first, rest)) if first.trim_start_matches('-').parse::<f64>().is_ok() => rest,
        _ => r,
    };
    // An interval as the validation writes it: `[lo, hi]`, `(lo, hi]`, or Rust's `lo..=hi`.
    for (open, close) in [('[', ']'), ('(', ']'), ('(', ')'), ('[', ')')] {
        if let Some(at) = r.find(open)
            && let Some(len) = r[at..].find(close)
            && r[at..at + len].contains(", ")
        {
            return r[at..=at + len].to_string();
        }
    }
    if let Some((lo, hi)) = r
        .split_whitespace()
        .find_map(|w| w.trim_end_matches([',', ';', ')']).split_once("..="))
    {
        let lo = lo
            .rsplit(|c: char| !c.is_ascii_digit() && c != '.')
            .next()
            .unwrap_or(lo);
        return format!("[{lo}, {hi}]");
    }
    if r.contains("greater than 0") || r.contains("> 0") {
        return "> 0".into();
    }
    if r.contains(">= 0") {
        return ">= 0".into();
    }
    r.trim_start_matches("must be ").to_string()
}

/// The reference: one row per key of [`KEYS`], in its order.
pub fn reference() -> Vec<Row> {
    let doc = complete_document();
    let defaults = defaults();
    KEYS.iter()
        .map(|k| {
            let ty = type_words(&doc, k.path);
            let required = serde_error(&doc, k.path, None)
                .is_some_and(|m| m.contains(&format!("missing field `{}`", leaf(k.path))));
            let default = match get(&defaults, k.path) {
                Some(v) => value_text(v),
                None if required => "required".into(),
                None => "none".into(),
            };
            let range = match k.range {
                "" => probed_range(&doc, k.path, &ty),
                r => r.to_string(),
            };
            Row {
                path: k.path.to_string(),
                ty,
                default,
                unit: unit_of(k.path).to_string(),
                range,
                meaning: k.meaning.to_string(),
            }
        })
        .collect()
}

fn leaf(path: &str) -> &str {
    path.rsplit('.').next().unwrap_or(path)
}

/// A value as TOML text on one line: floats as the shortest text that reads back the same
/// (an `f32` setting serialised as `f64` shows as `0.9`, not `0.8999999761581421`).
pub fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::Float(f) => float_text(*f),
        toml::Value::Array(a) => format!(
            "[{}]",
            a.iter().map(value_text).collect::<Vec<_>>().join(", ")
        ),
        toml::Value::Table(t) => format!(
            "{{ {} }}",
            t.iter()
                .map(|(k, v)| format!("{k} = {}", value_text(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        other => other.to_string(),
    }
}

fn float_text(f: f64) -> String {
    let single = f as f32;
    // A float's debug form is its shortest round-trip text with a ".0" when whole: a TOML float.
    if f64::from(single) == f && single.is_finite() {
        format!("{single:?}") // debug form: a TOML float literal
    } else {
        format!("{f:?}") // debug form: a TOML float literal
    }
}

/// The reference as Markdown (docs/config-reference.md is this text).
pub fn reference_markdown() -> String {
    let mut out = String::from(
        "# Configuration key reference\n\n\
         Every key `visnav run` and `visnav check-config` accept, generated from the \
         configuration types by `visnav config reference` (this file is its output; a test \
         fails when they differ). `visnav config default` prints a complete configuration with \
         these defaults. Type, default and range come from the types and their validation: \
         `required` keys have no default, `none` means absent (off, or not used). The units \
         follow the key's suffix. docs/configuration.md explains the file, its paths and its \
         overrides.\n",
    );
    let mut section = String::new();
    for r in reference() {
        let s = r.path.rsplit_once('.').map_or("", |(s, _)| s).to_string();
        if s != section {
            out.push_str(&format!(
                "\n## `[{s}]`\n\n| key | type | default | unit | range | meaning |\n\
                 | --- | --- | --- | --- | --- | --- |\n"
            ));
            section = s;
        }
        let cell = |t: &str| match t {
            "" => String::new(),
            t => format!("`{}`", t.replace('|', "\\|")),
        };
        out.push_str(&format!(
            "| `{}` | {} | {} | {} | {} | {} |\n",
            leaf(&r.path),
            r.ty.replace('|', "\\|"),
            cell(&r.default),
            r.unit,
            r.range,
            r.meaning
        ));
    }
    out
}

/// A complete configuration: every section and key with its default, one comment line per key
/// (its meaning, unit and range); keys without a default commented out with an example, the
/// optional sections (`[frames]`, `[link.signing]`) commented out whole, and the values every
/// installation replaces (connection, camera calibration, map) active and marked as
/// placeholders. From the repository's root, `visnav check-config -` accepts it as it is.
pub fn default_config() -> String {
    let defaults = defaults();
    let optional = |path: &str| {
        OPTIONAL_SECTIONS
            .iter()
            .any(|(s, _)| path.starts_with(&format!("{s}.")))
    };
    let mut out = String::from(
        "# visnav configuration: every key with its default (`visnav config default`; the keys \
         are\n# explained in docs/config-reference.md, the file in docs/configuration.md).\n\
         # Replace the values marked \"placeholder\" (check-config warns about each until the \
         mark is\n# removed); relative paths are relative to this file's folder.\n",
    );
    let rows = reference();
    let mut section = String::new();
    for (k, r) in KEYS.iter().zip(&rows) {
        let s = k.path.rsplit_once('.').map_or("", |(s, _)| s);
        let off = optional(k.path);
        if s != section {
            out.push('\n');
            if off {
                out.push_str(&format!("# [{s}]  (optional section: uncomment to use)\n"));
            } else {
                out.push_str(&format!("[{s}]\n"));
            }
            section = s.to_string();
        }
        let mut about = vec![];
        if !r.unit.is_empty() {
            about.push(r.unit.clone());
        }
        if !r.range.is_empty() && r.range != "any" {
            about.push(r.range.clone());
        }
        if r.default == "required" {
            about.push("required".into());
        }
        let about = match about.is_empty() {
            true => String::new(),
            false => format!(" ({})", about.join("; ")),
        };
        out.push_str(&format!("# {}{about}\n", k.meaning));
        let key = leaf(k.path);
        let line = match (get(&defaults, k.path), k.placeholder) {
            (_, true) => format!("{key} = {}  # {PLACEHOLDER_MARK}\n", k.example),
            (Some(v), false) => format!("{key} = {}\n", value_text(v)),
            (None, false) => format!("# {key} = {}\n", k.example),
        };
        match off && !line.starts_with('#') {
            true => out.push_str(&format!("# {line}")),
            false => out.push_str(&line),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reference lists every key serde accepts, and no other, each once.
    #[test]
    fn the_reference_lists_exactly_the_accepted_keys() {
        let documented: Vec<&str> = KEYS.iter().map(|k| k.path).collect();
        let listed: BTreeSet<String> = documented.iter().map(|k| k.to_string()).collect();
        assert_eq!(listed.len(), documented.len(), "a key is listed twice");
        let accepted = accepted_keys();
        let missing: Vec<&String> = accepted.difference(&listed).collect();
        let unknown: Vec<&String> = listed.difference(&accepted).collect();
        assert!(
            missing.is_empty() && unknown.is_empty(),
            "keys the configuration accepts but config::reference::KEYS lacks: {missing:?}; \
             keys KEYS lists that the configuration refuses: {unknown:?}"
        );
        // Every key of a document with every key is known to unknown_keys too.
        let mut doc = complete_document();
        for k in KEYS.iter().filter(|k| !k.example.is_empty()) {
            set(&mut doc, &path_of(k.path), parse_value(k.example).unwrap());
        }
        let text = toml::to_string(&doc).unwrap();
        assert!(crate::config::unknown_keys::unknown_keys::<Config>(&text).is_empty());
        toml::from_str::<Config>(&text).unwrap();
    }

    /// Each section's serialised defaults read back as its `Default`: the hand-serialised
    /// sections miss no field and spell every enum as serde does.
    #[test]
    fn the_defaults_read_back_as_the_default_impls() {
        let mut doc = complete_document();
        set(
            &mut doc,
            &path_of("link.connection"),
            toml::Value::String("udpout:127.0.0.1:9".into()),
        );
        let cfg: Config = toml::from_str(&toml::to_string(&doc).unwrap()).unwrap();
        let mut link = visnav_link::config::LinkConfig::new("udpout:127.0.0.1:9");
        link.signing = toml::from_str("key_file = \"signing.key\"").ok();
        assert_eq!(format!("{:?}", cfg.link), format!("{link:?}"));
        let output = visnav_link::config::OutputConfig::default();
        assert_eq!(format!("{:?}", cfg.output), format!("{output:?}"));
        let frames = visnav_io::frames::FramesConfig::new(
            visnav_io::frames::SourceKind::Directory,
            "frames",
        );
        assert_eq!(cfg.frames, Some(frames));
        assert_eq!(cfg.vision, crate::config::vision::VisionConfig::default());
        assert_eq!(cfg.daemon, crate::config::DaemonConfig::default());
        assert_eq!(cfg.nav, visnav_core::nav::config::NavConfig::default());
        assert_eq!(cfg.fix, visnav_core::fix::FixParams::default());
        assert_eq!(cfg.vo, visnav_core::vo::VoConfig::default());
        assert_eq!(cfg.dtm_nav, visnav_core::dtm_nav::DtmNavConfig::default());
        assert_eq!(cfg.camera.distortion, Default::default());
        assert_eq!(cfg.camera.mount, Default::default());
    }

    /// Every key has a type, a default or an example, and a range where it is a number.
    #[test]
    fn every_row_is_complete() {
        let rows = reference();
        for (k, r) in KEYS.iter().zip(&rows) {
            assert!(!r.meaning.is_empty(), "{}: no meaning", r.path);
            assert_ne!(r.ty, "value", "{}: type not recognised", r.path);
            if r.default == "none" || r.default == "required" {
                assert!(
                    !k.example.is_empty(),
                    "{}: no default and no example",
                    r.path
                );
                parse_value(k.example).unwrap();
            }
            if r.ty == "number" || r.ty.starts_with("integer") {
                assert!(
                    !r.range.is_empty() && !r.range.starts_with("is "),
                    "{}: the validation's message gives no range ({:?}): write one in KEYS",
                    r.path,
                    r.range
                );
            }
        }
        let r = |p: &str| rows.iter().find(|r| r.path == p).unwrap().clone();
        assert_eq!(r("link.connection").default, "required");
        assert_eq!(
            r("daemon.gps").ty,
            "\"auto\" | \"gps1\" | \"gps2\" | \"none\""
        );
        assert_eq!(r("daemon.gps_sigma_h_m").range, "[0.01, 1000]");
        assert_eq!(r("daemon.gps_sigma_h_m").unit, "m");
        assert_eq!(r("fix.ratio").default, "0.9");
        assert_eq!(r("nav.imu.gyro_bias_deg_h").unit, "deg/h");
    }

    /// The default file parses, names every key, and marks exactly the placeholders.
    #[test]
    fn the_default_file_is_complete_and_marks_its_placeholders() {
        let text = default_config();
        let cfg: Config = toml::from_str(&text).unwrap();
        assert!(cfg.frames.is_none() && cfg.link.signing.is_none());
        for k in KEYS {
            let key = leaf(k.path);
            assert!(
                text.lines()
                    .any(|l| l.trim_start_matches("# ").starts_with(&format!("{key} = "))),
                "{}: not in the default file",
                k.path
            );
        }
        let marked: Vec<String> = crate::config::placeholders(&text)
            .into_iter()
            .map(|p| p.key)
            .collect();
        let want: Vec<&str> = KEYS
            .iter()
            .filter(|k| k.placeholder)
            .map(|k| k.path)
            .collect();
        assert_eq!(marked, want);
    }

    #[test]
    fn floats_print_as_they_were_written() {
        assert_eq!(value_text(&toml::Value::Float(f64::from(0.9f32))), "0.9");
        assert_eq!(value_text(&toml::Value::Float(0.1)), "0.1");
        assert_eq!(value_text(&toml::Value::Float(2.0)), "2.0");
        for v in [0.9f64, 1e10, 1e-7, 0.9999999] {
            let back = parse_value(&value_text(&toml::Value::Float(v))).unwrap();
            assert_eq!(back.as_float(), Some(v));
        }
    }
}
