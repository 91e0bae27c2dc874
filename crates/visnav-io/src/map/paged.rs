//! A tiled map in flight: the fix engine's [`Reference`] over the tiles of a tiled map that are
//! in memory now, with a loader thread that brings in the tiles asked for and a memory budget
//! that drops the least recently used.
//!
//! The frame path never waits on a load: [`Reference::select`] and [`Reference::level_window`]
//! answer from the tiles held at that moment (a short lock, no I/O); a tile the index has under
//! the rectangle but memory does not is a **miss**: counted, and queued for loading. The daemon
//! asks ahead with [`PagedMap::request`] (the prior's footprint and its uncertainty, then the
//! ground ahead along the velocity): the loader takes the queue front first, and each request
//! replaces the queue, so the newest need wins. Tiles of the latest request are never evicted
//! for others; when even they do not fit, the loader stops short and counts it.
//!
//! A tile's memory is its file (memory-mapped and read whole when opened, as its checksum is
//! verified) and, for a map built on a DEM, its heights (`tiled::TileHeights`, decoded): the
//! budget counts both. The terrain lent to the fix ([`Reference::dem`]) is then the heights of
//! the tiles in memory under the latest request, joined on the DEM's grid
//! (`super::terrain_mosaic`), so no DEM is read whole; `[map] dem` given overrides it. The tiles
//! share one level-0 pixel grid (each tile's bounds are moved out to it when built), so level
//! windows are assembled by whole-pixel offsets.

use std::collections::{HashMap, HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;

use visnav_core::fix::reference::{
    DemRef, HeightErrors, LevelWindow, MapImageBuf, RefFeature, RefSelection, Reference,
};
use visnav_core::geo::Crs;
use visnav_core::geo::dem::Dem;
use visnav_core::vision::FeatureSpec;

use super::MapSelection;
use super::reference::MapReferenceError;
use super::terrain_mosaic;
use super::tiled::{TileHeights, TiledIndex};
use super::{HeightInfo, MapError, MapHeader, ReferenceMap};

/// Largest level window assembled for one call, pixels: 64 M (a 8 000 px square; a blind
/// relocalisation over a large map asks for the whole map and is given the loaded tiles near it
/// only if they fit).
pub const MAX_WINDOW_PX: usize = 64 << 20;

/// Paging counters since the map was opened.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct PagingStats {
    /// Tiles loaded.
    pub loads: u64,
    /// Tiles dropped for the budget.
    pub evictions: u64,
    /// Tiles a select or level window needed that were not in memory (the frame went on without
    /// them; they were queued).
    pub misses: u64,
    /// Tiles that could not be loaded (the error is logged once per tile).
    pub load_errors: u64,
    /// Needed tiles the budget could not take (a request's needed tiles are more than the
    /// budget).
    pub over_budget: u64,
    /// Tiles in memory now.
    pub resident_tiles: usize,
    /// Their bytes.
    pub resident_bytes: u64,
    /// Tiles queued for loading now.
    pub queued: usize,
    /// Tiles of a frame's own footprint (the first rectangle of a request) that were not in
    /// memory when its request came: the look-ahead had not brought them, so the frame met them
    /// missing (in the background mode) or waited for them (inline).
    pub late: u64,
    /// Requests (frames) with at least one such tile.
    pub late_frames: u64,
}

/// How a paged map loads its tiles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LoadMode {
    /// A loader thread, in the background: the frame path never waits (flight).
    Background,
    /// In the caller's thread at each request, and a missed tile at once (the lock-step
    /// simulator: the same tiles at the same frames whatever the machine's speed).
    Inline,
}

/// One tile in memory.
struct Held {
    map: Arc<ReferenceMap>,
    /// Its heights (a map built on a DEM).
    heights: Option<Arc<Dem>>,
    bytes: u64,
    last_used: u64,
}

/// What the loader and the readers share.
struct State {
    held: HashMap<usize, Held>,
    queue: VecDeque<usize>,
    /// The needed tiles of the latest request, in its order (the frame's own footprint first):
    /// never evicted for others.
    needed: Vec<usize>,
    /// Every tile of the latest request (needed or ahead): an ahead tile evicts only tiles
    /// outside it.
    wanted: HashSet<usize>,
    /// Tiles whose load failed: not tried again.
    failed: HashSet<usize>,
    tick: u64,
    stats: PagingStats,
    /// The loader is opening this tile now.
    loading: Option<usize>,
    stop: bool,
}

