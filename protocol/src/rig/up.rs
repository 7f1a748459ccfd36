//! The world's up direction: declared by the calibration, set by the user, or estimated
//! from every camera's image up.

use nalgebra::Vector3;

use super::{Camera, RigError};

/// An estimate within this angle of a world axis is snapped to it, degrees: calibration
/// worlds are set up axis-aligned, while cameras are tilted and rolled by a few degrees
/// each, so an estimate this close is the axis plus mounting noise.
pub const SNAP_TO_AXIS_DEG: f64 = 10.0;

/// A camera whose optical axis lies within this angle of the world's up (or down) looks
/// along it: its frames have no up to infer a mount from, degrees.
const ALONG_UP_DEG: f64 = 20.0;

/// Largest angle between the world's up, as a camera's image shows it, and the nearest
/// quarter-turn direction for [`upright_turns`] to name that turn, degrees: beyond it (a
/// camera rolled by about 45 degrees) no turn is clearly the one.
const MOUNT_TOLERANCE_DEG: f64 = 35.0;

/// Weiszfeld iterations for the geometric median: each one at least halves the distance
/// to the median for realistic rigs; 100 is far more than a rig of a few cameras needs.
const MEDIAN_ITERATIONS: usize = 100;

/// The world's up direction and where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldUp {
    /// Unit vector in world coordinates.
    pub direction: Vector3<f64>,
    /// Where the direction came from.
    pub source: UpSource,
}

/// Where a [`WorldUp`] came from.
#[derive(Clone, Debug, PartialEq)]
pub enum UpSource {
    /// The calibration file states it (`[metadata] up = [x, y, z]` in the rig TOML).
    Calibration,
    /// The user set it ([`super::Rig::set_up`]: a pipeline file or `--up`).
    Configured,
    /// Estimated from the cameras' image up directions.
    Estimated {
        /// How, and how well the cameras agreed, for the user.
        how: String,
    },
}

impl std::fmt::Display for UpSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            UpSource::Calibration => f.write_str("stated by the calibration"),
            UpSource::Configured => f.write_str("configured"),
            UpSource::Estimated { how } => write!(f, "estimated: {how}"),
        }
    }
}

/// A direction `x,y,z` as the command lines take an up (`--up 0,0,1`): three finite numbers,
/// not all zero.
pub fn parse_direction(text: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|_| format!("`{v}` is not a number")))
        .collect::<Result<_, _>>()?;
    match values[..] {
        [x, y, z] if [x, y, z].iter().all(|v| v.is_finite()) && (x, y, z) != (0.0, 0.0, 0.0) => Ok([x, y, z]),
        _ => Err(format!("expected a direction `x,y,z` of three finite numbers, not all zero; got `{text}`")),
    }
}

/// `direction` normalised, or why it cannot be an up direction.
pub(crate) fn unit_up(direction: Vector3<f64>) -> Result<Vector3<f64>, String> {
    if !direction.iter().all(|c| c.is_finite()) {
        return Err(format!("not finite ([{}, {}, {}])", direction.x, direction.y, direction.z));
    }
    direction
        .try_normalize(1e-12)
        .ok_or_else(|| format!("zero length ([{}, {}, {}])", direction.x, direction.y, direction.z))
}

impl WorldUp {
    /// A declared up (calibration or configured), normalised; errors on a zero or
    /// non-finite vector.
    pub(crate) fn declared(direction: Vector3<f64>, source: UpSource) -> Result<WorldUp, RigError> {
        let direction = unit_up(direction).map_err(|problem| RigError::Up { problem })?;
        Ok(WorldUp { direction, source })
    }
}

/// "+Y", "-Z", ... for the world axis `axis` (0, 1, 2) with `sign`.
fn axis_name(axis: usize, sign: f64) -> String {
    format!("{}{}", if sign < 0.0 { '-' } else { '+' }, ['X', 'Y', 'Z'][axis])
}

/// The world axis closest to the unit vector `v`: (index, sign, angle in degrees).
fn nearest_axis(v: &Vector3<f64>) -> (usize, f64, f64) {
    let axis = v.iamax();
    let sign = v[axis].signum();
    let angle = v[axis].abs().clamp(0.0, 1.0).acos().to_degrees();
    (axis, sign, angle)
}

/// Geometric median of unit vectors (Weiszfeld), normalised. Robust where a mean is not:
/// with a majority agreeing, one camera whose up is wrong (mounted sideways without
/// saying so) moves it only a little, not by a third of its error.
fn median_direction(ups: &[Vector3<f64>]) -> Option<Vector3<f64>> {
    let mean: Vector3<f64> = ups.iter().sum();
    let mut median = mean.try_normalize(1e-9).or_else(|| ups.first().copied())?;
    for _ in 0..MEDIAN_ITERATIONS {
        let (mut sum, mut weights) = (Vector3::zeros(), 0.0);
        for up in ups {
            // Bounded weight: a vector at the current estimate must not divide by zero.
            let weight = 1.0 / (up - median).norm().max(1e-9);
            sum += up * weight;
            weights += weight;
        }
        let next = sum / weights;
        let moved = (next - median).norm();
        median = next;
        if moved < 1e-13 {
            break;
        }
    }
    median.try_normalize(1e-9)
}

