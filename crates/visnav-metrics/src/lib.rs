//! visnav's metrics framework: the building blocks of its one registry (`prometheus-client`'s
//! [`Registry`], rendered in the Prometheus text format 0.0.4 by [`render`]), shared by the
//! link's metrics and the daemon's.
//!
//! A set of metrics is declared once with [`metric_set!`]: per metric its field, kind,
//! Prometheus name, help and (for a member of a labelled counter family) its label. The macro
//! makes the live structure (the handles: atomics, updated from any task or thread without a
//! lock), its registration into a [`Registry`] and a typed copy of the values (the snapshot,
//! serialisable). Adding a metric is one line there and its use sites.
//!
//! Kinds ([`Declare`]): [`Counter`] (names without `_total`: the encoder appends it),
//! [`Gauge`] (an integer in the program's unit, exposed divided by a divisor: µs / 1e6 as
//! seconds), [`Histogram`] (durations in the program's unit, Prometheus' default buckets in
//! seconds), [`Reasons`] (a counter family by `reason`: the class its caller gives, at most
//! [`MAX_REASONS`]; the snapshot shows each class's latest reason with its numbers). Counters of
//! one name with different labels form one family.

#![warn(missing_docs)]

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use prometheus_client::encoding::{EncodeMetric, MetricEncoder, NoLabelSet};
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Metric;
use serde::Serialize;
use visnav_core::reasons::ReasonCount;
use visnav_core::reasons::ReasonTally;

pub use prometheus_client::collector::Collector;
pub use prometheus_client::metrics::counter::Counter;
pub use prometheus_client::registry::Registry;

/// The `Content-Type` of [`render`]'s text.
pub const CONTENT_TYPE: &str = prometheus_client::encoding::prometheus_text::CONTENT_TYPE;

/// Distinct classes a [`Reasons`] family keeps; later ones count as `other`.
pub const MAX_REASONS: usize = 64;

/// Histogram bucket bounds, seconds (Prometheus' default buckets).
pub const BUCKETS_S: [f64; 11] = [
    0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

/// The registry as Prometheus text (format 0.0.4).
pub fn render(registry: &Registry) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail; a metric's own encode error leaves what was written.
    let _ = prometheus_client::encoding::prometheus_text::encode(&mut out, registry);
    out
}

/// One kind of metric: created with its unit divisor, registered under a name, read as a value.
pub trait Declare {
    /// The value in a snapshot.
    type Value;
    /// A new metric; the program's unit divided by `divisor` is the exposed one (1 for counts).
    fn new(divisor: f64) -> Self;
    /// Register in `r` as `name` (`label`: a counter family's `(label, value)`).
    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, label: Label);
    /// The current value.
    fn value(&self) -> Self::Value;
}

/// A family member's label and value.
pub type Label = Option<(&'static str, &'static str)>;

/// The members (label value, counter) of one labelled counter family, shared with its collector.
type FamilyMembers = Arc<Mutex<Vec<(&'static str, Counter)>>>;

/// Registers metrics in a [`Registry`]; counters of one name with labels form one family.
pub struct Registrar<'a> {
    reg: &'a mut Registry,
    families: Vec<(String, FamilyMembers)>,
}

impl<'a> Registrar<'a> {
    /// Register into `reg`.
    pub fn new(reg: &'a mut Registry) -> Self {
        Self {
            reg,
            families: Vec::new(),
        }
    }

    /// Register one metric.
    pub fn metric(&mut self, name: impl Into<String>, help: impl Into<String>, m: impl Metric) {
        self.reg.register(name, help, m);
    }

    /// Register a collector (metrics found at each scrape).
    pub fn collector(&mut self, c: impl Collector) {
        self.reg.register_collector(Box::new(c));
    }

