//! Time: mapping the companion's monotonic clock to the autopilot's boot time (TIMESYNC), UTC of
//! the autopilot (SYSTEM_TIME), and GPS week / time of week.
//!
//! # Clock mapping
//! The MAVLink TIMESYNC protocol (<https://mavlink.io/en/services/timesync.html>): we send
//! `TIMESYNC{tc1 = 0, ts1 = t_c}` with `t_c` our monotonic time in ns; the autopilot answers
//! `TIMESYNC{tc1 = t_a, ts1 = t_c}` with `t_a` its boot time in ns. Received at our time `t_r`,
//! the round trip is `rtt = t_r - t_c` and, assuming a symmetric path, the offset sample is
//! `o = t_a - (t_c + t_r) / 2`, so that `t_autopilot = t_companion + o`.
//!
//! The samples go through an alpha-beta filter on (offset, drift): prediction
//! `o_pred = o + d (t - t_last)`, residual `r = o_meas - o_pred`, `o <- o_pred + alpha r`,
//! `d <- d + beta r / dt`, with `alpha = max(1 / n, 0.05)` and `beta = alpha^2 / (2 - alpha)`
//! (the critically damped alpha-beta pair). Samples whose round trip exceeds the configured
//! limit are dropped; once converged, a residual above [`OUTLIER_NS`] is dropped unless three in
//! a row agree (then the filter restarts: a step of the autopilot clock).
//!
//! # Reboot
//! An autopilot reboot shows as its time going backwards: a TIMESYNC `tc1`, a `time_boot_ms`
//! (SYSTEM_TIME, ATTITUDE, IMU, ...) more than [`REBOOT_BACKSTEP_US`] below the last one. One such
//! message is not enough: a stale packet (a replay, a router's buffer, a spoofer) looks the same.
//! [`BootClock`] declares a reboot only when the evidence agrees: at least
//! [`REBOOT_MIN_MESSAGES`] messages of at least [`REBOOT_MIN_STREAMS`] different kinds report one
//! new clock (consistent with each other within [`REBOOT_CLOCK_TOLERANCE_US`]), and the old clock
//! has been silent for [`REBOOT_OLD_CLOCK_SILENT_NS`] (an autopilot says nothing while it boots;
//! a stale burst arrives among live messages, and any live one drops the candidate). Until then
//! the backwards messages are stale and not used. A message stamped more than
//! [`REBOOT_BACKSTEP_US`] ahead of the clock (its last time plus the companion time elapsed since)
//! is stale too: a forged or corrupt stamp must not become the clock.
//!
//! # Output times
//! What we send must never go back in time: [`Monotonic`] stamps each output at least 1 µs after
//! the previous one (the clock mapping's small corrections otherwise step back a few µs). The
//! autopilot's UTC (SYSTEM_TIME) is latched ([`UtcMap`]): small differences are slewed in, a step
//! beyond [`UTC_STEP_US`] (a clock set by hand, a jump of an hour, a year back, jitter of a
//! second) is counted and reported but not followed.
//!
//! # GPS time
//! GPS time = UTC + leap seconds (18 s since 2017-01-01, [`GPS_LEAP_S`]), counted from the GPS
//! epoch 1980-01-06 00:00:00 UTC (Unix 315 964 800 s); week = floor(t / 604 800 s),
//! time of week = t mod 604 800 s.

