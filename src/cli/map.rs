//! `visnav map build` (orthophoto(s) + DEM -> `.vnm` reference map, or a tiled map), the tiled
//! map's jobs (`map plan`, `map build-tile`, `map gather`), `visnav map info` and `map compare`.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use visnav::geo::Crs;
use visnav::map::{BuildProgress, BuildSpec, HeightInfo, HeightSource, ReferenceMap, build_map};
use visnav::vision::OrbParams;

#[derive(clap::Args, Debug)]
pub struct MapArgs {
    #[command(subcommand)]
    pub command: MapCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum MapCommand {
    /// Build a reference map (.vnm) from orthophoto(s) and a DEM or constant ground height.
    Build(BuildArgs),
    /// Print a map file's header (CRS, levels, feature counts, bounds, sources), or a tiled
    /// map's index (area, tiles, bytes per km², resolution, sources, build command).
    Info(InfoArgs),
    /// Plan a tiled map for building across machines: the arguments of `map build` with
    /// `--tile-m` and the folder `--out`; writes `plan.json` there, one job per grid square.
    Plan(BuildArgs),
    /// Build square K of a plan into the plan's folder (kept when an earlier build left it
    /// intact); any machine that sees the plan's files may run any K.
    BuildTile(BuildTileArgs),
    /// Write a planned tiled map's `index.json` once every square is built.
    Gather(GatherArgs),
    /// Convert a map file (.vnm) into a tiled map: its features, level images and heights cut
    /// along the tiled grid, bit for bit (no orthophoto needed).
    Convert(ConvertArgs),
    /// Measure how two orthophotos of the same area are registered to each other (e.g. the map's
    /// year against another year): per-patch shifts and their mean over footprint-sized windows.
    Compare(CompareArgs),
}

#[derive(clap::Args, Debug)]
pub struct CompareArgs {
    /// The reference orthophoto (GeoTIFF); shifts are given on its pixel grid.
    pub a: PathBuf,
    /// The other orthophoto of the same area, same CRS (any pixel size and grid).
    pub b: PathBuf,
    /// Side of the windows over which the shift is averaged (a camera footprint), metres.
    #[arg(long, default_value_t = 1500.0)]
    pub window_m: f64,
    /// Minimum peak normalised cross-correlation for a patch to count.
    #[arg(long, default_value_t = 0.85)]
    pub min_ncc: f64,
    /// Largest shift searched, pixels of A.
    #[arg(long, default_value_t = 4)]
    pub search_px: usize,
    /// Write every matched patch (x_m, y_m, dx_m, dy_m, ncc) to this CSV file.
    #[arg(long)]
    pub patches_csv: Option<PathBuf>,
    /// Print the report as JSON (without the per-patch list; see --patches-csv).
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
#[command(group(clap::ArgGroup::new("heights").required(true).args(["dem", "ground_height"])))]
pub struct BuildArgs {
    /// Orthophoto GeoTIFF (repeat for several; one CRS and pixel size).
    #[arg(long, required = true)]
    pub ortho: Vec<PathBuf>,
    /// DEM GeoTIFF in the orthophotos' CRS (heights in its own datum, normally AMSL).
    #[arg(long)]
    pub dem: Option<PathBuf>,
    /// Constant ground height, metres AMSL, instead of a DEM.
    #[arg(long, allow_negative_numbers = true)]
    pub ground_height: Option<f64>,
    /// How far the surface the camera sees (roofs, trees, relief) may be from the heights, 1
    /// sigma, metres; stored in the map and used by every fix (default: 10 with --ground-height,
    /// 0 with --dem, i.e. the DEM is the surface; give a bare-earth or 30 m DEM its own figure).
    #[arg(long)]
    pub height_sigma_m: Option<f64>,
    /// How fast that height error changes across a footprint, metres per metre (1 sigma;
    /// default 0.01 with --ground-height, 0 with --dem).
    #[arg(long)]
    pub height_slope_sigma: Option<f64>,
    /// The height error left per point once a footprint's offset and slope are taken out,
    /// metres (1 sigma; default 2 with --ground-height, --height-sigma-m with --dem).
    #[arg(long)]
    pub height_point_sigma_m: Option<f64>,
    /// Output map file; with --tile-m, the tiled map's folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of pyramid levels (default: halve while the short side is >= 256 px, at most 6).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Tile core side in level pixels.
    #[arg(long, default_value_t = 1024)]
    pub tile_px: usize,
    /// Feature cap per tile and level (even spatial spread).
    #[arg(long, default_value_t = 4000)]
    pub max_features_per_tile: usize,
    /// The features: `surf` (the default and the fix's tuned family) or `orb` (ORB-like binary
    /// features, FAST-9 + steered BRIEF-256; the detector seam's second family, docs/surf.md).
    #[arg(long, value_enum, default_value_t = Detector::Surf)]
    pub detector: Detector,
    /// SURF Hessian threshold (OpenCV meaning).
    #[arg(long, default_value_t = 100.0)]
    pub hessian_threshold: f32,
    /// SURF octaves.
    #[arg(long, default_value_t = 4)]
    pub octaves: usize,
    /// Build the finest level at 1, 2 or 4 times the orthophotos' resolution (cubic
    /// interpolation before SURF): more features when the camera's ground pixel is finer than the
    /// map's (a 5 m map from 1000 m), at about 4x the features and time per factor of 2.
    #[arg(long, default_value_t = 1)]
    pub upsample: usize,
    /// UTM zone to assume for files whose GeoKeys are missing, e.g. "32614" (EPSG code of a
    /// WGS84/NAD83 UTM zone).
    #[arg(long)]
    pub crs_override_epsg: Option<u32>,
    /// Build only this part of the orthophotos: `MIN_X,MIN_Y,MAX_X,MAX_Y`, metres in their CRS
    /// (a flight area out of a larger orthophoto, or one part of a partition; the features are
    /// the whole build's inside it, docs/map-format.md "Part of the orthophotos").
    #[arg(long, value_parser = parse_area)]
    pub area: Option<visnav::geo::raster::Bounds>,
    /// Build a tiled map instead of one file: squares of this side (metres) on the CRS grid, one
    /// `.vnm` each, with `index.json`, into the folder `--out` (resumable: a second run keeps the
    /// finished tiles; about 2000 level-0 pixels a side; docs/maps.md).
    #[arg(long, conflicts_with = "area")]
    pub tile_m: Option<f64>,
}

/// `MIN_X,MIN_Y,MAX_X,MAX_Y` in metres, each finite, the box not empty.
fn parse_area(s: &str) -> Result<visnav::geo::raster::Bounds, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| "expected four numbers MIN_X,MIN_Y,MAX_X,MAX_Y (metres)".to_string())?;
    let [min_x_m, min_y_m, max_x_m, max_y_m] = v[..] else {
        return Err("expected four numbers MIN_X,MIN_Y,MAX_X,MAX_Y (metres)".into());
    };
    if !v.iter().all(|x| x.is_finite()) || max_x_m <= min_x_m || max_y_m <= min_y_m {
        return Err("the box must be finite with MIN_X < MAX_X and MIN_Y < MAX_Y".into());
    }
    Ok(visnav::geo::raster::Bounds {
        min_x_m,
        min_y_m,
        max_x_m,
        max_y_m,
    })
}

