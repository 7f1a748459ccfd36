//! Video recordings through the real decoder: lossless round trips, caliscope timestamps,
//! encoder padding, and a corrupt frame in the middle.
//!
//! Fixtures are encoded here with the `ffmpeg` command-line tool (a test tool only; handflow
//! decodes with GStreamer). Without it the tests say so and pass, unless
//! `HANDFLOW_REQUIRE_FFMPEG=1` (as in CI), which makes its absence a failure.

#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

use handflow_ingest::{Layout, OpenOptions, Recording};
use handflow_protocol::{Camera, Distortion, Rig};
use nalgebra::{Matrix3, Rotation3, Vector3};

const W: u32 = 48;
const H: u32 = 32;
const FRAMES: u32 = 6;

fn have_ffmpeg() -> bool {
    let found = Command::new("ffmpeg").arg("-version").output().is_ok_and(|o| o.status.success());
    if !found {
        assert!(
            std::env::var("HANDFLOW_REQUIRE_FFMPEG").as_deref() != Ok("1"),
            "ffmpeg is required (HANDFLOW_REQUIRE_FFMPEG=1) but not installed"
        );
        eprintln!("skipping: the `ffmpeg` tool that encodes the fixtures is not installed");
    }
    found
}

fn rig(names: &[&str], width: u32, height: u32) -> Rig {
    let cameras = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            Camera::new(
                *name,
                width,
                height,
                Matrix3::new(40.0, 0.0, 23.5, 0.0, 40.0, 15.5, 0.0, 0.0, 1.0),
                Distortion::default(),
                Rotation3::identity(),
                Vector3::new(-0.1 * k as f64, 0.0, 1.0),
            )
            .unwrap()
        })
        .collect();
    Rig::new(cameras)
}

/// Frame `f` of camera `c`: smooth ramps (lossy codecs keep them within a few levels) that
/// differ per pixel, frame and camera.
fn pixels(c: u32, f: u32) -> image::RgbImage {
    image::RgbImage::from_fn(W, H, |x, y| {
        image::Rgb([(x * 5 + f * 17) as u8, (y * 7 + c * 50) as u8, (x * 3 + y * 2 + f * 29 + c) as u8])
    })
}

/// Encodes camera `c`'s frames into `out` with `codec_args` (ffmpeg options after `-i`).
fn encode(c: u32, out: &Path, codec_args: &[&str]) {
    let frames = tempfile::tempdir().unwrap();
    for f in 0..FRAMES {
        pixels(c, f).save(frames.path().join(format!("{f:06}.png"))).unwrap();
    }
    let status = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-framerate", "10", "-i"])
        .arg(frames.path().join("%06d.png"))
        .args(codec_args)
        .arg(out)
        .status()
        .unwrap();
    assert!(status.success(), "ffmpeg encoding {}", out.display());
}

const LOSSLESS: [&str; 4] = ["-c:v", "ffv1", "-pix_fmt", "bgr0"];
/// Lossless RGB in an mp4 (x264's RGB mode), as a capture tool could write it.
const LOSSLESS_MP4: [&str; 6] = ["-c:v", "libx264rgb", "-qp", "0", "-pix_fmt", "rgb24"];