/// Unix time of the GPS epoch (1980-01-06T00:00:00Z), seconds.
pub const GPS_EPOCH_UNIX_S: u64 = 315_964_800;
/// GPS - UTC in seconds (valid since 2017-01-01; no leap second announced since).
pub const GPS_LEAP_S: u64 = 18;
/// Seconds in a GPS week.
pub const WEEK_S: u64 = 604_800;
/// After convergence, TIMESYNC residuals larger than this are outliers (ns).
pub const OUTLIER_NS: f64 = 10e6;
/// The autopilot's time going back by more than this means it rebooted (µs).
pub const REBOOT_BACKSTEP_US: u64 = 1_000_000;
/// Accepted samples before the mapping is considered usable.
pub const CONVERGED_AFTER: u32 = 4;
/// Messages reporting the new clock before a reboot is declared.
pub const REBOOT_MIN_MESSAGES: usize = 3;
/// Different message kinds among them (several streams going back together).
pub const REBOOT_MIN_STREAMS: usize = 2;
/// The new clock's messages agree on `boot time - arrival time` within this (µs): link jitter
/// plus the autopilot's scheduling, far below the seconds a reboot steps back.
pub const REBOOT_CLOCK_TOLERANCE_US: i64 = 500_000;
/// The old clock must have been silent this long (ns) before a reboot is declared: an autopilot
/// says nothing for seconds while it boots, while stale packets arrive among live ones.
pub const REBOOT_OLD_CLOCK_SILENT_NS: i64 = 500_000_000;
/// The autopilot's UTC minus boot time may move by this much (µs) between SYSTEM_TIME messages
/// and still be followed (slewed): `time_boot_ms` has 1 ms resolution and the two fields are
/// sampled a little apart. A larger difference is a step of the clock.
pub const UTC_STEP_US: i128 = 20_000;
/// Fraction of a small UTC difference applied per SYSTEM_TIME (slew, so output time stays smooth).
pub const UTC_SLEW_GAIN: f64 = 0.1;

/// GPS week number and time of week in milliseconds for a Unix time in microseconds.
/// `None` before the GPS epoch.
pub fn gps_week_ms(unix_us: u64) -> Option<(u16, u32)> {
    let gps_us = unix_us.checked_sub(GPS_EPOCH_UNIX_S * 1_000_000)? + GPS_LEAP_S * 1_000_000;
    let week = gps_us / (WEEK_S * 1_000_000);
    let tow_ms = (gps_us % (WEEK_S * 1_000_000)) / 1000;
    Some((u16::try_from(week).ok()?, tow_ms as u32)) // ok: tow_ms < 604_800_000 < u32::MAX
}

/// Earliest plausible Unix time of a real clock (2020-01-01); earlier means "clock not set".
pub const PLAUSIBLE_UNIX_US: u64 = 1_577_836_800_000_000;

/// One TIMESYNC round trip, all in nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimesyncSample {
    /// Our monotonic time when the request left (echoed back as `ts1`).
    pub sent_companion_ns: i64,
    /// The autopilot's boot time in the reply (`tc1`).
    pub autopilot_ns: i64,
    /// Our monotonic time when the reply arrived.
    pub received_companion_ns: i64,
}

/// What one sample did to the filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SyncUpdate {
    /// Used.
    Accepted,
    /// Round trip too long, negative, or an outlier.
    Rejected,
}

/// Filtered companion-monotonic -> autopilot-boot clock mapping (see module docs).
#[derive(Debug, Clone)]
pub struct TimeSync {
    max_rtt_ns: f64,
    offset_ns: f64,
    drift: f64,
    t_last_ns: i64,
    n: u32,
    outliers_in_row: u32,
    /// Last accepted round-trip time, ns.
    pub last_rtt_ns: f64,
}

impl TimeSync {
    /// A filter that drops round trips longer than `max_rtt_ms`.
    pub fn new(max_rtt_ms: f64) -> Self {
        Self {
            max_rtt_ns: max_rtt_ms * 1e6,
            offset_ns: 0.0,
            drift: 0.0,
            t_last_ns: 0,
            n: 0,
            outliers_in_row: 0,
            last_rtt_ns: f64::NAN,
        }
    }

    /// Forget the mapping (after a reboot or a reconnect).
    pub fn reset(&mut self) {
        *self = Self::new(self.max_rtt_ns / 1e6);
    }

    /// True once enough samples agree.
    pub fn converged(&self) -> bool {
        self.n >= CONVERGED_AFTER
    }

    /// Number of accepted samples since the last reset.
    pub fn samples(&self) -> u32 {
        self.n
    }

