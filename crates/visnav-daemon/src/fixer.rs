//! The vision fix as the daemon's frame path sees it: the engine behind a trait
//! ([`FrameFixer`]), with the odometer and the DTM navigator over the same camera and terrain.

use visnav_core::dtm_nav::{DtmNavConfig, DtmNavigator};
use visnav_core::fix::{FixPrior, FixReport};
use visnav_core::vision::GrayImage;

/// The vision fix as the daemon sees it: one frame plus a prior to a report. Called on a fix
/// worker thread (blocking is fine); must not panic (a panic is caught and counted as a
/// rejection).
pub trait FrameFixer: Send + Sync + 'static {
    /// The fix of `image` with `prior` (accepted or refused with its reason).
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport;

    /// Visual odometry with this engine's camera and terrain (`[vo]`); `None`: not available.
    fn odometer(&self, _cfg: &visnav_core::vo::VoConfig) -> Option<visnav_core::vo::Odometer> {
        None
    }

    /// The DTM navigator with this engine's camera and terrain model (`[dtm_nav]`); `None`: not
    /// available.
    fn dtm_navigator(&self, _cfg: &DtmNavConfig) -> Option<DtmNavigator> {
        None
    }

    /// A tiled map's paging counters now (`crate::paging`); `None`: the map is one file.
    fn paging(&self) -> Option<visnav_io::map::paged::PagingStats> {
        None
    }
}
