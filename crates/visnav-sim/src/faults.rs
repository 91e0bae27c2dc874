//! Scripted fault events of a closed-loop scenario (`[[faults]]`) and the answers the
//! simulator's parts ask of them: the autopilot emulator (silence, reboots, the UTC clock, the IMU
//! and the aiding GPS), the simulated camera (stall, freeze, corruption), the wrapper of the
//! daemon's fix engine (a map that cannot be matched) and a spoofer that sends foreign HEARTBEATs
//! to the daemon's port. Every question is asked with the scenario time (the time since the
//! emulator started, which a reboot does not reset), so a lock-step run with faults is as
//! reproducible as one without.
//!
//! What the daemon is expected to do under each fault is docs/operations.md's fault table; the
//! scoring of a run ([`FaultOutcome`]) measures it and `tests/sim_faults.rs` checks it.

use serde::{Deserialize, Serialize};
use visnav_core::validate::Problems;

/// One kind of fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FaultKind {
    /// The autopilot sends nothing for `duration_s` (a hung autopilot, a cut cable); it still
    /// receives.
    LinkSilence,
    /// The autopilot reboots at `at_s`: its boot clock restarts at 0, its streams and EKF origin
    /// are forgotten, and it is silent while it boots (`autopilot::BOOT_SILENCE`).
    Reboot,
    /// `accel_g` (body FRD, g) is added to every accelerometer sample for `duration_s` (a hard
    /// landing, a vibration burst); the 16-bit MAVLink fields saturate as a real sensor does.
    ImuBurst,
    /// The aiding GPS reports positions `offset_ne_m` (north, east) away for `duration_s` (a
    /// jumping receiver, a spoofer).
    GpsJump,
    /// The autopilot's UTC clock (SYSTEM_TIME) steps by `clock_step_s` at `at_s` and stays there.
    ClockJump,
    /// The camera delivers no frame for `duration_s`.
    CameraStall,
    /// The camera delivers its last image again and again for `duration_s`, newly stamped (a
    /// frozen driver buffer).
    CameraFreeze,
    /// The camera's frames are torn for `duration_s`: a band of noise and the rows below it
    /// shifted sideways (a corrupt transfer that still decodes).
    CameraCorrupt,
    /// For `duration_s`, another component of the autopilot's system (a gimbal) and another
    /// vehicle (system 42) send HEARTBEATs to the daemon's port at 10 Hz, with junk between them.
    SpoofedHeartbeat,
    /// For `duration_s` the map cannot be matched (water, snow, fresh crops, a map far older than
    /// the season): every vision fix attempt on a frame captured in the window is refused with
    /// [`MAP_WITHHELD_REASON`] without running the engine. The camera still delivers its frames
    /// (visual odometry keeps working).
    MapWithheld,
    /// For `duration_s` the attitude prior of every vision fix attempt has its heading turned
    /// by `yaw_offset_deg` while claiming the filter's sigma (a compass near the motors, a
    /// heading drifted without GPS): what the engine's widened heading search is for. The filter
    /// itself is left as it is.
    HeadingBias,
}

/// The reason of a fix refused by [`FaultKind::MapWithheld`].
pub const MAP_WITHHELD_REASON: &str = "map withheld (scenario fault)";

impl FaultKind {
    /// Instantaneous kinds (`duration_s` must be 0); the others last `duration_s` > 0.
    pub fn instantaneous(self) -> bool {
        matches!(self, FaultKind::Reboot | FaultKind::ClockJump)
    }

    /// The name used in scenario files and reports.
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::LinkSilence => "link_silence",
            FaultKind::Reboot => "reboot",
            FaultKind::ImuBurst => "imu_burst",
            FaultKind::GpsJump => "gps_jump",
            FaultKind::ClockJump => "clock_jump",
            FaultKind::CameraStall => "camera_stall",
            FaultKind::CameraFreeze => "camera_freeze",
            FaultKind::CameraCorrupt => "camera_corrupt",
            FaultKind::SpoofedHeartbeat => "spoofed_heartbeat",
            FaultKind::MapWithheld => "map_withheld",
            FaultKind::HeadingBias => "heading_bias",
        }
    }
}

