//! caliscope's calibrations, in both layouts its versions write:
//!
//! - `camera_array.toml`: one `[cameras.N]` table per camera;
//! - the project's `config.toml` of older versions: one `[cam_N]` table per camera, with its
//!   `port`, beside the project's other settings (`[charuco]`, `camera_count`, ...), which are
//!   ignored; rotations there are Rodrigues vectors (caliscope saved them so).
//!
//! Each camera table has `size`, `matrix` (K), `distortions` (k1 k2 p1 p2 k3; with
//! `fisheye = true`, OpenCV's fisheye k1 k2 k3 k4), `rotation` (world to camera, 3x3 or a
//! Rodrigues vector), `translation` (world to camera, metres) and `rotation_count`
//! (clockwise quarter turns that make the raw frames upright, -3..=3); the calibration is
//! of the raw frames, so it is kept as [`super::Camera::mount_quarter_turns`] and
//! projection ignores it. caliscope's bookkeeping (`cam_id`, `port`, `error`, `exposure`,
//! `grid_count`, `verified_resolutions`) is ignored; an `ignore = true` camera is left out
//! with a note, and so is a camera caliscope has not calibrated yet (no `matrix` and
//! `distortions`) or not posed yet (no `rotation` and `translation`): caliscope writes no
//! field it has no value for, and a project lists every camera connected. Camera `N`
//! (or port `N`) is named `cam_N`, and cameras are in the order of `N`.

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

/// Key prefix of a camera table in the older `config.toml`.
const CONFIG_CAMERA_PREFIX: &str = "cam_";

/// The port field of a camera table in the older `config.toml`.
const PORT: &str = "port";

/// True when the document is an older caliscope project's `config.toml`: a top-level
/// `[cam_N]` table with an integer `port` (anipose's camera tables have a `name` instead).
pub(super) fn is_caliscope_config(root: &OrderedRoot) -> bool {
    root.0.iter().any(|(key, value)| config_camera_id(key, value).is_some())
}

/// `N` of a `[cam_N]` camera table of the older `config.toml`.
fn config_camera_id(key: &str, value: &Value) -> Option<u64> {
    let id = key.strip_prefix(CONFIG_CAMERA_PREFIX)?.parse::<u64>().ok()?;
    match value {
        Value::Table(table) if matches!(table.get(PORT), Some(Value::Integer(_))) => Some(id),
        _ => None,
    }
}

/// The rig of a caliscope `camera_array.toml` (see the module documentation).
pub(super) fn parse(root: OrderedRoot) -> Result<Rig, RigError> {
    let Some(Value::Table(cameras)) = root.0.into_iter().find(|(key, _)| key == CAMERAS).map(|(_, v)| v) else {
        return Err(RigError::NoCameras);
    };
    rig_of(cameras.into_iter().map(|(id, value)| (format!("{CAMERAS}.{id}"), id, value)).collect())
}

/// The rig of an older caliscope project's `config.toml` (see the module documentation).
pub(super) fn parse_config(root: OrderedRoot) -> Result<Rig, RigError> {
    let entries = root
        .0
        .into_iter()
        .filter_map(|(key, value)| config_camera_id(&key, &value).map(|n| (key, n.to_string(), value)))
        .collect();
    rig_of(entries)
}

/// The rig of camera tables `(table key, N, table)`, in the order of `N`.
fn rig_of(mut entries: Vec<(String, String, Value)>) -> Result<Rig, RigError> {
    // By N as a number: the table's own order is by key text ("10" before "2").
    entries.sort_by(|(_, a, _), (_, b, _)| match (a.parse::<u64>(), b.parse::<u64>()) {
        (Ok(x), Ok(y)) => x.cmp(&y),
        _ => a.cmp(b),
    });
    let mut rig = Rig::new(Vec::new());
    let mut cameras = CameraList::default();
    for (key, id, value) in entries {
        let name = format!("cam_{id}");
        let context = Context { key: &key, name: Some(&name) };
        let Value::Table(table) = value else {
            return Err(RigError::NotATable { key, found: describe(&value) });
        };
        let left_out = match table.get("ignore") {
            None | Some(Value::Boolean(false)) => None,
            Some(Value::Boolean(true)) => Some("is marked `ignore = true` by caliscope"),
            Some(other) => {
                return Err(context.error("ignore", format!("expected a boolean, found {}", describe(other))))
            }
        };
        // caliscope writes no field it has no value for: a camera without its lens's fields
        // is not calibrated yet, one without both pose fields not posed yet. A table missing
        // only some of either is damaged, and its first missing field is the error.
        let left_out = left_out.or_else(|| {
            if !table.contains_key("matrix") && !table.contains_key("distortions") {
                Some("has no `matrix` or `distortions`: not calibrated yet")
            } else if !table.contains_key("rotation") && !table.contains_key("translation") {
                Some("has no `rotation` or `translation`: not posed yet (only its lens is calibrated)")
            } else {
                None
            }
        });
        if let Some(why) = left_out {
            let note = format!("camera `{name}` (table `{key}`) {why}: left out");
            tracing::warn!("{note}");
            rig.notes.push(note);
            continue;
        }
        cameras.push(&key, camera_from_table(&key, name.clone(), &table, ROTATION_COUNT)?)?;
    }
    rig.cameras = cameras.finish()?;
    Ok(rig)
}
