//! Everything that can go wrong with a scene folder, each error naming the file and the
//! field or pixel at fault.

use std::io;
use std::path::PathBuf;

/// Why a Middlebury scene could not be loaded, posed, cropped or written.
#[derive(thiserror::Error, Debug)]
pub enum SceneError {
    /// The folder has no `scene.toml`.
    #[error("`{path}` not found: a scene folder needs a scene.toml describing its views (see data/README.md)")]
    MissingDescription {
        /// Where `scene.toml` was expected.
        path: PathBuf,
    },
    /// A file could not be read or written.
    #[error("`{path}`: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: io::Error,
    },
    /// `scene.toml` is not valid TOML.
    #[error("`{path}` is not valid TOML: {source}")]
    Toml {
        /// The file.
        path: PathBuf,
        /// The parser's complaint.
        #[source]
        source: toml::de::Error,
    },
    /// A required key is absent from `scene.toml`.
    #[error("`{path}`: missing key `{key}`")]
    MissingKey {
        /// The file.
        path: PathBuf,
        /// The key.
        key: &'static str,
    },
    /// A key of `scene.toml` has the wrong type or an impossible value.
    #[error("`{path}`: key `{key}`: {reason}")]
    BadKey {
        /// The file.
        path: PathBuf,
        /// The key.
        key: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A view image listed by `views` is absent.
    #[error("`{path}` not found: scene.toml declares {views} views (im0 .. im{last}); tried {tried}")]
    MissingImage {
        /// The first file name tried.
        path: PathBuf,
        /// The declared view count.
        views: usize,
        /// The last view index.
        last: usize,
        /// The extensions tried.
        tried: String,
    },
    /// A view listed in `gt_views` has no disparity map.
    #[error("`{path}` not found: scene.toml lists view {view} in `gt_views` but its disparity map is missing")]
    MissingDisparity {
        /// The first file name tried.
        path: PathBuf,
        /// The view.
        view: usize,
    },
    /// An image could not be decoded.
    #[error("`{path}` is not a readable image: {source}")]
    Image {
        /// The file.
        path: PathBuf,
        /// The decoder's complaint.
        #[source]
        source: image::ImageError,
    },
    /// An image's size differs from `width` x `height` of `scene.toml`.
    #[error("`{path}` is {got_width}x{got_height} pixels but scene.toml says {width}x{height}")]
    ImageSize {
        /// The file.
        path: PathBuf,
        /// Width from `scene.toml`.
        width: u32,
        /// Height from `scene.toml`.
        height: u32,
        /// Width of the file.
        got_width: u32,
        /// Height of the file.
        got_height: u32,
    },
    /// A disparity map is not a single-channel integer image.
    #[error("`{path}`: a disparity map must be a single-channel 8- or 16-bit grey image, this one is {kind}")]
    DisparityFormat {
        /// The file.
        path: PathBuf,
        /// What the file holds instead.
        kind: String,
    },
    /// A crop window that does not fit the scene.
    #[error(
        "scene `{scene}`: crop {width}x{height} at ({x0}, {y0}) does not fit its {scene_width}x{scene_height} images"
    )]
    Crop {
        /// Scene name.
        scene: String,
        /// Left column of the window.
        x0: u32,
        /// Top row of the window.
        y0: u32,
        /// Window width.
        width: u32,
        /// Window height.
        height: u32,
        /// Scene width.
        scene_width: u32,
        /// Scene height.
        scene_height: u32,
    },
    /// The scene's view count does not fit the layout table.
    #[error("scene `{scene}` (`{path}`) has {views} views; the `{layout}` layout is defined for {expected} views (im0 .. im8)")]
    ViewCount {
        /// Scene name.
        scene: String,
        /// Scene folder.
        path: PathBuf,
        /// Layout name.
        layout: String,
        /// Views of the scene.
        views: usize,
        /// Views the layout needs.
        expected: usize,
    },
    /// The protocol refused a camera of the problem.
    #[error("scene `{scene}`: camera `{camera}`: {reason}")]
    Camera {
        /// Scene name.
        scene: String,
        /// Camera name.
        camera: String,
        /// The protocol's complaint.
        reason: String,
    },
    /// An estimate handed to the map writers has the wrong number of pixels.
    #[error("{what}: {got} entries for a {width}x{height} reference view (expected {expected})")]
    EstimateSize {
        /// Which array.
        what: &'static str,
        /// Entries given.
        got: usize,
        /// Entries expected.
        expected: usize,
        /// Reference width.
        width: u32,
        /// Reference height.
        height: u32,
    },
    /// A map image could not be encoded.
    #[error("`{path}`: cannot write image: {source}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's complaint.
        #[source]
        source: image::ImageError,
    },
}

impl SceneError {
    /// An I/O error on `path`.
    pub(crate) fn io(path: impl Into<PathBuf>, source: io::Error) -> Self {
        Self::Io { path: path.into(), source }
    }
}