/// One `[[faults]]` entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultConfig {
    /// What fails.
    pub kind: FaultKind,
    /// Scenario time of the start, s.
    pub at_s: f64,
    /// How long it lasts, s (0 for `reboot` and `clock_jump`).
    #[serde(default)]
    pub duration_s: f64,
    /// `imu_burst`: specific force added, body FRD, g.
    #[serde(default)]
    pub accel_g: Option<[f64; 3]>,
    /// `gps_jump`: the offset of the reported positions, north and east, m.
    #[serde(default)]
    pub offset_ne_m: Option<[f64; 2]>,
    /// `clock_jump`: the step of the autopilot's UTC clock, s.
    #[serde(default)]
    pub clock_step_s: Option<f64>,
    /// `heading_bias`: the turn added to the fix prior's heading, degrees.
    #[serde(default)]
    pub yaw_offset_deg: Option<f64>,
}

impl FaultConfig {
    /// End of the fault (scenario time), s.
    pub fn until_s(&self) -> f64 {
        self.at_s + self.duration_s
    }

    fn active(&self, kind: FaultKind, t_s: f64) -> bool {
        self.kind == kind && t_s >= self.at_s && t_s < self.until_s()
    }

    /// Check one entry of a scenario lasting `dur_s` (keys relative to `faults[i]`).
    pub fn validate(&self, p: &mut Problems, dur_s: f64) {
        p.range("at_s", self.at_s, 0.0, dur_s);
        if self.kind.instantaneous() {
            if self.duration_s != 0.0 {
                p.push(
                    "duration_s",
                    format!(
                        "{} is instantaneous: leave duration_s out",
                        self.kind.name()
                    ),
                );
            }
        } else {
            p.range("duration_s", self.duration_s, 0.01, dur_s);
        }
        let param = |p: &mut Problems, key: &str, given: bool, wanted: bool| match (given, wanted) {
            (true, false) => p.push(key, format!("not a key of {}", self.kind.name())),
            (false, true) => p.push(key, format!("{} needs {key}", self.kind.name())),
            _ => {}
        };
        param(
            p,
            "accel_g",
            self.accel_g.is_some(),
            self.kind == FaultKind::ImuBurst,
        );
        param(
            p,
            "offset_ne_m",
            self.offset_ne_m.is_some(),
            self.kind == FaultKind::GpsJump,
        );
        param(
            p,
            "clock_step_s",
            self.clock_step_s.is_some(),
            self.kind == FaultKind::ClockJump,
        );
        param(
            p,
            "yaw_offset_deg",
            self.yaw_offset_deg.is_some(),
            self.kind == FaultKind::HeadingBias,
        );
        if let Some(y) = self.yaw_offset_deg {
            p.range("yaw_offset_deg", y, -180.0, 180.0);
        }
        for a in self.accel_g.iter().flatten() {
            p.range("accel_g", *a, -1000.0, 1000.0);
        }
        for d in self.offset_ne_m.iter().flatten() {
            p.range("offset_ne_m", *d, -1e6, 1e6);
        }
        if let Some(s) = self.clock_step_s {
            p.range("clock_step_s", s, -1e9, 1e9);
        }
    }
}

/// Standard gravity for `accel_g`, m/s^2.
const G0_M_S2: f64 = 9.806_65;

/// What the camera does at an instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraFault {
    /// Frames as usual.
    None,
    /// No frame ([`FaultKind::CameraStall`]).
    Stall,
    /// The last image again, newly stamped ([`FaultKind::CameraFreeze`]).
    Freeze,
    /// Torn frames ([`FaultKind::CameraCorrupt`]).
    Corrupt,
}

/// The scenario's faults, asked by scenario time (see the module doc).
#[derive(Debug, Clone, Default)]
pub struct FaultPlan {
    /// The `[[faults]]` entries.
    pub faults: Vec<FaultConfig>,
}

impl FaultPlan {
    /// The plan of a scenario's `[[faults]]` entries.
    pub fn new(faults: Vec<FaultConfig>) -> Self {
        Self { faults }
    }

    fn any(&self, kind: FaultKind, t_s: f64) -> bool {
        self.faults.iter().any(|f| f.active(kind, t_s))
    }

    /// The autopilot sends nothing.
    pub fn link_silent(&self, t_s: f64) -> bool {
        self.any(FaultKind::LinkSilence, t_s)
    }

