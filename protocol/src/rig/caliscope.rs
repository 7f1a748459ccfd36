//! caliscope's `camera_array.toml`: one `[cameras.N]` table per camera.
//!
//! Each table has `size`, `matrix` (K), `distortions` (k1 k2 p1 p2 k3), `rotation` (3x3,
//! world to camera), `translation` (world to camera, metres) and `rotation_count`
//! (clockwise quarter turns that make the raw frames upright, -3..=3); the calibration is
//! of the raw frames, so it is kept as [`super::Camera::mount_quarter_turns`] and
//! projection ignores it. caliscope's bookkeeping (`cam_id`, `error`, `exposure`,
//! `grid_count`, `verified_resolutions`) is ignored; an `ignore = true` camera is left out
//! with a note. Camera `N` is named `cam_N`, and cameras are in the order of `N`.

use toml::Value;

use super::toml_format::{camera_from_table, describe, Context, OrderedRoot};
use super::{CameraList, Rig, RigError};

/// The top-level table holding the cameras.
const CAMERAS: &str = "cameras";

/// caliscope's quarter-turn field.
const ROTATION_COUNT: &str = "rotation_count";

/// True when the document is caliscope's: a top-level `cameras` table of tables (an
/// anipose file could only have a camera table called `cameras`, with a `matrix`).
pub(super) fn is_caliscope(root: &OrderedRoot) -> bool {
    root.0.iter().any(|(key, value)| match value {
        Value::Table(table) if key == CAMERAS => {
            !table.contains_key("matrix") && table.values().any(|v| matches!(v, Value::Table(_)))
        }
        _ => false,
    })
}

/// The rig of a caliscope document (see the module documentation).
pub(super) fn parse(root: OrderedRoot) -> Result<Rig, RigError> {
    let Some(Value::Table(cameras)) = root.0.into_iter().find(|(key, _)| key == CAMERAS).map(|(_, v)| v) else {
        return Err(RigError::NoCameras);
    };
    // Sort by N as a number: the table's own order is by key text ("10" before "2").
    let mut entries: Vec<(String, Value)> = cameras.into_iter().collect();
    entries.sort_by(|(a, _), (b, _)| match (a.parse::<u64>(), b.parse::<u64>()) {
        (Ok(x), Ok(y)) => x.cmp(&y),
        _ => a.cmp(b),
    });
    let mut rig = Rig::new(Vec::new());
    let mut cameras = CameraList::default();
    for (id, value) in entries {
        let key = format!("{CAMERAS}.{id}");
        let name = format!("cam_{id}");
        let context = Context { key: &key, name: Some(&name) };
        let Value::Table(table) = value else {
            return Err(RigError::NotATable { key, found: describe(&value) });
        };
        match table.get("ignore") {
            None | Some(Value::Boolean(false)) => {}
            Some(Value::Boolean(true)) => {
                let note = format!("camera `{name}` (table `{key}`) is marked `ignore = true` by caliscope: left out");
                tracing::warn!("{note}");
                rig.notes.push(note);
                continue;
            }
            Some(other) => {
                return Err(context.error("ignore", format!("expected a boolean, found {}", describe(other))))
            }
        }
        cameras.push(&key, camera_from_table(&key, name.clone(), &table, ROTATION_COUNT)?)?;
    }
    rig.cameras = cameras.finish()?;
    Ok(rig)
}
