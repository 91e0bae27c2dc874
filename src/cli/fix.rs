//! `visnav fix --map MAP --image F --camera cam.toml [--attitude R,P,Y [--attitude-sigma-deg S]
//! [--yaw-sigma-deg S]] [--prior LAT,LON,ALT,SIGMA_M] [--json]`: one vision fix from one frame. MAP is a reference map (`.vnm`, see `visnav map build`)
//! or, for small areas, an orthophoto GeoTIFF used directly (a map is built from it into a
//! temporary file; give `--dem` or `--ground-height`). Exit status: 0 accepted, 2 rejected (the JSON or the text
//! says why), 1 on an error (bad file, bad argument).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::{Context, bail};
use visnav::camera::{Attitude, Camera, CameraConfig};
use visnav::fix::{
    AltitudePrior, AttitudePriorNed, FixEngine, FixParams, FixPrior, MapReference,
    PositionPriorGeo, Reference,
};
use visnav::geo::dem::Dem;
use visnav::map::{BuildSpec, HeightSource};
use visnav::vision::{GrayImage, GrayImageFile};
use visnav_core::text::quote;
use visnav_core::validate::{Problems, Validate};

#[derive(clap::Args, Debug)]
pub struct FixArgs {
    /// Reference map: a `.vnm` file, or an orthophoto GeoTIFF (small areas).
    #[arg(long)]
    pub map: PathBuf,
    /// The camera frame (PNG, JPEG, TIFF; colour is converted to grey).
    #[arg(long)]
    pub image: PathBuf,
    /// Camera model: a TOML file with the `[camera]` keys (or a whole visnav config).
    #[arg(long)]
    pub camera: PathBuf,
    /// Vehicle attitude from the autopilot, degrees: ROLL,PITCH,YAW (body FRD to NED).
    #[arg(long, value_name = "ROLL,PITCH,YAW", allow_hyphen_values = true)]
    pub attitude: Option<String>,
    /// 1-sigma of --attitude's roll and pitch (the tilt), degrees.
    #[arg(long, default_value_t = 1.0)]
    pub attitude_sigma_deg: f64,
    /// 1-sigma of --attitude's heading, degrees (default: --attitude-sigma-deg). A compass or
    /// drifted heading is often tens of degrees off: give it its own sigma and the headings
    /// within 3 sigma are searched (180: unknown heading, tilt still used).
    #[arg(long)]
    pub yaw_sigma_deg: Option<f64>,
    /// Position prior: latitude and longitude (deg), altitude AMSL (m), 1-sigma horizontal (m).
    /// Without it the whole map is searched (global relocalisation).
    #[arg(long, value_name = "LAT,LON,ALT,SIGMA_M", allow_hyphen_values = true)]
    pub prior: Option<String>,
    /// Without --prior: the altitude alone, AMSL (m), and its 1-sigma (m), as a barometer gives
    /// it after the position is lost. With a tilt (--attitude), the relocalisation then
    /// searches the map image at every heading allowed (docs/fix.md, "Relocalisation").
    #[arg(
        long,
        value_name = "ALT,SIGMA_M",
        allow_hyphen_values = true,
        conflicts_with = "prior"
    )]
    pub altitude: Option<String>,
    /// 1-sigma of the prior altitude, metres (default: the horizontal sigma).
    #[arg(long)]
    pub prior_sigma_v_m: Option<f64>,
    /// Settings of the `[fix]` section (TOML file with the keys at the top level).
    #[arg(long)]
    pub settings: Option<PathBuf>,
    /// The DEM (heights AMSL, same CRS): needed with a GeoTIFF --map; with a .vnm map it
    /// replaces the DEM the map was built from.
    #[arg(long, conflicts_with = "ground_height")]
    pub dem: Option<PathBuf>,
    /// Constant ground height AMSL, metres (instead of --dem).
    #[arg(long)]
    pub ground_height: Option<f64>,
    /// With a GeoTIFF --map: the heights' sigma against the surface the camera sees, metres (as
    /// `visnav map build --height-sigma-m`; default 10 with --ground-height, 0 with --dem).
    #[arg(long)]
    pub height_sigma_m: Option<f64>,
    /// With a GeoTIFF --map: how fast that height error changes across a footprint, metres per
    /// metre (as `visnav map build --height-slope-sigma`).
    #[arg(long)]
    pub height_slope_sigma: Option<f64>,
    /// With a GeoTIFF --map: the height error per point, metres (as `visnav map build
    /// --height-point-sigma-m`).
    #[arg(long)]
    pub height_point_sigma_m: Option<f64>,
    /// Print the result as one JSON document.
    #[arg(long)]
    pub json: bool,
}