    /// Reboots scripted at or before `t_s`.
    pub fn reboots_by(&self, t_s: f64) -> u32 {
        self.faults
            .iter()
            .filter(|f| f.kind == FaultKind::Reboot && f.at_s <= t_s)
            .count() as u32
    }

    /// The sum of the clock steps at or before `t_s`, µs.
    pub fn utc_offset_us(&self, t_s: f64) -> i64 {
        self.faults
            .iter()
            .filter(|f| f.kind == FaultKind::ClockJump && f.at_s <= t_s)
            .filter_map(|f| f.clock_step_s)
            .map(|s| (s * 1e6).round() as i64)
            .sum()
    }

    /// Specific force added to the accelerometer, body FRD, m/s^2.
    pub fn extra_accel_m_s2(&self, t_s: f64) -> [f64; 3] {
        let mut a = [0.0; 3];
        for f in self
            .faults
            .iter()
            .filter(|f| f.active(FaultKind::ImuBurst, t_s))
        {
            for (k, g) in f.accel_g.unwrap_or_default().iter().enumerate() {
                a[k] += g * G0_M_S2;
            }
        }
        a
    }

    /// Offset of the aiding GPS's positions, north and east, m.
    pub fn gps_offset_ne_m(&self, t_s: f64) -> [f64; 2] {
        let mut d = [0.0; 2];
        for f in self
            .faults
            .iter()
            .filter(|f| f.active(FaultKind::GpsJump, t_s))
        {
            let o = f.offset_ne_m.unwrap_or_default();
            d[0] += o[0];
            d[1] += o[1];
        }
        d
    }

    /// What the camera does (stall wins over freeze over corruption when they overlap).
    pub fn camera(&self, t_s: f64) -> CameraFault {
        if self.any(FaultKind::CameraStall, t_s) {
            CameraFault::Stall
        } else if self.any(FaultKind::CameraFreeze, t_s) {
            CameraFault::Freeze
        } else if self.any(FaultKind::CameraCorrupt, t_s) {
            CameraFault::Corrupt
        } else {
            CameraFault::None
        }
    }

    /// The map cannot be matched: a fix on a frame captured at `t_s` is refused
    /// ([`FaultKind::MapWithheld`]).
    pub fn map_withheld(&self, t_s: f64) -> bool {
        self.any(FaultKind::MapWithheld, t_s)
    }

    /// The turn added to the heading of a fix attempt's attitude prior for a frame captured at
    /// `t_s`, degrees ([`FaultKind::HeadingBias`]; 0 outside one).
    pub fn heading_bias_deg(&self, t_s: f64) -> f64 {
        self.faults
            .iter()
            .filter(|f| f.active(FaultKind::HeadingBias, t_s))
            .filter_map(|f| f.yaw_offset_deg)
            .sum()
    }

    /// Foreign HEARTBEATs are being sent to the daemon.
    pub fn spoofing(&self, t_s: f64) -> bool {
        self.any(FaultKind::SpoofedHeartbeat, t_s)
    }

    /// Whether any fault needs the spoofer task.
    pub fn has(&self, kind: FaultKind) -> bool {
        self.faults.iter().any(|f| f.kind == kind)
    }
}

/// The spoofer of [`FaultKind::SpoofedHeartbeat`]: while `plan` says so at the run time
/// `run_s()`, every 100 ms it sends to `to` (the daemon's `udpin` port) a HEARTBEAT of a gimbal
/// in the autopilot's system (1/154, MAV_TYPE_GIMBAL), one of another vehicle (42/1, a quadrotor
/// running ArduPilot) and a datagram of junk, each from its own socket. Runs until dropped.
pub async fn spoof_heartbeats(
    to: std::net::SocketAddr,
    plan: FaultPlan,
    run_s: impl Fn() -> f64 + Send + 'static,
) -> std::io::Result<()> {
    use mavlink::dialects::ardupilotmega::{
        HEARTBEAT_DATA, MavAutopilot, MavMessage, MavModeFlag, MavState, MavType,
    };
    use mavlink::{MAVLinkV2MessageRaw, MavHeader};
    let bind = || tokio::net::UdpSocket::bind("127.0.0.1:0");
    let (gimbal, vehicle, junk) = (bind().await?, bind().await?, bind().await?);
    let mut seq = 0u8;
    let mut tick = tokio::time::interval(std::time::Duration::from_millis(100));
    loop {
        tick.tick().await;
        if !plan.spoofing(run_s()) {
            continue;
        }
        seq = seq.wrapping_add(1);
        for (sock, sys, comp, mavtype, autopilot) in [
            (
                &gimbal,
                1,
                154,
                MavType::MAV_TYPE_GIMBAL,
                MavAutopilot::MAV_AUTOPILOT_INVALID,
            ),
            (
                &vehicle,
                42,
                1,
                MavType::MAV_TYPE_QUADROTOR,
                MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            ),
        ] {
            let mut raw = MAVLinkV2MessageRaw::new();
            raw.serialize_message(
                MavHeader {
                    system_id: sys,
                    component_id: comp,
                    sequence: seq,
                },
                &MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                    custom_mode: 0,
                    mavtype,
                    autopilot,
                    base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                    system_status: MavState::MAV_STATE_ACTIVE,
                    mavlink_version: 3,
                }),
            );
            // Loopback UDP: a lost datagram is the daemon's business, not the spoofer's.
            let _ = sock.send_to(raw.raw_bytes(), to).await;
        }
        let _ = junk.send_to(&[0xFD, 0x09, 0x00, seq, 0xff, 0x42], to).await;
    }
}