#[test]
fn lossless_videos_decode_to_the_frames_they_were_encoded_from() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    rig(&["cam_0", "cam_1"], W, H).save(dir.path().join("rig.toml")).unwrap();
    for c in 0..2 {
        encode(c, &dir.path().join(format!("cam_{c}.mkv")), &LOSSLESS);
    }
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!(rec.layout(), Layout::Videos);
    assert_eq!(rec.len(), FRAMES as usize);
    // No timestamp file: the containers' times, 10 frames per second.
    assert!((rec.frame_rate() - 10.0).abs() < 1e-6, "{}", rec.frame_rate());
    assert_eq!(rec.capture_spread().map(|s| s.max_s), Some(0.0));
    let mut buf = vec![0u8; rec.frame_set_len()];
    // In order, then backwards (a seek), then a jump.
    for k in [0u32, 1, 2, 3, 4, 5, 1, 4, 0] {
        let info = rec.read_frame_into(u64::from(k), false, &mut buf).unwrap();
        assert_eq!(info.frame, u64::from(k));
        let views = rec.views(&buf);
        for c in 0..2u32 {
            assert!(views[c as usize] == pixels(c, k).as_raw().as_slice(), "camera {c}, frame {k}: pixels differ");
        }
    }
    // --start and --frames select a part, keeping frame numbers.
    let options = OpenOptions { start: Some(2), frames: Some(3), ..OpenOptions::default() };
    let part = Recording::open_with(dir.path(), &options).unwrap();
    assert_eq!(part.frames().iter().map(|f| f.frame).collect::<Vec<_>>(), vec![2, 3, 4]);
    let info = part.read_frame_into(0, false, &mut buf).unwrap();
    assert_eq!(info.frame, 2);
    assert!(part.views(&buf)[1] == pixels(1, 2).as_raw().as_slice());
    // Preloading gives the same bytes.
    let mut preloaded = Recording::open(dir.path()).unwrap();
    preloaded.preload().unwrap();
    let mut again = vec![0u8; rec.frame_set_len()];
    preloaded.read_frame_into(3, false, &mut again).unwrap();
    rec.read_frame_into(3, false, &mut buf).unwrap();
    assert!(buf == again);
}

#[test]
fn caliscope_sessions_group_frames_by_sync_index_and_match_cameras_by_number() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // Pose2Sim-style names in the calibration, caliscope-style video names and cam_ids.
    rig(&["cam_01", "cam_02"], W, H).save(dir.path().join("rig.toml")).unwrap();
    for c in 0..2 {
        encode(c, &dir.path().join(format!("cam_{}.mp4", c + 1)), &["-c:v", "mpeg4", "-q:v", "2"]);
    }
    // Capture indices start at 40; camera 2 misses sync 42 (its frame 2 belongs to 43).
    let mut csv = String::from("sync_index,cam_id,frame_index,frame_time\n");
    for sync in 40..46u32 {
        let t = f64::from(sync) * 0.1;
        csv.push_str(&format!("{sync},1,{sync},{t}\n"));
        if sync != 42 {
            csv.push_str(&format!("{sync},2,{},{}\n", if sync < 42 { sync } else { sync - 1 }, t + 0.02));
        }
    }
    std::fs::write(dir.path().join("timestamps.csv"), csv).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    let numbers: Vec<u64> = rec.frames().iter().map(|f| f.frame).collect();
    assert_eq!(numbers, vec![0, 1, 3, 4, 5], "sync 42 lacks camera 2, so frame 2 is left out");
    assert!(rec.notes().iter().any(|n| n.contains("left out")), "{:?}", rec.notes());
    let spread = rec.capture_spread().unwrap();
    assert!((spread.max_s - 0.02).abs() < 1e-9 && (spread.median_s - 0.02).abs() < 1e-9, "{spread:?}");
    assert!((rec.frames()[0].timestamp - 4.01).abs() < 1e-9);
    // Frame 3 (sync 43) is video frame 3 of camera 1 and video frame 2 of camera 2.
    let mut buf = vec![0u8; rec.frame_set_len()];
    rec.read_frame_into(2, false, &mut buf).unwrap();
    let views = rec.views(&buf);
    let close = |view: &[u8], expected: &image::RgbImage| {
        let mean: f64 = view.iter().zip(expected.as_raw()).map(|(&a, &b)| f64::from(a.abs_diff(b))).sum::<f64>()
            / view.len() as f64;
        mean < 6.0
    };
    assert!(close(views[0], &pixels(0, 3)) && !close(views[0], &pixels(0, 2)), "camera 1 shows its frame 3");
    assert!(close(views[1], &pixels(1, 2)) && !close(views[1], &pixels(1, 3)), "camera 2 shows its frame 2");
}

