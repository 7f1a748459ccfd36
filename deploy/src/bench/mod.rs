//! Speed measurements; each reports against a baseline measured in the same run.

pub mod cluster;
pub mod decode;
pub mod hop;
pub mod inject;
pub mod soak;
pub mod stream;