/// The feature family a map is built with.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Detector {
    /// SURF (upright SURF-64).
    Surf,
    /// ORB-like binary features.
    Orb,
}

/// `map build-tile`.
#[derive(clap::Args, Debug)]
pub struct BuildTileArgs {
    /// The plan (`plan.json` in the tiled map's folder, from `visnav map plan`).
    pub plan: PathBuf,
    /// The square to build: 0 to the plan's square count minus one.
    pub square: usize,
}

/// `map convert`.
#[derive(clap::Args, Debug)]
pub struct ConvertArgs {
    /// The map file (.vnm) to convert.
    pub file: PathBuf,
    /// Side of the tiles' grid squares, metres (200 to 1 000 000; docs/maps.md says how to
    /// choose it).
    #[arg(long)]
    pub tile_m: f64,
    /// The tiled map's folder (created; one that already holds a tiled map is refused).
    #[arg(long)]
    pub out: PathBuf,
}

/// `map gather`.
#[derive(clap::Args, Debug)]
pub struct GatherArgs {
    /// The tiled map's folder (or its `plan.json`).
    pub dir: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// The map file, or a tiled map's folder (or its `index.json`).
    pub file: PathBuf,
    /// Print the header as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: MapArgs) -> anyhow::Result<ExitCode> {
    match args.command {
        MapCommand::Build(a) => build(a),
        MapCommand::Info(a) => info(a),
        MapCommand::Compare(a) => compare(a),
        MapCommand::Plan(a) => plan(a),
        MapCommand::BuildTile(a) => build_tile(a),
        MapCommand::Gather(a) => gather(a),
        MapCommand::Convert(a) => convert(a),
    }
}

