//! The fix priors the frame path reads ([`SharedPriors`]): the navigation task's output history
//! and the autopilot's attitudes, shared with the fix workers and the odometry thread.

use std::sync::Mutex;

use crate::frames::PriorSource;
use crate::inputs::{self, OutputBook};
use visnav_core::camera::Attitude;
use visnav_core::fix::FixPrior;
use visnav_core::nav::{NavConfig, NavOutput};

/// Output history and autopilot attitudes shared with the fix workers.
pub(crate) struct SharedPriors {
    pub(crate) nav: NavConfig,
    pub(crate) book: Mutex<OutputBook>,
    pub(crate) attitudes: Mutex<std::collections::VecDeque<(u64, Attitude)>>,
    /// After an autopilot reboot restarted the filter: its last solution, re-stamped on the new
    /// boot clock, the fix prior's position until the new filter has an output
    /// (`inputs::reacquisition_prior`).
    pub(crate) reacquire: Mutex<Option<NavOutput>>,
}

impl PriorSource for SharedPriors {
    fn prior_at(&self, t_us: u64) -> FixPrior {
        let out = self
            .book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .nearest(t_us)
            .cloned();
        let reacquire = match out {
            Some(_) => None,
            None => self
                .reacquire
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
        };
        let att = self
            .attitudes
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .min_by_key(|(t, _)| t.abs_diff(t_us))
            .filter(|(t, _)| t.abs_diff(t_us) <= 200_000)
            .map(|(_, a)| *a);
        match reacquire {
            Some(r) => inputs::reacquisition_prior(t_us, &r, att, &self.nav),
            None => inputs::prior_at(t_us, out.as_ref(), att, &self.nav),
        }
    }

    fn pose_at(&self, t_us: u64) -> FixPrior {
        let out = self.book.lock().unwrap_or_else(|e| e.into_inner()).at(t_us);
        inputs::prior_at(t_us, out.as_ref(), None, &self.nav)
    }

    fn body_rotation(&self, t0_us: u64, t1_us: u64) -> Option<(nalgebra::Rotation3<f64>, f64)> {
        self.book
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .body_rotation(t0_us, t1_us)
    }
}
