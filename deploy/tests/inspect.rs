//! End-to-end test of `handflow inspect` on a tiny rendered recording: the pictures it
//! writes, its summary, the diagnostics it logs by default and its errors.

#![allow(clippy::unwrap_used)]

mod common;

use std::path::Path;

use common::{describe, handflow};
use handflow::commands::inspect::{LAYERS, MONTAGE_TILE_WIDTH};

fn arg(path: &Path) -> &str {
    path.to_str().expect("UTF-8 temporary path")
}

/// Decodes a PNG (by its content, not its name) and returns its size.
fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("reading `{}`: {e}", path.display()));
    assert!(bytes.starts_with(b"\x89PNG\r\n\x1a\n"), "`{}` is not a PNG", path.display());
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .unwrap_or_else(|e| panic!("decoding `{}`: {e}", path.display()));
    (img.width(), img.height())
}

/// `handflow inspect` writes every layer of every camera at the camera's size, a montage of
/// them all, a summary naming each camera, and (with no log settings) the diagnostics.
#[test]
fn inspect_writes_every_layer_of_every_camera_and_a_montage() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-3cam", "--frames", "4", "--out", arg(&rec)]);
    assert!(r.status.success(), "{}", describe(&r));
    let out = tmp.path().join("inspect");
    let r = handflow(&["inspect", "--recording", arg(&rec), "--frame", "2", "--out", arg(&out)]);
    assert!(r.status.success(), "{}", describe(&r));
    let summary = String::from_utf8_lossy(&r.stdout);
    let cameras = handflow_ingest::Recording::open(&rec).unwrap().rig().cameras.clone();
    assert_eq!(cameras.len(), 3);
    for cam in &cameras {
        assert!(summary.contains(&format!("camera `{}`: skin", cam.name)), "{}", describe(&r));
        for layer in LAYERS {
            let path = out.join(&cam.name).join(format!("{layer}.png"));
            assert_eq!(png_size(&path), (cam.width, cam.height), "{}", path.display());
        }
    }
    assert!(summary.contains("clusters:") && summary.contains("tracks:"), "{}", describe(&r));
    let tile_height = cameras[0].height * MONTAGE_TILE_WIDTH / cameras[0].width;
    assert_eq!(
        png_size(&out.join("montage.png")),
        (MONTAGE_TILE_WIDTH * LAYERS.len() as u32, tile_height * cameras.len() as u32)
    );
    // The scene points the clusters were fitted to: as many rows as the summary counts,
    // each a finite position, velocity, weight and skin probability.
    let csv = std::fs::read_to_string(out.join("points.csv")).unwrap();
    let mut rows = csv.lines();
    assert_eq!(rows.next(), Some("x,y,z,vx,vy,vz,weight,skin"));
    let rows: Vec<Vec<f32>> = rows.map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    let counted = format!(", {} points", rows.len());
    assert!(summary.lines().next().is_some_and(|l| l.ends_with(&counted)), "{counted}\n{}", describe(&r));
    assert!(!rows.is_empty() && rows.iter().all(|r| r.len() == 8 && r.iter().all(|v| v.is_finite())));
    // The diagnostics show without HANDFLOW_LOG: skin shares and every camera's face status.
    let log = String::from_utf8_lossy(&r.stderr);
    assert!(log.contains("skin share of the image"), "{}", describe(&r));
    for cam in &cameras {
        assert!(log.contains(&format!("camera `{}`: ", cam.name)), "{}", describe(&r));
    }
}

/// A frame without an estimate or outside the recording is named.
#[test]
fn inspect_names_a_frame_it_cannot_show() {
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    let r = handflow(&["render", "--preset", "signer-2cam-narrow", "--frames", "3", "--out", arg(&rec)]);
    assert!(r.status.success(), "{}", describe(&r));
    let out = tmp.path().join("inspect");
    let no_first = ["--set", "estimate_first_frame=false"];
    for (frame, extra, expected) in
        [("0", &no_first[..], "first frame"), ("99", &[][..], "frame 99 is not in recording")]
    {
        let mut args = vec!["inspect", "--recording", arg(&rec), "--frame", frame, "--out", arg(&out)];
        args.extend_from_slice(extra);
        let r = handflow(&args);
        assert!(!r.status.success(), "{}", describe(&r));
        let err = String::from_utf8_lossy(&r.stderr);
        assert!(err.contains(expected), "expected `{expected}`\n{}", describe(&r));
    }
}
