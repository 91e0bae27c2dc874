//! Feature tracks carried from frame to frame: Shi-Tomasi corners on a spread grid
//! ([`crate::vision::klt::good_features`]), followed into each new frame by the pyramidal
//! Lucas-Kanade tracker with its forward-backward check ([`crate::vision::klt::track_checked`],
//! OpenCV's `calcOpticalFlowPyrLK` semantics), from a caller's prediction of where each one will
//! be (the gyros' rotation and the aircraft's motion over the terrain). Tracks that survive are
//! kept; when fewer than [`TrackingConfig::replenish_below`] remain, or when they have drawn
//! together and cover fewer than [`REPLENISH_COVERAGE_FRACTION`] of the spread-grid cells they
//! covered after the last top-up (a climb or a descent: every track moves towards or away from
//! the image centre, none is lost, and those left crowd the middle until the resection's spread
//! check refuses them), the tracks of over-full cells are thinned to the grid's per-cell limit
//! (the oldest kept) and new corners at least [`TrackingConfig::new_corner_distance_px`] from
//! every live track top them up to [`TrackingConfig::max_corners`] (the usual KLT odometry loop,
//! e.g. Forster et al. 2017's front end without the keyframes).
//!
//! Pixels are the raw (distorted) image's, OpenCV's convention (x right, y down, pixel centres at
//! integer coordinates).

use serde::{Deserialize, Serialize};

use crate::validate::{Problems, Validate};
use crate::vision::GrayImage;
use crate::vision::VisionError;
use crate::vision::klt::{self, FeatureParams, Pyramid, SpreadCounter, SpreadGrid, TrackParams};

/// How features are found and followed (`[vo.tracking]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Most live tracks.
    pub max_corners: usize,
    /// Fewer live tracks than this: detect new corners.
    pub replenish_below: usize,
    /// A new corner keeps this distance from every live track, px.
    pub new_corner_distance_px: f32,
    /// Spread grid of the detector: at most `max_corners / (cols rows)` corners per cell, so one
    /// textured corner of the image cannot take them all.
    pub grid_cols: usize,
    /// Rows of the spread grid (see `grid_cols`).
    pub grid_rows: usize,
    /// Tracker window side, odd, px (`winSize`).
    pub win_size_px: usize,
    /// Top pyramid level (`maxLevel`): the tracker follows motions up to about
    /// `win / 2 x 2^level` pixels (80 px with 21 and 3).
    pub max_level: usize,
    /// Largest forward-backward round-trip error of a kept track, px.
    pub max_fb_error_px: f32,
}

/// Default most tracks: 300 give the resection a consensus in a 30 % overlap strip at a few
/// milliseconds per VGA frame (`visnav bench vo`).
const DEFAULT_MAX_CORNERS: usize = 300;
/// Default replenishment threshold: two thirds of the maximum, so detection (about 1 ms at VGA)
/// runs every few frames, not every frame.
const DEFAULT_REPLENISH_BELOW: usize = 200;
/// Default spacing of new corners: half the tracker's window, so two tracks rarely share texture.
const DEFAULT_NEW_CORNER_DISTANCE_PX: f32 = 10.0;
/// Default spread grid: 8 x 6 cells of 80 px on a VGA frame.
const DEFAULT_GRID: (usize, usize) = (8, 6);

impl Default for TrackingConfig {
    fn default() -> Self {
        let tp = TrackParams::default();
        Self {
            max_corners: DEFAULT_MAX_CORNERS,
            replenish_below: DEFAULT_REPLENISH_BELOW,
            new_corner_distance_px: DEFAULT_NEW_CORNER_DISTANCE_PX,
            grid_cols: DEFAULT_GRID.0,
            grid_rows: DEFAULT_GRID.1,
            win_size_px: tp.win_size_px,
            max_level: tp.max_level,
            max_fb_error_px: tp.max_fb_error_px,
        }
    }
}

