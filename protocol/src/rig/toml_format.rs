//! Reading and writing the anipose / Pose2Sim rig TOML layout.
//!
//! Parsing goes through `toml::Value` by hand rather than serde derive so that
//! every error can name the camera, the field and what exactly is wrong.

use std::fmt::{self, Write as _};

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use serde::de::{Deserialize, Deserializer, MapAccess, Visitor};
use toml::Value;

use super::camera::rotation_problem;
use super::up::unit_up;
use super::{Camera, CameraList, Distortion, Fisheye, Rig, RigError, RigFormat, UpSource, WorldUp};

/// Tables with this name and no `matrix` hold calibration metadata, not a camera.
const METADATA_TABLE: &str = "metadata";

/// The top-level entries in file order. `toml::Table` sorts its keys unless
/// toml's `preserve_order` feature is on; toml's deserializer itself yields
/// them in document order, so collecting them here keeps the camera order
/// without changing the feature for the whole workspace.
pub(super) struct OrderedRoot(pub(super) Vec<(String, Value)>);

impl<'de> Deserialize<'de> for OrderedRoot {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct RootVisitor;
        impl<'de> Visitor<'de> for RootVisitor {
            type Value = OrderedRoot;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a TOML document")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<OrderedRoot, A::Error> {
                let mut entries = Vec::new();
                while let Some(entry) = map.next_entry::<String, Value>()? {
                    entries.push(entry);
                }
                Ok(OrderedRoot(entries))
            }
        }
        deserializer.deserialize_map(RootVisitor)
    }
}

/// Parses a rig file's text.
pub(crate) fn parse(text: &str) -> Result<Rig, RigError> {
    parse_detect(text).map(|(rig, _)| rig)
}

/// Parses a TOML rig file in any of its layouts: caliscope's (a `cameras` table of camera
/// tables, or an older project's `config.toml`, see [`super::caliscope`]) or anipose's.
pub(crate) fn parse_detect(text: &str) -> Result<(Rig, RigFormat), RigError> {
    let root: OrderedRoot = toml::from_str(text).map_err(|e| syntax_error(text, &e))?;
    if super::caliscope::is_caliscope(&root) {
        return super::caliscope::parse(root).map(|rig| (rig, RigFormat::Caliscope));
    }
    if super::caliscope::is_caliscope_config(&root) {
        return super::caliscope::parse_config(root).map(|rig| (rig, RigFormat::CaliscopeConfig));
    }
    parse_anipose(root).map(|rig| (rig, RigFormat::AniposeToml))
}

fn parse_anipose(root: OrderedRoot) -> Result<Rig, RigError> {
    let mut cameras = CameraList::default();
    let mut declared_up = None;
    for (key, value) in root.0 {
        let Value::Table(table) = value else {
            return Err(RigError::NotATable { key, found: describe(&value) });
        };
        if key == METADATA_TABLE && !table.contains_key("matrix") {
            declared_up = parse_metadata_up(&table)?;
            continue;
        }
        cameras.push(&key, parse_camera(&key, &table)?)?;
    }
    Ok(Rig { declared_up, ..Rig::new(cameras.finish()?) })
}

/// Keys of the `metadata` table that may state the world's up (ours writes `up`).
const UP_KEYS: [&str; 2] = ["up", "world_up"];

/// The up a `metadata` table declares, if any: `up` (or `world_up`) as 3 numbers, and
/// `up_source = "calibration" | "configured"` (default `calibration`), which our writer
/// emits so that a user's choice stays one across processes.
fn parse_metadata_up(table: &toml::Table) -> Result<Option<WorldUp>, RigError> {
    let Some((field, value)) = UP_KEYS.iter().find_map(|key| table.get(*key).map(|v| (*key, v))) else {
        return Ok(None);
    };
    let metadata_error = |field: &str, problem: String| RigError::Metadata { field: field.to_owned(), problem };
    let v = parse_numbers(value, 3, "expected 3 numbers (x, y, z)").map_err(|p| metadata_error(field, p))?;
    let direction = unit_up(Vector3::new(v[0], v[1], v[2])).map_err(|p| metadata_error(field, p))?;
    let source = match table.get("up_source") {
        None => UpSource::Calibration,
        Some(Value::String(s)) if s == "calibration" => UpSource::Calibration,
        Some(Value::String(s)) if s == "configured" => UpSource::Configured,
        Some(other) => {
            return Err(metadata_error(
                "up_source",
                format!("expected \"calibration\" or \"configured\", found {}", describe(other)),
            ))
        }
    };
    Ok(Some(WorldUp { direction, source }))
}

