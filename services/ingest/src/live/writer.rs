//! Frame sets written as a recording that `handflow run` and `handflow track` replay: the
//! calibration as `rig.toml`, `frames.csv` with each set's capture time, and one video per
//! camera, lossless (FFV1 in Matroska) unless a quality is given (H.264 at that quantizer).

use std::io::Write;
use std::path::{Path, PathBuf};

use gstreamer as gst;
use gstreamer::prelude::*;
use gstreamer_app as gst_app;
use handflow_protocol::Rig;

/// How long finishing a video may take before the recording is declared broken.
const FINISH_TIMEOUT_S: u64 = 30;

/// Why a recording could not be written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WriteError {
    /// A file of the recording could not be written.
    #[error("recording `{}`: {problem}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        problem: String,
    },
}

/// GStreamer encoder and muxer of a WebM video (VP8) that browsers and players read: what
/// `handflow overlay --video` writes.
pub const WEBM_VP8: &str =
    "vp8enc deadline=1 cpu-used=4 end-usage=cq cq-level=12 target-bitrate=8000000 keyframe-max-dist=60 ! webmmux";

/// One video being written from RGB8 frames at a fixed rate.
pub struct VideoFileWriter {
    path: PathBuf,
    pipeline: gst::Pipeline,
    source: gst_app::AppSrc,
    frame_len: usize,
    fps: f64,
    written: u64,
}

impl std::fmt::Debug for VideoFileWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoFileWriter").field("path", &self.path).field("written", &self.written).finish()
    }
}

impl VideoFileWriter {
    /// Starts `path`, `width` x `height` RGB8 frames at `fps` through `encoder` (a GStreamer
    /// description from the encoder to the muxer, e.g. [`WEBM_VP8`]).
    pub fn create(path: &Path, width: u32, height: u32, fps: f64, encoder: &str) -> Result<Self, WriteError> {
        crate::recording::video::init_gstreamer().map_err(|e| file_error(path, e))?;
        let (n, d) = if (fps - fps.round()).abs() < 1e-3 {
            (fps.round() as i32, 1)
        } else {
            ((fps * 1001.0).round() as i32, 1001)
        };
        let description = format!(
            "appsrc name=src format=time caps=video/x-raw,format=RGB,width={width},height={height},framerate={n}/{d} ! \
             videoconvert ! {encoder} ! filesink location=\"{}\"",
            path.display()
        );
        let pipeline = gst::parse::launch(&description)
            .map_err(|e| file_error(path, format!("cannot build the encoder ({e}); Debian: apt-get install gstreamer1.0-libav gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly")))?
            .downcast::<gst::Pipeline>()
            .map_err(|_| file_error(path, "the encoder is not a pipeline"))?;
        let source = pipeline
            .by_name("src")
            .and_then(|e| e.downcast::<gst_app::AppSrc>().ok())
            .ok_or_else(|| file_error(path, "the encoder has no source"))?;
        // Never drop: a video holds every frame it was given.
        source.set_block(true);
        source.set_max_bytes(64 << 20);
        pipeline
            .set_state(gst::State::Playing)
            .map_err(|e| file_error(path, format!("the encoder would not start: {e}")))?;
        let frame_len = width as usize * height as usize * 3;
        Ok(Self { path: path.to_owned(), pipeline, source, frame_len, fps, written: 0 })
    }

