//! OpenCV FileStorage calibration files, YAML and XML, as OpenCV's calibration tools write
//! them.
//!
//! Only the subset calibration files use is read: maps, sequences, scalars and
//! `opencv-matrix` nodes (`rows`, `cols`, `dt`, `data`). A camera is a map with
//! `camera_matrix` or `K` (3x3), `distortion_coefficients` or `D` (4, 5, 8, 12 or 14
//! numbers; beyond `k1 k2 p1 p2 k3` they must be zero), `R` (3x3, or 3 numbers: Rodrigues)
//! or `rvec` (Rodrigues), `T` or `tvec`, `image_width` and `image_height` (or
//! `image_size = [w, h]`), and optionally `name` / `camera_name` and `rotation_count`.
//!
//! One camera per file: those entries at the top level; the camera is named by its
//! `name` entry, else by the file stem. Several cameras in one file: one top-level map per
//! camera (`cam_0: { K: ..., D: ... }` in YAML, `<cam_0><K ...>` in XML), named by its
//! `name` entry, else by its key.

use nalgebra::{Matrix3, Rotation3, Vector3};

use super::toml_format::rotation_from_matrix;
use super::{Camera, CameraList, Distortion, Rig, RigError};

/// A FileStorage node.
#[derive(Clone, Debug, PartialEq)]
enum Node {
    /// Entries in file order.
    Map(Vec<(String, Node)>),
    /// Items in order.
    Seq(Vec<Node>),
    /// Text as written (quotes removed).
    Scalar(String),
    /// An `opencv-matrix` node's entries (`rows`, `cols`, `dt`, `data`), read when the
    /// camera that holds it is known so that errors can name it.
    Matrix(Vec<(String, Node)>),
}