    /// Estimated offset (autopilot - companion) at companion time `t_ns`, in ns.
    pub fn offset_ns_at(&self, t_ns: i64) -> Option<f64> {
        self.converged()
            .then(|| self.offset_ns + self.drift * (t_ns - self.t_last_ns) as f64)
    }

    /// Estimated drift of the autopilot's clock relative to ours (dimensionless, 1e-6 = 1 ppm).
    pub fn drift(&self) -> f64 {
        self.drift
    }

    /// Autopilot boot time in µs at companion monotonic time `t_ns`; `None` until converged or if
    /// the result would be before the autopilot's boot.
    pub fn to_autopilot_us(&self, t_ns: i64) -> Option<u64> {
        let a_ns = t_ns as f64 + self.offset_ns_at(t_ns)?;
        (a_ns.is_finite() && a_ns >= 0.0).then(|| (a_ns / 1000.0).round() as u64)
    }

    /// Companion monotonic time in ns of autopilot boot time `t_boot_us` (inverse mapping).
    pub fn to_companion_ns(&self, t_boot_us: u64) -> Option<i64> {
        if !self.converged() {
            return None;
        }
        // t_a = t_c + o + d (t_c - t_last)  =>  t_c = (t_a - o + d t_last) / (1 + d)
        let a = t_boot_us as f64 * 1000.0;
        let c = (a - self.offset_ns + self.drift * self.t_last_ns as f64) / (1.0 + self.drift);
        c.is_finite().then(|| c.round() as i64)
    }

    /// Feed one TIMESYNC round trip.
    pub fn update(&mut self, s: TimesyncSample) -> SyncUpdate {
        let rtt = (s.received_companion_ns - s.sent_companion_ns) as f64;
        if !(0.0..=self.max_rtt_ns).contains(&rtt) || s.autopilot_ns <= 0 {
            return SyncUpdate::Rejected;
        }
        let t = s.sent_companion_ns / 2 + s.received_companion_ns / 2;
        let measured = s.autopilot_ns as f64 - t as f64;
        if self.n == 0 {
            self.offset_ns = measured;
            self.drift = 0.0;
            self.t_last_ns = t;
            self.n = 1;
            self.last_rtt_ns = rtt;
            return SyncUpdate::Accepted;
        }
        let dt = (t - self.t_last_ns) as f64;
        if dt <= 0.0 {
            return SyncUpdate::Rejected;
        }
        let predicted = self.offset_ns + self.drift * dt;
        let r = measured - predicted;
        if self.converged() && r.abs() > OUTLIER_NS.max(rtt) {
            self.outliers_in_row += 1;
            if self.outliers_in_row >= 3 {
                // The autopilot's clock stepped: start over from this sample.
                self.reset();
                return self.update(s);
            }
            return SyncUpdate::Rejected;
        }
        self.outliers_in_row = 0;
        let alpha = (1.0 / (self.n as f64 + 1.0)).max(0.05);
        let beta = alpha * alpha / (2.0 - alpha);
        self.offset_ns = predicted + alpha * r;
        // Drift is only meaningful over a useful baseline; clamp to +-500 ppm (crystal clocks).
        self.drift = (self.drift + beta * r / dt).clamp(-5e-4, 5e-4);
        self.t_last_ns = t;
        self.n += 1;
        self.last_rtt_ns = rtt;
        SyncUpdate::Accepted
    }
}

/// What one message's boot time says (see the module doc, "Reboot").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BootVerdict {
    /// On the current clock: use the message.
    Current,
    /// Behind the current clock and not (yet) a confirmed reboot: drop it.
    Stale,
    /// The evidence for a reboot is complete: restart everything on the new clock (the message
    /// is on it).
    Reboot,
}

#[derive(Debug, Clone)]
struct RebootCandidate {
    /// `boot time - arrival time` of the new clock, µs.
    clock_us: i64,
    /// Message kinds and count seen on the new clock.
    kinds: Vec<u32>,
    messages: usize,
}