    /// Appends one RGB8 frame, shown for one frame interval after the previous one.
    pub fn push(&mut self, rgb: &[u8]) -> Result<(), WriteError> {
        if rgb.len() != self.frame_len {
            return Err(file_error(&self.path, format!("a frame of {} bytes, {} expected", rgb.len(), self.frame_len)));
        }
        let pts = gst::ClockTime::from_nseconds((self.written as f64 * 1e9 / self.fps) as u64);
        let duration = gst::ClockTime::from_nseconds((1e9 / self.fps) as u64);
        let mut buffer = gst::Buffer::from_mut_slice(rgb.to_vec());
        if let Some(b) = buffer.get_mut() {
            b.set_pts(pts);
            b.set_duration(duration);
        }
        self.source
            .push_buffer(buffer)
            .map_err(|e| file_error(&self.path, format!("encoding frame {}: {e}", self.written)))?;
        self.written += 1;
        Ok(())
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Says the video has ended; [`VideoFileWriter::wait`] then waits for its file.
    fn end(&self) -> Result<(), WriteError> {
        self.source.end_of_stream().map_err(|e| file_error(&self.path, format!("ending the video: {e}")))?;
        Ok(())
    }

    /// Waits until the ended video's file is complete.
    fn wait(&self) -> Result<(), WriteError> {
        let bus = self.pipeline.bus().ok_or_else(|| file_error(&self.path, "the encoder has no bus"))?;
        let done = bus.timed_pop_filtered(
            gst::ClockTime::from_seconds(FINISH_TIMEOUT_S),
            &[gst::MessageType::Eos, gst::MessageType::Error],
        );
        let _ = self.pipeline.set_state(gst::State::Null);
        match done.as_ref().map(|m| m.view()) {
            Some(gst::MessageView::Eos(_)) => Ok(()),
            Some(gst::MessageView::Error(e)) => Err(file_error(&self.path, e.error())),
            _ => Err(file_error(&self.path, format!("not finished within {FINISH_TIMEOUT_S} s"))),
        }
    }

    /// Ends the video; its file is complete once this returns.
    pub fn finish(self) -> Result<PathBuf, WriteError> {
        self.end()?;
        self.wait()?;
        Ok(self.path.clone())
    }

    /// Frames written so far.
    pub fn written(&self) -> u64 {
        self.written
    }
}

impl Drop for VideoFileWriter {
    fn drop(&mut self) {
        let _ = self.pipeline.set_state(gst::State::Null);
    }
}

/// A recording being written, one frame set at a time.
pub struct RecordingWriter {
    dir: PathBuf,
    videos: Vec<VideoFileWriter>,
    frames_csv: std::io::BufWriter<std::fs::File>,
    written: u64,
}

impl std::fmt::Debug for RecordingWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecordingWriter").field("dir", &self.dir).field("written", &self.written).finish()
    }
}

fn file_error(path: &Path, problem: impl std::fmt::Display) -> WriteError {
    WriteError::File { path: path.to_owned(), problem: problem.to_string() }
}

impl RecordingWriter {
    /// Starts a recording of `rig`'s cameras (all of one size) in `dir` (created; it must
    /// not hold a recording already), at a nominal `fps` (the videos' frame rate; the true
    /// capture times go to `frames.csv`). `quality`: `None` lossless, else H.264 at that
    /// quantizer (0 best, 51 worst).
    pub fn create(dir: &Path, rig: &Rig, fps: f64, quality: Option<u32>) -> Result<RecordingWriter, WriteError> {
        crate::recording::video::init_gstreamer().map_err(|e| file_error(dir, e))?;
        std::fs::create_dir_all(dir).map_err(|e| file_error(dir, e))?;
        if dir.join("frames.csv").exists() {
            return Err(file_error(dir, "already holds a recording (frames.csv); choose a new folder"));
        }
        let rig_path = dir.join("rig.toml");
        std::fs::write(&rig_path, rig.to_toml_string()).map_err(|e| file_error(&rig_path, e))?;
        let csv_path = dir.join("frames.csv");
        let file = std::fs::File::create(&csv_path).map_err(|e| file_error(&csv_path, e))?;
        let mut frames_csv = std::io::BufWriter::new(file);
        writeln!(frames_csv, "frame,timestamp").map_err(|e| file_error(&csv_path, e))?;
        let mut videos = Vec::with_capacity(rig.cameras.len());
        for cam in &rig.cameras {
            let (extension, encoder) = match quality {
                None => ("mkv", "avenc_ffv1 ! matroskamux".to_string()),
                Some(q) => {
                    ("mp4", format!("x264enc pass=quant quantizer={} speed-preset=veryfast ! mp4mux", q.min(51)))
                }
            };
            let path = dir.join(format!("{}.{extension}", cam.name));
            videos.push(VideoFileWriter::create(&path, cam.width, cam.height, fps, &encoder)?);
        }
        Ok(RecordingWriter { dir: dir.to_owned(), videos, frames_csv, written: 0 })
    }