    /// Add `counter` to the family `name` with `label = value` (the family is registered with its
    /// first member).
    pub fn member(
        &mut self,
        name: &str,
        help: &str,
        (label, value): (&'static str, &'static str),
        counter: &Counter,
    ) {
        let members = match self.families.iter().find(|(n, _)| *n == name) {
            Some((_, m)) => m.clone(),
            None => {
                let m = Arc::new(Mutex::new(Vec::new()));
                self.families.push((name.to_string(), m.clone()));
                self.reg.register(
                    name,
                    help,
                    CounterFamily {
                        label,
                        members: m.clone(),
                    },
                );
                m
            }
        };
        lock(&members).push((value, counter.clone()));
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Counters with fixed label values under one name (filled at registration; read at a scrape).
#[derive(Debug)]
struct CounterFamily {
    label: &'static str,
    members: FamilyMembers,
}

impl EncodeMetric for CounterFamily {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        let members: Vec<(&str, u64)> = lock(&self.members)
            .iter()
            .map(|(v, c)| (*v, c.get()))
            .collect();
        for (value, n) in members {
            encode_count(&mut encoder, [(self.label, value)], n)?;
        }
        Ok(())
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Counter
    }
}

/// One sample of a counter family.
pub fn encode_count(
    encoder: &mut MetricEncoder,
    labels: [(&str, &str); 1],
    n: u64,
) -> Result<(), std::fmt::Error> {
    encoder
        .encode_family(&labels)?
        .encode_counter::<NoLabelSet, u64, u64>(&n, None)
}

impl Declare for Counter {
    type Value = u64;

    fn new(_divisor: f64) -> Self {
        Counter::default()
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, label: Label) {
        match label {
            Some(l) => r.member(name, help, l, self),
            None => r.metric(name, help, self.clone()),
        }
    }

    fn value(&self) -> u64 {
        self.get()
    }
}

/// A gauge: an integer in the program's unit, exposed divided by its divisor (µs -> seconds:
/// 1e6).
#[derive(Debug, Clone)]
pub struct Gauge {
    value: Arc<AtomicU64>,
    divisor: f64,
}

impl Gauge {
    /// Set the value.
    pub fn set(&self, v: u64) {
        self.value.store(v, Ordering::Relaxed);
    }

    /// Raise the value to `v` if it is lower.
    pub fn max(&self, v: u64) {
        self.value.fetch_max(v, Ordering::Relaxed);
    }

    /// The value (program's unit).
    pub fn get(&self) -> u64 {
        self.value.load(Ordering::Relaxed)
    }
}

impl EncodeMetric for Gauge {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        if self.divisor == 1.0 {
            encoder.encode_gauge(&self.get())
        } else {
            encoder.encode_gauge(&(self.get() as f64 / self.divisor))
        }
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Gauge
    }
}

impl Declare for Gauge {
    type Value = u64;

    fn new(divisor: f64) -> Self {
        Self {
            value: Arc::default(),
            divisor,
        }
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, _: Label) {
        r.metric(name, help, self.clone());
    }

    fn value(&self) -> u64 {
        self.get()
    }
}

/// A histogram of durations in the program's unit (ms, µs), bucketed in seconds ([`BUCKETS_S`]).
#[derive(Debug, Clone)]
pub struct Histogram {
    inner: Arc<HistogramCells>,
    divisor: f64,
}

#[derive(Debug, Default)]
struct HistogramCells {
    /// Per bucket (not cumulative); the last is above the largest bound.
    buckets: [AtomicU64; BUCKETS_S.len() + 1],
    /// Sum of the observations, program's unit.
    sum: AtomicU64,
}

/// A histogram in a snapshot (program's unit).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct HistogramValues {
    /// Observations.
    pub count: u64,
    /// Their sum.
    pub sum: u64,
    /// Their mean (0 without any).
    pub mean: f64,
}

impl Histogram {
    /// Record one observation.
    pub fn observe(&self, v: u64) {
        let s = v as f64 / self.divisor;
        let i = BUCKETS_S
            .iter()
            .position(|b| s <= *b)
            .unwrap_or(BUCKETS_S.len());
        self.inner.buckets[i].fetch_add(1, Ordering::Relaxed);
        self.inner.sum.fetch_add(v, Ordering::Relaxed);
    }