/// The autopilot's boot clock as seen in its messages; tells stale messages from a reboot.
#[derive(Debug, Clone, Default)]
pub struct BootClock {
    last_us: Option<u64>,
    /// Arrival of the latest message on the current clock, ns.
    last_current_ns: Option<i64>,
    candidate: Option<RebootCandidate>,
    /// Messages dropped as stale.
    pub stale: u64,
}

impl BootClock {
    /// Judge one message of kind `msg_id` stamped `boot_us` arriving at companion time `t_ns`.
    pub fn observe(&mut self, msg_id: u32, boot_us: u64, t_ns: i64) -> BootVerdict {
        let Some(last) = self.last_us else {
            self.last_us = Some(boot_us);
            self.last_current_ns = Some(t_ns);
            return BootVerdict::Current;
        };
        // Ahead of the clock by more than the companion time since its last message: a
        // forged or corrupt stamp (one far-future IMU time would otherwise become the clock,
        // and every real message after it would look stale).
        if let Some(lc) = self.last_current_ns {
            let elapsed_us = u64::try_from((t_ns - lc).max(0) / 1000).unwrap_or(0);
            if boot_us
                > last
                    .saturating_add(elapsed_us)
                    .saturating_add(REBOOT_BACKSTEP_US)
            {
                self.stale += 1;
                return BootVerdict::Stale;
            }
        }
        if boot_us.saturating_add(REBOOT_BACKSTEP_US) >= last {
            self.candidate = None; // the old clock goes on: no reboot
            self.last_us = Some(last.max(boot_us));
            self.last_current_ns = Some(t_ns);
            return BootVerdict::Current;
        }
        let clock_us = boot_us as i64 - t_ns / 1000;
        let c = match &mut self.candidate {
            Some(c) if (c.clock_us - clock_us).abs() <= REBOOT_CLOCK_TOLERANCE_US => c,
            _ => self.candidate.insert(RebootCandidate {
                clock_us,
                kinds: Vec::new(),
                messages: 0,
            }),
        };
        c.messages += 1;
        if !c.kinds.contains(&msg_id) {
            c.kinds.push(msg_id);
        }
        let old_silent = self
            .last_current_ns
            .is_none_or(|l| t_ns - l >= REBOOT_OLD_CLOCK_SILENT_NS);
        if old_silent && c.messages >= REBOOT_MIN_MESSAGES && c.kinds.len() >= REBOOT_MIN_STREAMS {
            self.candidate = None;
            self.last_us = Some(boot_us);
            return BootVerdict::Reboot;
        }
        self.stale += 1;
        BootVerdict::Stale
    }

    /// Forget everything (a new connection).
    pub fn reset(&mut self) {
        *self = Self {
            stale: self.stale,
            ..Self::default()
        };
    }
}

/// Stamps that never go back: each at least 1 µs after the previous one.
#[derive(Debug, Clone, Copy, Default)]
pub struct Monotonic {
    last: Option<u64>,
    /// Stamps moved forward (the raw value was not after the previous one).
    pub held: u64,
}

impl Monotonic {
    /// `t`, or 1 µs after the previous stamp when `t` is not after it.
    pub fn stamp(&mut self, t: u64) -> u64 {
        let out = match self.last {
            Some(l) if t <= l => {
                self.held += 1;
                l.saturating_add(1)
            }
            _ => t,
        };
        self.last = Some(out);
        out
    }

    /// Start over (after an autopilot reboot: its boot time starts again at 0).
    pub fn reset(&mut self) {
        self.last = None;
    }
}

