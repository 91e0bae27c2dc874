//! Reasons counted by class: why fixes, motions or poses were refused, grouped so that two
//! refusals differing only in their numbers count once, yet shown with their numbers.
//!
//! A reason's class ([`reason_class`]) is its wording without its numbers: the grouping key, and
//! the label of a metric (a bounded set: the wordings are the program's). What a user reads is
//! [`ReasonCount`]: the class's most recent reason as it was written ("only 45 matches where
//! chance gives 70 (need 117)"), how many times the class occurred, and the class.

use std::collections::BTreeMap;

use serde::Serialize;

/// Units dropped with the number before them: the class says what was measured, not in what.
const UNITS: &[&str] = &[
    "m", "km", "cm", "mm", "m/s", "m/s²", "s", "ms", "us", "µs", "deg", "°", "rad", "px", "hz",
    "khz", "db", "kb", "mb", "gb", "kib", "mib", "gib", "million",
];

/// The class of `reason`: its words in their order with every number left out (a word whose
/// first digit-or-letter run starts with a digit: `45`, `-12.5`, `3-sigma`, `d^2`), the unit
/// after a number, a parenthesised aside that holds a number (`(need 117)`: the details), and
/// the operators left between numbers (`<`, `=`); spaces collapsed. "only 45 matches where
/// chance gives 70 (need 117)" is "only matches where chance gives"; "altitude 580.1 m AMSL is
/// not above the terrain" is "altitude AMSL is not above the terrain". Words, not placeholders:
/// it reads as text in a metric label, and stays the same however the numbers change.
/// `unknown` when nothing is left.
pub fn reason_class(reason: &str) -> String {
    let mut words: Vec<String> = Vec::new();
    let mut after_number = false;
    for word in without_numbered_asides(reason).split_whitespace() {
        if is_number(word) {
            after_number = true;
            continue;
        }
        let bare = word.trim_end_matches([',', ';', ':', '.']);
        if after_number && UNITS.contains(&bare.to_lowercase().as_str()) {
            after_number = false;
            continue;
        }
        after_number = false;
        if !word.chars().any(char::is_alphanumeric) {
            // Separating punctuation stays with the word before it; operators go with the
            // numbers they compared.
            if word.chars().all(|c| matches!(c, ',' | ';' | ':'))
                && let Some(last) = words.last_mut()
                && !last.ends_with([',', ';', ':'])
            {
                last.push_str(word);
            }
            continue;
        }
        words.push(word.to_string());
    }
    let class = words.join(" ");
    let class = class.trim_matches([',', ';', ':', ' ']);
    if class.is_empty() {
        "unknown".into()
    } else {
        class.to_string()
    }
}

/// Whether `word` is a number (with or without a unit or suffix glued to it): one of its runs of
/// letters and digits starts with a digit. `GPS2_RAW` and `x-ray` are words.
fn is_number(word: &str) -> bool {
    word.split(|c: char| !(c.is_alphanumeric() || c == '_'))
        .any(|run| run.starts_with(|c: char| c.is_ascii_digit()))
}

/// `text` without its parenthesised asides that hold a digit (nested ones included).
fn without_numbered_asides(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    // The open asides: where each starts in `out`.
    let mut open: Vec<usize> = Vec::new();
    for c in text.chars() {
        match c {
            '(' => {
                open.push(out.len());
                out.push(c);
            }
            ')' => {
                out.push(c);
                if let Some(start) = open.pop()
                    && out[start..].chars().any(|c| c.is_ascii_digit())
                {
                    out.truncate(start);
                    // Keep the words on either side apart.
                    out.push(' ');
                }
            }
            _ => out.push(c),
        }
    }
    out
}

/// One class of reasons: the most recent reason with its numbers, how many, and the class.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ReasonCount {
    /// The class's most recent reason, as written.
    pub reason: String,
    /// Reasons of this class counted.
    pub count: u64,
    /// [`reason_class`] (or the counter's own class): the grouping key.
    pub class: String,
}

/// Reasons counted by class, each with its most recent reason: the latest is what the
/// conditions were when counting stopped, and what the log showed last.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReasonTally {
    by_class: BTreeMap<String, (u64, String)>,
}