/// An optional quarter-turn count: an integer, taken modulo 4 (caliscope writes -3..=3).
pub(super) fn parse_quarter_turns(value: Option<&Value>) -> Result<u8, String> {
    match value {
        None => Ok(0),
        // rem_euclid(4) is in 0..4, so the cast is exact.
        Some(Value::Integer(i)) => Ok(i.rem_euclid(4) as u8),
        Some(other) => Err(format!("expected an integer number of quarter turns, found {}", describe(other))),
    }
}

/// Turns toml's error into [`RigError::Syntax`] with a 1-based line and column.
pub(super) fn syntax_error(text: &str, error: &toml::de::Error) -> RigError {
    let before = error.span().and_then(|span| text.get(..span.start));
    let (line, column) = match before {
        Some(before) => {
            let line = before.matches('\n').count() + 1;
            let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            (Some(line), Some(column))
        }
        None => (None, None),
    };
    let mut message = error.message().trim().to_owned();
    if message.is_empty() {
        // toml says nothing for some inputs: show the line it stopped on instead.
        let at = line.and_then(|l| text.lines().nth(l - 1)).unwrap_or_default();
        message = format!("this line does not parse as TOML: `{}`", at.trim());
    }
    RigError::Syntax { line, column, message }
}

/// Where a problem is: the camera table's key and, once read, its name.
pub(super) struct Context<'a> {
    pub(super) key: &'a str,
    pub(super) name: Option<&'a str>,
}

impl Context<'_> {
    pub(super) fn error(&self, field: &str, problem: impl Into<String>) -> RigError {
        RigError::Field {
            camera: self.key.to_owned(),
            name: self.name.map(str::to_owned),
            field: field.to_owned(),
            problem: problem.into(),
        }
    }
}

fn parse_camera(key: &str, table: &toml::Table) -> Result<Camera, RigError> {
    let context = Context { key, name: None };
    let name = match table.get("name") {
        Some(Value::String(name)) => name.clone(),
        Some(other) => return Err(context.error("name", format!("expected a string, found {}", describe(other)))),
        None => return Err(context.error("name", "missing")),
    };
    camera_from_table(key, name, table, MOUNT_KEY)
}

/// The camera of table `key` named `name`: `size`, `matrix`, `distortions`, `rotation`,
/// `translation`, optional `fisheye` (then `distortions` are its `k1 k2 k3 k4`) and the
/// optional quarter-turn count `mount_key`. Shared by the anipose and caliscope layouts,
/// which agree on these fields.
pub(super) fn camera_from_table(
    key: &str,
    name: String,
    table: &toml::Table,
    mount_key: &str,
) -> Result<Camera, RigError> {
    let context = Context { key, name: Some(&name) };
    let get = |field: &str| table.get(field).ok_or_else(|| context.error(field, "missing"));

    // First: it decides what `distortions` hold.
    let fisheye = match table.get("fisheye") {
        None | Some(Value::Boolean(false)) => false,
        Some(Value::Boolean(true)) => true,
        Some(other) => return Err(context.error("fisheye", format!("expected a boolean, found {}", describe(other)))),
    };

    let (width, height) = parse_size(get("size")?).map_err(|p| context.error("size", p))?;
    let matrix =
        parse_matrix3(get("matrix")?, "expected 3 rows of 3 numbers").map_err(|p| context.error("matrix", p))?;
    let (distortion, fisheye) = if fisheye {
        let k = parse_numbers(get("distortions")?, 4, "expected the 4 fisheye coefficients k1 k2 k3 k4")
            .map_err(|p| context.error("distortions", p))?;
        (Distortion::default(), Some(Fisheye { k1: k[0], k2: k[1], k3: k[2], k4: k[3] }))
    } else {
        (parse_distortions(get("distortions")?).map_err(|p| context.error("distortions", p))?, None)
    };
    let rotation = parse_rotation(get("rotation")?).map_err(|p| context.error("rotation", p))?;
    let translation = parse_numbers(get("translation")?, 3, "expected 3 numbers (x, y, z)")
        .map(|v| Vector3::new(v[0], v[1], v[2]))
        .map_err(|p| context.error("translation", p))?;

    let turns = parse_quarter_turns(table.get(mount_key)).map_err(|p| context.error(mount_key, p))?;

    Camera::new(name.clone(), width, height, matrix, distortion, rotation, translation)
        .and_then(|camera| match fisheye {
            Some(fisheye) => camera.with_fisheye(fisheye),
            None => Ok(camera),
        })
        .map(|camera| camera.with_mount_quarter_turns(turns))
        .map_err(|error| match error {
            // Camera::new knows the camera by name only; point at the table too.
            RigError::Field { field, problem, .. } => context.error(&field, problem),
            other => other,
        })
}