    /// Appends a frame set: frame number `frame`, capture time `timestamp_s` (seconds,
    /// increasing), every camera's RGB8 view back to back in rig order.
    pub fn write_set(&mut self, frame: u64, timestamp_s: f64, views: &[u8]) -> Result<(), WriteError> {
        let total: usize = self.videos.iter().map(|v| v.frame_len).sum();
        if views.len() != total {
            return Err(file_error(&self.dir, format!("a frame set of {} bytes, {total} expected", views.len())));
        }
        let mut offset = 0;
        for video in &mut self.videos {
            let view = &views[offset..offset + video.frame_len];
            offset += video.frame_len;
            video.push(view)?;
        }
        // The shortest text that reads back as the same number: replays see the same times.
        writeln!(self.frames_csv, "{frame},{timestamp_s}").map_err(|e| file_error(&self.dir.join("frames.csv"), e))?;
        self.written += 1;
        Ok(())
    }

    /// Frame sets written so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Ends every video (their files are complete once this returns) and `frames.csv`.
    pub fn finish(mut self) -> Result<PathBuf, WriteError> {
        self.frames_csv.flush().map_err(|e| file_error(&self.dir.join("frames.csv"), e))?;
        // Every video ended first, so they finish together.
        for video in &self.videos {
            video.end()?;
        }
        for video in &self.videos {
            video.wait()?;
        }
        Ok(self.dir.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Recording;

    #[test]
    fn a_lossless_recording_reads_back_bit_for_bit_with_its_times() {
        let dir = tempfile::tempdir().unwrap();
        let rig_text = "[cam_a]\nname = \"cam_a\"\nsize = [32, 24]\nmatrix = [[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]]\n\
                        distortions = [0.0, 0.0, 0.0, 0.0, 0.0]\nrotation = [0.0, 0.0, 0.0]\ntranslation = [0.0, 0.0, 0.0]\n\n\
                        [cam_b]\nname = \"cam_b\"\nsize = [32, 24]\nmatrix = [[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]]\n\
                        distortions = [0.0, 0.0, 0.0, 0.0, 0.0]\nrotation = [0.0, 0.0, 0.0]\ntranslation = [0.2, 0.0, 0.0]\n";
        let rig = Rig::from_str_detect(rig_text, "rig").unwrap().0;
        let out = dir.path().join("rec");
        let mut writer = RecordingWriter::create(&out, &rig, 10.0, None).unwrap();
        let view = 32 * 24 * 3;
        let sets: Vec<Vec<u8>> = (0..5u32)
            .map(|f| (0..2 * view).map(|i| ((i as u32 * 7 + f * 31 + (i as u32 / 97) * 13) % 251) as u8).collect())
            .collect();
        let times = [0.0, 0.1003, 0.2001, 0.35, 0.4012345678901];
        for (f, set) in sets.iter().enumerate() {
            writer.write_set(f as u64, times[f], set).unwrap();
        }
        assert!(RecordingWriter::create(&out, &rig, 10.0, None).unwrap_err().to_string().contains("already holds"));
        writer.finish().unwrap();
        let rec = Recording::open(&out).unwrap();
        assert_eq!(rec.len(), 5);
        let mut buf = vec![0u8; 2 * view];
        for (f, set) in sets.iter().enumerate() {
            let info = rec.read_frame_into(f as u64, false, &mut buf).unwrap();
            assert_eq!(info.timestamp, times[f]);
            assert!(buf == *set, "frame {f} differs");
        }
    }
}