impl ReasonTally {
    /// Count `reason` under `class`.
    pub fn add(&mut self, class: &str, reason: &str) {
        match self.by_class.get_mut(class) {
            Some((n, latest)) => {
                *n += 1;
                if latest != reason {
                    reason.clone_into(latest);
                }
            }
            None => {
                self.by_class
                    .insert(class.to_string(), (1, reason.to_string()));
            }
        }
    }

    /// Count `reason` under its [`reason_class`].
    pub fn add_reason(&mut self, reason: &str) {
        self.add(&reason_class(reason), reason);
    }

    /// Classes counted.
    pub fn len(&self) -> usize {
        self.by_class.len()
    }

    /// Whether nothing was counted.
    pub fn is_empty(&self) -> bool {
        self.by_class.is_empty()
    }

    /// Whether `class` was counted.
    pub fn contains(&self, class: &str) -> bool {
        self.by_class.contains_key(class)
    }

    /// All reasons counted.
    pub fn total(&self) -> u64 {
        self.by_class.values().map(|(n, _)| n).sum()
    }

    /// The classes, most frequent first (then by class, so the order is the same every run).
    pub fn counts(&self) -> Vec<ReasonCount> {
        let mut v: Vec<ReasonCount> = self
            .by_class
            .iter()
            .map(|(class, (count, reason))| ReasonCount {
                reason: reason.clone(),
                count: *count,
                class: class.clone(),
            })
            .collect();
        v.sort_by(|a, b| b.count.cmp(&a.count).then_with(|| a.class.cmp(&b.class)));
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_class_is_the_wording_without_numbers_units_or_numbered_asides() {
        let c = reason_class;
        for (reason, class) in [
            (
                "only 45 matches where chance gives 70 (need 117)",
                "only matches where chance gives",
            ),
            (
                "prior altitude 580.1 m AMSL is not above the terrain",
                "prior altitude AMSL is not above the terrain",
            ),
            ("offset -12.5 m, x-ray", "offset x-ray"),
            (
                "inconsistent with the navigation: height +3 m and tilt 0.25 deg from the \
                 guess's (squared Mahalanobis distance 12.1 over 9): a wrong minimum",
                "inconsistent with the navigation: height and tilt from the guess's: a wrong \
                 minimum",
            ),
            (
                "peak 0.53 ahead of another place by 0.02 < 0.05",
                "peak ahead of another place by",
            ),
            (
                "2.50 s since the previous frame (at most 2 s)",
                "since the previous frame",
            ),
            (
                "only 3 map features under the footprint (outside the map?)",
                "only map features under the footprint (outside the map?)",
            ),
            ("no GPS2_RAW for 5 s", "no GPS2_RAW for"),
            (
                "horizontal 3-sigma 61 m > chi-square(2) gate",
                "horizontal chi-square gate",
            ),
            ("no map", "no map"),
            ("", "unknown"),
            ("12.5", "unknown"),
        ] {
            assert_eq!(c(reason), class, "{reason}");
        }
        // Two reasons that differ only in their numbers share a class.
        assert_eq!(
            c("only 9 matches where chance gives 5 (need 20)"),
            c("only 31 matches where chance gives 16 (need 36)")
        );
    }

    #[test]
    fn a_tally_keeps_the_latest_reason_of_each_class_most_frequent_first() {
        let mut t = ReasonTally::default();
        t.add_reason("no map");
        for i in 0..3 {
            t.add_reason(&format!("only {i} features in the frame"));
        }
        assert_eq!((t.len(), t.total()), (2, 4));
        assert_eq!(
            t.counts(),
            [
                ReasonCount {
                    reason: "only 2 features in the frame".into(),
                    count: 3,
                    class: "only features in the frame".into(),
                },
                ReasonCount {
                    reason: "no map".into(),
                    count: 1,
                    class: "no map".into(),
                },
            ]
        );
        let json = serde_json::to_string(&t.counts()[0]).unwrap();
        assert_eq!(
            json,
            r#"{"reason":"only 2 features in the frame","count":3,"class":"only features in the frame"}"#
        );
    }
}