struct Shared {
    state: Mutex<State>,
    wake: Condvar,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock leaves counters at worst; the tiles stay usable.
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// A tiled map opened for flight (module doc).
pub struct PagedMap {
    dir: PathBuf,
    index: TiledIndex,
    /// The tiles by grid square (`(col, row)` -> position in the index).
    by_square: HashMap<(i64, i64), usize>,
    /// The first tile's header: what every tile shares (CRS, detector, levels, heights).
    header: MapHeader,
    terrain: Terrain,
    budget_bytes: u64,
    shared: Arc<Shared>,
    loader: Option<JoinHandle<()>>,
    mode: LoadMode,
    /// Each tile's file, the checksum the index records and its size (the budget counts it).
    files: Arc<Vec<TileFile>>,
}

impl PagedMap {
    /// Opens the tiled map in the folder `dir` (or its `index.json`) with a memory budget of
    /// `memory_mb` MB for tiles, and starts its loader. The terrain: `dem` when given, else the
    /// tiles' constant ground height, or the heights its tiles carry (a map built on a DEM; one
    /// whose tiles carry none needs the DEM given).
    pub fn open(dir: &Path, memory_mb: u64, dem: Option<Dem>) -> Result<Self, MapReferenceError> {
        Self::open_with(dir, memory_mb, dem, LoadMode::Background)
    }

    /// [`Self::open`] with the load mode given.
    pub fn open_with(
        dir: &Path,
        memory_mb: u64,
        dem: Option<Dem>,
        mode: LoadMode,
    ) -> Result<Self, MapReferenceError> {
        let index = TiledIndex::read(dir)?;
        let dir = if dir.is_dir() {
            dir.to_path_buf()
        } else {
            dir.parent()
                .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
        };
        let Some(first) = index.tiles.first() else {
            return Err(MapError::Input {
                path: dir.clone(),
                reason: "the tiled map has no tile".into(),
            }
            .into());
        };
        let header = ReferenceMap::open(&dir.join(&first.file))?.header().clone();
        let terrain = Terrain::of(dem, &header, &index, &dir)?;
        let shared = Arc::new(Shared {
            state: Mutex::new(State {
                held: HashMap::new(),
                queue: VecDeque::new(),
                needed: Vec::new(),
                wanted: HashSet::new(),
                failed: HashSet::new(),
                tick: 0,
                stats: PagingStats::default(),
                loading: None,
                stop: false,
            }),
            wake: Condvar::new(),
        });
        let budget_bytes = memory_mb.saturating_mul(1 << 20);
        let files: Arc<Vec<TileFile>> = Arc::new(
            index
                .tiles
                .iter()
                .map(|t| {
                    // The tile's heights are loaded (and counted) when the terrain comes from
                    // the tiles, not when `[map] dem` gives it.
                    let heights = match (&terrain, &t.heights) {
                        (Terrain::Tiles { .. }, Some(h)) => Some((dir.join(&h.file), h.clone())),
                        _ => None,
                    };
                    TileFile {
                        path: dir.join(&t.file),
                        crc32: t.crc32,
                        bytes: t
                            .file_bytes
                            .saturating_add(heights.as_ref().map_or(0, |(_, h)| h.memory_bytes())),
                        heights,
                        crs: index.crs,
                    }
                })
                .collect(),
        );
        let loader = match mode {
            LoadMode::Inline => None,
            LoadMode::Background => {
                let (shared, files) = (Arc::clone(&shared), Arc::clone(&files));
                Some(
                    std::thread::Builder::new()
                        .name("visnav-tiles".into())
                        .spawn(move || load_loop(&shared, &files, budget_bytes))
                        .map_err(|e| MapError::Io {
                            path: dir.clone(),
                            what: "cannot start the tile loader",
                            cause: e,
                        })?,
                )
            }
        };
        let by_square = index
            .tiles
            .iter()
            .enumerate()
            .map(|(k, t)| ((t.col, t.row), k))
            .collect();
        Ok(Self {
            dir,
            index,
            by_square,
            header,
            terrain,
            budget_bytes,
            shared,
            loader,
            mode,
            files,
        })
    }

