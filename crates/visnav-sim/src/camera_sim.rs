//! The simulated camera as a frame source: renders the camera-year orthophoto (never the map's
//! image; `sitl::render` module doc) at the vehicle's TRUE pose, at a fixed rate, and hands the
//! frames to the daemon like a real camera would, stamped with the autopilot boot time of the
//! truth sample used (the capture time a hardware trigger would log).
//!
//! Truth comes from a [`TruthFeed`]: the built-in simulator's trajectory (closed loop,
//! `sitl::closed_loop`) or a real SITL's own state (ArduPilot SIMSTATE, PX4 SIM_STATE). The feed
//! also scripts camera faults (`sitl::faults`): a stall delivers nothing, a freeze the last image
//! again with a new stamp, a corrupt frame is torn ([`tear`]).
//!
//! Geometry: the truth's latitude/longitude are projected into the scene's CRS, its altitude AMSL
//! is taken as the DEM's vertical datum (the bundled maps are AMSL), the attitude is relative to
//! true north (`R_ned_body = Rz(yaw) Ry(pitch) Rx(roll)`), and [`RenderPose::from_body`] adds the
//! camera mount and the grid convergence.

use std::io::Write;
use std::sync::Arc;
use std::time::{Duration, Instant};

use nalgebra::Vector3;

use super::autopilot::TruthState;
use super::faults::CameraFault;
use super::render::{RenderPose, Renderer, Scene};
use visnav_core::camera::{Attitude, Mount};
use visnav_core::geo::{Crs, GeoError};
use visnav_core::vision::GrayImage;
use visnav_io::frames::{CaptureTime, Frame, FrameError, FrameSource};

/// The latest vehicle truth with its autopilot boot time, µs.
pub trait TruthFeed: Send + Sync {
    /// `None` until the first truth sample is known (the camera waits).
    fn latest(&self) -> Option<(u64, TruthState)>;
    /// True when no more truth will come (the camera ends its stream).
    fn ended(&self) -> bool {
        false
    }
    /// A scripted camera fault now. Default: none.
    fn camera_fault(&self) -> CameraFault {
        CameraFault::None
    }
}

/// What the simulated camera renders and how often.
pub struct SimCameraSpec {
    /// The camera-year scene (orthophoto + DEM).
    pub scene: Arc<Scene>,
    /// Camera model and photometric effects.
    pub renderer: Arc<Renderer>,
    /// CRS of the scene's orthophoto and DEM.
    pub crs: Crs,
    /// Camera mount on the body.
    pub mount: Mount,
    /// Frame rate, Hz.
    pub rate_hz: f64,
    /// Stop after this many frames (`None`: run until the truth feed ends).
    pub max_frames: Option<u64>,
    /// Lock-step (the caller paces on the simulated clock): no pacing and no waiting here; the
    /// frame is the latest truth sample's.
    pub lockstep: bool,
}

/// A [`FrameSource`] rendering the scene at the truth pose (see the module doc).
pub struct SimCamera {
    spec: SimCameraSpec,
    feed: Arc<dyn TruthFeed>,
    seq: u64,
    next_at: Option<Instant>,
    t0_us: Option<u64>,
    last_t_us: Option<u64>,
    /// The last image delivered (what a frozen camera repeats).
    last_image: Option<GrayImage>,
    /// Where each delivered frame's truth goes ([`SimCamera::with_truth_log`]).
    truth_log: Option<Box<dyn std::io::Write + Send>>,
}

impl SimCamera {
    /// A camera rendering `spec` at the poses `feed` gives; no frame taken yet.
    pub fn new(spec: SimCameraSpec, feed: Arc<dyn TruthFeed>) -> Self {
        Self {
            spec,
            feed,
            seq: 0,
            next_at: None,
            t0_us: None,
            last_t_us: None,
            last_image: None,
            truth_log: None,
        }
    }

    /// Also write the truth of every frame delivered, one JSON line each: `seq`, `t_capture_us`
    /// (autopilot boot), `lat_deg`, `lon_deg`, `alt_amsl_m`, `vel_ned_m_s`, `rpy_rad` (the body's;
    /// the camera is on its mount), flushed per frame. What `sitl/vo_check.py` scores the visual
    /// odometry log against. A write error stops the log with a message, not the camera.
    pub fn with_truth_log(mut self, out: Box<dyn std::io::Write + Send>) -> Self {
        self.truth_log = Some(out);
        self
    }

    fn log_truth(&mut self, seq: u64, t_us: u64, s: &TruthState) {
        let Some(out) = self.truth_log.as_mut() else {
            return;
        };
        let line = truth_line(seq, t_us, s);
        if let Err(e) = writeln!(out, "{line}").and_then(|()| out.flush()) {
            tracing::warn!("simulated camera: truth log: {e}; logging stopped");
            self.truth_log = None;
        }
    }

    /// The render pose of a truth state (body position in the scene grid, camera via the mount).
    pub fn pose_of(&self, s: &TruthState) -> Result<RenderPose, TruthPoseError> {
        pose_of(&self.spec.crs, &self.spec.mount, s)
    }

