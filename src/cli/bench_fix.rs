//! `visnav bench fix [--frames N] [--seed S] [--json] [--per-frame]`: the NAIP cross-date acceptance
//! run of the vision fix (frames rendered from the 2014 orthophoto, map from 2009; see
//! `visnav::sitl::fixeval`) with its frame-to-fix timing (p50/p95). Build with `--release`.

use std::process::ExitCode;

use anyhow::Context;
use visnav::fix::FixParams;
use visnav::sitl::fixeval::{AttitudeMode, HeightSigmas, MapHeights, NaipEval};
use visnav::vision::{DescriptorKind, SurfParams};
use visnav_core::text::{num, quote};

#[derive(clap::Args, Debug)]
pub struct FixBenchArgs {
    /// Number of frames.
    #[arg(long, default_value_t = 100)]
    pub frames: usize,
    /// Random seed of the poses and priors.
    #[arg(long, default_value_t = 2024)]
    pub seed: u64,
    /// Print one JSON document instead of a summary.
    #[arg(long)]
    pub json: bool,
    /// Print one line per frame (stderr).
    #[arg(long)]
    pub per_frame: bool,
    /// SURF Hessian threshold of the map and the query.
    #[arg(long, default_value_t = 100.0)]
    pub hessian_threshold: f32,
    /// Descriptor: 36, 64 or 128.
    #[arg(long, default_value_t = 64)]
    pub descriptor: usize,
    /// No position prior: global relocalisation (attitude prior only).
    #[arg(long)]
    pub no_prior: bool,
    /// With --no-prior: no altitude either (by default relocalisation keeps the prior's
    /// altitude, as a barometer would give it).
    #[arg(long, requires = "no_prior")]
    pub no_altitude: bool,
    /// Standard deviation of the prior attitude's error per axis, degrees (the prior states
    /// 0.5 deg). The frames and the other draws stay the same for every value.
    #[arg(long, default_value_t = 0.3)]
    pub attitude_error_deg: f64,
    /// A heading error of this size added to the prior's heading, degrees (sign alternating by
    /// frame), on top of --attitude-error-deg: a compass heading or one drifted after GPS loss.
    #[arg(long, default_value_t = 0.0)]
    pub yaw_error_deg: f64,
    /// The heading sigma the prior states, degrees (default 0.5, as the tilt's; with
    /// --yaw-error-deg, 30).
    #[arg(long)]
    pub yaw_sigma_deg: Option<f64>,
    /// The prior carries roll and pitch only (the heading unknown).
    #[arg(long, conflicts_with = "no_attitude")]
    pub tilt_only: bool,
    /// The prior carries no attitude at all.
    #[arg(long)]
    pub no_attitude: bool,
    /// DIAGNOSTIC, not an accuracy figure: render the frames from the map's own orthophoto (the
    /// solver's error without the cross-date matching's).
    #[arg(long)]
    pub same_imagery: bool,
    /// Build the map from this orthophoto instead of the bundled 2009 one (repeat to stack
    /// several co-registered years of the NAIP area, e.g. ../shared/data/naip_nd/*2010*.tif). The
    /// camera year (2014) is refused.
    #[arg(long = "map-ortho", value_name = "TIF")]
    pub map_ortho: Vec<std::path::PathBuf>,
    /// Build the map's finest level at 1, 2 or 4 times the orthophoto's resolution
    /// (`[map] upsample`).
    #[arg(long, default_value_t = 1)]
    pub map_upsample: usize,
    /// Heights above ground of the frames, metres: `LO:HI` (uniform) or one value (default: the
    /// site's envelope, 1200:2500 for NAIP, 80:300 for Autzen).
    #[arg(long, value_name = "LO[:HI]")]
    pub agl_m: Option<String>,
    /// Largest tilt of the frames from level, degrees (default: the site's, 20 for NAIP, 10 for
    /// Autzen).
    #[arg(long)]
    pub max_tilt_deg: Option<f64>,
    /// Override `[fix]` settings with a TOML snippet, e.g. 'ratio = 0.9' (keys of the `[fix]` section).
    #[arg(long)]
    pub set: Option<String>,
    /// The site: `naip` (cross-date, 1200-2500 m) or `autzen` (drone scale over the lidar surface
    /// model, 80-300 m, ../shared/data/autzen; one date: the map and the frames come from two
    /// differently degraded copies of its photo).
    #[arg(long, default_value = "naip", value_parser = ["naip", "autzen"])]
    pub site: String,
    /// Autzen: the heights the map is built on: `surface` (the lidar surface model the frames are
    /// rendered on) or `constant` (its median, as a user without a DEM would).
    #[arg(long, default_value = "surface", value_parser = ["surface", "constant"])]
    pub map_heights: String,
    /// The camera: `vga` (640 x 480, 60 deg) or `drone` (1280 x 960, 80 deg, a multirotor's);
    /// default: the site's (VGA for NAIP, the drone camera for Autzen).
    #[arg(long, value_parser = ["vga", "drone"])]
    pub camera: Option<String>,
    /// The height sigma stated at the map's build, metres (default: the build's default for its
    /// height source; Autzen's surface model: 1 m, for its 1 m cells under the 0.3 m photo).
    #[arg(long)]
    pub height_sigma_m: Option<f64>,
    /// The height slope sigma stated at the map's build, metres per metre (default: the build's
    /// default for its height source).
    #[arg(long)]
    pub height_slope_sigma: Option<f64>,
    /// The per-point height sigma stated at the map's build, metres (default: the build's default
    /// for its height source).
    #[arg(long)]
    pub height_point_sigma_m: Option<f64>,
}