    /// The map's index.
    pub fn index(&self) -> &TiledIndex {
        &self.index
    }

    /// The map's folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The memory budget for tiles, bytes.
    pub fn budget_bytes(&self) -> u64 {
        self.budget_bytes
    }

    /// The paging counters now.
    pub fn stats(&self) -> PagingStats {
        let st = self.shared.lock();
        PagingStats {
            resident_tiles: st.held.len(),
            resident_bytes: st.held.values().map(|h| h.bytes).sum(),
            queued: st.queue.len() + usize::from(st.loading.is_some()),
            ..st.stats
        }
    }

    /// Asks for the tiles under `rects_m` (each `[min_x, min_y, max_x, max_y]`), most needed
    /// first, the frame's own footprint first of all: they are loaded in that order (in the
    /// background, or here in [`LoadMode::Inline`]). The first `needed` rectangles' tiles are
    /// kept over any other tile; the rest (the ground further ahead) are loaded only into room the
    /// budget has or that tiles outside this request free, so the budget fills ahead of the
    /// aircraft without ever pushing out what the frames need. Replaces the previous request's
    /// queue.
    pub fn request(&self, rects_m: &[[f64; 4]], needed: usize) {
        let mut order: Vec<usize> = Vec::new();
        let (mut own, mut pinned) = (0, 0);
        for (i, r) in rects_m.iter().enumerate() {
            for k in self.tiles_under(*r) {
                if !order.contains(&k) {
                    order.push(k);
                }
            }
            if i == 0 {
                own = order.len();
            }
            if i + 1 == needed.min(rects_m.len()) {
                pinned = order.len();
            }
        }
        let mut st = self.shared.lock();
        let late = order[..own]
            .iter()
            .filter(|k| !st.held.contains_key(k) && !st.failed.contains(k))
            .count();
        st.stats.late += late as u64;
        st.stats.late_frames += u64::from(late > 0);
        st.needed = order[..pinned].to_vec();
        st.wanted = order.iter().copied().collect();
        if self.mode == LoadMode::Inline {
            drop(st);
            for k in order {
                self.load_inline(k);
            }
            return;
        }
        st.queue = order
            .into_iter()
            .filter(|k| !st.held.contains_key(k) && !st.failed.contains(k))
            .collect();
        drop(st);
        self.shared.wake.notify_one();
    }

    /// Waits until the loader's queue is empty (tests and start-up; never on the frame path),
    /// at most `timeout`. Whether it emptied.
    pub fn wait_loaded(&self, timeout: std::time::Duration) -> bool {
        let deadline = std::time::Instant::now() + timeout;
        let mut st = self.shared.lock();
        while !(st.queue.is_empty() && st.loading.is_none()) {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return false;
            }
            st = self
                .shared
                .wake
                .wait_timeout(st, left)
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .0;
        }
        true
    }

    /// Loads tile `k` in this thread unless it is held or failed ([`LoadMode::Inline`]).
    fn load_inline(&self, k: usize) {
        let Some(f) = self.files.get(k) else {
            return;
        };
        {
            let mut st = self.shared.lock();
            if st.held.contains_key(&k) || st.failed.contains(&k) {
                return;
            }
            if !make_room(&mut st, k, f.bytes, self.budget_bytes) {
                return;
            }
        }
        let opened = open_tile(f);
        finish_load(&mut self.shared.lock(), k, &f.path, opened);
    }