impl TrackingConfig {
    /// The tracker's parameters.
    pub fn track_params(&self) -> TrackParams {
        TrackParams {
            win_size_px: self.win_size_px,
            max_level: self.max_level,
            max_fb_error_px: self.max_fb_error_px,
            ..TrackParams::default()
        }
    }

    /// The detector's parameters.
    pub fn feature_params(&self) -> FeatureParams {
        let cells = (self.grid_cols * self.grid_rows).max(1);
        FeatureParams {
            max_corners: self.max_corners,
            spread: Some(SpreadGrid {
                cols: self.grid_cols,
                rows: self.grid_rows,
                max_per_cell: self.max_corners.div_ceil(cells),
            }),
            ..FeatureParams::default()
        }
    }
}

impl Validate for TrackingConfig {
    fn validate(&self, p: &mut Problems) {
        if !(12..=5000).contains(&self.max_corners) {
            p.push(
                "max_corners",
                format!("{} must be in 12..=5000", self.max_corners),
            );
        }
        if self.replenish_below > self.max_corners {
            p.push(
                "replenish_below",
                format!(
                    "{} is above max_corners ({})",
                    self.replenish_below, self.max_corners
                ),
            );
        }
        if !(self.new_corner_distance_px.is_finite() && self.new_corner_distance_px >= 0.0) {
            p.push(
                "new_corner_distance_px",
                format!("{} must be finite and >= 0", self.new_corner_distance_px),
            );
        }
        if !(1..=64).contains(&self.grid_cols) || !(1..=64).contains(&self.grid_rows) {
            p.push(
                "grid_cols",
                format!(
                    "grid {} x {} must be 1..=64 each way",
                    self.grid_cols, self.grid_rows
                ),
            );
        }
        if let Err(e) = self.track_params().validate() {
            p.push("win_size_px", e.to_string());
        }
        if let Err(e) = self.feature_params().validate() {
            p.push("max_corners", e.to_string());
        }
    }
}

/// Below this fraction of the spread-grid cells the tracks covered right after the last top-up,
/// they are topped up whatever their number. Relative to what the last detection achieved (not
/// to the whole grid), so ground without texture in part of the frame (water, a field of one
/// colour) does not start a detection on every frame; 3/4 tops up a 2 Hz climb at 8 m/s about
/// every 60 m of height from 500 m, long before the tracks leave the outer third of the frame.
pub const REPLENISH_COVERAGE_FRACTION: f64 = 0.75;

/// Features of the previous frame and its pyramid.
pub struct Tracker {
    cfg: TrackingConfig,
    prev: Option<(Pyramid, Vec<[f32; 2]>)>,
    /// Spread-grid cells covered by the tracks right after the last top-up.
    covered_after_top_up: usize,
}

/// A feature seen in the previous frame and found in the new one (raw pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawTrack {
    /// Position in the previous frame, pixels as captured (distorted), `[x, y]`.
    pub prev_px: [f32; 2],
    /// Position in the new frame, pixels as captured (distorted), `[x, y]`.
    pub next_px: [f32; 2],
}

impl Tracker {
    /// A tracker without a previous frame.
    pub fn new(cfg: TrackingConfig) -> Self {
        Self {
            cfg,
            prev: None,
            covered_after_top_up: 0,
        }
    }

    /// Forget the previous frame (the next one starts a new sequence).
    pub fn reset(&mut self) {
        self.prev = None;
        self.covered_after_top_up = 0;
    }

    /// The live features of the previous frame (raw pixels).
    pub fn live(&self) -> &[[f32; 2]] {
        self.prev.as_ref().map_or(&[], |(_, p)| p.as_slice())
    }

    /// The pyramid of a new frame (the first, costly half of [`Tracker::advance`]).
    pub fn pyramid(&self, image: GrayImage) -> Result<Pyramid, VisionError> {
        Pyramid::from_image(image, self.cfg.max_level, self.cfg.win_size_px)
    }

    /// [`Tracker::track`] then [`Tracker::top_up`].
    pub fn advance(
        &mut self,
        next: Pyramid,
        predict: impl Fn([f32; 2]) -> [f32; 2],
    ) -> Result<Option<Vec<RawTrack>>, VisionError> {
        let pairs = self.track(next, predict)?;
        self.top_up()?;
        Ok(pairs)
    }