pub fn run(a: FixBenchArgs) -> anyhow::Result<ExitCode> {
    let maps = super::repo_file("sitl/maps");
    let params: FixParams = match &a.set {
        Some(t) => {
            let v: toml::Value = toml::from_str(t).context("--set: not valid TOML")?;
            visnav::daemon::config::fix::fix_params_from_toml(v)
                .context("--set: not valid [fix] settings")?
        }
        None => FixParams::default(),
    };
    let descriptor = match a.descriptor {
        36 => DescriptorKind::Surf36,
        64 => DescriptorKind::Surf64,
        128 => DescriptorKind::Surf128,
        other => anyhow::bail!("--descriptor {other}: expected 36, 64 or 128"),
    };
    let surf = SurfParams {
        upright: true,
        hessian_threshold: a.hessian_threshold,
        descriptor,
        ..SurfParams::default()
    };
    let map_orthos = if a.map_ortho.is_empty() {
        vec![maps.join("naip_nd_2009.tif")]
    } else {
        a.map_ortho.clone()
    };
    if !(a.attitude_error_deg.is_finite() && a.attitude_error_deg >= 0.0) {
        anyhow::bail!(
            "--attitude-error-deg {}: expected a finite value >= 0",
            num(a.attitude_error_deg)
        );
    }
    if !(a.yaw_error_deg.is_finite() && (0.0..=180.0).contains(&a.yaw_error_deg)) {
        anyhow::bail!(
            "--yaw-error-deg {}: expected 0 to 180",
            num(a.yaw_error_deg)
        );
    }
    let yaw_sigma_deg = a
        .yaw_sigma_deg
        .unwrap_or(if a.yaw_error_deg > 0.0 { 30.0 } else { 0.5 });
    if !(yaw_sigma_deg.is_finite() && yaw_sigma_deg > 0.0 && yaw_sigma_deg <= 180.0) {
        anyhow::bail!(
            "--yaw-sigma-deg {}: expected more than 0, at most 180",
            num(yaw_sigma_deg)
        );
    }
    let attitude_mode = if a.no_attitude {
        AttitudeMode::None
    } else if a.tilt_only {
        AttitudeMode::TiltOnly
    } else {
        AttitudeMode::Full
    };
    let autzen = a.site == "autzen";
    let agl_range_m = match &a.agl_m {
        None => None,
        Some(t) => Some(parse_range(t).with_context(|| format!("--agl-m {}", quote(t)))?),
    };
    if let Some(t) = a.max_tilt_deg
        && !(t.is_finite() && (0.0..=60.0).contains(&t))
    {
        anyhow::bail!("--max-tilt-deg {}: expected 0 to 60", num(t));
    }
    let sigmas = HeightSigmas {
        offset_m: a.height_sigma_m,
        slope: a.height_slope_sigma,
        point_m: a.height_point_sigma_m,
    };

    let mut eval = if autzen {
        if !a.map_ortho.is_empty() || a.map_upsample != 1 || a.same_imagery {
            anyhow::bail!(
                "--map-ortho, --map-upsample and --same-imagery apply to the NAIP site only"
            );
        }
        let heights = if a.map_heights == "constant" {
            MapHeights::Constant(sigmas)
        } else if sigmas == HeightSigmas::default() {
            MapHeights::SurfaceModel(visnav::sitl::fixeval::AUTZEN_SURFACE_HEIGHTS)
        } else {
            MapHeights::SurfaceModel(sigmas)
        };
        let dir = super::repo_file("../shared/data/autzen");
        NaipEval::autzen(&dir, params, heights)
            .map_err(anyhow::Error::msg)
            .with_context(|| {
                format!(
                    "setting up the Autzen evaluation (data expected in {})",
                    dir.display()
                )
            })?
    } else {
        NaipEval::with_map_heights(&maps, &map_orthos, a.map_upsample, params, surf, sigmas)
            .map_err(anyhow::Error::msg)
            .context("setting up the NAIP cross-date evaluation")?
    };
    let camera_name = a
        .camera
        .clone()
        .unwrap_or_else(|| if autzen { "drone" } else { "vga" }.to_string());
    // Each site comes with its own camera (NaipEval); another is swapped in.
    match (camera_name.as_str(), autzen) {
        ("drone", false) => {
            let camera = visnav::sitl::render::drone_camera().context("the drone camera")?;
            eval = eval.with_camera(camera).map_err(anyhow::Error::msg)?;
        }
        ("vga", true) => {
            let camera = visnav::sitl::render::vga_camera().context("the VGA camera")?;
            eval = eval.with_camera(camera).map_err(anyhow::Error::msg)?;
        }
        _ => {}
    }
    let camera_text = if camera_name == "drone" {
        "1280 x 960 80 deg"
    } else {
        "VGA 60 deg"
    };
    eval.attitude_prior_error_rad = a.attitude_error_deg.to_radians();
    if let Some(r) = agl_range_m {
        eval.agl_range_m = r;
    }
    if let Some(t) = a.max_tilt_deg {
        eval.max_tilt_deg = t;
    }
    eval.yaw_error_deg = a.yaw_error_deg;
    eval.yaw_sigma_deg = yaw_sigma_deg;
    eval.attitude_mode = attitude_mode;
    eval.same_imagery = a.same_imagery;
    eval.altitude_without_position = !a.no_altitude;
    let per_frame = a.per_frame;
    let s = eval
        .run_with(a.frames, a.seed, !a.no_prior, &mut |line| {
            if per_frame {
                eprintln!("{line}");
            }
        })
        .map_err(anyhow::Error::msg)?;
    let prior_text = format!(
        "{}; {}",
        if a.no_prior && a.no_altitude {
            "no position prior, no altitude"
        } else if a.no_prior {
            "no position prior (the altitude prior kept)"
        } else {
            if autzen {
                "position prior 20 m off per axis"
            } else {
                "position prior 100 m off"
            }
        },
        match attitude_mode {
            AttitudeMode::None => "no attitude".to_string(),
            AttitudeMode::TiltOnly => format!(
                "tilt only ({:.1} deg off per axis, heading unknown)",
                a.attitude_error_deg
            ),
            AttitudeMode::Full => format!(
                "attitude {:.1} deg off per axis{}, heading sigma {yaw_sigma_deg} deg",
                a.attitude_error_deg,
                if a.yaw_error_deg > 0.0 {
                    format!(" + heading {} deg off", a.yaw_error_deg)
                } else {
                    String::new()
                }
            ),
        }
    );
    if a.json {
        let mut v = serde_json::to_value(&s)?;
        if let Some(o) = v.as_object_mut() {
            o.insert("prior".into(), prior_text.into());
            o.insert("same_imagery_diagnostic".into(), a.same_imagery.into());
            o.insert("site".into(), a.site.clone().into());
            o.insert("camera".into(), camera_name.clone().into());
            if autzen {
                o.insert("map_heights".into(), a.map_heights.clone().into());
            }
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        if a.same_imagery {
            println!(
                "DIAGNOSTIC: frames rendered from the map's own orthophoto (the solver's error, not an accuracy figure)"
            );
        }
        if autzen {
            println!(
                "Autzen (map on the {}, frames ray-cast on the lidar surface model, {camera_text}, {:.0}-{:.0} m AGL, tilt <= {} deg, {prior_text}): {} frames",
                if a.map_heights == "constant" {
                    "surface model's median height (constant)"
                } else {
                    "lidar surface model"
                },
                eval.agl_range_m.0,
                eval.agl_range_m.1,
                eval.max_tilt_deg,
                s.frames
            );
        } else {
            println!(
                "NAIP {} (map {} x{}, frames {}, {camera_text}, {:.0}-{:.0} m AGL, tilt <= {} deg, {prior_text}): {} frames",
                if a.same_imagery {
                    "same-imagery"
                } else {
                    "cross-date"
                },
                map_orthos
                    .iter()
                    .map(|p| p.file_name().unwrap_or_default().to_string_lossy())
                    .collect::<Vec<_>>()
                    .join(" + "),
                a.map_upsample,
                if a.same_imagery {
                    "from the map image"
                } else {
                    "2014"
                },
                eval.agl_range_m.0,
                eval.agl_range_m.1,
                eval.max_tilt_deg,
                s.frames
            );
        }
        println!(
            "  accepted {} ({:.0} %), beyond 3 sigma on an axis {}, wrong {} ({} more than {} m off in 3-D, {} outside {} sigma on an axis or jointly horizontally), image-only NEES(6) mean {}",
            s.accepted,
            100.0 * s.fix_rate,
            s.beyond_3_sigma,
            s.wrong_fixes,
            s.wrong_far,
            visnav::sitl::fixeval::WRONG_FIX_M,
            s.wrong_beyond_sigma,
            visnav::sitl::fixeval::WRONG_FIX_SIGMAS,
            // Placement fixes carry no image-only pose: with only those there is no mean.
            if s.nees6_mean.is_finite() {
                format!("{:.1}", s.nees6_mean)
            } else {
                "- (no image-only pose)".to_string()
            }
        );
        if s.accepted > 0 {
            println!(
                "  horizontal error median {:.1} m ({:.2} map px) p90 {:.1} max {:.1}; vertical median {:.1} p90 {:.1} max {:.1}",
                s.err_h_m.median,
                s.median_err_map_px,
                s.err_h_m.p90,
                s.err_h_m.max,
                s.err_v_m.median,
                s.err_v_m.p90,
                s.err_v_m.max
            );
        } else {
            println!("  no fix accepted: no errors to report");
        }
        println!(
            "  frame to fix: p50 {:.1} ms, p95 {:.1} ms",
            s.ms_p50, s.ms_p95
        );
        // One line per kind of reason, with the latest of its kind as the engine wrote it.
        for r in &s.rejections {
            println!("  rejected {:3}, latest: {}", r.count, r.reason);
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `LO:HI` or one value (LO = HI), metres above ground: finite, 30 m to 10 km, LO <= HI.
fn parse_range(t: &str) -> anyhow::Result<(f64, f64)> {
    let num = |s: &str| -> anyhow::Result<f64> {
        s.trim()
            .parse::<f64>()
            .with_context(|| format!("{} is not a number", quote(s)))
    };
    let (lo, hi) = match t.split_once(':') {
        Some((l, h)) => (num(l)?, num(h)?),
        None => {
            let v = num(t)?;
            (v, v)
        }
    };
    if !(lo.is_finite()
        && hi.is_finite()
        && (30.0..=10_000.0).contains(&lo)
        && lo <= hi
        && hi <= 10_000.0)
    {
        anyhow::bail!("expected heights from 30 to 10000 m with LO <= HI");
    }
    Ok((lo, hi))
}

#[cfg(test)]
mod tests {
    use super::parse_range;

    #[test]
    fn agl_range_parses_and_refuses() {
        assert_eq!(parse_range("1000").ok(), Some((1000.0, 1000.0)));
        assert_eq!(parse_range("900:1100").ok(), Some((900.0, 1100.0)));
        for bad in ["", "abc", "1100:900", "20", "NaN", "1000:inf", "1:2:3"] {
            assert!(parse_range(bad).is_err(), "{bad}");
        }
    }
}