    /// Indices (into the index's tiles) of the tiles whose bounds overlap `r`.
    fn tiles_under(&self, r: [f64; 4]) -> Vec<usize> {
        let t = self.index.tile_m;
        if !(r.iter().all(|v| v.is_finite()) && r[0] <= r[2] && r[1] <= r[3] && t > 0.0) {
            return Vec::new();
        }
        // Bounds reach a little past their square (moved out to the coarsest pixel grid): look
        // one square further and test the bounds.
        let (c0, c1) = ((r[0] / t).floor() as i64 - 1, (r[2] / t).floor() as i64 + 1); // ok: finite
        let (r0, r1) = ((r[1] / t).floor() as i64 - 1, (r[3] / t).floor() as i64 + 1);
        if (c1 - c0).saturating_mul(r1 - r0) > self.index.tiles.len() as i64 {
            return self
                .index
                .tiles
                .iter()
                .enumerate()
                .filter(|(_, e)| overlaps(e, r))
                .map(|(k, _)| k)
                .collect();
        }
        let mut out = Vec::new();
        for row in (r0..=r1).rev() {
            for col in c0..=c1 {
                if let Some(&k) = self.by_square.get(&(col, row))
                    && overlaps(&self.index.tiles[k], r)
                {
                    out.push(k);
                }
            }
        }
        out
    }

    /// The held tiles under `r`, marked used; the tiles under `r` not held are counted as misses
    /// and queued for loading (or, inline, loaded now) unless queued or failed already.
    fn held_under(&self, r: [f64; 4]) -> Vec<(usize, Arc<ReferenceMap>)> {
        let under = self.tiles_under(r);
        let mut st = self.shared.lock();
        st.tick += 1;
        let tick = st.tick;
        let mut out = Vec::with_capacity(under.len());
        let mut missed = Vec::new();
        for k in under {
            if let Some(h) = st.held.get_mut(&k) {
                h.last_used = tick;
                out.push((k, Arc::clone(&h.map)));
            } else if !st.failed.contains(&k) {
                st.stats.misses += 1;
                if st.loading != Some(k) && !st.queue.contains(&k) {
                    missed.push(k);
                }
            }
        }
        if self.mode == LoadMode::Background {
            st.queue.extend(missed.iter().copied());
        }
        drop(st);
        match self.mode {
            LoadMode::Background if !missed.is_empty() => self.shared.wake.notify_one(),
            LoadMode::Inline => {
                // Missed here: loaded at once, so the same frame gets the same tiles anywhere.
                for k in missed {
                    self.load_inline(k);
                    let st = self.shared.lock();
                    if let Some(h) = st.held.get(&k) {
                        out.push((k, Arc::clone(&h.map)));
                    }
                }
            }
            LoadMode::Background => {}
        }
        out
    }
}

/// Where a paged map's terrain comes from.
enum Terrain {
    /// One terrain for the whole map: `[map] dem`, or the constant height the tiles were built
    /// on.
    Whole(Dem),
    /// The heights the tiles carry, joined over the tiles in memory under the latest request
    /// (cached by that set of tiles); `none` while there is none.
    Tiles {
        joined: Mutex<Option<(Vec<usize>, Arc<Dem>)>>,
        none: Arc<Dem>,
    },
}

impl Terrain {
    /// The terrain of a map with header `header` and index `index` in `dir`: `dem` when given,
    /// else the tiles' constant height, else the heights they carry (at least one must).
    fn of(
        dem: Option<Dem>,
        header: &MapHeader,
        index: &TiledIndex,
        dir: &Path,
    ) -> Result<Self, MapReferenceError> {
        match (dem, &header.height) {
            (Some(d), _) => Ok(Self::Whole(d)),
            (None, HeightInfo::Constant { amsl_m }) => Ok(Self::Whole(
                super::reference::constant_terrain(dir, *amsl_m)?,
            )),
            (None, HeightInfo::Dem { file, .. }) => {
                // The whole map's height range: the union of its tiles' (a tile's header holds
                // its own area's only).
                let (lo, hi) = index
                    .tiles
                    .iter()
                    .filter_map(|t| t.heights.as_ref())
                    .filter(|h| h.min_m.is_finite() && h.max_m.is_finite())
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), h| {
                        (lo.min(h.min_m), hi.max(h.max_m))
                    });
                let refuse = |reason: &str| MapReferenceError::Dem {
                    map: dir.display().to_string(),
                    dem: file.clone(),
                    reason: reason.into(),
                };
                if lo > hi {
                    return Err(refuse(
                        "the tiles carry no heights (built before tiles carried them, or \
                         converted without the DEM at hand): give the DEM ([map] dem) or build \
                         the map again",
                    ));
                }
                let none = terrain_mosaic::none(&index.bounds, index.crs, lo, hi)
                    .ok_or_else(|| refuse("the index's bounds or height range are not usable"))?;
                Ok(Self::Tiles {
                    joined: Mutex::new(None),
                    none: Arc::new(none),
                })
            }
        }
    }
}