#[test]
fn a_frame_a_webcam_dropped_leaves_its_set_to_the_other_cameras() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    rig(&["cam_0", "cam_1", "cam_2"], W, H).save(dir.path().join("rig.toml")).unwrap();
    // `cam_1` dropped its frame of sync 2 (its video holds five of the six instants), `cam_2`
    // its frames of syncs 2 and 4: set 2 has one camera, set 4 two.
    let kept = |c: u32, sync: u32| !matches!((c, sync), (1, 2) | (2, 2) | (2, 4));
    let mut csv = String::from("sync_index,cam_id,frame_index,frame_time\n");
    for c in 0..3u32 {
        let frames = tempfile::tempdir().unwrap();
        let mut position = 0;
        for sync in 0..FRAMES {
            if kept(c, sync) {
                pixels(c, sync).save(frames.path().join(format!("{position:06}.png"))).unwrap();
                csv.push_str(&format!("{sync},{c},{position},{}\n", f64::from(sync) * 0.1 + 0.01 * f64::from(c)));
                position += 1;
            }
        }
        let status = Command::new("ffmpeg")
            .args(["-loglevel", "error", "-y", "-framerate", "10", "-i"])
            .arg(frames.path().join("%06d.png"))
            .args(LOSSLESS)
            .arg(dir.path().join(format!("cam_{c}.mkv")))
            .status()
            .unwrap();
        assert!(status.success());
    }
    std::fs::write(dir.path().join("timestamps.csv"), csv).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    let numbers: Vec<u64> = rec.frames().iter().map(|f| f.frame).collect();
    assert_eq!(numbers, vec![0, 1, 3, 4, 5], "set 2 has one camera's frame: left out");
    let missing: Vec<u32> = rec.frames().iter().map(|f| f.missing_views).collect();
    assert_eq!(missing, vec![0, 0, 0, 0b100, 0], "set 4 is read without `cam_2`");
    let notes = rec.notes().join("\n");
    assert!(notes.contains("read with the other cameras: `cam_2` 1\n"), "{notes}");
    assert!(notes.contains("1 of 6 frame sets have frames from fewer than 2 cameras"), "{notes}");
    // Positions after a drop are the camera's own: set 3 is `cam_1`'s position 2, `cam_2`'s 2.
    let mut buf = vec![0u8; rec.frame_set_len()];
    for (index, sync) in [(2usize, 3u32), (3, 4), (4, 5)] {
        let info = rec.read_frame_into(index as u64, false, &mut buf).unwrap();
        assert_eq!(info.missing_views, missing[index]);
        for (c, view) in rec.views(&buf).into_iter().enumerate() {
            if kept(c as u32, sync) {
                assert_eq!(view, pixels(c as u32, sync).as_raw().as_slice(), "set {sync}, camera {c}");
            } else {
                assert!(view.iter().all(|&b| b == 0), "set {sync}: the dropped view reads as zeros");
            }
        }
    }
}

#[test]
fn padded_videos_are_accepted_and_other_sizes_refused_naming_camera_and_sizes() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    encode(0, &dir.path().join("cam_0.mkv"), &LOSSLESS);
    // The calibration says 8 px wider and 2 px taller: encoder padding.
    rig(&["cam_0"], W + 8, H + 2).save(dir.path().join("rig.toml")).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!((rec.rig().cameras[0].width, rec.rig().cameras[0].height), (W, H));
    assert_eq!(rec.rig().cameras[0].matrix, rig(&["cam_0"], W + 8, H + 2).cameras[0].matrix);
    assert!(rec.notes().iter().any(|n| n.contains("padding")), "{:?}", rec.notes());
    rig(&["cam_0"], W + 16, H).save(dir.path().join("rig.toml")).unwrap();
    let e = Recording::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("cam_0") && e.contains(&format!("{W}x{H}")) && e.contains(&format!("{}x{H}", W + 16)), "{e}");
    // A camera without a video is refused listing both sides.
    rig(&["cam_0", "side"], W, H).save(dir.path().join("rig.toml")).unwrap();
    let e = Recording::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("side") && e.contains("cam_0.mkv"), "{e}");
}