/// Our key for [`Camera::mount_quarter_turns`] (written only when non-zero, so that files
/// of upright rigs stay plain anipose files).
const MOUNT_KEY: &str = "mount_quarter_turns";

/// "a string", "an array of 2 values", ... for error messages.
pub(super) fn describe(value: &Value) -> String {
    match value {
        Value::Array(items) => format!("an array of {} value{}", items.len(), plural(items.len())),
        Value::Integer(i) => format!("an integer ({i})"),
        Value::Float(f) => format!("a float ({f})"),
        Value::String(s) => format!("a string ({s:?})"),
        Value::Boolean(b) => format!("a boolean ({b})"),
        Value::Datetime(_) => "a datetime".to_owned(),
        Value::Table(_) => "a table".to_owned(),
    }
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}

/// A finite number; integers are accepted for floats (anipose writes both).
fn parse_number(value: &Value, what: &str) -> Result<f64, String> {
    match value {
        // i64 -> f64 may round beyond 2^53, which no calibration value reaches.
        Value::Integer(i) => Ok(*i as f64),
        Value::Float(f) if f.is_finite() => Ok(*f),
        Value::Float(f) => Err(format!("{what} is not finite ({f})")),
        other => Err(format!("{what}: expected a number, found {}", describe(other))),
    }
}

/// Exactly `len` finite numbers; `expected` describes the shape for errors.
fn parse_numbers(value: &Value, len: usize, expected: &str) -> Result<Vec<f64>, String> {
    let numbers = parse_number_list(value, expected)?;
    if numbers.len() != len {
        return Err(format!("{expected}, found {} number{}", numbers.len(), plural(numbers.len())));
    }
    Ok(numbers)
}

/// An array of finite numbers of any length.
fn parse_number_list(value: &Value, expected: &str) -> Result<Vec<f64>, String> {
    let Value::Array(items) = value else {
        return Err(format!("{expected}, found {}", describe(value)));
    };
    items.iter().enumerate().map(|(i, item)| parse_number(item, &format!("element {i}"))).collect()
}

fn parse_matrix3(value: &Value, expected: &str) -> Result<Matrix3<f64>, String> {
    let Value::Array(rows) = value else {
        return Err(format!("{expected}, found {}", describe(value)));
    };
    if rows.len() != 3 {
        return Err(format!("{expected}, found {} row{}", rows.len(), plural(rows.len())));
    }
    let mut matrix = Matrix3::zeros();
    for (i, row) in rows.iter().enumerate() {
        let Value::Array(entries) = row else {
            return Err(format!("{expected}, row {i} is {}", describe(row)));
        };
        if entries.len() != 3 {
            return Err(format!("{expected}, row {i} has {} number{}", entries.len(), plural(entries.len())));
        }
        for (j, entry) in entries.iter().enumerate() {
            matrix[(i, j)] = parse_number(entry, &format!("row {i}, column {j}"))?;
        }
    }
    Ok(matrix)
}