impl PagedMap {
    /// The tiles' heights joined over the needed tiles of the latest request that are in
    /// memory, in the request's order (the frame's own footprint first; a tile that would
    /// make the join too large is left out: `terrain_mosaic::join`), every tile in memory
    /// before any request, or `none`. Cached by that list of tiles.
    fn joined_terrain(
        &self,
        joined: &Mutex<Option<(Vec<usize>, Arc<Dem>)>>,
        none: &Arc<Dem>,
    ) -> Arc<Dem> {
        let tiles: Vec<(usize, Arc<Dem>)> = {
            let st = self.shared.lock();
            let mut ks: Vec<usize> = if st.needed.is_empty() {
                let mut all: Vec<usize> = st.held.keys().copied().collect();
                all.sort_unstable();
                all
            } else {
                st.needed.clone()
            };
            ks.dedup();
            ks.into_iter()
                .filter_map(|k| {
                    st.held
                        .get(&k)
                        .and_then(|h| h.heights.clone())
                        .map(|d| (k, d))
                })
                .collect()
        };
        if tiles.is_empty() {
            return Arc::clone(none);
        }
        let key: Vec<usize> = tiles.iter().map(|(k, _)| *k).collect();
        let mut cache = joined
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some((k, d)) = cache.as_ref()
            && *k == key
        {
            return Arc::clone(d);
        }
        let dems: Vec<Arc<Dem>> = tiles.into_iter().map(|(_, d)| d).collect();
        match terrain_mosaic::join(&dems) {
            Some(d) => {
                let d = Arc::new(d);
                *cache = Some((key, Arc::clone(&d)));
                d
            }
            None => Arc::clone(none),
        }
    }
}

impl Drop for PagedMap {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.wake.notify_all();
        if let Some(h) = self.loader.take() {
            let _ = h.join();
        }
    }
}

/// A tile's file as the index records it.
struct TileFile {
    path: PathBuf,
    crc32: u32,
    /// Its size and its heights' decoded size, bytes: what the budget counts before it is
    /// opened.
    bytes: u64,
    /// Its heights file and record, when the map's terrain comes from the tiles.
    heights: Option<(PathBuf, TileHeights)>,
    /// The map's CRS (the heights must be in it).
    crs: Crs,
}

/// Whether tile `e`'s bounds overlap `r`.
fn overlaps(e: &super::tiled::TileEntry, r: [f64; 4]) -> bool {
    let b = &e.bounds;
    b.min_x_m <= r[2] && b.max_x_m >= r[0] && b.min_y_m <= r[3] && b.max_y_m >= r[1]
}

/// The loader: opens queued tiles one at a time (outside the lock), evicting the least recently
/// used unpinned tiles to stay within `budget` bytes.
fn load_loop(shared: &Shared, files: &[TileFile], budget: u64) {
    loop {
        let k = {
            let mut st = shared.lock();
            loop {
                if st.stop {
                    return;
                }
                if let Some(k) = st.queue.pop_front() {
                    if st.held.contains_key(&k) || st.failed.contains(&k) {
                        continue;
                    }
                    let Some(f) = files.get(k) else {
                        continue;
                    };
                    if !make_room(&mut st, k, f.bytes, budget) {
                        continue;
                    }
                    st.loading = Some(k);
                    break k;
                }
                shared.wake.notify_all();
                st = shared
                    .wake
                    .wait(st)
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
            }
        };
        let f = &files[k];
        let opened = open_tile(f);
        let mut st = shared.lock();
        st.loading = None;
        finish_load(&mut st, k, &f.path, opened);
        drop(st);
        shared.wake.notify_all();
    }
}

/// A tile and its heights in memory.
type Opened = (ReferenceMap, Option<Arc<Dem>>);