    /// Follows the live features into `next` from the guesses `predict` gives for them, makes
    /// `next` the previous frame with the surviving features and returns the pairs. Without a
    /// previous frame: `next` becomes it, without features, and `None`.
    pub fn track(
        &mut self,
        next: Pyramid,
        predict: impl Fn([f32; 2]) -> [f32; 2],
    ) -> Result<Option<Vec<RawTrack>>, VisionError> {
        let Some((prev_pyr, live)) = self.prev.take() else {
            self.prev = Some((next, Vec::new()));
            return Ok(None);
        };
        let guesses: Vec<[f32; 2]> = live.iter().map(|p| predict(*p)).collect();
        let tracks = klt::track_checked(
            &prev_pyr,
            &next,
            &live,
            Some(&guesses),
            &self.cfg.track_params(),
        )?;
        let pairs: Vec<RawTrack> = live
            .iter()
            .zip(&tracks)
            .filter(|(_, t)| t.is_tracked())
            .map(|(a, t)| RawTrack {
                prev_px: *a,
                next_px: t.point,
            })
            .collect();
        let kept = pairs.iter().map(|p| p.next_px).collect();
        self.prev = Some((next, kept));
        Ok(Some(pairs))
    }

    /// Detects new corners in the previous frame when fewer than `replenish_below` tracks live
    /// or they have drawn together (the module doc); returns whether it did.
    pub fn top_up(&mut self) -> Result<bool, VisionError> {
        let Some((pyr, mut live)) = self.prev.take() else {
            return Ok(false);
        };
        let low = live.len() < self.cfg.replenish_below;
        let gathered = (self.covered(&pyr, &live) as f64)
            < REPLENISH_COVERAGE_FRACTION * self.covered_after_top_up as f64;
        let run = low || gathered;
        let out = if run {
            self.thin(&pyr, &mut live);
            let r = self.replenish(&pyr, &mut live);
            self.covered_after_top_up = self.covered(&pyr, &live);
            r
        } else {
            Ok(())
        };
        self.prev = Some((pyr, live));
        out.map(|()| run)
    }

    /// The detector's spread grid over `pyr`'s frame, empty (`None`: no grid configured).
    fn spread(&self, pyr: &Pyramid) -> Option<SpreadCounter> {
        let grid = self.cfg.feature_params().spread?;
        let l0 = pyr.levels().first()?;
        Some(SpreadCounter::new(
            grid,
            l0.image().width().max(1),
            l0.image().height().max(1),
        ))
    }

    /// Spread-grid cells holding at least one of `pts`.
    fn covered(&self, pyr: &Pyramid, pts: &[[f32; 2]]) -> usize {
        self.spread(pyr).map_or(0, |mut s| {
            pts.iter().for_each(|p| s.add(*p));
            s.covered()
        })
    }

    /// At most the detector's per-cell limit of tracks per cell, the oldest (first) kept.
    fn thin(&self, pyr: &Pyramid, pts: &mut Vec<[f32; 2]>) {
        if let Some(mut s) = self.spread(pyr) {
            pts.retain(|p| {
                let keep = !s.is_full(*p);
                if keep {
                    s.add(*p);
                }
                keep
            });
        }
    }

    /// Corners of `pyr` at least `new_corner_distance_px` from every live track, added to them
    /// up to `max_corners`.
    fn replenish(&self, pyr: &Pyramid, live: &mut Vec<[f32; 2]>) -> Result<(), VisionError> {
        let fresh = pyr.good_features(&self.cfg.feature_params())?;
        let d2 = self.cfg.new_corner_distance_px.powi(2);
        let existing = live.clone();
        for c in fresh {
            if live.len() >= self.cfg.max_corners {
                break;
            }
            let far = existing
                .iter()
                .all(|p| (p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) >= d2);
            if far {
                live.push(c);
            }
        }
        Ok(())
    }
}