fn compare(a: CompareArgs) -> anyhow::Result<ExitCode> {
    use visnav::geo::geotiff::load_geotiff;
    use visnav::map::coreg::{CoregParams, coregister};
    let t0 = Instant::now();
    let ra = load_geotiff(&a.a, None).with_context(|| format!("reading {}", a.a.display()))?;
    let rb = load_geotiff(&a.b, None).with_context(|| format!("reading {}", a.b.display()))?;
    let params = CoregParams {
        window_m: a.window_m,
        min_ncc: a.min_ncc,
        search_px: a.search_px,
        ..CoregParams::default()
    };
    let mut r = coregister(&ra, &rb, &params)
        .with_context(|| format!("comparing {} with {}", a.a.display(), a.b.display()))?;
    if let Some(path) = &a.patches_csv {
        let mut f = std::io::BufWriter::new(
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
        );
        writeln!(f, "x_m,y_m,dx_m,dy_m,ncc")?;
        for p in &r.patches {
            writeln!(
                f,
                "{:.2},{:.2},{:.3},{:.3},{:.4}",
                p.x_m, p.y_m, p.dx_m, p.dy_m, p.ncc
            )?;
        }
        f.flush()
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if a.json {
        r.patches.clear();
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{} -> {} ({:.1} s)",
        a.a.display(),
        a.b.display(),
        t0.elapsed().as_secs_f64()
    );
    println!(
        "  patches: {} matched of {} textured ({:.1} m pixels of A)",
        r.patches_matched, r.patches_tried, r.pixel_m
    );
    let (Some(sm), Some(sp), Some(dx), Some(dy)) =
        (r.shift_m, r.shift_px, r.median_dx_m, r.median_dy_m)
    else {
        println!("  no patch shows the same structure in both images: nothing measured");
        return Ok(ExitCode::SUCCESS);
    };
    println!(
        "  shift per patch: median {:.2} m ({:.2} px), p90 {:.2} m ({:.2} px), max {:.2} m",
        sm.median, sp.median, sm.p90, sp.p90, sm.max
    );
    println!(
        "  median shift: {dx:+.2} m along x, {dy:+.2} m along y (the ground of A lies there in B)"
    );
    match (r.window_shift_m, r.window_shift_px) {
        (Some(wm), Some(wp)) => println!(
            "  mean shift over {} windows of {:.0} m: median {:.2} m ({:.2} px), p90 {:.2} m ({:.2} px), max {:.2} m ({:.2} px)",
            r.windows.len(),
            r.window_m,
            wm.median,
            wp.median,
            wm.p90,
            wp.p90,
            wm.max,
            wp.max
        ),
        _ => println!(
            "  no {:.0} m window holds enough matched patches for a window mean",
            r.window_m
        ),
    }
    Ok(ExitCode::SUCCESS)
}

fn epsg_crs(code: u32) -> anyhow::Result<Crs> {
    let (zone, north) = match code {
        32601..=32660 => (code - 32600, true),
        32701..=32760 => (code - 32700, false),
        26901..=26923 => (code - 26900, true),
        3857 => return Ok(Crs::WebMercator),
        _ => anyhow::bail!(
            "--crs-override-epsg {code}: only UTM (326zz, 327zz, 269zz) and 3857 are supported"
        ),
    };
    Ok(Crs::Utm {
        zone: zone as u8, // ok: 1..=60
        north,
    })
}

/// The build `a` asks for (without its output).
fn spec_of(a: &BuildArgs) -> anyhow::Result<BuildSpec> {
    let height = match (&a.dem, a.ground_height) {
        (Some(d), None) => HeightSource::Dem(d.clone()),
        (None, Some(h)) => HeightSource::ConstantAmsl(h),
        _ => anyhow::bail!("give exactly one of --dem and --ground-height"),
    };
    let mut spec = BuildSpec::new(a.ortho.clone(), height);
    spec.levels = a.levels;
    spec.tile_px = a.tile_px;
    spec.max_features_per_tile = a.max_features_per_tile;
    spec.surf.hessian_threshold = a.hessian_threshold;
    spec.surf.n_octaves = a.octaves;
    if a.detector == Detector::Orb {
        spec.orb = Some(OrbParams::default());
    }
    spec.upsample = a.upsample;
    spec.height_sigma_m = a.height_sigma_m;
    spec.height_slope_sigma = a.height_slope_sigma;
    spec.height_point_sigma_m = a.height_point_sigma_m;
    spec.crs_override = a.crs_override_epsg.map(epsg_crs).transpose()?;
    spec.area = a.area;
    Ok(spec)
}

/// The command line as the provenance of a tiled build: `visnav map build` and its arguments
/// without `--out` (the folder is where the map is, not what it holds), so a plan run across
/// machines and a build on one record the same.
fn build_command() -> String {
    let mut words = vec!["visnav".to_string(), "map".into(), "build".into()];
    let argv: Vec<String> = std::env::args_os()
        .map(|w| w.to_string_lossy().into_owned())
        .collect();
    // The arguments after `map build` / `map plan` (global options may come before `map`).
    let start = argv
        .windows(2)
        .position(|w| w[0] == "map" && (w[1] == "build" || w[1] == "plan"))
        .map_or(argv.len(), |i| i + 2);
    let mut args = argv.into_iter().skip(start);
    while let Some(w) = args.next() {
        if w == "--out" {
            args.next();
        } else if !w.starts_with("--out=") {
            words.push(shell_word(&w));
        }
    }
    words.join(" ")
}

/// `w` quoted for a POSIX shell when it holds anything but plain path characters.
fn shell_word(w: &str) -> String {
    let plain = !w.is_empty()
        && w.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./=,:+@%".contains(c));
    if plain {
        w.to_string()
    } else {
        format!("'{}'", w.replace('\'', "'\\''"))
    }
}

fn build(a: BuildArgs) -> anyhow::Result<ExitCode> {
    let spec = spec_of(&a)?;
    if let Some(t) = a.tile_m {
        return build_tiled_cli(&spec, t, &a.out);
    }
    let tty = std::io::stderr().is_terminal();
    let mut last_log = Instant::now();
    let mut progress = |p: BuildProgress| {
        let pct = 100.0 * p.tiles_done as f64 / p.tiles_total.max(1) as f64;
        if tty {
            let mut e = std::io::stderr();
            let _ = write!(
                e,
                "\r[{:<30}] {pct:5.1} %  tile {}/{}  ortho {} level {}  {} features",
                "#".repeat((pct / 100.0 * 30.0) as usize),
                p.tiles_done,
                p.tiles_total,
                p.ortho,
                p.level,
                p.features
            );
            let _ = e.flush();
        } else if last_log.elapsed().as_secs_f64() > 5.0 || p.tiles_done == p.tiles_total {
            last_log = Instant::now();
            tracing::info!(
                tiles_done = p.tiles_done,
                tiles_total = p.tiles_total,
                features = p.features,
                "map build {pct:.1} %"
            );
        }
    };
    let s = build_map(&spec, &a.out, &mut progress)
        .with_context(|| format!("building {}", a.out.display()))?;
    if tty {
        eprintln!();
    }
    println!(
        "{}: {} features in {} level(s), {} bytes, {:.2} s ({} tiles; dropped {} at nodata, {} without height)",
        a.out.display(),
        s.header.n_features(),
        s.header.levels.len(),
        s.file_bytes,
        s.elapsed_s,
        s.tiles,
        s.dropped_nodata,
        s.dropped_no_height
    );
    Ok(ExitCode::SUCCESS)
}

/// `map build --tile-m`: the tiled map into the folder `out`, a line per grid square in the log.
fn build_tiled_cli(spec: &BuildSpec, tile_m: f64, out: &Path) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let s = visnav::map::tiled::build_tiled(spec, tile_m, out, Some(build_command()), &mut |p| {
        tracing::info!(
            done = p.done,
            total = p.total,
            kept = p.reused,
            "tiled map build: square {} of {}",
            p.done,
            p.total
        );
    })
    .with_context(|| format!("building the tiled map {}", out.display()))?;
    let features: u64 = s.index.tiles.iter().map(|t| t.features).sum();
    let bytes: u64 = s.index.tiles.iter().map(|t| t.file_bytes).sum();
    println!(
        "{}: {} tiles of {} m ({} squares without features), {features} features, {bytes} bytes, \
         {} level(s); {} squares built, {} kept from an earlier build, {:.2} s",
        out.display(),
        s.index.tiles.len(),
        s.index.tile_m,
        s.index.empty.len(),
        s.index.levels,
        s.built,
        s.reused,
        t0.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// `map plan`: the tiled build's jobs into `--out/plan.json`.
fn plan(a: BuildArgs) -> anyhow::Result<ExitCode> {
    use visnav::map::tiled::{PLAN_FILE, TilePlan};
    let Some(tile_m) = a.tile_m else {
        anyhow::bail!("map plan needs --tile-m (the side of the grid squares, metres)");
    };
    let spec = spec_of(&a)?;
    let plan = TilePlan::new(&spec, tile_m, Some(build_command()))
        .with_context(|| format!("planning the tiled map {}", a.out.display()))?;
    plan.write(&a.out)
        .with_context(|| format!("writing the plan into {}", a.out.display()))?;
    let n = plan.squares.len();
    let path = a.out.join(PLAN_FILE);
    println!(
        "{}: {n} squares of {tile_m} m, {} level(s) of {} m and coarser; build each with \
         `visnav map build-tile {} K` (K = 0 to {}), then `visnav map gather {}`",
        path.display(),
        plan.levels,
        plan.gsd_m,
        path.display(),
        n.saturating_sub(1),
        a.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// The plan and its folder, from the plan's path or the folder.
fn read_plan(path: &Path) -> anyhow::Result<(visnav::map::tiled::TilePlan, PathBuf)> {
    use visnav::map::tiled::{PLAN_FILE, TilePlan};
    let (file, dir) = if path.is_dir() {
        (path.join(PLAN_FILE), path.to_path_buf())
    } else {
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        (path.to_path_buf(), dir)
    };
    let plan = TilePlan::read(&file).with_context(|| format!("reading {}", file.display()))?;
    Ok((plan, dir))
}

/// `map build-tile PLAN K`.
fn build_tile(a: BuildTileArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let (plan, dir) = read_plan(&a.plan)?;
    let o = plan
        .build_square(&dir, a.square)
        .with_context(|| format!("building square {} of {}", a.square, a.plan.display()))?;
    let [col, row] = [o.result.col, o.result.row];
    let what = match &o.result.tile {
        Some(t) => format!(
            "{}: {} features, {} bytes",
            t.file, t.features, t.file_bytes
        ),
        None => "no features (no file)".into(),
    };
    println!(
        "square {} of {} (x{col}_y{row}): {what}; {} in {:.2} s",
        a.square,
        plan.squares.len(),
        if o.reused {
            "kept from an earlier build"
        } else {
            "built"
        },
        t0.elapsed().as_secs_f64()
    );
    Ok(ExitCode::SUCCESS)
}

/// `map gather DIR`.
fn gather(a: GatherArgs) -> anyhow::Result<ExitCode> {
    let (plan, dir) = read_plan(&a.dir)?;
    let ix = plan
        .gather(&dir)
        .with_context(|| format!("gathering the tiled map {}", dir.display()))?;
    println!(
        "{}: {} tiles ({} squares without features), {} features, {} bytes",
        dir.join(visnav::map::tiled::INDEX_FILE).display(),
        ix.tiles.len(),
        ix.empty.len(),
        ix.total_features(),
        ix.total_bytes()
    );
    Ok(ExitCode::SUCCESS)
}

/// `map convert FILE --tile-m T --out DIR`.
fn convert(a: ConvertArgs) -> anyhow::Result<ExitCode> {
    let t0 = Instant::now();
    let command = format!(
        "visnav map convert {} --tile-m {}",
        a.file.display(),
        a.tile_m
    );
    let s = visnav::map::convert::convert_to_tiled(&a.file, a.tile_m, &a.out, Some(command))
        .with_context(|| format!("converting {} into {}", a.file.display(), a.out.display()))?;
    println!(
        "{}: {} tiles ({} squares without features), {} features, {} bytes, in {:.2} s",
        a.out.join(visnav::map::tiled::INDEX_FILE).display(),
        s.index.tiles.len(),
        s.index.empty.len(),
        s.features,
        s.index.total_bytes(),
        t0.elapsed().as_secs_f64()
    );
    let file = ReferenceMap::open(&a.file)?;
    match (&file.header().height, &s.heights_from) {
        (HeightInfo::Dem { .. }, Some(dem)) => {
            println!("  each tile carries its heights from {}", dem.display());
        }
        (HeightInfo::Dem { file, .. }, None) => println!(
            "  the DEM the map names ({file}) is not at hand: the tiles carry no heights, so \
             `[map] dem` must give them in flight"
        ),
        (HeightInfo::Constant { .. }, _) => {}
    }
    Ok(ExitCode::SUCCESS)
}

/// `map info` of a tiled map (its folder or `index.json`).
fn tiled_info(path: &Path, json: bool) -> anyhow::Result<ExitCode> {
    let ix = visnav::map::tiled::TiledIndex::read(path)
        .with_context(|| format!("reading the tiled map {}", path.display()))?;
    if json {
        println!("{}", serde_json::to_string_pretty(&ix)?);
        return Ok(ExitCode::SUCCESS);
    }
    let b = &ix.bounds;
    let (w, h) = (b.max_x_m - b.min_x_m, b.max_y_m - b.min_y_m);
    let km2 = ix.tiles_area_km2();
    println!("{} (tiled map, format v{})", path.display(), ix.version);
    println!("  built by {}", ix.built_by);
    if let Some(c) = &ix.command {
        println!("  build command: {c}");
    }
    println!("  CRS {}", ix.crs);
    println!(
        "  orthophotos' union x {:.2} .. {:.2} m, y {:.2} .. {:.2} m ({:.0} x {:.0} m, {:.1} km²)",
        b.min_x_m,
        b.max_x_m,
        b.min_y_m,
        b.max_y_m,
        w,
        h,
        w * h / 1e6
    );
    println!(
        "  {} tiles of {} m covering {km2:.1} km² ({} squares without features); {} level(s), level 0 {} m per pixel",
        ix.tiles.len(),
        ix.tile_m,
        ix.empty.len(),
        ix.levels,
        ix.gsd_m
    );
    let per_km2 = if km2 > 0.0 {
        ix.total_bytes() as f64 / km2
    } else {
        0.0
    };
    println!(
        "  {} features, {} bytes ({:.0} kB per km², largest tile {} bytes)",
        ix.total_features(),
        ix.total_bytes(),
        per_km2 / 1e3,
        ix.tiles.iter().map(|t| t.file_bytes).max().unwrap_or(0)
    );
    let heights: Vec<_> = ix.tiles.iter().filter_map(|t| t.heights.as_ref()).collect();
    if !heights.is_empty() {
        println!(
            "  heights carried by {} of the {} tiles: {} bytes on disk, {} bytes in memory",
            heights.len(),
            ix.tiles.len(),
            heights.iter().map(|h| h.file_bytes).sum::<u64>(),
            heights.iter().map(|h| h.memory_bytes()).sum::<u64>()
        );
    }
    for s in &ix.sources {
        println!("  source {s}");
    }
    Ok(ExitCode::SUCCESS)
}

fn info(a: InfoArgs) -> anyhow::Result<ExitCode> {
    if a.file.is_dir() || a.file.extension().is_some_and(|e| e == "json") {
        return tiled_info(&a.file, a.json);
    }
    let t0 = Instant::now();
    let m = ReferenceMap::open(&a.file)?;
    let open_s = t0.elapsed().as_secs_f64();
    let h = m.header();
    if a.json {
        println!("{}", serde_json::to_string_pretty(h)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{} (format v{}, opened in {:.1} ms)",
        a.file.display(),
        h.version,
        open_s * 1e3
    );
    println!(
        "  built by {} at {} (unix {})",
        h.built_by,
        iso8601_utc(h.built_unix_s),
        h.built_unix_s
    );
    println!("  CRS {}", h.crs);
    println!(
        "  bounds x {:.2} .. {:.2} m, y {:.2} .. {:.2} m ({:.0} x {:.0} m)",
        h.bounds.min_x_m,
        h.bounds.max_x_m,
        h.bounds.min_y_m,
        h.bounds.max_y_m,
        h.bounds.max_x_m - h.bounds.min_x_m,
        h.bounds.max_y_m - h.bounds.min_y_m
    );
    match &h.height {
        HeightInfo::Dem { file, min_m, max_m } => {
            println!("  heights from DEM {file} ({min_m:.1} .. {max_m:.1} m)")
        }
        HeightInfo::Constant { amsl_m } => println!("  constant ground height {amsl_m} m AMSL"),
    }
    let e = h.height_errors();
    println!(
        "  height sigma (the surface the camera sees against these heights): {} m shared by a footprint, {} m per m across it, {} m per point",
        e.offset_sigma_m, e.slope_sigma, e.point_sigma_m
    );
    println!("  vertical datum: {}", h.vertical_datum);
    match &h.orb {
        Some(o) => println!(
            "  {} descriptors, FAST threshold {}, {} levels x {}, upright {}; tile {} px, cap {} per tile",
            h.feature_spec(),
            o.fast_threshold,
            o.n_levels,
            o.scale_factor,
            o.upright,
            h.tile_px,
            h.max_features_per_tile
        ),
        None => println!(
            "  {} descriptors, threshold {}, {} octaves x {} layers, upright {}; tile {} px, cap {} per tile",
            h.surf.descriptor,
            h.surf.hessian_threshold,
            h.surf.n_octaves,
            h.surf.n_octave_layers,
            h.surf.upright,
            h.tile_px,
            h.max_features_per_tile
        ),
    }
    for (i, l) in h.levels.iter().enumerate() {
        println!(
            "  level {i}: {:.3} m/px, {} features, index {} x {} cells of {:.0} m",
            l.gsd_m, l.n_features, l.grid.cols, l.grid.rows, l.grid.cell_m
        );
    }
    for o in &h.orthos {
        println!(
            "  ortho {} ({} x {} px, {} bands, {} m/px)",
            o.file, o.width_px, o.height_px, o.bands, o.pixel_size_m
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Seconds in a day (UTC has no leap seconds in Unix time: every day is this long).
const SECONDS_PER_DAY: u64 = 86_400;

/// Days from 0000-03-01 to 1970-01-01 in the proleptic Gregorian calendar: counting from a March
/// first puts the leap day at the end of the year (Hinnant's `civil_from_days`).
const DAYS_0000_03_01_TO_EPOCH: u64 = 719_468;

/// Days in a 400-year Gregorian cycle (97 leap years).
const DAYS_PER_400_YEARS: u64 = 146_097;

/// The largest year ISO 8601's basic four-digit form writes.
const MAX_ISO_YEAR: u64 = 9999;

/// Unix seconds as an ISO 8601 UTC date and time, `2026-11-28T21:49:29Z` (what `map info` says
/// a map was built at); a time after the year 9999 stays in Unix seconds.
fn iso8601_utc(unix_s: u64) -> String {
    let days = unix_s / SECONDS_PER_DAY;
    let secs = unix_s % SECONDS_PER_DAY;
    // Hinnant's civil_from_days on unsigned numbers (times before 1970 do not occur here).
    let z = days + DAYS_0000_03_01_TO_EPOCH;
    let era = z / DAYS_PER_400_YEARS;
    let doe = z % DAYS_PER_400_YEARS; // day of the 400-year era, 0..=146096
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365; // 0..=399
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100); // day of the March-based year, 0..=365
    let mp = (5 * doy + 2) / 153; // month from March, 0..=11
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + u64::from(month <= 2);
    if year > MAX_ISO_YEAR {
        return format!("unix {unix_s}");
    }
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        secs / 3600,
        secs % 3600 / 60,
        secs % 60
    )
}

#[cfg(test)]
mod tests {
    use super::iso8601_utc;

    /// Known instants (checked against `date -u -d @N`), leap days of leap years including a
    /// century divisible by 400, and the days around the ones that are not leap days.
    #[test]
    fn unix_seconds_as_iso8601_utc() {
        for (unix_s, want) in [
            (0, "1970-01-01T00:00:00Z"),
            (86_399, "1970-01-01T23:59:59Z"),
            (951_782_400, "2000-02-29T00:00:00Z"),
            (951_868_800, "2000-03-01T00:00:00Z"),
            (1_078_099_199, "2004-02-29T23:59:59Z"),
            (1_709_164_800, "2024-02-29T00:00:00Z"),
            (1_677_628_800, "2023-03-01T00:00:00Z"),
            (1_795_902_569, "2026-11-28T21:49:29Z"),
            (1_677_585_600, "2023-02-28T12:00:00Z"),
            (4_107_456_000, "2100-02-28T00:00:00Z"),
            (4_107_542_400, "2100-03-01T00:00:00Z"),
            (253_402_300_799, "9999-12-31T23:59:59Z"),
        ] {
            assert_eq!(iso8601_utc(unix_s), want, "{unix_s}");
        }
        assert_eq!(iso8601_utc(253_402_300_800), "unix 253402300800");
        assert_eq!(iso8601_utc(u64::MAX), format!("unix {}", u64::MAX));
    }
}