/// Opens a tile, its checksum verified against the one the index records, and its heights
/// (size and checksum verified the same way) when the terrain comes from the tiles.
fn open_tile(f: &TileFile) -> Result<Opened, MapError> {
    let m = ReferenceMap::open(&f.path)?;
    if m.stored_crc() != f.crc32 {
        return Err(MapError::Format {
            path: f.path.clone(),
            reason: "the tile's checksum is not the one the index records (rebuilt without \
                     gathering?)"
                .into(),
        });
    }
    let Some((path, h)) = &f.heights else {
        return Ok((m, None));
    };
    if !super::tiled::heights_intact(h, path) {
        return Err(MapError::Format {
            path: path.clone(),
            reason: "the tile's heights are not the file the index records (size or checksum)"
                .into(),
        });
    }
    let dem = crate::geo::dem::load_dem(path, None).map_err(|e| MapError::Dem {
        path: path.clone(),
        cause: Box::new(e),
    })?;
    // The grid the index records, in the map's CRS: anything else is not this tile's.
    match &dem {
        Dem::Grid(g)
            if g.crs() == f.crs && (g.width() as u64, g.height() as u64) == (h.width, h.height) => {
        }
        _ => {
            return Err(MapError::Format {
                path: path.clone(),
                reason: "the tile's heights are not the grid the index records (size or CRS)"
                    .into(),
            });
        }
    }
    Ok((m, Some(Arc::new(dem))))
}

/// Holds the opened tile `k`, or marks it failed (logged once).
fn finish_load(st: &mut State, k: usize, path: &Path, opened: Result<Opened, MapError>) {
    match opened {
        Ok((m, heights)) => {
            let grid_bytes = heights.as_deref().map_or(0, |d| match d {
                Dem::Grid(g) => 4 * (g.width() * g.height()) as u64,
                Dem::Flat { .. } => 0,
            });
            let bytes = m.file_len() + grid_bytes;
            let tick = st.tick;
            st.held.insert(
                k,
                Held {
                    map: Arc::new(m),
                    heights,
                    bytes,
                    last_used: tick,
                },
            );
            st.stats.loads += 1;
        }
        Err(e) => {
            tracing::warn!(tile = %path.display(), "tiled map: a tile cannot be loaded: {e}");
            st.failed.insert(k);
            st.stats.load_errors += 1;
        }
    }
}

/// Makes room for tile `k` of `bytes` within `budget`, evicting the least recently used tiles
/// it may: a needed tile (pinned) any tile not pinned, a tile ahead only tiles outside the latest
/// request. Whether it fits; a needed tile that does not is counted (`over_budget`).
fn make_room(st: &mut State, k: usize, bytes: u64, budget: u64) -> bool {
    let needed = st.needed.contains(&k);
    loop {
        let used: u64 = st.held.values().map(|h| h.bytes).sum();
        if used.saturating_add(bytes) <= budget {
            return true;
        }
        let protected = |t: &usize| {
            if needed {
                st.needed.contains(t)
            } else {
                st.wanted.contains(t)
            }
        };
        let victim = st
            .held
            .iter()
            .filter(|(k, _)| !protected(k))
            .min_by_key(|(_, h)| h.last_used)
            .map(|(k, _)| *k);
        match victim {
            Some(v) => {
                st.held.remove(&v);
                st.stats.evictions += 1;
            }
            None => {
                if needed {
                    st.stats.over_budget += 1;
                }
                return false;
            }
        }
    }
}

/// A map selection as the fix engine's.
pub(crate) fn ref_selection(s: MapSelection) -> RefSelection {
    RefSelection {
        features: s
            .features
            .iter()
            .map(|f| RefFeature {
                x_m: f.x_m,
                y_m: f.y_m,
                z_amsl_m: f.z_amsl_m,
                scale_m: f.scale_m,
                laplacian: f.laplacian,
            })
            .collect(),
        descriptors: s.descriptors,
        kind: s.kind,
    }
}

