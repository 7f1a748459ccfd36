//! `handflow export`: a trajectory file (JSON Lines) as TRC, C3D or CSV; `handflow track
//! --format` writes the same files directly.

use std::io::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use handflow_publish::TrajectoryRecord;

use crate::export::{c3d::write_c3d, csv::write_csv, trc::write_trc, MarkerSeries};

/// What a trajectory file is written as.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// JSON Lines, one record per frame (handflow's own).
    Jsonl,
    /// CSV with a header, one line per record.
    Csv,
    /// TRC markers `Head`, `LHand`, `RHand` (OpenSim, Pose2Sim).
    Trc,
    /// C3D points `Head`, `LHand`, `RHand` with residuals from the confidence.
    C3d,
}

impl Format {
    /// The format a file name's extension implies, if any.
    pub fn from_extension(path: &Path) -> Option<Format> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "jsonl" | "json" => Some(Format::Jsonl),
            "csv" => Some(Format::Csv),
            "trc" => Some(Format::Trc),
            "c3d" => Some(Format::C3d),
            _ => None,
        }
    }

    /// Whether the whole stream must be known before the file is written (a header that
    /// counts the frames).
    pub fn needs_all_records(self) -> bool {
        matches!(self, Format::Trc | Format::C3d)
    }
}

/// The format to write: `format` if given, else `out`'s extension, else JSON Lines.
pub fn choose_format(format: Option<Format>, out: Option<&Path>) -> Format {
    format.or_else(|| out.and_then(Format::from_extension)).unwrap_or(Format::Jsonl)
}

/// Writes `records` as `format` into `out` (standard output when `None`, except C3D, which
/// is binary and needs a file). `rate_hz` overrides the rate the records imply.
pub fn write_records(
    records: &[TrajectoryRecord],
    format: Format,
    out: Option<&Path>,
    rate_hz: Option<f64>,
) -> Result<()> {
    let mut sink: Box<dyn std::io::Write> = match out {
        Some(path) => Box::new(std::io::BufWriter::new(
            std::fs::File::create(path).with_context(|| format!("creating `{}`", path.display()))?,
        )),
        None if format == Format::C3d => bail!("C3D is binary: give the file to write with --out"),
        None => Box::new(std::io::stdout().lock()),
    };
    let name = out.and_then(|p| p.file_name()).map_or("stdout".into(), |n| n.to_string_lossy().into_owned());
    let written = match format {
        Format::Jsonl => records.iter().try_for_each(|r| {
            serde_json::to_writer(&mut sink, r)?;
            writeln!(sink)?;
            Ok(())
        }),
        Format::Csv => write_csv(records, &mut sink),
        Format::Trc => {
            let series = MarkerSeries::from_records(records, rate_hz)?;
            write_trc(&series, &name, &mut sink).map_err(anyhow::Error::from)
        }
        Format::C3d => {
            let series = MarkerSeries::from_records(records, rate_hz)?;
            write_c3d(&series, &mut sink).map_err(anyhow::Error::from)
        }
    };
    written.and_then(|()| sink.flush().map_err(anyhow::Error::from)).with_context(|| match out {
        Some(path) => format!("writing `{}`", path.display()),
        None => "writing to standard output".into(),
    })
}

/// `handflow export`: reads `tracks` and writes it as `format` (or as `out`'s extension says).
pub fn export(tracks: &Path, format: Option<Format>, out: Option<&PathBuf>, rate_hz: Option<f64>) -> Result<usize> {
    let records = crate::eval::tracks::read_tracks(tracks)?;
    let format = choose_format(format, out.map(PathBuf::as_path));
    write_records(&records, format, out.map(PathBuf::as_path), rate_hz)?;
    Ok(records.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_format_follows_the_flag_then_the_extension() {
        assert_eq!(choose_format(None, Some(Path::new("a/take.TRC"))), Format::Trc);
        assert_eq!(choose_format(None, Some(Path::new("take.c3d"))), Format::C3d);
        assert_eq!(choose_format(Some(Format::Csv), Some(Path::new("take.c3d"))), Format::Csv);
        assert_eq!(choose_format(None, Some(Path::new("take.txt"))), Format::Jsonl);
        assert_eq!(choose_format(None, None), Format::Jsonl);
    }

    #[test]
    fn c3d_to_standard_output_is_refused() {
        let error = write_records(&[], Format::C3d, None, None).unwrap_err().to_string();
        assert!(error.contains("--out"), "{error}");
    }
}
