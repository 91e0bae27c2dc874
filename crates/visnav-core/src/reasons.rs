//! Reasons counted by class: why fixes, motions or poses were refused, grouped so that two
//! refusals differing only in their numbers count once, yet shown with their numbers.
//!
//! A reason's class is given by its typed refusal (`fix::Rejection::class`,
//! `vo::VoRefusal::class`, `dtm_nav::DtmRefusal::class`: names from closed sets, never read
//! back from the words): the grouping key, and the label of a metric. What a user reads is
//! [`ReasonCount`]: the class's most recent reason as it was written ("only 45 matches where
//! chance gives 70 (need 117)"), how many times the class occurred, and the class.

use std::collections::BTreeMap;

use serde::Serialize;

/// One class of reasons: the most recent reason with its numbers, how many, and the class.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ReasonCount {
    /// The class's most recent reason, as written.
    pub reason: String,
    /// Reasons of this class counted.
    pub count: u64,
    /// The refusal's class: the grouping key.
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
    fn a_tally_keeps_the_latest_reason_of_each_class_most_frequent_first() {
        let mut t = ReasonTally::default();
        t.add("old_map", "no map");
        for i in 0..3 {
            t.add("few_features", &format!("only {i} features in the frame"));
        }
        assert_eq!((t.len(), t.total()), (2, 4));
        assert_eq!(
            t.counts(),
            [
                ReasonCount {
                    reason: "only 2 features in the frame".into(),
                    count: 3,
                    class: "few_features".into(),
                },
                ReasonCount {
                    reason: "no map".into(),
                    count: 1,
                    class: "old_map".into(),
                },
            ]
        );
        let json = serde_json::to_string(&t.counts()[0]).unwrap();
        assert_eq!(
            json,
            r#"{"reason":"only 2 features in the frame","count":3,"class":"few_features"}"#
        );
    }
}
