//! Visual odometry in the daemon (`[vo] enabled`): every frame the reader takes also goes to one
//! odometry thread (its own one-frame slot: the newest wins unless lossless; in lock-step, in
//! order on the blocking pool), which runs the [`Odometer`] with the filter's pose at the frame's
//! capture time ([`PriorSource::pose_at`]: its solution interpolated to the instant) and the
//! gyros' rotation since the previous frame ([`PriorSource::body_rotation`]: the filter's
//! bias-compensated rates integrated, without its corrections in between; its sigma the gyros'
//! noise and residual bias over the interval and what sampling the rates at the filter's output
//! rate leaves unknown). Each result goes to
//! the navigation task, which fuses a motion as a [`visnav_core::nav::VoFix`] and counts the
//! rest (`metrics::Sequence`). A frozen camera's repeated frames never get here (the reader
//! drops them); a blank or torn frame gives no motion (too few tracks, or no consensus).
//!
//! The DTM navigator (`[dtm_nav] enabled`, [`DtmNavigator`]) runs on the same thread with the
//! same frames and priors (either or both may be on): each frame paired with an earlier one far
//! enough away, the pair's flow over the terrain model solved for the frame's absolute pose,
//! which the navigation task fuses as a pose measurement (`metrics.dtm`).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use tracing::{error, info};

use crate::handoff::{PriorSource, Slot, Take, capture_time_us};
use crate::metrics::DaemonMetrics;
use visnav_core::dtm_nav::{DtmNavigator, DtmStep};
use visnav_core::fix::FixPrior;
use visnav_core::nav::NavConfig;
use visnav_core::vision::GrayImage;
use visnav_core::vo::{GyroDelta, Odometer, VoStep};
use visnav_io::frames::Frame;
use visnav_link::Clock;

/// One frame's odometry for the navigation task.
#[derive(Debug, Clone)]
pub struct VoResult {
    /// Capture time, autopilot boot µs.
    pub t_capture_us: u64,
    /// The frame's sequence number.
    pub seq: u64,
    /// The odometer's step (`None`: visual odometry off).
    pub step: Option<VoStep>,
    /// The DTM navigator's (`None`: off).
    pub dtm: Option<DtmStep>,
    /// The filter's attitude the frame was given (roll, pitch, yaw, deg) and its tilt and yaw
    /// sigma (deg); for the VO log.
    pub prior_attitude_deg: Option<([f64; 3], [f64; 2])>,
}

/// Floor of the gyros' rotation sigma between two frames, rad (0.006 deg): the filter's rates are
/// sampled at its output rate, not integrated over every IMU sample, and an autopilot's IMU
/// stream is itself a sampled one; below this the prior would be trusted beyond what a sampled
/// rate gives over a turn's onset.
const GYRO_DELTA_SIGMA_FLOOR_RAD: f64 = 1e-4;

/// The gyros' error over a frame interval, from the filter's IMU model (`[nav.imu]`).
#[derive(Debug, Clone, Copy)]
pub struct GyroNoise {
    arw_rad_sqrt_s: f64,
    bias_rad_s: f64,
}

impl GyroNoise {
    /// From the filter's IMU model: angle random walk and the bias instability (the residual
    /// bias once the filter has calibrated the turn-on part).
    pub fn from_nav(nav: &NavConfig) -> Self {
        Self {
            arw_rad_sqrt_s: nav.imu.gyro_arw_deg_sqrt_h.to_radians() / 60.0,
            bias_rad_s: nav.imu.gyro_bias_instability_deg_h.to_radians() / 3600.0,
        }
    }

    /// 1-sigma per axis of the rotation over `dt_s`, rad.
    pub fn sigma_rad(&self, dt_s: f64) -> f64 {
        let s2 = self.arw_rad_sqrt_s.powi(2) * dt_s + (self.bias_rad_s * dt_s).powi(2);
        s2.sqrt().max(GYRO_DELTA_SIGMA_FLOOR_RAD)
    }
}

/// What the odometry path holds.
pub struct VoCtx {
    /// The visual odometer (None: off).
    pub odometer: Option<Odometer>,
    /// The DTM navigator (None: off).
    pub dtm: Option<DtmNavigator>,
    /// The priors at a capture time.
    pub priors: Arc<dyn PriorSource>,
    /// Where the results go (the navigation task).
    pub results: mpsc::Sender<VoResult>,
    /// The counters.
    pub metrics: Arc<DaemonMetrics>,
    /// The gyros' noise, for the rotation's sigma between frames.
    pub gyro: GyroNoise,
    /// Capture time of the previous frame given to the odometer.
    pub last_t_us: Option<u64>,
}

/// A frame's odometry inputs, read from the navigation state (on the runtime's thread in
/// lock-step, so two runs read it at the same point of their schedule).
pub struct VoInputs {
    prior: FixPrior,
    gyro: Option<GyroDelta>,
}

impl VoCtx {
    /// The filter's pose at `t_us` and the gyros' rotation since the previous frame.
    pub fn inputs(&self, t_us: u64) -> VoInputs {
        let gyro = self.last_t_us.and_then(|t0| {
            let (r, unknown_rad) = self.priors.body_rotation(t0, t_us)?;
            let dt_s = t_us.saturating_sub(t0) as f64 * 1e-6;
            Some(GyroDelta {
                r_body_prev_next: r,
                sigma_rad: self.gyro.sigma_rad(dt_s).hypot(unknown_rad),
                sampling_sigma_rad: unknown_rad,
            })
        });
        VoInputs {
            prior: self.priors.pose_at(t_us),
            gyro,
        }
    }