    /// Lock-step: the latest truth sample, rendered (an error when it is not newer than the last
    /// frame's: the caller skips that tick).
    fn lockstep_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        if self.feed.ended() {
            return Ok(None);
        }
        match self.feed.latest() {
            // A new sample (the stamp differs: an autopilot reboot restarts it from 0).
            Some((t, s)) if self.last_t_us != Some(t) => self.render_frame(t, &s),
            _ => Err(FrameError::NotReady),
        }
    }

    /// The frame at truth state `state` (time `t_us`), with the feed's camera fault applied
    /// (`NotReady` while the camera stalls).
    fn render_frame(&mut self, t_us: u64, state: &TruthState) -> Result<Option<Frame>, FrameError> {
        let fault = self.feed.camera_fault();
        let image = match (fault, &self.last_image) {
            (CameraFault::Stall, _) => return Err(FrameError::NotReady),
            (CameraFault::Freeze, Some(last)) => last.clone(),
            _ => {
                let mut image = self.render(state)?;
                if fault == CameraFault::Corrupt {
                    tear(&mut image, self.seq);
                }
                image
            }
        };
        self.last_image = Some(image.clone());
        let t0 = *self.t0_us.get_or_insert(t_us);
        self.last_t_us = Some(t_us);
        self.log_truth(self.seq, t_us, state);
        let frame = Frame {
            image,
            t_capture: CaptureTime::AutopilotBootUs(t_us),
            t_rel_s: t_us.saturating_sub(t0) as f64 * 1e-6,
            seq: self.seq,
        };
        self.seq += 1;
        Ok(Some(frame))
    }

    /// Render the scene at truth state `state`.
    fn render(&self, state: &TruthState) -> Result<GrayImage, FrameError> {
        let pose = self
            .pose_of(state)
            .map_err(|e| FrameError::Config(e.to_string()))?;
        let f = self
            .spec
            .renderer
            .render(&self.spec.scene, &pose, self.seq)
            .map_err(|e| FrameError::Config(format!("simulated camera: {e}")))?;
        GrayImage::new(f.width, f.height, f.grey())
            .map_err(|e| FrameError::Config(format!("simulated camera: {e}")))
    }
}

/// One line of the truth log ([`SimCamera::with_truth_log`], `frames_truth.jsonl`): the frame's
/// sequence number, capture time (autopilot boot, µs) and the body's true state.
pub fn truth_line(seq: u64, t_us: u64, s: &TruthState) -> serde_json::Value {
    serde_json::json!({
        "seq": seq,
        "t_capture_us": t_us,
        "lat_deg": s.lat_deg,
        "lon_deg": s.lon_deg,
        "alt_amsl_m": s.alt_amsl_m,
        "vel_ned_m_s": s.vel_ned_m_s,
        "rpy_rad": s.rpy_rad,
    })
}

/// Tear a frame as a corrupt transfer that still decodes does: from a row chosen by `seq`, a
/// band of a fifth of the height is noise and every row below it is shifted sideways by a
/// tenth of the width or more (wrapping). Seeded by `seq`: the same frame is torn the same way.
pub fn tear(image: &mut GrayImage, seq: u64) {
    let (w, h) = (image.width(), image.height());
    let mut rng = visnav_core::rng::Rng::new(seq.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ 0x7ea2);
    let band = (h / 5).max(1);
    let start = rng.below(h.saturating_sub(band).max(1));
    let shift = w / 10 + rng.below((w / 4).max(1));
    let data = image.data_mut();
    for y in start..h {
        let row = &mut data[y * w..(y + 1) * w];
        if y < start + band {
            for v in row.iter_mut() {
                *v = rng.range(0.0, 255.0) as f32;
            }
        } else {
            row.rotate_right(shift % w);
        }
    }
}

/// Why a truth state has no render pose in the scene's CRS.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TruthPoseError {
    /// The latitude and longitude could not be projected into the CRS.
    #[error("truth position: {0}")]
    Position(GeoError),
    /// The CRS's grid convergence could not be had at the position.
    #[error("grid convergence: {0}")]
    Convergence(GeoError),
}

/// The render pose of a truth state in `crs` (see the module doc).
pub fn pose_of(crs: &Crs, mount: &Mount, s: &TruthState) -> Result<RenderPose, TruthPoseError> {
    let (x_m, y_m) = crs
        .from_geodetic(s.lat_deg, s.lon_deg)
        .map_err(TruthPoseError::Position)?;
    let gamma_rad = crs
        .grid_convergence_deg(s.lat_deg, s.lon_deg)
        .map_err(TruthPoseError::Convergence)?
        .to_radians();
    let [r, p, y] = s.rpy_rad;
    let att = Attitude::new(r, p, y);
    Ok(RenderPose::from_body(
        Vector3::new(x_m, y_m, s.alt_amsl_m),
        &att,
        mount,
        gamma_rad,
    ))
}

