//! `visnav camera import FILE [--camera camN]`: another tool's calibration (OpenCV / ROS
//! `camera_info` YAML, Kalibr camchain) printed as the configuration's `[camera]` and
//! `[camera.distortion]` sections (`visnav_io::calibration`), checked as `check-config` would.

use std::path::PathBuf;
use std::process::ExitCode;

use visnav::camera::calibration::{camera_toml, read_calibration};
use visnav_core::validate::{Problems, Validate};

#[derive(clap::Args, Debug)]
pub struct CameraArgs {
    #[command(subcommand)]
    pub command: CameraCommand,
}

#[derive(clap::Subcommand, Debug)]
pub enum CameraCommand {
    /// Print a calibration file (OpenCV or ROS camera_info YAML, Kalibr camchain YAML) as the
    /// configuration's [camera] and [camera.distortion] sections, to paste into it.
    Import(ImportArgs),
}

#[derive(clap::Args, Debug)]
pub struct ImportArgs {
    /// The calibration file.
    pub file: PathBuf,
    /// Which camera of a Kalibr camchain with several (cam0, cam1, ...).
    #[arg(long)]
    pub camera: Option<String>,
}

pub fn run(args: CameraArgs) -> anyhow::Result<ExitCode> {
    let CameraCommand::Import(a) = args.command;
    let cal = read_calibration(&a.file, a.camera.as_deref())?;
    let mut p = Problems::default();
    cal.camera.validate(&mut p);
    if !p.list.is_empty() {
        let list: Vec<String> = p.list.iter().map(|i| i.to_string()).collect();
        anyhow::bail!(
            "{}: the calibration is outside what visnav accepts:\n  {}",
            a.file.display(),
            list.join("\n  ")
        );
    }
    // Said on stderr too: the printed section is usually pasted without reading its comments.
    for n in &cal.notes {
        eprintln!("warning: {}: {n}", a.file.display());
    }
    print!("{}", camera_toml(&cal, &a.file));
    Ok(ExitCode::SUCCESS)
}
