//! Scoring: the scene-flow engine on Middlebury, the skin decision against masks, and
//! trajectories against ground truth or another tracker (a `handflow-reference/1` file or
//! OpenPose keypoints, triangulated).

pub mod middlebury;
pub mod middlebury_run;
pub mod openpose;
pub mod reference;
pub mod skin;
pub mod tracks;
pub mod tracks_reference;
pub mod triangulation;