impl Reference for PagedMap {
    fn crs(&self) -> Crs {
        self.header.crs
    }
    fn level_gsd_m(&self) -> Vec<f64> {
        self.header.levels.iter().map(|l| l.gsd_m).collect()
    }
    fn ortho_pixel_m(&self) -> f64 {
        let h = &self.header;
        h.orthos
            .first()
            .map(|o| o.pixel_size_m)
            .or_else(|| h.levels.first().map(|l| l.gsd_m))
            .unwrap_or(0.0)
    }
    fn feature_spec(&self) -> FeatureSpec {
        self.header.feature_spec()
    }
    fn bounds_m(&self) -> [f64; 4] {
        let b = &self.index.bounds;
        [b.min_x_m, b.min_y_m, b.max_x_m, b.max_y_m]
    }
    fn height_amsl_m(&self, x_m: f64, y_m: f64) -> Option<f64> {
        self.dem().height_at(x_m, y_m)
    }
    fn dem(&self) -> DemRef<'_> {
        match &self.terrain {
            Terrain::Whole(d) => DemRef::Borrowed(d),
            Terrain::Tiles { joined, none } => DemRef::Shared(self.joined_terrain(joined, none)),
        }
    }
    fn height_sigma_m(&self) -> f64 {
        self.header.height_sigma_m
    }
    fn height_errors(&self) -> HeightErrors {
        self.header.height_errors()
    }
    fn select(&self, level: usize, rect_m: [f64; 4]) -> RefSelection {
        let mut out = RefSelection::empty(self.header.descriptor_kind());
        for (_, m) in self.held_under(rect_m) {
            let s = m.select(level, rect_m[0], rect_m[1], rect_m[2], rect_m[3]);
            let s = ref_selection(s);
            out.features.extend(s.features);
            out.descriptors.extend(s.descriptors);
        }
        out
    }
    fn level_window(&self, level: usize, rect_m: [f64; 4]) -> Option<LevelWindow<'_>> {
        let gsd = self.header.levels.get(level)?.gsd_m;
        let held = self.held_under(rect_m);
        let images: Vec<_> = held
            .iter()
            .filter_map(|(_, m)| m.level_image(level))
            .collect();
        let (first, _) = images.first()?;
        // The shared pixel grid, through the first tile's image corner.
        let (gx, gy) = (first.origin_x_m, first.origin_y_m);
        let col = |x: f64| ((x - gx) / gsd).floor() as i64; // ok: finite map coordinates
        let row = |y: f64| ((gy - y) / gsd).floor() as i64;
        // The rectangle, clipped to the held tiles' images.
        let (mut x0, mut y0, mut x1, mut y1) = (i64::MAX, i64::MAX, i64::MIN, i64::MIN);
        for (info, _) in &images {
            let ox = ((info.origin_x_m - gx) / gsd).round() as i64;
            let oy = ((gy - info.origin_y_m) / gsd).round() as i64;
            x0 = x0.min(ox);
            y0 = y0.min(oy);
            x1 = x1.max(ox + info.width_px as i64);
            y1 = y1.max(oy + info.height_px as i64);
        }
        let (x0, y0) = (x0.max(col(rect_m[0])), y0.max(row(rect_m[3])));
        let (x1, y1) = (x1.min(col(rect_m[2]) + 1), y1.min(row(rect_m[1]) + 1));
        if x1 <= x0 || y1 <= y0 {
            return None;
        }
        let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
        if w.saturating_mul(h) > MAX_WINDOW_PX {
            return None;
        }
        let mut data = vec![0u8; w * h];
        for (info, px) in &images {
            let ox = ((info.origin_x_m - gx) / gsd).round() as i64;
            let oy = ((gy - info.origin_y_m) / gsd).round() as i64;
            let (iw, ih) = (info.width_px as i64, info.height_px as i64);
            for y in y0.max(oy)..y1.min(oy + ih) {
                let src_row = ((y - oy) * iw) as usize;
                let dst_row = ((y - y0) as usize) * w;
                for x in x0.max(ox)..x1.min(ox + iw) {
                    let v = px[src_row + (x - ox) as usize];
                    // Tiles overlap by their grid snapping: a pixel one holds beats another's gap.
                    if v != 0 {
                        data[dst_row + (x - x0) as usize] = v;
                    }
                }
            }
        }
        Some(LevelWindow::Owned(MapImageBuf {
            data,
            width: w,
            height: h,
            origin_x_m: gx + x0 as f64 * gsd,
            origin_y_m: gy - y0 as f64 * gsd,
            gsd_m: gsd,
        }))
    }
}
