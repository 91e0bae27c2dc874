//! Paging a tiled map in flight: the frame path's fixer over a [`PagedMap`] asks, before each
//! fix, for the tiles the frame's prior can touch and for the ground ahead, and never waits for
//! them (`visnav_io::map::paged` loads in the background; what a fix misses is counted there).
//!
//! What is asked, most needed first:
//! 1. the prior's footprint grown by its uncertainty: the prior position +- (3 sigma + the
//!    footprint's radius, from the altitude above the map's terrain and the lens's diagonal field
//!    of view, doubled for tilt and heading error);
//! 2. the same square carried along the velocity (from the last two priors) [`LOOKAHEAD_S`]
//!    ahead: the tiles the next frames need are loaded while this one is fixed;
//! 3. the same [`PREFETCH_S`] ahead, loaded only into room the budget has (prefetch);
//! 4. without a position prior (relocalisation): the last position a prior gave, grown by
//!    [`RELOC_SPEED_BOUND_M_S`] for every second since, so the search widens with the time lost
//!    and stays near where the aircraft can be.

use std::sync::{Arc, Mutex};

use visnav_core::dtm_nav::{DtmNavConfig, DtmNavigator};
use visnav_core::fix::{FixEngine, FixPrior, FixReport, Reference};
use visnav_core::vision::GrayImage;
use visnav_io::map::paged::PagedMap;

use crate::fixer::FrameFixer;

/// Seconds ahead along the velocity whose ground is needed (kept over any other tile): at
/// 25-60 m/s that is 0.4-1.8 km, and a tile (a few MB) loads in tens of milliseconds.
pub const LOOKAHEAD_S: [f64; 2] = [15.0, 30.0];

/// Seconds further ahead whose ground is loaded into what the memory budget has left (never
/// pushing out a needed tile): the budget fills ahead of the aircraft early in the flight and
/// stays full, rather than growing over the route, and a slow disk has minutes of warning.
pub const PREFETCH_S: [f64; 3] = [60.0, 120.0, 240.0];

/// The fastest the aircraft may move while no prior bounds it, m/s (a fixed-wing drone's dash):
/// how fast the relocalisation area grows.
pub const RELOC_SPEED_BOUND_M_S: f64 = 60.0;

/// Footprint radius over altitude above ground beyond the lens's own (tilt and heading error
/// move and turn the footprint): the radius is doubled.
const FOOTPRINT_MARGIN: f64 = 2.0;

/// Largest tangent of half the diagonal field of view counted (70 deg): a fisheye's footprint
/// beyond it is ground the fix's rectification does not use.
const MAX_TAN_HALF_DIAG: f64 = 2.75;

/// Longest gap between two priors that still gives a velocity, microseconds: older positions say
/// little about where the aircraft goes now.
const MAX_VELOCITY_GAP_US: u64 = 10_000_000;

/// Paging summaries in the log at most this often, capture-time microseconds.
const LOG_EVERY_US: u64 = 60_000_000;

/// Where the aircraft was when a prior last gave a position.
#[derive(Clone, Copy, Debug)]
struct Track {
    t_us: u64,
    xy_m: [f64; 2],
    /// Map-grid velocity from the two latest positions, m/s.
    v_m_s: Option<[f64; 2]>,
    /// The footprint radius then, m.
    radius_m: f64,
}

/// The fix engine over a paged map, as the daemon's frame path sees it (module doc).
pub struct PagedFixer {
    engine: FixEngine,
    map: Arc<PagedMap>,
    state: Mutex<PagerState>,
}

#[derive(Default)]
struct PagerState {
    track: Option<Track>,
    last_log_us: u64,
}

impl PagedFixer {
    /// The fixer of `engine`, whose reference is `map`.
    pub fn new(engine: FixEngine, map: Arc<PagedMap>) -> Self {
        Self {
            engine,
            map,
            state: Mutex::new(PagerState::default()),
        }
    }

    /// The paged map.
    pub fn map(&self) -> &Arc<PagedMap> {
        &self.map
    }