fn parse_size(value: &Value) -> Result<(u32, u32), String> {
    const EXPECTED: &str = "expected [width, height] as 2 positive integers";
    let Value::Array(items) = value else {
        return Err(format!("{EXPECTED}, found {}", describe(value)));
    };
    if items.len() != 2 {
        return Err(format!("{EXPECTED}, found {} value{}", items.len(), plural(items.len())));
    }
    let dimension = |item: &Value, what: &str| -> Result<u32, String> {
        // Pose2Sim writes sizes as floats (`1920.0`): accept integral values.
        let number = match item {
            Value::Integer(i) => *i as f64,
            Value::Float(f) if f.is_finite() && f.fract() == 0.0 => *f,
            Value::Float(f) => return Err(format!("{EXPECTED}, {what} is {f}")),
            other => return Err(format!("{EXPECTED}, {what} is {}", describe(other))),
        };
        if number < 1.0 || number > f64::from(u32::MAX) {
            return Err(format!("{EXPECTED}, {what} is {number}"));
        }
        Ok(number as u32)
    };
    Ok((dimension(&items[0], "width")?, dimension(&items[1], "height")?))
}

fn parse_distortions(value: &Value) -> Result<Distortion, String> {
    const EXPECTED: &str = "expected 4 or 5 numbers (k1 k2 p1 p2 [k3])";
    let c = parse_number_list(value, EXPECTED)?;
    match c[..] {
        // Four coefficients (Pose2Sim) mean k3 = 0, as in OpenCV.
        [k1, k2, p1, p2] => Ok(Distortion { k1, k2, p1, p2, k3: 0.0 }),
        [k1, k2, p1, p2, k3] => Ok(Distortion { k1, k2, p1, p2, k3 }),
        _ => Err(format!("{EXPECTED}, found {} number{}", c.len(), plural(c.len()))),
    }
}

/// A Rodrigues vector, or a 3x3 rotation matrix (some tools write that).
fn parse_rotation(value: &Value) -> Result<Rotation3<f64>, String> {
    const EXPECTED: &str = "expected a Rodrigues vector of 3 numbers or a 3x3 rotation matrix";
    if let Value::Array(items) = value {
        if let Some(Value::Array(_)) = items.first() {
            let matrix = parse_matrix3(value, "3x3 rotation matrix: expected 3 rows of 3 numbers")?;
            return rotation_from_matrix(&matrix);
        }
    }
    let v = parse_numbers(value, 3, EXPECTED)?;
    Ok(Rotation3::new(Vector3::new(v[0], v[1], v[2])))
}

/// Checks that `matrix` is a rotation, then removes its rounding noise (the
/// nearest rotation, `U Vᵀ`) so that it survives saving as a Rodrigues vector.
pub(super) fn rotation_from_matrix(matrix: &Matrix3<f64>) -> Result<Rotation3<f64>, String> {
    if let Some(problem) = rotation_problem(matrix) {
        return Err(problem);
    }
    let svd = matrix.svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => Ok(Rotation3::from_matrix_unchecked(u * v_t)),
        _ => Err("3x3 rotation matrix: SVD failed".to_owned()),
    }
}

/// The Rodrigues vector (axis × angle, angle in [0, π]) of a rotation.
///
/// Not `Rotation3::scaled_axis`: that one returns zero for a half-turn (the
/// axis it extracts from `R − Rᵀ` vanishes) and loses digits near 0 and π
/// (acos of the trace). Going through the quaternion is accurate everywhere.
pub(crate) fn rodrigues(rotation: &Rotation3<f64>) -> Vector3<f64> {
    let q = UnitQuaternion::from_rotation_matrix(rotation);
    // q and -q are the same rotation; w >= 0 gives the angle in [0, π].
    let (w, v) = if q.w < 0.0 { (-q.w, -q.imag()) } else { (q.w, q.imag()) };
    let s = v.norm();
    if s == 0.0 {
        return Vector3::zeros();
    }
    v * (2.0 * s.atan2(w) / s)
}

/// The rig in the file format.
pub(crate) fn write(rig: &Rig) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail.
    let _ = write_into(rig, &mut out);
    out
}

