//! `handflow rig show FILE` and `handflow rig convert FILE --out rig.toml`: a calibration as
//! handflow understands it, and the same in handflow's own TOML.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Subcommand;
use handflow_protocol::{Rig, RigFormat};

/// The `rig` subcommands.
#[derive(Subcommand, Debug)]
pub enum RigCommand {
    /// Print a calibration as understood: format, cameras (size, focal lengths, centre,
    /// viewing direction, mount quarter turns), baselines, the world's up and notes.
    Show {
        /// Calibration file (anipose/Pose2Sim TOML, caliscope camera_array.toml, OpenCV
        /// YAML or XML), or a recording folder holding one.
        file: PathBuf,
    },
    /// Write a calibration in handflow's TOML (the rig.toml of a recording).
    Convert {
        /// Calibration file in any supported format, or a recording folder holding one.
        file: PathBuf,
        /// Where to write the rig TOML.
        #[arg(long)]
        out: PathBuf,
    },
}

/// Runs a `rig` subcommand, printing to standard output.
pub fn run(command: &RigCommand) -> Result<()> {
    match command {
        RigCommand::Show { file } => {
            let (rig, source) = load(file)?;
            print!("{}", describe(&rig, &source));
            Ok(())
        }
        RigCommand::Convert { file, out } => {
            let (rig, source) = load(file)?;
            rig.save(out)?;
            println!(
                "wrote {} camera{} ({}) to {}",
                rig.cameras.len(),
                plural(rig.cameras.len()),
                source,
                out.display()
            );
            Ok(())
        }
    }
}

/// The rig of a file or folder and a description of where it came from.
fn load(path: &Path) -> Result<(Rig, String)> {
    if path.is_dir() {
        let files = Rig::find_in_dir(path)?;
        let mut rig = match files.as_slice() {
            [one] => Rig::load(one)?,
            several => Rig::load_files(several)?,
        };
        // A recording's rig as `track` takes it: its up from the faces where they overrule the
        // cameras' estimate. A folder whose recording does not open shows its calibration.
        if let Ok(rec) = handflow_ingest::Recording::open(path) {
            if let Some(found) = crate::face_up::face_up(&rec, rec.rig())? {
                rig.set_up(found.direction)?;
                rig.notes.push(found.summary());
            }
        }
        let names: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
        let format = files.first().map_or(Ok(None), |f| format_of(f).map(Some))?;
        let format = format.map_or_else(String::new, |f| format!("{f}: "));
        return Ok((rig, format!("{format}{}", names.join(", "))));
    }
    let (rig, format) = Rig::load_detected(path)?;
    Ok((rig, format!("{format}: {}", path.display())))
}

fn format_of(path: &Path) -> Result<RigFormat> {
    Rig::load_detected(path).map(|(_, format)| format).with_context(|| format!("reading {}", path.display()))
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}

fn vector(v: &nalgebra::Vector3<f64>) -> String {
    format!("[{:.4}, {:.4}, {:.4}]", v.x, v.y, v.z)
}

/// The text `rig show` prints.
pub fn describe(rig: &Rig, source: &str) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail.
    let _ = write_description(rig, source, &mut out);
    out
}

fn write_description(rig: &Rig, source: &str, out: &mut String) -> std::fmt::Result {
    writeln!(out, "format: {source}")?;
    writeln!(out, "cameras: {}", rig.cameras.len())?;
    for camera in &rig.cameras {
        let k = &camera.matrix;
        writeln!(out, "  {}:", camera.name)?;
        writeln!(out, "    size: {}x{}", camera.width, camera.height)?;
        writeln!(out, "    focal length: fx {:.2} px, fy {:.2} px", k[(0, 0)], k[(1, 1)])?;
        writeln!(out, "    principal point: ({:.2}, {:.2}) px", k[(0, 2)], k[(1, 2)])?;
        let coefficients = |values: &[f64]| values.iter().map(|v| format!("{v}")).collect::<Vec<_>>().join(" ");
        match &camera.fisheye {
            Some(lens) => writeln!(out, "    lens: fisheye, k1 k2 k3 k4 = {}", coefficients(&lens.as_array()))?,
            None if camera.distortion.is_zero() => writeln!(out, "    lens: pinhole, no distortion")?,
            None => {
                writeln!(out, "    lens: pinhole, k1 k2 p1 p2 k3 = {}", coefficients(&camera.distortion.as_array()))?
            }
        }
        writeln!(out, "    centre: {} m", vector(&camera.centre().coords))?;
        writeln!(out, "    viewing direction: {}", vector(&camera.viewing_direction()))?;
        writeln!(out, "    mount quarter turns: {}", camera.mount_quarter_turns)?;
    }
    if rig.cameras.len() > 1 {
        writeln!(out, "baselines (m):")?;
        let width = rig.cameras.iter().map(|c| c.name.chars().count()).max().unwrap_or(0).max(8);
        write!(out, "  {:width$}", "")?;
        for camera in &rig.cameras {
            write!(out, " {:>width$}", camera.name)?;
        }
        writeln!(out)?;
        for a in &rig.cameras {
            write!(out, "  {:width$}", a.name)?;
            for b in &rig.cameras {
                write!(out, " {:>width$.3}", (a.centre() - b.centre()).norm())?;
            }
            writeln!(out)?;
        }
    }
    let up = rig.world_up();
    writeln!(out, "world up: {} ({})", vector(&up.direction), up.source)?;
    if rig.notes.is_empty() {
        writeln!(out, "notes: none")?;
    } else {
        writeln!(out, "notes:")?;
        for note in &rig.notes {
            writeln!(out, "  {note}")?;
        }
    }
    Ok(())
}