impl Node {
    fn get(&self, key: &str) -> Option<&Node> {
        match self {
            Node::Map(entries) | Node::Matrix(entries) => entries.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }

    fn describe(&self) -> String {
        match self {
            Node::Map(_) => "a map".to_owned(),
            Node::Seq(items) => format!("a sequence of {} items", items.len()),
            Node::Scalar(text) => format!("{text:?}"),
            Node::Matrix(_) => "a matrix".to_owned(),
        }
    }
}

fn syntax(format: &'static str, line: usize, message: impl Into<String>) -> RigError {
    RigError::FormatSyntax { format, line, message: message.into() }
}

const YAML: &str = "OpenCV YAML";
const XML: &str = "OpenCV XML";

// ---------------------------------------------------------------------------------------
// YAML

/// One meaningful line: 1-based number, indentation and text without comment.
struct Line {
    number: usize,
    indent: usize,
    text: String,
}

/// Byte index of the first `#` outside quotes that starts a comment.
fn comment_start(text: &str) -> Option<usize> {
    let mut quote = None;
    for (i, c) in text.char_indices() {
        match (quote, c) {
            (None, '"' | '\'') => quote = Some(c),
            (Some(q), c) if c == q => quote = None,
            (None, '#') if i == 0 || text[..i].ends_with([' ', '\t']) => return Some(i),
            _ => {}
        }
    }
    None
}

/// Open minus closed brackets outside quotes.
fn bracket_depth(text: &str) -> i64 {
    let (mut depth, mut quote) = (0, None);
    for c in text.chars() {
        match (quote, c) {
            (None, '"' | '\'') => quote = Some(c),
            (Some(q), c) if c == q => quote = None,
            (None, '[' | '{') => depth += 1,
            (None, ']' | '}') => depth -= 1,
            _ => {}
        }
    }
    depth
}

fn yaml_lines(text: &str) -> Result<Vec<Line>, RigError> {
    let mut lines: Vec<Line> = Vec::new();
    let mut open: Option<Line> = None;
    for (i, raw) in text.lines().enumerate() {
        let number = i + 1;
        let raw = raw.trim_end_matches('\r');
        let trimmed = raw.trim();
        if trimmed.starts_with('%') || trimmed == "---" || trimmed == "..." {
            continue;
        }
        let content = comment_start(raw).map_or(raw, |at| &raw[..at]);
        if content.trim().is_empty() {
            continue;
        }
        let indent = content.len() - content.trim_start_matches(' ').len();
        if content[indent..].starts_with('\t') {
            return Err(syntax(YAML, number, "tab used for indentation (YAML indents with spaces)"));
        }
        // A flow sequence (`data: [ 1., 2.,`) may continue over several lines: join them.
        let line = match open.take() {
            Some(mut pending) => {
                pending.text.push(' ');
                pending.text.push_str(content.trim());
                pending
            }
            None => Line { number, indent, text: content.trim().to_owned() },
        };
        match bracket_depth(&line.text) {
            0 => lines.push(line),
            d if d > 0 => open = Some(line),
            _ => return Err(syntax(YAML, line.number, "unbalanced `]` or `}`")),
        }
    }
    if let Some(pending) = open {
        return Err(syntax(YAML, pending.number, "unclosed `[` or `{`"));
    }
    Ok(lines)
}

/// Splits `key: rest` at the first `:` outside quotes followed by a space or the end.
fn split_key(text: &str) -> Option<(String, &str)> {
    let mut quote = None;
    for (i, c) in text.char_indices() {
        match (quote, c) {
            (None, '"' | '\'') => quote = Some(c),
            (Some(q), c) if c == q => quote = None,
            (None, ':') if text[i + 1..].is_empty() || text[i + 1..].starts_with(' ') => {
                return Some((unquote(text[..i].trim()), text[i + 1..].trim()));
            }
            _ => {}
        }
    }
    None
}

fn unquote(text: &str) -> String {
    let t = text.trim();
    for q in ['"', '\''] {
        if t.len() >= 2 && t.starts_with(q) && t.ends_with(q) {
            return t[1..t.len() - 1].to_owned();
        }
    }
    t.to_owned()
}

/// Splits flow-collection content at top-level commas.
fn split_flow(inner: &str) -> Vec<&str> {
    let (mut parts, mut start, mut depth, mut quote) = (Vec::new(), 0, 0i64, None);
    for (i, c) in inner.char_indices() {
        match (quote, c) {
            (None, '"' | '\'') => quote = Some(c),
            (Some(q), c) if c == q => quote = None,
            (None, '[' | '{') => depth += 1,
            (None, ']' | '}') => depth -= 1,
            (None, ',') if depth == 0 => {
                parts.push(&inner[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    parts.push(&inner[start..]);
    parts.into_iter().map(str::trim).filter(|p| !p.is_empty()).collect()
}

/// A value written on one line: a flow sequence, a flow map or a scalar.
fn inline_value(text: &str, number: usize) -> Result<Node, RigError> {
    let text = text.trim();
    if let Some(inner) = text.strip_prefix('[') {
        let inner = inner.strip_suffix(']').ok_or_else(|| syntax(YAML, number, "expected `]` at the end"))?;
        return split_flow(inner)
            .into_iter()
            .map(|item| inline_value(item, number))
            .collect::<Result<_, _>>()
            .map(Node::Seq);
    }
    if let Some(inner) = text.strip_prefix('{') {
        let inner = inner.strip_suffix('}').ok_or_else(|| syntax(YAML, number, "expected `}` at the end"))?;
        let mut entries = Vec::new();
        for item in split_flow(inner) {
            let (key, rest) = split_key(item)
                .ok_or_else(|| syntax(YAML, number, format!("expected `key: value` in {{ }}, found `{item}`")))?;
            let (tag, rest) = split_tag(rest);
            entries.push((key, tagged(tag, inline_value(rest, number)?, number)?));
        }
        return Ok(Node::Map(entries));
    }
    Ok(Node::Scalar(unquote(text)))
}

/// `!!opencv-matrix rest` -> (Some(tag), rest).
fn split_tag(rest: &str) -> (Option<&str>, &str) {
    if rest.starts_with('!') {
        let end = rest.find(' ').unwrap_or(rest.len());
        (Some(&rest[..end]), rest[end..].trim())
    } else {
        (None, rest)
    }
}

fn tagged(tag: Option<&str>, value: Node, number: usize) -> Result<Node, RigError> {
    match (tag, value) {
        (Some(tag), Node::Map(entries)) if tag.contains("opencv-matrix") || tag.contains("opencv-nd-matrix") => {
            Ok(Node::Matrix(entries))
        }
        (Some(tag), other) if tag.contains("opencv-matrix") => Err(syntax(
            YAML,
            number,
            format!("`{tag}` must be followed by a map (rows, cols, dt, data), found {}", other.describe()),
        )),
        (_, value) => Ok(value),
    }
}

/// The block (map or sequence) whose lines start at `lines[*pos]` with `indent`.
fn yaml_block(lines: &[Line], pos: &mut usize, indent: usize) -> Result<Node, RigError> {
    let is_item = |line: &Line| line.text == "-" || line.text.starts_with("- ");
    if lines.get(*pos).is_some_and(is_item) {
        let mut items = Vec::new();
        while let Some(line) = lines.get(*pos) {
            if line.indent < indent || (line.indent == indent && !is_item(line)) {
                break;
            }
            if line.indent > indent || !is_item(line) {
                return Err(syntax(YAML, line.number, "unexpected indentation in a sequence"));
            }
            *pos += 1;
            let rest = line.text[1..].trim();
            if rest.is_empty() {
                match lines.get(*pos) {
                    Some(next) if next.indent > indent => items.push(yaml_block(lines, pos, next.indent)?),
                    _ => items.push(Node::Scalar(String::new())),
                }
            } else {
                items.push(inline_value(rest, line.number)?);
            }
        }
        return Ok(Node::Seq(items));
    }
    let mut entries = Vec::new();
    while let Some(line) = lines.get(*pos) {
        if line.indent < indent {
            break;
        }
        if line.indent > indent {
            return Err(syntax(YAML, line.number, "unexpected indentation"));
        }
        let (key, rest) = split_key(&line.text)
            .ok_or_else(|| syntax(YAML, line.number, format!("expected `key: value`, found `{}`", line.text)))?;
        *pos += 1;
        let (tag, rest) = split_tag(rest);
        let value = if rest.is_empty() {
            match lines.get(*pos) {
                Some(next) if next.indent > indent => yaml_block(lines, pos, next.indent)?,
                // A sequence may sit at its key's indentation.
                Some(next) if next.indent == indent && is_item(next) => yaml_block(lines, pos, indent)?,
                _ => Node::Scalar(String::new()),
            }
        } else {
            inline_value(rest, line.number)?
        };
        entries.push((key, tagged(tag, value, line.number)?));
    }
    Ok(Node::Map(entries))
}

fn parse_yaml(text: &str) -> Result<Node, RigError> {
    let lines = yaml_lines(text)?;
    let mut pos = 0;
    let indent = lines.first().map_or(0, |l| l.indent);
    let root = yaml_block(&lines, &mut pos, indent)?;
    if let Some(line) = lines.get(pos) {
        return Err(syntax(YAML, line.number, "unexpected indentation"));
    }
    Ok(root)
}

// ---------------------------------------------------------------------------------------
// XML

struct Xml<'a> {
    text: &'a str,
    pos: usize,
}

impl<'a> Xml<'a> {
    fn line(&self) -> usize {
        self.text[..self.pos].matches('\n').count() + 1
    }

    fn error(&self, message: impl Into<String>) -> RigError {
        syntax(XML, self.line(), message)
    }

    fn rest(&self) -> &'a str {
        &self.text[self.pos..]
    }

    /// Skips whitespace, comments and processing instructions.
    fn skip_misc(&mut self) -> Result<(), RigError> {
        loop {
            let trimmed = self.rest().trim_start();
            self.pos = self.text.len() - trimmed.len();
            let (open, close) = if trimmed.starts_with("<!--") {
                ("<!--", "-->")
            } else if trimmed.starts_with("<?") {
                ("<?", "?>")
            } else {
                return Ok(());
            };
            let end = trimmed.find(close).ok_or_else(|| self.error(format!("unclosed `{open}`")))?;
            self.pos += end + close.len();
        }
    }

    /// After `<`: the tag's name, its `type_id` attribute and whether it closes itself.
    fn open_tag(&mut self) -> Result<(String, Option<String>, bool), RigError> {
        let end = self.rest().find('>').ok_or_else(|| self.error("unclosed tag"))?;
        let inside = &self.rest()[1..end];
        let self_closing = inside.ends_with('/');
        let inside = inside.trim_end_matches('/');
        let name = inside.split_whitespace().next().unwrap_or("").to_owned();
        if name.is_empty() || name.starts_with('/') {
            return Err(self.error("expected an element name"));
        }
        let type_id = inside.find("type_id=").and_then(|at| {
            let value = &inside[at + "type_id=".len()..];
            let quote = value.chars().next()?;
            let value = &value[quote.len_utf8()..];
            value.find(quote).map(|end| value[..end].to_owned())
        });
        self.pos += end + 1;
        Ok((name, type_id, self_closing))
    }

    /// The content of element `name`, up to and including its closing tag.
    fn element(&mut self, name: &str, type_id: Option<&str>) -> Result<Node, RigError> {
        let opened = self.line();
        let mut children: Vec<(String, Node)> = Vec::new();
        let mut text = String::new();
        loop {
            let next = self.rest().find('<').ok_or_else(|| self.error(format!("element `{name}` is not closed")))?;
            text.push_str(&self.rest()[..next]);
            self.pos += next;
            if self.rest().starts_with("<!--") || self.rest().starts_with("<?") {
                self.skip_misc()?;
                continue;
            }
            if let Some(close) = self.rest().strip_prefix("</") {
                let end = close.find('>').ok_or_else(|| self.error("unclosed tag"))?;
                let closing = close[..end].trim();
                if closing != name {
                    return Err(self.error(format!(
                        "expected `</{name}>` (closing `<{name}>` of line {opened}), found `</{closing}>`"
                    )));
                }
                self.pos += 2 + end + 1;
                break;
            }
            let (child, child_type, self_closing) = self.open_tag()?;
            let value =
                if self_closing { Node::Scalar(String::new()) } else { self.element(&child, child_type.as_deref())? };
            children.push((child, value));
        }
        if type_id.is_some_and(|t| t.contains("opencv-matrix")) {
            return Ok(Node::Matrix(children));
        }
        if children.is_empty() {
            return Ok(Node::Scalar(unquote(&decode_entities(text.trim()))));
        }
        // FileStorage writes sequence items of structures as `<_>` elements.
        if children.iter().all(|(k, _)| k == "_") {
            return Ok(Node::Seq(children.into_iter().map(|(_, v)| v).collect()));
        }
        Ok(Node::Map(children))
    }
}

fn decode_entities(text: &str) -> String {
    text.replace("&lt;", "<").replace("&gt;", ">").replace("&quot;", "\"").replace("&apos;", "'").replace("&amp;", "&")
}

fn parse_xml(text: &str) -> Result<Node, RigError> {
    let mut xml = Xml { text: text.trim_start_matches('\u{feff}'), pos: 0 };
    xml.skip_misc()?;
    if !xml.rest().starts_with('<') {
        return Err(xml.error("expected `<opencv_storage>`"));
    }
    let (name, _, self_closing) = xml.open_tag()?;
    if name != "opencv_storage" {
        return Err(xml.error(format!("expected the root element `<opencv_storage>`, found `<{name}>`")));
    }
    let root = if self_closing { Node::Map(Vec::new()) } else { xml.element(&name, None)? };
    xml.skip_misc()?;
    if !xml.rest().is_empty() {
        return Err(xml.error("content after `</opencv_storage>`"));
    }
    // An empty storage reads as an empty scalar.
    Ok(match root {
        Node::Scalar(s) if s.is_empty() => Node::Map(Vec::new()),
        other => other,
    })
}

// ---------------------------------------------------------------------------------------
// Cameras

const MATRIX_KEYS: [&str; 2] = ["camera_matrix", "K"];
const DISTORTION_KEYS: [&str; 2] = ["distortion_coefficients", "D"];
const ROTATION_KEYS: [&str; 2] = ["R", "rvec"];
const TRANSLATION_KEYS: [&str; 2] = ["T", "tvec"];
const NAME_KEYS: [&str; 2] = ["name", "camera_name"];

/// Where a problem is: the camera's key (file stem or map key) and its name.
struct Context<'a> {
    key: &'a str,
    name: &'a str,
}

impl Context<'_> {
    fn error(&self, field: &str, problem: impl Into<String>) -> RigError {
        RigError::Field {
            camera: self.key.to_owned(),
            name: (self.name != self.key).then(|| self.name.to_owned()),
            field: field.to_owned(),
            problem: problem.into(),
        }
    }
}

/// The first of `keys` present: (key, node).
fn first_of<'a>(node: &'a Node, keys: &[&'static str]) -> Option<(&'static str, &'a Node)> {
    keys.iter().find_map(|key| node.get(key).map(|value| (*key, value)))
}

fn is_camera(node: &Node) -> bool {
    first_of(node, &MATRIX_KEYS).is_some()
}

/// A number as FileStorage writes it (`1.`, `-2.5e-03`, `.nan`, `.Inf`).
fn number(text: &str, what: &str) -> Result<f64, String> {
    let t = text.trim();
    let special = match t.to_ascii_lowercase().as_str() {
        ".nan" | "nan" => Some(f64::NAN),
        ".inf" | "inf" | "+.inf" => Some(f64::INFINITY),
        "-.inf" | "-inf" => Some(f64::NEG_INFINITY),
        _ => None,
    };
    match special {
        Some(value) => Ok(value),
        None => t.parse::<f64>().map_err(|_| format!("{what}: expected a number, found {t:?}")),
    }
}

/// The numbers of a sequence, or of a scalar of whitespace-separated numbers (XML).
fn number_list(node: &Node, what: &str) -> Result<Vec<f64>, String> {
    match node {
        Node::Seq(items) => items
            .iter()
            .enumerate()
            .map(|(i, item)| match item {
                Node::Scalar(text) => number(text, &format!("{what} element {i}")),
                other => Err(format!("{what} element {i}: expected a number, found {}", other.describe())),
            })
            .collect(),
        Node::Scalar(text) => text
            .split([' ', '\t', '\n', '\r', ','])
            .filter(|s| !s.is_empty())
            .enumerate()
            .map(|(i, s)| number(s, &format!("{what} element {i}")))
            .collect(),
        other => Err(format!("{what}: expected numbers, found {}", other.describe())),
    }
}

fn integer(node: &Node, what: &str) -> Result<i64, String> {
    match node {
        Node::Scalar(text) => {
            text.trim().parse::<i64>().map_err(|_| format!("{what}: expected an integer, found {:?}", text.trim()))
        }
        other => Err(format!("{what}: expected an integer, found {}", other.describe())),
    }
}

/// A matrix node as (rows, cols, row-major data); a plain list of numbers is a column.
fn matrix(node: &Node) -> Result<(usize, usize, Vec<f64>), String> {
    let Node::Matrix(_) = node else {
        let data = number_list(node, "value")?;
        return Ok((data.len(), 1, data));
    };
    let dimension = |key: &str| -> Result<usize, String> {
        let value = node.get(key).ok_or_else(|| format!("opencv-matrix lacks `{key}`"))?;
        let n = integer(value, key)?;
        usize::try_from(n).map_err(|_| format!("{key} is {n}"))
    };
    let (rows, cols) = (dimension("rows")?, dimension("cols")?);
    let data = number_list(node.get("data").ok_or("opencv-matrix lacks `data`")?, "data")?;
    if data.len() != rows * cols {
        return Err(format!("opencv-matrix of {rows}x{cols} has {} numbers in `data`", data.len()));
    }
    Ok((rows, cols, data))
}

/// Exactly 3 numbers: a 3x1 or 1x3 matrix or a list.
fn vector3(node: &Node, expected: &str) -> Result<Vector3<f64>, String> {
    let (rows, cols, data) = matrix(node)?;
    if data.len() != 3 {
        return Err(format!("{expected}, found a {rows}x{cols} matrix"));
    }
    Ok(Vector3::new(data[0], data[1], data[2]))
}

/// Coefficients beyond `k3` that are zero may be dropped: the model has none.
fn distortion(data: &[f64]) -> Result<Distortion, String> {
    match data.len() {
        4 => Ok(Distortion { k1: data[0], k2: data[1], p1: data[2], p2: data[3], k3: 0.0 }),
        5 | 8 | 12 | 14 => {
            if let Some((i, value)) = data.iter().enumerate().skip(5).find(|(_, v)| **v != 0.0) {
                return Err(format!(
                    "{} coefficients with coefficient {i} = {value} non-zero: only k1 k2 p1 p2 k3 are supported \
                     (the rational, thin-prism and tilt terms must be 0)",
                    data.len()
                ));
            }
            Ok(Distortion { k1: data[0], k2: data[1], p1: data[2], p2: data[3], k3: data[4] })
        }
        n => Err(format!("expected 4, 5, 8, 12 or 14 coefficients (k1 k2 p1 p2 [k3 ...]), found {n}")),
    }
}

fn size(camera: &Node, context: &Context) -> Result<(u32, u32), RigError> {
    let dimension = |field: &str, node: &Node| -> Result<u32, RigError> {
        let n = integer(node, field).map_err(|p| context.error(field, p))?;
        u32::try_from(n)
            .ok()
            .filter(|n| *n > 0)
            .ok_or_else(|| context.error(field, format!("must be a positive integer, found {n}")))
    };
    match (camera.get("image_width"), camera.get("image_height"), camera.get("image_size")) {
        (Some(w), Some(h), _) => Ok((dimension("image_width", w)?, dimension("image_height", h)?)),
        (_, _, Some(size)) => {
            let v = number_list(size, "image_size").map_err(|p| context.error("image_size", p))?;
            match v[..] {
                [w, h] => Ok((
                    dimension("image_size", &Node::Scalar(format!("{w}")))?,
                    dimension("image_size", &Node::Scalar(format!("{h}")))?,
                )),
                _ => Err(context.error("image_size", format!("expected [width, height], found {} numbers", v.len()))),
            }
        }
        (None, _, None) => Err(context.error("image_width", "missing")),
        (Some(_), None, None) => Err(context.error("image_height", "missing")),
    }
}

fn camera(key: &str, node: &Node) -> Result<Camera, RigError> {
    let name = match first_of(node, &NAME_KEYS) {
        Some((_, Node::Scalar(name))) if !name.is_empty() => name.clone(),
        Some((field, other)) => {
            return Err(RigError::field(key, field, format!("expected a name, found {}", other.describe())));
        }
        None => key.to_owned(),
    };
    let context = Context { key, name: &name };
    let (field, k) = first_of(node, &MATRIX_KEYS).ok_or_else(|| context.error("camera_matrix", "missing (or `K`)"))?;
    let (rows, cols, data) = matrix(k).map_err(|p| context.error(field, p))?;
    if (rows, cols) != (3, 3) {
        return Err(context.error(field, format!("expected a 3x3 matrix, found {rows}x{cols}")));
    }
    let k = Matrix3::from_row_slice(&data);

    let (field, d) =
        first_of(node, &DISTORTION_KEYS).ok_or_else(|| context.error("distortion_coefficients", "missing (or `D`)"))?;
    let distortion = matrix(d).and_then(|(_, _, data)| distortion(&data)).map_err(|p| context.error(field, p))?;

    let (field, r) = first_of(node, &ROTATION_KEYS)
        .ok_or_else(|| context.error("R", "missing (or `rvec`): a rig needs every camera's pose, world to camera"))?;
    let (rows, cols, data) = matrix(r).map_err(|p| context.error(field, p))?;
    let rotation = match data.len() {
        9 if (rows, cols) == (3, 3) => rotation_from_matrix(&Matrix3::from_row_slice(&data)),
        3 => Ok(Rotation3::new(Vector3::new(data[0], data[1], data[2]))),
        _ => Err(format!("expected a 3x3 rotation matrix or a Rodrigues vector of 3 numbers, found {rows}x{cols}")),
    }
    .map_err(|p| context.error(field, p))?;

    let (field, t) = first_of(node, &TRANSLATION_KEYS).ok_or_else(|| context.error("T", "missing (or `tvec`)"))?;
    let translation = vector3(t, "expected 3 numbers (x, y, z)").map_err(|p| context.error(field, p))?;

    let (width, height) = size(node, &context)?;
    let turns = match node.get("rotation_count") {
        None => 0,
        Some(value) => {
            let n = integer(value, "rotation_count").map_err(|p| context.error("rotation_count", p))?;
            // rem_euclid(4) is in 0..4, so the cast is exact.
            n.rem_euclid(4) as u8
        }
    };
    Camera::new(name.clone(), width, height, k, distortion, rotation, translation)
        .map(|camera| camera.with_mount_quarter_turns(turns))
        .map_err(|error| match error {
            // Camera::new names the model's fields; point at the file's keys instead.
            RigError::Field { field, problem, .. } => {
                let key = match field.as_str() {
                    "matrix" => first_of(node, &MATRIX_KEYS).map_or("camera_matrix", |(k, _)| k),
                    "distortions" => first_of(node, &DISTORTION_KEYS).map_or("distortion_coefficients", |(k, _)| k),
                    "rotation" => first_of(node, &ROTATION_KEYS).map_or("R", |(k, _)| k),
                    "translation" => first_of(node, &TRANSLATION_KEYS).map_or("T", |(k, _)| k),
                    "size" => "image_width",
                    _ => "",
                };
                context.error(if key.is_empty() { &field } else { key }, problem)
            }
            other => other,
        })
}

/// The cameras of a parsed document (see the module documentation).
fn rig(root: &Node, stem: &str) -> Result<Rig, RigError> {
    if is_camera(root) {
        return Ok(Rig::new(vec![camera(stem, root)?]));
    }
    let Node::Map(entries) = root else {
        return Err(RigError::NoCameras);
    };
    let mut cameras = CameraList::default();
    for (key, node) in entries.iter().filter(|(_, node)| is_camera(node)) {
        cameras.push(key, camera(key, node)?)?;
    }
    Ok(Rig::new(cameras.finish()?))
}

/// Parses OpenCV FileStorage YAML; a file of one camera names it `stem` unless it says.
pub(crate) fn parse_yaml_rig(text: &str, stem: &str) -> Result<Rig, RigError> {
    rig(&parse_yaml(text)?, stem)
}

/// Parses OpenCV FileStorage XML; a file of one camera names it `stem` unless it says.
pub(crate) fn parse_xml_rig(text: &str, stem: &str) -> Result<Rig, RigError> {
    rig(&parse_xml(text)?, stem)
}