impl FrameSource for SimCamera {
    fn next_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        if self.spec.max_frames.is_some_and(|n| self.seq >= n) {
            return Ok(None);
        }
        if self.spec.lockstep {
            return self.lockstep_frame();
        }
        loop {
            match self.realtime_frame() {
                // A stalled camera: nothing at this period; try at the next one.
                Err(FrameError::NotReady) => continue,
                r => return r,
            }
        }
    }

    fn describe(&self) -> String {
        let c = self.spec.renderer.camera();
        format!(
            "simulated camera: {}x{} px at {} Hz, rendered at the true pose",
            c.width_px(),
            c.height_px(),
            self.spec.rate_hz
        )
    }

    fn rate_hz(&self) -> Option<f64> {
        Some(self.spec.rate_hz)
    }
}

impl SimCamera {
    /// Real time: the next period's frame (`NotReady` while the camera stalls).
    fn realtime_frame(&mut self) -> Result<Option<Frame>, FrameError> {
        let period = Duration::from_secs_f64(1.0 / self.spec.rate_hz.max(1e-3));
        // Pace: one frame per period of the companion's clock (the truth feed is real time).
        if let Some(at) = self.next_at {
            let now = Instant::now();
            if at > now {
                std::thread::sleep(at - now);
            }
        }
        // Wait for a truth sample newer than the last frame's: as long as it takes for the
        // first one (the feed may start the camera late), at most 10 s once it has run (a
        // stalled feed is an error).
        let wait_from = Instant::now();
        let (t_us, state) = loop {
            let latest = self.feed.latest();
            match latest {
                Some((t, s)) if self.last_t_us != Some(t) => break (t, s),
                _ => {}
            }
            if self.feed.ended() {
                return Ok(None);
            }
            let started = self.last_t_us.is_some() || latest.is_some();
            if started && wait_from.elapsed() > Duration::from_secs(10) {
                return Err(FrameError::Config(
                    "simulated camera: no new truth sample for 10 s".into(),
                ));
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        self.next_at = Some(self.next_at.map_or(Instant::now(), |a| a) + period);
        let r = self.render_frame(t_us, &state);
        if matches!(r, Err(FrameError::NotReady)) {
            self.last_t_us = Some(t_us);
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::{ColourMode, RenderSpec, vga_camera};
    use std::path::Path;
    use std::sync::Mutex;
    use visnav_core::geo::dem::Dem;
    use visnav_io::geo::geotiff::load_geotiff;

    struct Fixed(Mutex<u64>, TruthState);
    impl TruthFeed for Fixed {
        fn latest(&self) -> Option<(u64, TruthState)> {
            let mut t = self.0.lock().ok()?;
            *t += 10_000;
            Some((*t, self.1))
        }
    }

    #[test]
    fn renders_the_scene_below_the_truth_with_boot_time_stamps() {
        let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("sitl/maps");
        let raster = load_geotiff(&dir.join("naip_nd_2014.tif"), None).unwrap();
        let crs = raster.crs();
        let b = raster.bounds();
        let (cx, cy) = ((b.min_x_m + b.max_x_m) / 2.0, (b.min_y_m + b.max_y_m) / 2.0);
        let (lat, lon) = crs.to_geodetic(cx, cy).unwrap();
        let scene = Scene::new(&raster, Dem::flat(580.0).unwrap(), ColourMode::Grey).unwrap();
        let renderer = Renderer::new(vga_camera().unwrap(), RenderSpec::default()).unwrap();
        let truth = TruthState {
            lat_deg: lat,
            lon_deg: lon,
            alt_amsl_m: 1180.0,
            vel_ned_m_s: [0.0; 3],
            rpy_rad: [0.0, 0.0, 0.3],
            gyro_body_rad_s: [0.0; 3],
            accel_body_m_s2: [0.0; 3],
        };
        let mut cam = SimCamera::new(
            SimCameraSpec {
                scene: Arc::new(scene),
                renderer: Arc::new(renderer),
                crs,
                mount: Mount::nadir(),
                rate_hz: 50.0,
                max_frames: Some(2),
                lockstep: false,
            },
            Arc::new(Fixed(Mutex::new(0), truth)),
        );
        let pose = cam.pose_of(&truth).unwrap();
        assert!((pose.centre_map_m.x - cx).abs() < 1e-3 && (pose.centre_map_m.y - cy).abs() < 1e-3);
        let f0 = cam.next_frame().unwrap().unwrap();
        let f1 = cam.next_frame().unwrap().unwrap();
        assert!(cam.next_frame().unwrap().is_none());
        let (CaptureTime::AutopilotBootUs(t0), CaptureTime::AutopilotBootUs(t1)) =
            (f0.t_capture, f1.t_capture)
        else {
            panic!("frames must carry autopilot boot time");
        };
        assert!(t1 > t0);
        assert_eq!((f0.seq, f1.seq), (0, 1));
        assert_eq!((f0.image.width(), f0.image.height()), (640, 480));
        // 600 m above flat ground over the map centre: the whole frame sees the orthophoto; it
        // must have texture (not the fill value).
        let px = f0.image.data();
        let mean = px.iter().map(|&v| f64::from(v)).sum::<f64>() / px.len() as f64;
        let var = px
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / px.len() as f64;
        assert!(
            mean > 20.0 && var.sqrt() > 5.0,
            "mean {mean} sd {}",
            var.sqrt()
        );
    }
}