    fn counts(&self) -> [u64; BUCKETS_S.len() + 1] {
        std::array::from_fn(|i| self.inner.buckets[i].load(Ordering::Relaxed))
    }
}

impl EncodeMetric for Histogram {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        let counts = self.counts();
        let buckets: Vec<(f64, u64)> = BUCKETS_S
            .iter()
            .chain([f64::INFINITY].iter())
            .copied()
            .zip(counts)
            .collect();
        let sum = self.inner.sum.load(Ordering::Relaxed) as f64 / self.divisor;
        encoder.encode_histogram::<NoLabelSet>(sum, counts.iter().sum(), &buckets, None)
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Histogram
    }
}

impl Declare for Histogram {
    type Value = HistogramValues;

    fn new(divisor: f64) -> Self {
        Self {
            inner: Arc::default(),
            divisor,
        }
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, _: Label) {
        r.metric(name, help, self.clone());
    }

    fn value(&self) -> HistogramValues {
        let count: u64 = self.counts().iter().sum();
        let sum = self.inner.sum.load(Ordering::Relaxed);
        HistogramValues {
            count,
            sum,
            mean: if count > 0 {
                sum as f64 / count as f64
            } else {
                0.0
            },
        }
    }
}

/// A counter family by `reason`: each reason counted by the class its caller gives (a typed
/// refusal's `class()`: a name from a closed set, without numbers), at most [`MAX_REASONS`]
/// classes (then `other`), so the label's values stay few. The snapshot keeps
/// each class's most recent reason with its numbers: what a user reads.
#[derive(Debug, Clone, Default)]
pub struct Reasons {
    counts: Arc<Mutex<ReasonTally>>,
}

impl Reasons {
    /// Count one `reason` under `class`.
    pub fn count(&self, class: &str, reason: &str) {
        let mut m = lock(&self.counts);
        let class = if m.len() < MAX_REASONS || m.contains(class) {
            class
        } else {
            "other"
        };
        m.add(class, reason);
    }

    /// All reasons counted.
    pub fn total(&self) -> u64 {
        lock(&self.counts).total()
    }
}

impl EncodeMetric for Reasons {
    fn encode(&self, mut encoder: MetricEncoder) -> Result<(), std::fmt::Error> {
        // By class, in a fixed order: the label is the class, never the reason with its numbers.
        let mut counts = self.value();
        counts.sort_by(|a, b| a.class.cmp(&b.class));
        for r in counts {
            encode_count(&mut encoder, [("reason", r.class.as_str())], r.count)?;
        }
        Ok(())
    }

    fn metric_type(&self) -> MetricType {
        MetricType::Counter
    }
}

impl Declare for Reasons {
    type Value = Vec<ReasonCount>;

    fn new(_divisor: f64) -> Self {
        Self::default()
    }

    fn declare(&self, r: &mut Registrar, name: &'static str, help: &'static str, _: Label) {
        r.metric(name, help, self.clone());
    }

    /// Most frequent first, each class with its most recent reason.
    fn value(&self) -> Vec<ReasonCount> {
        lock(&self.counts).counts()
    }
}

