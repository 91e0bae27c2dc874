//! Every unknown key of a configuration file at once. The sections' serde types deny unknown
//! fields, and serde stops at the first: a file with three misspelt keys would need three runs
//! of `check-config` to find them. Here the document is normalised (parsed as plain TOML and
//! written back: one `key = value` per line under `[section]` headers), then parsed as the
//! configuration again and again, each unknown key found removed from the text (a whole table
//! when the unknown key is a table), up to [`MAX_UNKNOWN_KEYS`].

use serde::de::DeserializeOwned;

/// Most unknown keys listed (a file written for another program stops here).
pub const MAX_UNKNOWN_KEYS: usize = 50;

/// The unknown keys of `text` as the configuration type `T` sees them, each as its dotted path
/// and serde's message (`link.conection: unknown field ..., expected one of ...`), sorted by
/// path. Empty when the text is not TOML or has none.
pub fn unknown_keys<T: DeserializeOwned>(text: &str) -> Vec<String> {
    let Ok(table) = toml::from_str::<toml::Table>(text) else {
        return Vec::new();
    };
    let Ok(mut doc) = toml::to_string(&table) else {
        return Vec::new();
    };
    let mut found = Vec::new();
    while found.len() < MAX_UNKNOWN_KEYS {
        let Err(e) = toml::from_str::<T>(&doc) else {
            break;
        };
        if !e.message().starts_with("unknown field") {
            break;
        }
        let field = e
            .message()
            .split('`')
            .nth(1)
            .unwrap_or_default()
            .to_string();
        let Some((path, lines)) = e.span().and_then(|s| locate(&doc, s.start, &field)) else {
            break;
        };
        // Serde's first line (a nested section adds "in `...`", which the path already says).
        let message = e.message().lines().next().unwrap_or_default().trim_end();
        found.push(format!("{path}: {message}"));
        doc = doc
            .split_inclusive('\n')
            .enumerate()
            .filter(|(i, _)| !lines.contains(i))
            .map(|(_, l)| l)
            .collect();
    }
    found.sort();
    found
}

/// The unknown key `field` reported at byte `pos` of a normalised document: its dotted path and
/// the lines that hold it (its own line, or a table's header, its keys and its sub-tables). A
/// nested section's error may point at its table's header instead of the key: the key is then
/// looked up among the table's lines.
fn locate(doc: &str, pos: usize, field: &str) -> Option<(String, std::ops::Range<usize>)> {
    let lines: Vec<&str> = doc.split_inclusive('\n').collect();
    let mut start = 0;
    let at = lines.iter().position(|l| {
        start += l.len();
        pos < start
    })?;
    let line = lines[at].trim();
    if let Some(table) = header(line) {
        let inside = |l: &str| {
            header(l.trim()).is_none_or(|h| h == table || h.starts_with(&format!("{table}.")))
        };
        let end = (at + 1..lines.len())
            .find(|&i| !inside(lines[i]))
            .unwrap_or(lines.len());
        let own_key = (at + 1..end)
            .find(|&i| header(lines[i].trim()).is_none() && key_of(lines[i]) == Some(field));
        return Some(match own_key {
            Some(i) if table.rsplit('.').next() != Some(field) => {
                (format!("{table}.{field}"), i..i + 1)
            }
            _ => (table.to_string(), at..end),
        });
    }
    let key = key_of(line)?;
    let table = lines[..at].iter().rev().find_map(|l| header(l.trim()));
    let path = match table {
        Some(t) => format!("{t}.{key}"),
        None => key.to_string(),
    };
    Some((path, at..at + 1))
}

/// The key of a `key = value` line.
fn key_of(line: &str) -> Option<&str> {
    Some(line.split_once('=')?.0.trim().trim_matches('"'))
}

/// The table path of a `[table]` or `[[array]]` header line.
fn header(line: &str) -> Option<&str> {
    let inner = line.strip_prefix('[')?.strip_suffix(']')?;
    let inner = inner
        .strip_prefix('[')
        .and_then(|i| i.strip_suffix(']'))
        .unwrap_or(inner);
    Some(inner.trim())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)] // parsed, never read
    struct Cfg {
        #[serde(default)]
        a: Option<Section>,
        #[serde(default)]
        b: Option<Section>,
        #[serde(default)]
        top: Option<f64>,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Section {
        #[serde(default)]
        x: Option<f64>,
        #[serde(default)]
        y: Option<Vec<f64>>,
    }

    #[test]
    fn every_unknown_key_is_named_with_its_section() {
        let text = "top = 1\ntpo = 2\n[a]\nx = 1\nz = [1, 2]\n[b]\nw = 3\ny = [1.0]\n\
                    [extra]\nq = 1\n[extra.deeper]\nr = 2\n";
        let keys = unknown_keys::<Cfg>(text);
        let paths: Vec<&str> = keys.iter().filter_map(|k| k.split(':').next()).collect();
        assert_eq!(paths, ["a.z", "b.w", "extra", "tpo"], "{keys:?}");
        assert!(keys.iter().all(|k| !k.contains('\n')), "{keys:?}");
        assert!(keys[0].contains("unknown field `z`"), "{keys:?}");
    }

    #[test]
    fn a_good_file_or_no_toml_gives_none() {
        assert!(unknown_keys::<Cfg>("top = 1\n[a]\nx = 2\n").is_empty());
        assert!(unknown_keys::<Cfg>("this is [ not toml").is_empty());
        // A wrong type is not an unknown key: not listed.
        assert!(unknown_keys::<Cfg>("top = \"high\"\n").is_empty());
    }

    #[test]
    fn many_unknown_keys_stop_at_the_cap() {
        let text: String = (0..MAX_UNKNOWN_KEYS + 10)
            .map(|i| format!("k{i} = {i}\n"))
            .collect();
        assert_eq!(unknown_keys::<Cfg>(&text).len(), MAX_UNKNOWN_KEYS);
    }
}