fn write_into(rig: &Rig, out: &mut String) -> fmt::Result {
    for (i, camera) in rig.cameras.iter().enumerate() {
        if i > 0 {
            writeln!(out)?;
        }
        let k = &camera.matrix;
        writeln!(out, "[cam_{i}]")?;
        writeln!(out, "name = {}", quote(&camera.name))?;
        writeln!(out, "size = [{}, {}]", camera.width, camera.height)?;
        let rows: Vec<String> = (0..3).map(|r| list(&[k[(r, 0)], k[(r, 1)], k[(r, 2)]])).collect();
        writeln!(out, "matrix = [{}]", rows.join(", "))?;
        match &camera.fisheye {
            Some(fisheye) => writeln!(out, "distortions = {}", list(&fisheye.as_array()))?,
            None => writeln!(out, "distortions = {}", list(&camera.distortion.as_array()))?,
        }
        writeln!(out, "rotation = {}", list(rodrigues(&camera.rotation).as_slice()))?;
        writeln!(out, "translation = {}", list(camera.translation.as_slice()))?;
        writeln!(out, "fisheye = {}", camera.fisheye.is_some())?;
        if camera.mount_quarter_turns != 0 {
            writeln!(out, "{MOUNT_KEY} = {}", camera.mount_quarter_turns)?;
        }
    }
    if let Some(up) = &rig.declared_up {
        let source = match up.source {
            UpSource::Configured => "configured",
            // An estimate is recomputed by the reader; it is never declared.
            UpSource::Calibration | UpSource::Estimated { .. } => "calibration",
        };
        writeln!(out, "\n[{METADATA_TABLE}]")?;
        writeln!(out, "up = {}", list(up.direction.as_slice()))?;
        writeln!(out, "up_source = {}", quote(source))?;
    }
    Ok(())
}

/// `[a, b, c]` with each number written to read back bit for bit.
fn list(values: &[f64]) -> String {
    let items: Vec<String> = values.iter().map(|&v| float(v)).collect();
    format!("[{}]", items.join(", "))
}

/// Rust's `{:?}` is the shortest text that reads back to the same f64 and is
/// valid TOML (`1.0`, `1e-7`, `inf`), except NaN.
fn float(value: f64) -> String {
    if value.is_nan() {
        "nan".to_owned()
    } else {
        format!("{value:?}")
    }
}

/// A TOML basic string.
fn quote(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\t' => out.push_str("\\t"),
            '\r' => out.push_str("\\r"),
            c if c.is_control() => {
                let _ = write!(out, "\\u{:04X}", u32::from(c));
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn rodrigues_round_trips_including_half_turns_and_tiny_angles() {
        let vectors = [
            Vector3::zeros(),
            Vector3::new(PI, 0.0, 0.0),
            Vector3::new(0.0, -PI, 0.0),
            Vector3::new(1.0, 1.0, 1.0).normalize() * PI,
            Vector3::new(1.0, -2.0, 0.5).normalize() * (PI - 1e-9),
            Vector3::new(1e-9, 2e-9, -3e-9),
            Vector3::new(1e-200, 0.0, 0.0),
            Vector3::new(0.3, -1.2, 0.7),
        ];
        for v in vectors {
            let rotation = Rotation3::new(v);
            let back = Rotation3::new(rodrigues(&rotation));
            let error = (back.matrix() - rotation.matrix()).amax();
            assert!(error < 1e-14, "{v:?}: {error}");
        }
        // What nalgebra's own scaled_axis gets wrong (see `rodrigues`'s doc).
        let half_turn = Rotation3::new(Vector3::new(PI, 0.0, 0.0));
        assert!((rodrigues(&half_turn).norm() - PI).abs() < 1e-15);
    }

    #[test]
    fn floats_are_written_as_valid_toml_that_reads_back_exactly() {
        for v in [0.0, -0.0, 1.0, 0.1, 1e-7, 1e16, 1e300, -2.5e-300, f64::MAX, f64::MIN_POSITIVE, 1.0 / 3.0] {
            let text = format!("x = {}", float(v));
            let table: toml::Table = toml::from_str(&text).unwrap();
            let back = table["x"].as_float().unwrap();
            assert_eq!(back.to_bits(), v.to_bits(), "{text}");
        }
    }

    #[test]
    fn names_are_quoted_so_they_read_back() {
        for name in ["left", "a \"quoted\" \\ name", "tab\there", "ünï", "bell\u{7}"] {
            let text = format!("x = {}", quote(name));
            let table: toml::Table = toml::from_str(&text).unwrap();
            assert_eq!(table["x"].as_str(), Some(name));
        }
    }
}