#[test]
fn a_corrupt_frame_in_the_middle_is_reported_and_the_rest_reads() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    rig(&["cam_0"], W, H).save(dir.path().join("rig.toml")).unwrap();
    let path = dir.path().join("cam_0.avi");
    encode(0, &path, &["-c:v", "mjpeg", "-q:v", "2"]);
    // Every MJPEG frame starts with a JPEG start-of-image marker; wipe frame 2's headers
    // (quantisation and Huffman tables, frame header) so that it cannot be decoded.
    let mut bytes = std::fs::read(&path).unwrap();
    let starts: Vec<usize> =
        bytes.windows(3).enumerate().filter(|(_, w)| *w == [0xFF, 0xD8, 0xFF]).map(|(i, _)| i).collect();
    assert_eq!(starts.len(), FRAMES as usize, "one JPEG per frame");
    for b in &mut bytes[starts[2] + 2..starts[2] + 400] {
        *b = 0;
    }
    std::fs::write(&path, bytes).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!(rec.len(), FRAMES as usize, "the container still lists every frame");
    let mut buf = vec![0u8; rec.frame_set_len()];
    for k in 0..FRAMES {
        let read = rec.read_frame_into(u64::from(k), false, &mut buf);
        if k == 2 {
            let e = read.unwrap_err();
            assert!(e.is_bad_frame(), "{e}");
            let e = e.to_string();
            assert!(e.contains("cam_0") && e.contains("frame 2"), "{e}");
        } else {
            read.unwrap_or_else(|e| panic!("frame {k}: {e}"));
            let mean: f64 = buf.iter().zip(pixels(0, k).as_raw()).map(|(&a, &b)| f64::from(a.abs_diff(b))).sum::<f64>()
                / buf.len() as f64;
            assert!(mean < 6.0, "frame {k} is its own image after the corrupt one (mean difference {mean})");
        }
    }
}

#[test]
fn a_video_cut_before_its_index_leaves_its_camera_out_quickly_while_two_remain() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    rig(&["cam_0", "cam_1", "cam_2"], W, H).save(dir.path().join("rig.toml")).unwrap();
    for c in 0..3 {
        // The index (`moov`) at the end, as capture tools write it: a cut copy has none.
        encode(c, &dir.path().join(format!("cam_{c}.mp4")), &LOSSLESS_MP4);
    }
    let cut = dir.path().join("cam_1.mp4");
    let bytes = std::fs::read(&cut).unwrap();
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    let started = std::time::Instant::now();
    let rec = Recording::open(dir.path()).unwrap();
    let took = started.elapsed();
    // The demuxer's error ends the probe at once, or (when `parsebin` swallows it, about one
    // open in ten) the first packet's 5 s timeout: not a 20 s wait for a stream that will
    // not come.
    assert!(took < std::time::Duration::from_secs(10), "opening took {took:?}");
    let names: Vec<&str> = rec.rig().cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["cam_0", "cam_2"]);
    let note = rec.notes().iter().find(|n| n.contains("left out")).expect("a note says which camera is left out");
    assert!(note.contains("cam_1") && note.contains("cam_1.mp4") && note.contains("2 of 3"), "{note}");
    assert_eq!(rec.len(), FRAMES as usize);
    let mut buf = vec![0u8; rec.frame_set_len()];
    let info = rec.read_frame_into(3, false, &mut buf).unwrap();
    assert_eq!(info.frame, 3);
    assert_eq!(&buf[(W * H * 3) as usize..], pixels(2, 3).as_raw().as_slice(), "the second view is cam_2's");

    // With only one readable video left there is nothing to replay: the cut camera's error.
    std::fs::remove_file(dir.path().join("cam_2.mp4")).unwrap();
    rig(&["cam_0", "cam_1"], W, H).save(dir.path().join("rig.toml")).unwrap();
    let e = Recording::open(dir.path()).unwrap_err().to_string();
    assert!(e.contains("cam_1") && e.contains("cam_1.mp4"), "{e}");
}