/// Maps autopilot boot time to Unix time: from SYSTEM_TIME (`time_unix_usec` at `time_boot_ms`)
/// when the autopilot has a real clock, else from the companion's system clock through the
/// TIMESYNC mapping.
#[derive(Debug, Clone, Default)]
pub struct UtcMap {
    /// Unix µs minus boot µs, from the autopilot's SYSTEM_TIME (latched, slewed).
    autopilot_offset_us: Option<i128>,
    /// The same from the companion's system clock (the fallback; latched, slewed).
    companion_offset_us: Option<i128>,
    /// The companion's clock is away from its latched offset (its step was counted).
    companion_stepped: bool,
    /// Where the autopilot's clock stepped to (its unix minus boot µs), while it stays away
    /// from the latched offset: a clock that stepped and stays there is one step, reported once.
    stepped_to_us: Option<i128>,
    /// Steps of the autopilot's clock seen and not followed.
    pub steps: u64,
}

impl UtcMap {
    /// Feed a SYSTEM_TIME message. Ignored when the autopilot's clock is not set. Returns the
    /// step in µs when the clock jumped by more than [`UTC_STEP_US`] (not followed); a clock that
    /// stays where it jumped to is reported once, a further jump again.
    pub fn observe_system_time(&mut self, time_unix_usec: u64, time_boot_ms: u32) -> Option<i128> {
        if time_unix_usec < PLAUSIBLE_UNIX_US {
            return None;
        }
        let measured = time_unix_usec as i128 - i128::from(time_boot_ms) * 1000;
        match self.autopilot_offset_us {
            None => {
                self.autopilot_offset_us = Some(measured);
                None
            }
            Some(o) if (measured - o).abs() <= UTC_STEP_US => {
                self.stepped_to_us = None;
                self.autopilot_offset_us =
                    Some(o + ((measured - o) as f64 * UTC_SLEW_GAIN) as i128);
                None
            }
            Some(o) => {
                let new_step = self
                    .stepped_to_us
                    .is_none_or(|s| (measured - s).abs() > UTC_STEP_US);
                self.stepped_to_us = Some(measured);
                new_step.then(|| {
                    self.steps += 1;
                    measured - o
                })
            }
        }
    }

    /// Forget both offsets (a reboot: the boot clock starts again; the step count stays).
    pub fn reset(&mut self) {
        *self = Self {
            steps: self.steps,
            ..Self::default()
        };
    }

    /// True if the autopilot reported a real clock.
    pub fn from_autopilot(&self) -> bool {
        self.autopilot_offset_us.is_some()
    }

    /// Unix µs of autopilot time `t_boot_us`. `companion_unix_minus_boot_us` is the fallback
    /// (companion system clock minus the mapped boot time), used when the autopilot has no clock.
    /// `None` when neither is plausible.
    ///
    /// The fallback is latched like the autopilot's clock: the companion's system clock can be
    /// stepped too (NTP, a hand-set clock), and following a step back would either send time
    /// going backwards or, held monotonic, freeze it. A step is counted once in `steps`.
    pub fn unix_us(
        &mut self,
        t_boot_us: u64,
        companion_unix_minus_boot_us: Option<i128>,
    ) -> Option<u64> {
        let off = match (self.autopilot_offset_us, companion_unix_minus_boot_us) {
            (Some(o), _) => o,
            (None, Some(f)) => self.companion_offset(f, t_boot_us),
            (None, None) => return None,
        };
        let u = off + t_boot_us as i128;
        u64::try_from(u).ok().filter(|u| *u >= PLAUSIBLE_UNIX_US)
    }