/// What the daemon did around one scripted fault (scored by the closed loop against the truth;
/// the expectations are docs/operations.md's fault table, checked by `tests/sim_faults.rs`).
#[derive(Debug, Clone, Serialize)]
pub struct FaultOutcome {
    /// The fault's kind ([`FaultKind::name`]).
    pub kind: &'static str,
    /// Scenario time of the fault's start, s.
    pub from_s: f64,
    /// Scenario time of the fault's end, s.
    pub until_s: f64,
    /// Injections of the scored message (fix type 3 for GPS_INPUT) received while the fault
    /// lasted.
    pub outputs_during: usize,
    /// The longest gap between consecutive injections from the fault's start to
    /// [`RECOVERY_WINDOW_S`] after its end, s.
    pub max_output_gap_s: f64,
    /// The first injection after the fault's end, s after it (`None`: none before the run ended).
    pub first_output_after_s: Option<f64>,
    /// Largest horizontal error of an injection from the start to [`RECOVERY_WINDOW_S`] after the
    /// end, m.
    pub max_err_m: Option<f64>,
    /// Largest horizontal error over the accuracy claimed with it (GPS_INPUT `horiz_accuracy`,
    /// the local messages' horizontal sigma) in the same window.
    pub max_err_over_claimed: Option<f64>,
    /// p90 horizontal error of the injections in the 20 s before the fault, m.
    pub err_before_p90_m: Option<f64>,
    /// p90 horizontal error of the injections in [`RECOVERY_WINDOW_S`] after the fault, m.
    pub err_after_p90_m: Option<f64>,
    /// Vision fix attempts on frames captured during the fault.
    pub fixes_attempted: usize,
    /// Of those, the accepted fixes.
    pub fixes_accepted: usize,
    /// Accepted fixes captured during the fault whose error is beyond their 3-sigma ellipse.
    pub fixes_beyond_3sigma: usize,
}

/// How long after a fault's end its recovery is judged, s.
pub const RECOVERY_WINDOW_S: f64 = 20.0;

/// The window before a fault whose error is its baseline, s.
pub const BASELINE_WINDOW_S: f64 = 20.0;

/// Counters of the vision daemon at the end of a run with faults (what the fault table says it
/// logs and counts).
#[derive(Debug, Clone, Default, Serialize)]
pub struct FaultCounters {
    /// Autopilot reboots the daemon detected (its filter restarted).
    pub autopilot_reboots: u64,
    /// Lock-on moved to another autopilot.
    pub relocks: u64,
    /// Steps of the autopilot's UTC clock reported (not followed).
    pub utc_steps: u64,
    /// Messages dropped as behind the autopilot's clock.
    pub rx_stale: u64,
    /// IMU stream timeouts (solution lost).
    pub imu_timeouts: u64,
    /// Frames dropped as identical to the previous one (a frozen camera).
    pub frames_frozen: u64,
    /// GPS_INPUT messages whose `time_usec` went back.
    pub gps_input_time_backsteps: usize,
    /// Injections the emulator received whose values were not finite.
    pub non_finite_injections: usize,
    /// Injections the emulator received from a system other than the companion.
    pub foreign_injections: usize,
}