#[test]
fn a_stream_without_colorimetry_decodes_as_ffmpeg_decodes_it() {
    if !have_ffmpeg() {
        return;
    }
    // 1280x720 with no colour tags, as OpenCV writes webcam recordings: GStreamer would guess
    // BT.709 from the size; the writers' (and ffmpeg's) convention is BT.601.
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (1280u32, 720u32);
    let frame = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([
            ((x / 160) * 36) as u8,
            (255 - (y / 90) * 30) as u8,
            if (x / 320 + y / 180) % 2 == 0 { 230 } else { 20 },
        ])
    });
    let source = dir.path().join("frame.png");
    frame.save(&source).unwrap();
    let video = dir.path().join("cam_0.mp4");
    let status = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-i"])
        .arg(&source)
        .args(["-c:v", "mpeg4", "-q:v", "2", "-pix_fmt", "yuv420p"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(status.success());
    let reference = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-i"])
        .arg(&video)
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
        .output()
        .unwrap();
    assert!(reference.status.success());
    rig(&["cam_0"], w, h).save(dir.path().join("rig.toml")).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    let mut buf = vec![0u8; rec.frame_set_len()];
    rec.read_frame_into(0, false, &mut buf).unwrap();
    assert_eq!(reference.stdout.len(), buf.len());
    let mean: f64 =
        buf.iter().zip(&reference.stdout).map(|(&a, &b)| f64::from(a.abs_diff(b))).sum::<f64>() / buf.len() as f64;
    assert!(mean < 1.5, "mean difference from ffmpeg's decoding: {mean}");
}

#[test]
fn sessions_laid_out_as_pose2sim_caliscope_and_freemocap_ship_them_open_as_they_are() {
    if !have_ffmpeg() {
        return;
    }
    // Pose2Sim: videos/cam01.mp4.., calibration/Calib_board.toml with cameras cam_01..,
    // and the project's Config.toml at the top, which is not a calibration.
    let session = tempfile::tempdir().unwrap();
    let root = session.path();
    std::fs::create_dir_all(root.join("videos")).unwrap();
    std::fs::create_dir_all(root.join("calibration")).unwrap();
    std::fs::write(root.join("Config.toml"), "[project]\nframe_rate = 10\n").unwrap();
    rig(&["cam_01", "cam_02"], W, H).save(root.join("calibration/Calib_board.toml")).unwrap();
    for c in 0..2 {
        encode(c, &root.join(format!("videos/cam{:02}.mp4", c + 1)), &LOSSLESS_MP4);
    }
    let rec = Recording::open(root).unwrap();
    assert_eq!(rec.layout(), Layout::Videos);
    assert!(rec.calibration_paths()[0].ends_with("calibration/Calib_board.toml"));
    assert_eq!(rec.len(), FRAMES as usize);
    let mut buf = vec![0u8; rec.frame_set_len()];
    rec.read_frame_into(1, false, &mut buf).unwrap();
    assert!(rec.views(&buf)[1] == pixels(1, 1).as_raw().as_slice(), "cam02.mp4 is camera cam_02");

    // caliscope: recordings/recording_1/ below the session's camera_array.toml, with the
    // older frame_time_history.csv (cameras as `port`, no sync_index).
    let session = tempfile::tempdir().unwrap();
    let recording = session.path().join("recordings/recording_1");
    std::fs::create_dir_all(&recording).unwrap();
    let calibration = rig(&["cam_0", "cam_1"], W, H).to_toml_string();
    let caliscope: String = calibration.replace("[cam_0]", "[cameras.0]").replace("[cam_1]", "[cameras.1]");
    std::fs::write(session.path().join("camera_array.toml"), caliscope).unwrap();
    for c in 0..2 {
        encode(c, &recording.join(format!("cam_{c}.mp4")), &LOSSLESS_MP4);
    }
    let mut csv = String::from("port,frame_index,frame_time\n");
    for f in 0..FRAMES {
        for c in 0..2 {
            csv.push_str(&format!("{c},{f},{}\n", 5.0 + f64::from(f) * 0.1 + f64::from(c) * 0.01));
        }
    }
    std::fs::write(recording.join("frame_time_history.csv"), csv).unwrap();
    let rec = Recording::open(&recording).unwrap_or_else(|e| panic!("{e}"));
    assert!(rec.calibration_paths()[0].ends_with("camera_array.toml"));
    assert_eq!(rec.len(), FRAMES as usize);
    let spread = rec.capture_spread().unwrap();
    assert!((spread.max_s - 0.01).abs() < 1e-9, "{spread:?}");

    // Older caliscope: the cameras in the project's config.toml (`[cam_N]` with a `port`,
    // among the project's settings), videos named by port.
    let old_config = calibration.replace("name = \"cam_0\"", "port = 0").replace("name = \"cam_1\"", "port = 1");
    let old_config = format!("camera_count = 2\n{old_config}\n[charuco]\ncolumns = 4\nrows = 5\n");
    std::fs::remove_file(session.path().join("camera_array.toml")).unwrap();
    for c in 0..2 {
        std::fs::rename(recording.join(format!("cam_{c}.mp4")), recording.join(format!("port_{c}.mp4"))).unwrap();
    }
    // A `config.toml` that is not caliscope's is not taken for a calibration.
    std::fs::write(session.path().join("config.toml"), "[project]\nframe_rate = 10\n").unwrap();
    let error = Recording::open(&recording).expect_err("no calibration").to_string();
    assert!(error.contains("calibration"), "{error}");
    std::fs::write(session.path().join("config.toml"), old_config).unwrap();
    let rec = Recording::open(&recording).unwrap_or_else(|e| panic!("{e}"));
    assert!(rec.calibration_paths()[0].ends_with("config.toml"));
    let names: Vec<&str> = rec.rig().cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["cam_0", "cam_1"]);
    assert_eq!(rec.len(), FRAMES as usize);
    rec.read_frame_into(1, false, &mut buf).unwrap();
    assert!(rec.views(&buf)[1] == pixels(1, 1).as_raw().as_slice(), "port_1.mp4 is camera cam_1");

    // FreeMoCap: synchronized_videos/Camera_000_synchronized.mp4.., the calibration as
    // `<session>_camera_calibration.toml` beside other files of the recording.
    let session = tempfile::tempdir().unwrap();
    let root = session.path();
    std::fs::create_dir_all(root.join("synchronized_videos")).unwrap();
    std::fs::create_dir_all(root.join("output_data")).unwrap();
    std::fs::write(root.join("settings.toml"), "[recording]\nname = \"session_1\"\n").unwrap();
    rig(&["cam_0", "cam_1"], W, H).save(root.join("session_1_camera_calibration.toml")).unwrap();
    // Before its videos are there, the error says where they were looked for.
    let error = Recording::open(root).expect_err("no videos yet").to_string();
    assert!(error.contains("no video") && error.contains("synchronized_videos/") && error.contains("cam_1"), "{error}");
    for c in 0..2 {
        encode(c, &root.join(format!("synchronized_videos/Camera_{c:03}_synchronized.mp4")), &LOSSLESS_MP4);
    }
    let rec = Recording::open(root).unwrap_or_else(|e| panic!("{e}"));
    assert!(rec.calibration_paths()[0].ends_with("session_1_camera_calibration.toml"));
    assert_eq!(rec.len(), FRAMES as usize);
    rec.read_frame_into(2, false, &mut buf).unwrap();
    assert!(rec.views(&buf)[1] == pixels(1, 2).as_raw().as_slice(), "Camera_001 is camera cam_1");
}