/// The world's up estimated from the cameras: the geometric median of their upright
/// image-up directions ([`Camera::image_up`]), snapped to a world axis within
/// [`SNAP_TO_AXIS_DEG`]. `+Y` for a rig without cameras.
pub(crate) fn estimate(cameras: &[Camera]) -> WorldUp {
    let ups: Vec<Vector3<f64>> = cameras.iter().map(Camera::image_up).collect();
    let Some(median) = median_direction(&ups) else {
        return WorldUp {
            direction: Vector3::y(),
            source: UpSource::Estimated { how: "no cameras: +Y assumed".to_owned() },
        };
    };
    let turned = cameras.iter().filter(|c| c.mount_quarter_turns != 0).count();
    let mounts = if turned == 0 { String::new() } else { format!(" ({turned} turned by their mount quarter turns)") };
    let worst = ups.iter().map(|u| u.dot(&median).clamp(-1.0, 1.0).acos().to_degrees()).fold(0.0, f64::max);
    let (axis, sign, angle) = nearest_axis(&median);
    let name = axis_name(axis, sign);
    let base = format!(
        "geometric median of the image up of {} camera{}{mounts}, cameras within {worst:.1}° of it",
        cameras.len(),
        if cameras.len() == 1 { "" } else { "s" },
    );
    if angle <= SNAP_TO_AXIS_DEG {
        let mut direction = Vector3::zeros();
        direction[axis] = sign;
        WorldUp {
            direction,
            source: UpSource::Estimated { how: format!("{base}; {angle:.1}° from {name}, snapped to it") },
        }
    } else {
        WorldUp {
            direction: median,
            source: UpSource::Estimated {
                how: format!("{base}; {angle:.1}° from the nearest axis {name}, too far to snap"),
            },
        }
    }
}

/// The clockwise quarter turns that make `camera`'s raw frames upright in a world whose up
/// is `up` (unit): the turn whose upright image up ([`Camera::image_up`]) lies closest to
/// it. `None` where the frames show no up (the camera looks along it, within
/// [`ALONG_UP_DEG`]) or no turn is clearly closest ([`MOUNT_TOLERANCE_DEG`]).
pub(crate) fn upright_turns(camera: &Camera, up: &Vector3<f64>) -> Option<u8> {
    let in_camera = camera.rotation * up;
    let across = in_camera.x.hypot(in_camera.y);
    if across < ALONG_UP_DEG.to_radians().sin() {
        return None;
    }
    let (x, y) = (in_camera.x / across, in_camera.y / across);
    // The raw image direction that is up once the frames are turned (as `image_up`).
    let (turns, alignment) = [(0u8, -y), (1, -x), (2, y), (3, x)].into_iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    (alignment >= MOUNT_TOLERANCE_DEG.to_radians().cos()).then_some(turns)
}

/// Mount turns from the geometry: each camera's [`upright_turns`] under the world's up
/// (declared, or estimated from the cameras as they are mounted now), for cameras whose
/// mount is not recorded (zero) or was inferred before (`inferred[k]`, set here for each
/// camera changed). With an estimated up, only when most cameras already agree with it, so
/// an up estimated from cameras mounted sideways without saying so corrects none of them.
/// Returns a note per camera changed.
pub(crate) fn infer_mounts(cameras: &mut [Camera], inferred: &mut Vec<bool>, up: &WorldUp) -> Vec<String> {
    inferred.resize(cameras.len(), false);
    let turns: Vec<Option<u8>> = cameras.iter().map(|c| upright_turns(c, &up.direction)).collect();
    let agreeing = cameras.iter().zip(&turns).filter(|(c, t)| **t == Some(c.mount_quarter_turns)).count();
    if matches!(up.source, UpSource::Estimated { .. }) && 2 * agreeing <= cameras.len() {
        return Vec::new();
    }
    let mut notes = Vec::new();
    for ((camera, turns), inferred) in cameras.iter_mut().zip(turns).zip(inferred.iter_mut()) {
        // A mount the file records is the user's word; only unrecorded (zero) or inferred
        // ones are set.
        let judged = camera.mount_quarter_turns == 0 || *inferred;
        let Some(turns) = turns.filter(|&t| judged && t != camera.mount_quarter_turns) else { continue };
        *inferred = true;
        notes.push(format!(
            "camera `{}`: mounted {turns} clockwise quarter turn(s) from upright, by its calibration and the \
             world's up (the file records no mount); its frames are turned that much for face detection",
            camera.name
        ));
        camera.mount_quarter_turns = turns;
    }
    notes
}