/// An injection as the scoring needs it: run time s, horizontal error m, claimed horizontal
/// 1-sigma m.
#[derive(Debug, Clone, Copy)]
pub struct ScoredOutput {
    /// Arrival (run time), s.
    pub t_s: f64,
    /// Horizontal error against the truth at arrival, m.
    pub err_h_m: f64,
    /// The horizontal accuracy the message claims, m.
    pub claimed_h_m: f64,
}

/// A vision fix as the scoring needs it: capture (run) time s, accepted, beyond its 3 sigma.
#[derive(Debug, Clone, Copy)]
pub struct ScoredFix {
    /// Capture (run) time, s.
    pub t_capture_s: f64,
    /// Whether the engine accepted it.
    pub accepted: bool,
    /// Whether its error lies beyond its own 3-sigma horizontal ellipse.
    pub beyond_3sigma: bool,
}

fn max_of(v: impl Iterator<Item = f64>) -> Option<f64> {
    v.fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.max(x))))
}

fn p90(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let i = ((v.len() - 1) as f64 * 0.9).round() as usize;
    Some(v[i])
}

/// Score every fault of `plan`: `outputs` in time order, the run ending at `end_s`.
pub fn outcomes(
    plan: &FaultPlan,
    outputs: &[ScoredOutput],
    fixes: &[ScoredFix],
    end_s: f64,
) -> Vec<FaultOutcome> {
    plan.faults
        .iter()
        .map(|f| outcome(f, outputs, fixes, end_s))
        .collect()
}