    /// The rectangles to ask for with `prior` (module doc), most needed first; updates the track.
    pub fn wanted(&self, prior: &FixPrior) -> Vec<[f64; 4]> {
        let mut st = self
            .state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let t = prior.t_capture_us;
        let Some(p) = &prior.position else {
            // Relocalisation: around the last known position, wider with every second lost.
            return st.track.map_or_else(
                || vec![self.map.bounds_m()],
                |tr| {
                    let lost_s = t.saturating_sub(tr.t_us) as f64 * 1e-6;
                    let r = tr.radius_m + RELOC_SPEED_BOUND_M_S * lost_s;
                    vec![square(tr.xy_m, r)]
                },
            );
        };
        let Ok(xy) = self.map.crs().from_geodetic(p.lat_deg, p.lon_deg) else {
            return Vec::new();
        };
        let xy_m = [xy.0, xy.1];
        let (lo, hi) = self.map.dem().height_range_m();
        let agl_m = (p.alt_amsl_m - 0.5 * (lo + hi)).max(0.0);
        // The tangent of half the lens's diagonal field of view.
        let k = &self.engine.camera().intrinsics;
        let tan_half_diag = (0.5 * f64::from(k.width_px) / k.fx_px)
            .hypot(0.5 * f64::from(k.height_px) / k.fy_px)
            .min(MAX_TAN_HALF_DIAG);
        let footprint_m = FOOTPRINT_MARGIN * agl_m * tan_half_diag;
        let radius_m = 3.0 * p.sigma_h_m.max(0.0) + footprint_m;
        let v_m_s = st.track.and_then(|tr| {
            let dt_us = t
                .checked_sub(tr.t_us)
                .filter(|d| (1..=MAX_VELOCITY_GAP_US).contains(d))?;
            let dt_s = dt_us as f64 * 1e-6;
            Some([(xy_m[0] - tr.xy_m[0]) / dt_s, (xy_m[1] - tr.xy_m[1]) / dt_s])
        });
        let mut rects = vec![square(xy_m, radius_m)];
        if let Some(v) = v_m_s.or(st.track.and_then(|tr| tr.v_m_s)) {
            for s in LOOKAHEAD_S.iter().chain(&PREFETCH_S) {
                rects.push(square([xy_m[0] + v[0] * s, xy_m[1] + v[1] * s], radius_m));
            }
        }
        st.track = Some(Track {
            t_us: t,
            xy_m,
            v_m_s: v_m_s.or(st.track.and_then(|tr| tr.v_m_s)),
            radius_m,
        });
        if t.saturating_sub(st.last_log_us) >= LOG_EVERY_US {
            st.last_log_us = t;
            log_stats(&self.map, "tiled map paging");
        }
        rects.retain(|r| r.iter().all(|v| v.is_finite()));
        rects
    }
}

/// One summary line of the map's paging counters.
fn log_stats(map: &PagedMap, what: &str) {
    let s = map.stats();
    tracing::info!(
        loads = s.loads,
        evictions = s.evictions,
        misses = s.misses,
        late = s.late,
        late_frames = s.late_frames,
        load_errors = s.load_errors,
        over_budget = s.over_budget,
        resident_tiles = s.resident_tiles,
        resident_mb = s.resident_bytes as f64 / 1e6,
        "{what}"
    );
}

impl Drop for PagedFixer {
    fn drop(&mut self) {
        // The whole run's counts, however short the run (the periodic line comes once a minute).
        log_stats(&self.map, "tiled map paging at the end");
    }
}

/// The square of half-side `r` around `c`.
fn square(c: [f64; 2], r: f64) -> [f64; 4] {
    [c[0] - r, c[1] - r, c[0] + r, c[1] + r]
}

impl FrameFixer for PagedFixer {
    fn fix(&self, image: &GrayImage, prior: &FixPrior) -> FixReport {
        let rects = self.wanted(prior);
        // The footprint and the ground just ahead are needed; the rest is prefetch.
        self.map.request(&rects, 1 + LOOKAHEAD_S.len());
        self.engine.fix(image, prior)
    }

    fn odometer(&self, cfg: &visnav_core::vo::VoConfig) -> Option<visnav_core::vo::Odometer> {
        FrameFixer::odometer(&self.engine, cfg)
    }

    fn dtm_navigator(&self, cfg: &DtmNavConfig) -> Option<DtmNavigator> {
        FrameFixer::dtm_navigator(&self.engine, cfg)
    }

    fn paging(&self) -> Option<visnav_io::map::paged::PagingStats> {
        Some(self.map.stats())
    }
}