/// Parse `n` comma-separated finite numbers of option `name`.
fn numbers(name: &str, text: &str, n: usize) -> anyhow::Result<Vec<f64>> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--{name} {}: not {n} comma-separated numbers", quote(text)))?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        bail!(
            "--{name} {}: expected {n} finite comma-separated numbers",
            quote(text)
        );
    }
    Ok(v)
}

/// The camera from a TOML file holding `[camera]` or the camera keys themselves.
pub fn load_camera(path: &Path) -> anyhow::Result<Camera> {
    let text = visnav_io::files::read_text(path, visnav_io::files::CONFIG)
        .with_context(|| format!("reading camera file {}", path.display()))?;
    let value: toml::Table =
        toml::from_str(&text).with_context(|| format!("{}: not valid TOML", path.display()))?;
    let (section, table) = match value.get("camera") {
        Some(toml::Value::Table(t)) => ("camera.", t.clone()),
        _ => ("", value),
    };
    let cfg: CameraConfig = toml::Value::Table(table)
        .try_into()
        .with_context(|| format!("{}: [camera]", path.display()))?;
    let mut problems = Problems::default();
    cfg.validate(&mut problems);
    if let Some(first) = problems.list.first() {
        bail!("{}: {section}{first}", path.display());
    }
    cfg.build()
        .with_context(|| format!("{}: camera model", path.display()))
}

fn load_reference(a: &FixArgs) -> anyhow::Result<Arc<dyn Reference>> {
    let ext = a
        .map
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    // The terrain: required with a GeoTIFF map, an override of the map's own with a .vnm.
    let dem = match (&a.dem, a.ground_height) {
        (Some(p), _) => Some(
            visnav::geo::dem::load_dem(p, None)
                .with_context(|| format!("loading the DEM {}", p.display()))?,
        ),
        (None, Some(h)) => Some(Dem::flat(h).context("--ground-height")?),
        (None, None) => None,
    };
    if ext == "tif" || ext == "tiff" {
        // The same map build as `visnav map build`, into a temporary file.
        let height = match (&a.dem, a.ground_height) {
            (Some(p), _) => HeightSource::Dem(p.clone()),
            (None, Some(h)) => HeightSource::ConstantAmsl(h),
            (None, None) => bail!("a GeoTIFF --map needs --dem F.tif or --ground-height M"),
        };
        let mut spec = BuildSpec::new(vec![a.map.clone()], height);
        spec.height_sigma_m = a.height_sigma_m;
        spec.height_slope_sigma = a.height_slope_sigma;
        spec.height_point_sigma_m = a.height_point_sigma_m;
        let r = MapReference::build_temporary(&spec, dem)
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("building a map from {}", a.map.display()))?;
        return Ok(Arc::new(r));
    }
    let r = MapReference::open(&a.map, dem)
        .with_context(|| format!("opening the map {}", a.map.display()))?;
    Ok(Arc::new(r))
}