fn outcome(
    f: &FaultConfig,
    outputs: &[ScoredOutput],
    fixes: &[ScoredFix],
    end_s: f64,
) -> FaultOutcome {
    let (from, until) = (f.at_s, f.until_s());
    let judged_until = (until + RECOVERY_WINDOW_S).min(end_s);
    let judged: Vec<&ScoredOutput> = outputs
        .iter()
        .filter(|o| o.t_s >= from && o.t_s <= judged_until)
        .collect();
    // Gaps over the judged window, counting its edges: no output at all is one long gap.
    let mut gap = 0.0f64;
    let mut last = from;
    for o in &judged {
        gap = gap.max(o.t_s - last);
        last = o.t_s;
    }
    gap = gap.max(judged_until - last);
    let in_window = |t: f64| t >= from && t < until.max(from + 1e-9);
    let during: Vec<&ScoredFix> = fixes.iter().filter(|x| in_window(x.t_capture_s)).collect();
    FaultOutcome {
        kind: f.kind.name(),
        from_s: from,
        until_s: until,
        outputs_during: outputs.iter().filter(|o| in_window(o.t_s)).count(),
        max_output_gap_s: gap,
        first_output_after_s: outputs
            .iter()
            .find(|o| o.t_s >= until)
            .map(|o| o.t_s - until),
        max_err_m: max_of(judged.iter().map(|o| o.err_h_m)),
        max_err_over_claimed: max_of(judged.iter().map(|o| o.err_h_m / o.claimed_h_m)),
        err_before_p90_m: p90(outputs
            .iter()
            .filter(|o| o.t_s >= from - BASELINE_WINDOW_S && o.t_s < from)
            .map(|o| o.err_h_m)
            .collect()),
        err_after_p90_m: p90(outputs
            .iter()
            .filter(|o| o.t_s > until && o.t_s <= judged_until)
            .map(|o| o.err_h_m)
            .collect()),
        fixes_attempted: during.len(),
        fixes_accepted: during.iter().filter(|x| x.accepted).count(),
        fixes_beyond_3sigma: during
            .iter()
            .filter(|x| x.accepted && x.beyond_3sigma)
            .count(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fault(kind: FaultKind, at_s: f64, duration_s: f64) -> FaultConfig {
        FaultConfig {
            kind,
            at_s,
            duration_s,
            accel_g: None,
            offset_ne_m: None,
            clock_step_s: None,
            yaw_offset_deg: None,
        }
    }

    #[test]
    fn a_heading_bias_turns_the_fix_prior_inside_its_window_only() {
        let parsed: FaultConfig = toml::from_str(
            "kind = \"heading_bias\"\nat_s = 120.0\nduration_s = 120.0\nyaw_offset_deg = 30.0\n",
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let mut two = parsed.clone();
        two.yaw_offset_deg = Some(-5.0);
        two.at_s = 200.0;
        let plan = FaultPlan::new(vec![parsed.clone(), two]);
        assert_eq!(plan.heading_bias_deg(119.999), 0.0);
        assert_eq!(plan.heading_bias_deg(120.0), 30.0);
        assert_eq!(plan.heading_bias_deg(210.0), 25.0, "overlapping biases add");
        assert_eq!(plan.heading_bias_deg(240.0), -5.0);
        assert_eq!(plan.heading_bias_deg(320.0), 0.0);
        assert!(!plan.map_withheld(150.0), "the map is still matched");
        assert_eq!(FaultKind::HeadingBias.name(), "heading_bias");
        let check = |f: FaultConfig| {
            let mut p = Problems::default();
            f.validate(&mut p, 400.0);
            p.list.iter().map(|i| i.to_string()).collect::<Vec<_>>()
        };
        assert!(check(parsed.clone()).is_empty());
        let e = check(fault(FaultKind::HeadingBias, 5.0, 2.0));
        assert!(e.len() == 1 && e[0].contains("yaw_offset_deg"), "{e:?}");
        let mut wild = parsed;
        wild.yaw_offset_deg = Some(400.0);
        let e = check(wild);
        assert!(e.len() == 1 && e[0].contains("yaw_offset_deg"), "{e:?}");
        let mut stray = fault(FaultKind::GpsJump, 5.0, 2.0);
        stray.offset_ne_m = Some([1.0, 0.0]);
        stray.yaw_offset_deg = Some(3.0);
        let e = check(stray);
        assert!(e.len() == 1 && e[0].contains("not a key"), "{e:?}");
    }

    #[test]
    fn windows_are_half_open_and_steps_accumulate() {
        let mut jump = fault(FaultKind::ClockJump, 10.0, 0.0);
        jump.clock_step_s = Some(3600.0);
        let mut back = fault(FaultKind::ClockJump, 20.0, 0.0);
        back.clock_step_s = Some(-1.5);
        let plan = FaultPlan::new(vec![
            fault(FaultKind::LinkSilence, 5.0, 2.0),
            jump,
            back,
            fault(FaultKind::Reboot, 30.0, 0.0),
        ]);
        assert!(!plan.link_silent(4.999));
        assert!(plan.link_silent(5.0));
        assert!(!plan.link_silent(7.0));
        assert_eq!(plan.utc_offset_us(9.9), 0);
        assert_eq!(plan.utc_offset_us(10.0), 3_600_000_000);
        assert_eq!(plan.utc_offset_us(25.0), 3_598_500_000);
        assert_eq!(plan.reboots_by(29.0), 0);
        assert_eq!(plan.reboots_by(30.0), 1);
    }

    #[test]
    fn sensor_faults_add_their_values_only_while_active() {
        let mut burst = fault(FaultKind::ImuBurst, 1.0, 4.0);
        burst.accel_g = Some([50.0, 0.0, -1.0]);
        let mut jump = fault(FaultKind::GpsJump, 2.0, 1.0);
        jump.offset_ne_m = Some([10_000.0, -5.0]);
        let plan = FaultPlan::new(vec![
            burst,
            jump,
            fault(FaultKind::CameraCorrupt, 0.0, 10.0),
            fault(FaultKind::CameraStall, 3.0, 1.0),
        ]);
        assert_eq!(plan.extra_accel_m_s2(0.5), [0.0; 3]);
        let a = plan.extra_accel_m_s2(3.0);
        assert!((a[0] - 490.3325).abs() < 1e-9 && a[1] == 0.0 && (a[2] + G0_M_S2).abs() < 1e-12);
        assert_eq!(plan.gps_offset_ne_m(2.5), [10_000.0, -5.0]);
        assert_eq!(plan.gps_offset_ne_m(3.0), [0.0, 0.0]);
        assert_eq!(plan.camera(1.0), CameraFault::Corrupt);
        assert_eq!(plan.camera(3.5), CameraFault::Stall);
        assert_eq!(plan.camera(10.0), CameraFault::None);
    }

    #[test]
    fn the_map_is_withheld_only_inside_its_window() {
        let plan = FaultPlan::new(vec![
            fault(FaultKind::MapWithheld, 20.0, 8.0),
            fault(FaultKind::CameraStall, 0.0, 30.0),
        ]);
        assert!(!plan.map_withheld(19.999));
        assert!(plan.map_withheld(20.0));
        assert!(plan.map_withheld(27.999));
        assert!(!plan.map_withheld(28.0));
        // Not a camera fault: the camera's answer is its own faults'.
        assert_eq!(plan.camera(25.0), CameraFault::Stall);
        assert!(!FaultPlan::new(vec![fault(FaultKind::CameraStall, 0.0, 30.0)]).map_withheld(5.0));
        assert_eq!(FaultKind::MapWithheld.name(), "map_withheld");
        let parsed: FaultConfig =
            toml::from_str("kind = \"map_withheld\"\nat_s = 20.0\nduration_s = 8.0\n")
                .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(parsed, fault(FaultKind::MapWithheld, 20.0, 8.0));
    }

    #[test]
    fn validation_names_the_key_of_each_problem() {
        let check = |f: FaultConfig| {
            let mut p = Problems::default();
            f.validate(&mut p, 100.0);
            p.list.iter().map(|i| i.to_string()).collect::<Vec<_>>()
        };
        assert!(check(fault(FaultKind::LinkSilence, 5.0, 2.0)).is_empty());
        assert!(check(fault(FaultKind::MapWithheld, 5.0, 2.0)).is_empty());
        // map_withheld lasts: a zero duration is refused.
        let e = check(fault(FaultKind::MapWithheld, 5.0, 0.0));
        assert!(e.len() == 1 && e[0].contains("duration_s"), "{e:?}");
        let e = check(fault(FaultKind::Reboot, 5.0, 2.0));
        assert!(
            e[0].contains("duration_s") && e[0].contains("instantaneous"),
            "{e:?}"
        );
        let e = check(fault(FaultKind::ImuBurst, 5.0, 2.0));
        assert!(e[0].contains("accel_g") && e[0].contains("needs"), "{e:?}");
        let mut f = fault(FaultKind::CameraStall, 150.0, 0.0);
        f.offset_ne_m = Some([1.0, 1.0]);
        let e = check(f);
        assert_eq!(e.len(), 3, "{e:?}");
        assert!(e.iter().any(|s| s.contains("at_s")));
        assert!(e.iter().any(|s| s.contains("duration_s")));
        assert!(
            e.iter()
                .any(|s| s.contains("offset_ne_m") && s.contains("not a key"))
        );
    }

    #[test]
    fn an_outcome_measures_the_gap_the_errors_and_the_fixes_of_its_window() {
        let plan = FaultPlan::new(vec![fault(FaultKind::LinkSilence, 10.0, 5.0)]);
        // Outputs every 0.5 s except 11..16 s; the error is 1 m, 50 m at 16 s (claimed 5 m).
        let outputs: Vec<ScoredOutput> = (0..80)
            .map(|i| i as f64 * 0.5)
            .filter(|t| !(11.0..16.0).contains(t))
            .map(|t| ScoredOutput {
                t_s: t,
                err_h_m: if t == 16.0 { 50.0 } else { 1.0 },
                claimed_h_m: 5.0,
            })
            .collect();
        let fixes = [
            ScoredFix {
                t_capture_s: 12.0,
                accepted: true,
                beyond_3sigma: true,
            },
            ScoredFix {
                t_capture_s: 14.5,
                accepted: false,
                beyond_3sigma: false,
            },
        ];
        let o = &outcomes(&plan, &outputs, &fixes, 40.0)[0];
        assert_eq!(o.kind, "link_silence");
        assert_eq!(o.outputs_during, 2); // 10.0, 10.5 and nothing until 16
        assert!((o.max_output_gap_s - 5.5).abs() < 1e-9);
        assert_eq!(o.first_output_after_s, Some(1.0));
        assert_eq!(o.max_err_m, Some(50.0));
        assert_eq!(o.max_err_over_claimed, Some(10.0));
        assert_eq!(o.err_before_p90_m, Some(1.0));
        assert_eq!(
            (o.fixes_attempted, o.fixes_accepted, o.fixes_beyond_3sigma),
            (2, 1, 1)
        );
        // Nothing after the fault: the gap runs to the end of the judged window.
        let o = &outcomes(&plan, &outputs[..5], &[], 40.0)[0];
        assert!((o.max_output_gap_s - 25.0).abs() < 1e-9 && o.first_output_after_s.is_none());
    }
}