    /// Odometry and DTM navigation of one frame (each counted and timed; a panic becomes a
    /// refusal and restarts that sequence).
    pub fn step(&mut self, image: GrayImage, seq: u64, inputs: VoInputs) -> VoResult {
        let t_us = inputs.prior.t_capture_us;
        let prior_attitude_deg = inputs.prior.attitude.map(|a| {
            let at = a.attitude;
            (
                [at.roll_rad, at.pitch_rad, at.yaw_rad].map(f64::to_degrees),
                [a.sigma_rad, a.sigma_yaw_rad].map(f64::to_degrees),
            )
        });
        // Each takes the frame: a copy only when both run.
        let (img_dtm, img_vo) = match (self.dtm.is_some(), self.odometer.is_some()) {
            (true, true) => (Some(image.clone()), Some(image)),
            (true, false) => (Some(image), None),
            (false, _) => (None, Some(image)),
        };
        let dtm = match (self.dtm.as_mut(), img_dtm) {
            (Some(nav), Some(img)) => Some(dtm_step(nav, img, seq, &inputs.prior, &self.metrics)),
            _ => None,
        };
        let step = match (self.odometer.as_mut(), img_vo) {
            (Some(odo), Some(img)) => Some(vo_step(odo, img, seq, inputs, &self.metrics)),
            _ => None,
        };
        self.last_t_us = Some(t_us);
        VoResult {
            t_capture_us: t_us,
            seq,
            step,
            dtm,
            prior_attitude_deg,
        }
    }
}

/// The odometer on one frame, counted and timed.
fn vo_step(
    odo: &mut Odometer,
    image: GrayImage,
    seq: u64,
    inputs: VoInputs,
    metrics: &DaemonMetrics,
) -> VoStep {
    // Wall time of the computation (reported, never used by the algorithm).
    let start = std::time::Instant::now();
    let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        odo.frame(image, &inputs.prior, inputs.gyro)
    }));
    let step = match caught {
        Ok(s) => s,
        Err(_) => {
            error!("visual odometry panicked on frame {seq}");
            odo.reset();
            VoStep::Refused(visnav_core::vo::VoRefusal::Panicked)
        }
    };
    let m = &metrics.vo;
    m.time(start.elapsed().as_micros() as u64);
    match &step {
        VoStep::Started => {
            m.started.inc();
        }
        VoStep::Motion(_) => {
            m.motions.inc();
        }
        VoStep::Refused(why) => m.refuse(why.class(), &why.to_string()),
    }
    step
}

/// The DTM navigator on one frame, counted and timed (`metrics.dtm`: `started` counts the frames
/// kept without a partner yet, `motions` the poses solved).
fn dtm_step(
    nav: &mut DtmNavigator,
    image: GrayImage,
    seq: u64,
    prior: &FixPrior,
    metrics: &DaemonMetrics,
) -> DtmStep {
    // Wall time of the computation (reported, never used by the algorithm).
    let start = std::time::Instant::now();
    let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| nav.frame(image, prior)));
    let step = match caught {
        Ok(s) => s,
        Err(_) => {
            error!("DTM navigation panicked on frame {seq}");
            nav.reset();
            DtmStep::Refused(visnav_core::dtm_nav::DtmRefusal::Panicked)
        }
    };
    let m = &metrics.dtm;
    m.time(start.elapsed().as_micros() as u64);
    match &step {
        DtmStep::Waiting => {
            m.started.inc();
        }
        DtmStep::Fix(_) => {
            m.motions.inc();
        }
        DtmStep::Refused(why) => m.refuse(why.class(), &why.to_string()),
    }
    step
}

/// The odometry thread (real time): slot -> odometer -> results until the slot is closed or the
/// navigation task is gone. Frames without a capture time, or older than `max_age_s`, are
/// skipped (the fix path counts them).
pub fn spawn_vo(
    slot: Arc<Slot<Frame>>,
    mut ctx: VoCtx,
    clock: Clock,
    max_age_s: f64,
) -> std::io::Result<std::thread::JoinHandle<()>> {
    let span = tracing::Span::current();
    std::thread::Builder::new()
        .name("visnav-vo".into())
        .spawn(move || {
            let _span = span.enter();
            info!("frame sequence (visual odometry, DTM navigation) on every frame");
            loop {
                let f = match slot.take(Duration::from_millis(200)) {
                    Take::Item(f) => f,
                    Take::Timeout => continue,
                    Take::Closed => return,
                };
                let (Some(t_c), Some(now)) =
                    (capture_time_us(&clock, &f), clock.autopilot_now_us())
                else {
                    continue;
                };
                if (now as f64 - t_c as f64) * 1e-6 > max_age_s {
                    continue;
                }
                let inputs = ctx.inputs(t_c);
                let r = ctx.step(f.image, f.seq, inputs);
                if ctx.results.blocking_send(r).is_err() {
                    return;
                }
            }
        })
}