/// Declare a set of metrics once: the live structure (`pub struct Live => Snapshot`), its
/// `register(&self, &mut Registry)`, `snapshot(&self) -> Snapshot` and `Default`.
///
/// Each entry: `field: Kind "name" "help"`, then optionally `["label" = "value"]` (a member of
/// the counter family `name`) and `/ divisor` (the program's unit divided by it is the exposed
/// one: `/ 1e3` for ms as seconds). `Kind` implements [`Declare`].
#[macro_export]
macro_rules! metric_set {
    (
        $(#[$meta:meta])*
        pub struct $live:ident => $snap:ident {
            $(
                $(#[$fmeta:meta])*
                $field:ident: $kind:ident $name:literal $help:literal
                    $([$label:literal = $value:literal])? $(/ $divisor:literal)?
            ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone)]
        pub struct $live {
            $( $(#[$fmeta])* pub $field: $kind, )*
        }

        /// A copy of the values (`snapshot()`), in the program's units.
        #[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
        pub struct $snap {
            $(
                $(#[$fmeta])*
                pub $field: <$kind as $crate::Declare>::Value,
            )*
        }

        impl Default for $live {
            fn default() -> Self {
                Self {
                    $(
                        $field: <$kind as $crate::Declare>::new(
                            $crate::metric_set!(@divisor $($divisor)?),
                        ),
                    )*
                }
            }
        }

        impl $live {
            /// The declared names (a family's once per member).
            pub const NAMES: &[&str] = &[$($name),*];

            /// Register every metric in `reg` (the handles are shared: updates show there).
            pub fn register(&self, reg: &mut $crate::Registry) {
                let mut r = $crate::Registrar::new(reg);
                $(
                    $crate::Declare::declare(
                        &self.$field,
                        &mut r,
                        $name,
                        $help,
                        $crate::metric_set!(@label $([$label = $value])?),
                    );
                )*
            }

            /// Copy the values.
            pub fn snapshot(&self) -> $snap {
                $snap {
                    $( $field: $crate::Declare::value(&self.$field), )*
                }
            }
        }
    };
    (@divisor) => { 1.0 };
    (@divisor $d:literal) => { $d };
    (@label) => { None };
    (@label [$l:literal = $v:literal]) => { Some(($l, $v)) };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn families_histograms_and_reasons() {
        crate::metric_set! {
            /// Test set.
            pub struct T => TSnap {
                /// a
                a: Counter "x_events" "events by kind" ["kind" = "a"],
                /// b
                b: Counter "x_events" "events by kind" ["kind" = "b"],
                /// t, ms
                t: Histogram "x_seconds" "time" / 1e3,
                /// r
                r: Reasons "x_refusals" "refusals by reason",
            }
        }
        let m = T::default();
        m.a.inc();
        m.b.inc_by(2);
        m.t.observe(20);
        m.t.observe(3000);
        for i in 0..100 {
            m.r.count("few_left", &format!("only {i} left"));
        }
        let mut reg = Registry::default();
        m.register(&mut reg);
        let text = render(&reg);
        for want in [
            "# TYPE x_events_total counter",
            "x_events_total{kind=\"a\"} 1",
            "x_events_total{kind=\"b\"} 2",
            "# TYPE x_seconds histogram",
            "x_seconds_bucket{le=\"0.025\"} 1",
            "x_seconds_bucket{le=\"2.5\"} 1",
            "x_seconds_bucket{le=\"5\"} 2",
            "x_seconds_bucket{le=\"+Inf\"} 2",
            "x_seconds_sum 3.02",
            "x_seconds_count 2",
            // The class is the label: bounded, without the reasons' numbers.
            "x_refusals_total{reason=\"few_left\"} 100",
        ] {
            assert!(
                text.lines().any(|l| l == want),
                "{want:?} missing in\n{text}"
            );
        }
        assert_eq!(text.matches("# TYPE x_events_total").count(), 1, "{text}");
        assert_eq!(
            T::NAMES,
            ["x_events", "x_events", "x_seconds", "x_refusals"]
        );
        let s = m.snapshot();
        assert_eq!((s.a, s.b), (1, 2));
        assert_eq!((s.t.count, s.t.sum, s.t.mean), (2, 3020, 1510.0));
        assert_eq!(s.r.len(), 1);
        // The snapshot shows the latest reason with its number.
        assert_eq!(
            (s.r[0].reason.as_str(), s.r[0].count, s.r[0].class.as_str()),
            ("only 99 left", 100, "few_left")
        );
        let many = Reasons::default();
        for i in 0..MAX_REASONS + 5 {
            many.count(&"x".repeat(i + 1), &"x".repeat(i + 1));
        }
        assert_eq!(many.value().len(), MAX_REASONS + 1);
        let other = many.value().into_iter().find(|r| r.class == "other");
        assert_eq!(
            other.map(|r| (r.count, r.reason)),
            Some((5, "x".repeat(MAX_REASONS + 5)))
        );
    }
}