pub fn run(a: FixArgs) -> anyhow::Result<ExitCode> {
    let camera = load_camera(&a.camera)?;
    let params = match &a.settings {
        Some(p) => {
            let text = visnav_io::files::read_text(p, visnav_io::files::CONFIG)
                .with_context(|| format!("reading settings {}", p.display()))?;
            let v: toml::Value = toml::from_str(&text)
                .with_context(|| format!("{}: not valid TOML", p.display()))?;
            visnav::daemon::config::fix::fix_params_from_toml(v)
                .with_context(|| format!("{}: [fix] settings", p.display()))?
        }
        None => FixParams::default(),
    };
    let image = GrayImage::load(&a.image).context("loading the frame")?;
    if image.width() != camera.width_px() as usize || image.height() != camera.height_px() as usize
    {
        bail!(
            "{} is {}x{} but the camera in {} is {}x{}",
            a.image.display(),
            image.width(),
            image.height(),
            a.camera.display(),
            camera.width_px(),
            camera.height_px()
        );
    }
    let attitude = match &a.attitude {
        Some(t) => {
            let v = numbers("attitude", t, 3)?;
            if !(a.attitude_sigma_deg.is_finite() && a.attitude_sigma_deg > 0.0) {
                bail!("--attitude-sigma-deg must be positive");
            }
            let yaw_sigma_deg = a.yaw_sigma_deg.unwrap_or(a.attitude_sigma_deg);
            if !(yaw_sigma_deg.is_finite() && yaw_sigma_deg > 0.0 && yaw_sigma_deg <= 180.0) {
                bail!("--yaw-sigma-deg must be more than 0 and at most 180");
            }
            Some(AttitudePriorNed {
                attitude: Attitude::from_deg(v[0], v[1], v[2]),
                sigma_rad: a.attitude_sigma_deg.to_radians(),
                sigma_yaw_rad: yaw_sigma_deg.to_radians(),
            })
        }
        None => None,
    };
    let position = match &a.prior {
        Some(t) => {
            let v = numbers("prior", t, 4)?;
            if !(-90.0..=90.0).contains(&v[0]) || !(-180.0..=180.0).contains(&v[1]) || v[3] <= 0.0 {
                bail!(
                    "--prior {}: latitude in [-90, 90], longitude in [-180, 180], sigma > 0",
                    quote(t)
                );
            }
            let sv = a.prior_sigma_v_m.unwrap_or(v[3]);
            if !(sv.is_finite() && sv > 0.0) {
                bail!("--prior-sigma-v-m must be positive");
            }
            Some(PositionPriorGeo {
                lat_deg: v[0],
                lon_deg: v[1],
                alt_amsl_m: v[2],
                sigma_h_m: v[3],
                sigma_v_m: sv,
            })
        }
        None => None,
    };
    let altitude = match &a.altitude {
        Some(t) => {
            let v = numbers("altitude", t, 2)?;
            if !(v[1].is_finite() && v[1] > 0.0) {
                bail!("--altitude {}: the sigma must be positive", quote(t));
            }
            Some(AltitudePrior {
                alt_amsl_m: v[0],
                sigma_m: v[1],
            })
        }
        None => None,
    };
    let reference = load_reference(&a)?;
    let engine = FixEngine::new(reference, camera, params).context("fix engine")?;
    let start = std::time::Instant::now();
    let mut report = engine.fix(
        &image,
        &FixPrior {
            t_capture_us: 0,
            position,
            attitude,
            altitude,
            attitude_from_filter: false,
            widen_heading: true,
        },
    );
    report.ms = start.elapsed().as_secs_f64() * 1e3;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else if report.accepted {
        println!(
            "accepted: lat {:.7} lon {:.7} alt {:.1} m AMSL (x {:.1} y {:.1} z {:.1} in the map CRS)",
            report.lat_deg, report.lon_deg, report.alt_amsl_m, report.x_m, report.y_m, report.z_m
        );
        println!(
            "  roll {:.3} pitch {:.3} yaw {:.3} deg; sigma N {:.1} E {:.1} D {:.1} m",
            report.roll_deg,
            report.pitch_deg,
            report.yaw_deg,
            report.cov_ned_m2[0][0].sqrt(),
            report.cov_ned_m2[1][1].sqrt(),
            report.cov_ned_m2[2][2].sqrt()
        );
        if report.reproj_rms_px.is_finite() {
            println!(
                "  {} inliers of {} matches ({}), reprojection RMS {:.2} px, level {}, {:.1} ms",
                report.inliers,
                report.matches,
                report.method,
                report.reproj_rms_px,
                report.level,
                report.ms
            );
        } else {
            // A placement fix: no tie points, so no residuals to show.
            println!(
                "  {}: position and heading from the area correlation, the tilt the prior's, \
                 level {}, {:.1} ms",
                report.method, report.level, report.ms
            );
        }
    } else {
        println!("rejected: {} ({:.1} ms)", report.reason(), report.ms);
    }
    Ok(if report.accepted {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(2)
    })
}