#[test]
fn every_codec_and_container_people_record_in_decodes_to_its_frames() {
    if !have_ffmpeg() {
        return;
    }
    let cases: [(&str, &[&str]); 6] = [
        ("h264.mp4", &["-c:v", "libx264", "-crf", "10", "-pix_fmt", "yuv420p"]),
        ("h265.mkv", &["-c:v", "libx265", "-crf", "10", "-pix_fmt", "yuv420p", "-x265-params", "log-level=error"]),
        ("vp9.webm", &["-c:v", "libvpx-vp9", "-crf", "10", "-b:v", "0"]),
        ("mjpeg.avi", &["-c:v", "mjpeg", "-q:v", "2"]),
        ("mpeg4.mov", &["-c:v", "mpeg4", "-q:v", "2"]),
        ("ffv1.mkv", &LOSSLESS),
    ];
    for (name, args) in cases {
        let dir = tempfile::tempdir().unwrap();
        rig(&["cam_0"], W, H).save(dir.path().join("rig.toml")).unwrap();
        encode(0, &dir.path().join(format!("cam_0.{}", name.rsplit('.').next().unwrap())), args);
        let rec = Recording::open(dir.path()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(rec.len(), FRAMES as usize, "{name}");
        let mut buf = vec![0u8; rec.frame_set_len()];
        for k in [0, 3, 5, 1] {
            rec.read_frame_into(u64::from(k), false, &mut buf).unwrap_or_else(|e| panic!("{name}, frame {k}: {e}"));
            let difference = |f: u32| {
                buf.iter().zip(pixels(0, f).as_raw()).map(|(&a, &b)| f64::from(a.abs_diff(b))).sum::<f64>()
                    / buf.len() as f64
            };
            let mean = difference(k);
            assert!(mean < 8.0, "{name}, frame {k}: mean difference {mean} from the frame encoded");
            let nearest = (0..FRAMES).min_by(|&a, &b| difference(a).total_cmp(&difference(b)));
            assert_eq!(nearest, Some(k), "{name}: the frame read is frame {k}, not another");
        }
    }
}

/// Camera 0's frames, lossless, in an mp4 whose orientation tag says to show them turned a
/// quarter (as a phone stores portrait video); ffmpeg's own decoding of it, turned as
/// players show it.
fn tagged_quarter_turn(dir: &Path) -> Vec<u8> {
    let stored = dir.join("stored.mp4");
    encode(0, &stored, &LOSSLESS_MP4);
    let video = dir.join("cam_0.mp4");
    let status = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-i"])
        .arg(&stored)
        .args(["-c", "copy", "-metadata:s:v:0", "rotate=90"])
        .arg(&video)
        .status()
        .unwrap();
    assert!(status.success());
    std::fs::remove_file(&stored).unwrap();
    let shown = Command::new("ffmpeg")
        .args(["-loglevel", "error", "-i"])
        .arg(&video)
        .args(["-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
        .output()
        .unwrap();
    assert!(shown.status.success());
    shown.stdout
}

#[test]
fn a_video_tagged_to_be_shown_turned_is_read_as_players_show_it_unless_calibrated_as_stored() {
    if !have_ffmpeg() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let shown_by_ffmpeg = tagged_quarter_turn(dir.path());
    let frame_len = (W * H * 3) as usize;
    assert_eq!(shown_by_ffmpeg.len(), FRAMES as usize * frame_len);

    // Calibrated on the frames as shown (what OpenCV-based calibration tools read): H x W.
    rig(&["cam_0"], H, W).save(dir.path().join("rig.toml")).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!((rec.rig().cameras[0].width, rec.rig().cameras[0].height), (H, W));
    assert!(
        rec.notes().iter().any(|n| n.contains("cam_0") && n.contains("turned as players show them")),
        "{:?}",
        rec.notes()
    );
    let mut buf = vec![0u8; rec.frame_set_len()];
    for f in 0..FRAMES as usize {
        rec.read_frame_into(f as u64, false, &mut buf).unwrap();
        assert_eq!(buf, shown_by_ffmpeg[f * frame_len..][..frame_len], "frame {f} differs from ffmpeg's");
        // The tag (`rotate=90` as ffmpeg writes it) shows the stored right edge on top.
        assert_eq!(buf, image::imageops::rotate270(&pixels(0, f as u32)).into_raw(), "frame {f}");
    }

    // Calibrated on the stored frames: read as stored, and said so.
    rig(&["cam_0"], W, H).save(dir.path().join("rig.toml")).unwrap();
    let rec = Recording::open(dir.path()).unwrap();
    assert_eq!((rec.rig().cameras[0].width, rec.rig().cameras[0].height), (W, H));
    assert!(rec.notes().iter().any(|n| n.contains("read as stored")), "{:?}", rec.notes());
    rec.read_frame_into(2, false, &mut buf).unwrap();
    assert_eq!(buf, pixels(0, 2).into_raw());

    // Neither: refused, naming the camera, both sizes and the tag.
    rig(&["cam_0"], 2 * W, 2 * H).save(dir.path().join("rig.toml")).unwrap();
    let e = Recording::open(dir.path()).unwrap_err().to_string();
    assert!(
        e.contains("cam_0")
            && e.contains(&format!("{H}x{W}"))
            && e.contains(&format!("stored {W}x{H}"))
            && e.contains("tagged"),
        "{e}"
    );
}