    fn companion_offset(&mut self, f: i128, t_boot_us: u64) -> i128 {
        match self.companion_offset_us {
            Some(c) if (f - c).abs() <= UTC_STEP_US => {
                self.companion_stepped = false;
                let c = c + ((f - c) as f64 * UTC_SLEW_GAIN) as i128;
                self.companion_offset_us = Some(c);
                c
            }
            Some(c) => {
                if !self.companion_stepped {
                    self.companion_stepped = true;
                    self.steps += 1;
                }
                c
            }
            None => {
                if f + t_boot_us as i128 >= PLAUSIBLE_UNIX_US as i128 {
                    self.companion_offset_us = Some(f);
                }
                f
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn gps_week_of_known_dates() {
        // 2024-01-01T00:00:00Z (a Monday): week 2295 began Sunday 2023-12-31; TOW = 1 day + 18 s.
        assert_eq!(gps_week_ms(1_704_067_200_000_000), Some((2295, 86_418_000)));
        // The GPS epoch itself: week 0, TOW = 18 s (the leap seconds we add).
        assert_eq!(gps_week_ms(GPS_EPOCH_UNIX_S * 1_000_000), Some((0, 18_000)));
        assert_eq!(gps_week_ms(0), None);
        // Sub-millisecond truncation.
        assert_eq!(gps_week_ms(1_704_067_200_000_999), Some((2295, 86_418_000)));
    }

    fn feed(ts: &mut TimeSync, offset_ns: f64, drift: f64, from_s: i64, n: i64, rtt_ns: i64) {
        for k in 0..n {
            let sent = (from_s + k) * 1_000_000_000 / 2;
            let mid = sent + rtt_ns / 2;
            let a = mid as f64 + offset_ns + drift * mid as f64;
            ts.update(TimesyncSample {
                sent_companion_ns: sent,
                autopilot_ns: a as i64,
                received_companion_ns: sent + rtt_ns,
            });
        }
    }

    #[test]
    fn converges_to_offset_and_drift() {
        let mut ts = TimeSync::new(50.0);
        assert!(ts.to_autopilot_us(0).is_none());
        // Autopilot 12.3 s ahead, running 40 ppm fast; 2 Hz samples for 200 s, 3 ms round trip.
        feed(&mut ts, 12.3e9, 40e-6, 0, 400, 3_000_000);
        assert!(ts.converged());
        let t = 200_000_000_000i64;
        let truth_us = (t as f64 + 12.3e9 + 40e-6 * t as f64) / 1000.0;
        let got = ts.to_autopilot_us(t).unwrap() as f64;
        assert!((got - truth_us).abs() < 50.0, "error {} us", got - truth_us);
        assert!((ts.drift() - 40e-6).abs() < 5e-6, "drift {}", ts.drift());
        // Inverse.
        let back = ts.to_companion_ns(got as u64).unwrap();
        assert!((back - t).abs() < 2_000, "{back} vs {t}");
    }

    #[test]
    fn long_round_trips_and_outliers_are_rejected() {
        let mut ts = TimeSync::new(20.0);
        assert_eq!(
            ts.update(TimesyncSample {
                sent_companion_ns: 0,
                autopilot_ns: 5_000_000_000,
                received_companion_ns: 30_000_000,
            }),
            SyncUpdate::Rejected
        );
        feed(&mut ts, 1e9, 0.0, 0, 20, 1_000_000);
        let before = ts.to_autopilot_us(20_000_000_000).unwrap();
        // One sample 200 ms off: rejected, mapping unchanged.
        let u = ts.update(TimesyncSample {
            sent_companion_ns: 10_500_000_000,
            autopilot_ns: 11_700_000_000,
            received_companion_ns: 10_501_000_000,
        });
        assert_eq!(u, SyncUpdate::Rejected);
        assert_eq!(ts.to_autopilot_us(20_000_000_000).unwrap(), before);
    }

    #[test]
    fn a_backwards_sample_is_an_outlier_until_the_reset() {
        let mut ts = TimeSync::new(50.0);
        feed(&mut ts, 100e9, 0.0, 0, 10, 1_000_000);
        assert!(ts.converged());
        // A TIMESYNC answer from a rebooted (or spoofed) clock: an outlier for the mapping; the
        // reboot itself is `BootClock`'s decision, after which the session resets the mapping.
        let back = TimesyncSample {
            sent_companion_ns: 6_000_000_000,
            autopilot_ns: 2_000_000_000,
            received_companion_ns: 6_001_000_000,
        };
        assert_eq!(ts.update(back), SyncUpdate::Rejected);
        assert!(ts.converged());
        ts.reset();
        assert!(!ts.converged());
        feed(&mut ts, -4e9, 0.0, 13, 10, 1_000_000);
        let got = ts.to_autopilot_us(10_000_000_000).unwrap();
        assert!((got as i64 - 6_000_000).abs() < 10, "{got}");
    }

    #[test]
    fn utc_map_prefers_autopilot_clock() {
        let mut m = UtcMap::default();
        assert_eq!(m.unix_us(1_000_000, None), None);
        assert_eq!(
            m.unix_us(1_000_000, Some(1_700_000_000_000_000)),
            Some(1_700_000_001_000_000)
        );
        // Autopilot without a clock: ignored.
        m.observe_system_time(5_000_000, 1000);
        assert!(!m.from_autopilot());
        m.observe_system_time(1_704_067_200_000_000, 2_000);
        assert!(m.from_autopilot());
        assert_eq!(m.unix_us(3_000_000, Some(0)), Some(1_704_067_201_000_000));
    }

    proptest! {
        #[test]
        fn gps_tow_is_in_range(unix_us in GPS_EPOCH_UNIX_S * 1_000_000..4_000_000_000_000_000u64) {
            let (w, ms) = gps_week_ms(unix_us).unwrap();
            prop_assert!(ms < 604_800_000);
            let back = (w as u64 * WEEK_S * 1000 + ms as u64) * 1000
                + GPS_EPOCH_UNIX_S * 1_000_000 - GPS_LEAP_S * 1_000_000;
            prop_assert!(unix_us - back < 1000);
        }
    }

    const ATT: u32 = 30;
    const SYS: u32 = 2;
    const IMU: u32 = 105;

    #[test]
    fn one_stale_message_is_not_a_reboot() {
        let mut c = BootClock::default();
        // 200 Hz on the clock, boot time = arrival + 50 s.
        let mut t_ns = 1_000_000_000i64;
        let boot = |t_ns: i64| (t_ns / 1000 + 50_000_000) as u64;
        for _ in 0..100 {
            assert_eq!(c.observe(IMU, boot(t_ns), t_ns), BootVerdict::Current);
            t_ns += 5_000_000;
        }
        // A spoofed ATTITUDE with time_boot_ms = 0, then a burst of stale messages of three kinds
        // interleaved with the real stream: never a reboot, every stale one dropped.
        assert_eq!(c.observe(ATT, 0, t_ns), BootVerdict::Stale);
        for k in 0..600u64 {
            t_ns += 5_000_000;
            let kind = [ATT, SYS, IMU][(k % 3) as usize];
            assert_eq!(
                c.observe(kind, 1_000_000 + k * 5000, t_ns),
                BootVerdict::Stale
            );
            if k % 2 == 0 {
                assert_eq!(c.observe(IMU, boot(t_ns), t_ns), BootVerdict::Current);
            }
        }
        assert_eq!(c.stale, 601);
    }

    #[test]
    fn a_far_future_stamp_is_stale_not_the_new_clock() {
        let mut c = BootClock::default();
        let mut t_ns = 1_000_000_000i64;
        let boot = |t_ns: i64| (t_ns / 1000 + 50_000_000) as u64;
        for _ in 0..10 {
            assert_eq!(c.observe(IMU, boot(t_ns), t_ns), BootVerdict::Current);
            t_ns += 5_000_000;
        }
        assert_eq!(c.observe(IMU, u64::MAX - 5, t_ns), BootVerdict::Stale);
        assert_eq!(
            c.observe(ATT, boot(t_ns) + 3_000_000, t_ns),
            BootVerdict::Stale
        );
        t_ns += 5_000_000;
        assert_eq!(c.observe(IMU, boot(t_ns), t_ns), BootVerdict::Current);
        // After 10 s of silence the clock has moved on 10 s: that is not ahead.
        t_ns += 10_000_000_000;
        assert_eq!(c.observe(IMU, boot(t_ns), t_ns), BootVerdict::Current);
    }

    #[test]
    fn a_real_reboot_is_confirmed_by_several_streams() {
        let mut c = BootClock::default();
        let mut t_ns = 1_000_000_000i64;
        for _ in 0..100 {
            c.observe(IMU, (t_ns / 1000 + 50_000_000) as u64, t_ns);
            t_ns += 5_000_000;
        }
        // 3 s of silence, then the autopilot is back with a clock starting near 0.
        t_ns += 3_000_000_000;
        let boot = |t_ns: i64, t0: i64| ((t_ns - t0) / 1000 + 100_000) as u64;
        let t0 = t_ns;
        assert_eq!(c.observe(IMU, boot(t_ns, t0), t_ns), BootVerdict::Stale);
        t_ns += 5_000_000;
        assert_eq!(c.observe(IMU, boot(t_ns, t0), t_ns), BootVerdict::Stale);
        t_ns += 5_000_000;
        // One stream alone is not enough; the second kind confirms.
        assert_eq!(c.observe(ATT, boot(t_ns, t0), t_ns), BootVerdict::Reboot);
        t_ns += 5_000_000;
        assert_eq!(c.observe(IMU, boot(t_ns, t0), t_ns), BootVerdict::Current);
    }

    #[test]
    fn output_stamps_never_go_back() {
        let mut m = Monotonic::default();
        assert_eq!(m.stamp(100), 100);
        assert_eq!(m.stamp(100), 101);
        assert_eq!(m.stamp(90), 102);
        assert_eq!(m.stamp(200), 200);
        assert_eq!(m.held, 2);
        m.reset();
        assert_eq!(m.stamp(5), 5);
    }

    #[test]
    fn a_step_of_the_companion_clock_is_not_followed_either() {
        let mut m = UtcMap::default();
        let off = 1_704_067_200_000_000i128;
        assert_eq!(m.unix_us(1_000_000, Some(off)), Some(1_704_067_201_000_000));
        // NTP steps the companion's clock back an hour: the output goes on from the latch.
        let back = off - 3_600_000_000;
        assert_eq!(
            m.unix_us(2_000_000, Some(back)),
            Some(1_704_067_202_000_000)
        );
        assert_eq!(
            m.unix_us(3_000_000, Some(back)),
            Some(1_704_067_203_000_000)
        );
        assert_eq!(m.steps, 1);
    }

    #[test]
    fn utc_steps_of_the_autopilot_clock_are_reported_not_followed() {
        let mut m = UtcMap::default();
        let t0 = 1_704_067_200_000_000u64;
        assert_eq!(m.observe_system_time(t0, 1000), None);
        let at = |m: &mut UtcMap, boot_us: u64| m.unix_us(boot_us, None).unwrap();
        assert_eq!(at(&mut m, 2_000_000), t0 + 1_000_000);
        // +1 h, a year back, a second of jitter: reported, the mapping stays.
        assert_eq!(
            m.observe_system_time(t0 + 3_600_000_000 + 1_000_000, 2000),
            Some(3_600_000_000)
        );
        // The clock stays an hour ahead: the same step, not reported again.
        for k in 1..5u64 {
            let t = t0 + 3_600_000_000 + 1_000_000 + k * 1_000_000;
            assert_eq!(m.observe_system_time(t, 2000 + 1000 * k as u32), None);
        }
        assert!(
            m.observe_system_time(t0 - 365 * 86_400_000_000 + 2_000_000, 3000)
                .is_some()
        );
        assert_eq!(
            m.observe_system_time(t0 + 3_000_000 - 1_000_000, 4000),
            Some(-1_000_000)
        );
        assert_eq!(m.steps, 3);
        assert_eq!(at(&mut m, 5_000_000), t0 + 4_000_000);
        // A few ms of difference is slewed in a tenth at a time.
        assert_eq!(m.observe_system_time(t0 + 9_000_000 + 10_000, 10_000), None);
        assert_eq!(at(&mut m, 10_000_000), t0 + 9_001_000);
    }
}
