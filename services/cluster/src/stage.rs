//! One frame's particle set in, three labelled objects out: EM in 6D, the move from the
//! visible surface to each object's middle, and labelling. The offline tracker and the
//! cluster service both run this, so they agree to the bit.

use std::time::Instant;

use handflow_protocol::messages::ScenePoint;
use handflow_protocol::Camera;
use nalgebra::{Matrix3, Point3, Vector3};

use crate::em::{extremity_means, farthest_point_seeds, fit_mixture, side_extremity, Component, EmConfig, EmFit};
use crate::hand::{continuity_weight, locate_hand, HAND_LENGTH_M, HEAD_CLEARANCE_M};
use crate::tracks::{HeadAnchor, Measurement, NotStarted, State, Tracker, TrackerConfig};
use crate::velocity::{VelocityFilter, HAND_ACCELERATION_DENSITY, HEAD_ACCELERATION_DENSITY, REFERENCE_INTERVAL_S};
use crate::WeightedPoint;

/// The largest half-thickness the centre correction assumes for a hand, metres: an adult
/// palm is 2-4 cm thick, a loose fist a little more.
pub const HAND_HALF_THICKNESS_M: f64 = 0.02;
/// The largest radius the head's centre correction assumes, metres: half an adult head's
/// depth, nose tip to the back of the head (about 20 cm). The visible skin of a head seen
/// whole (the synthetic head, skin all over) has its centroid 2r/3, up to 6.7 cm, in front
/// of the centre. A real head's skin the engine cannot place in depth needs no such move
/// ([`surface_share`]): the full move, bounded at 4.5 cm, put the shared real session's head
/// 3.8 cm behind its reference.
pub const HEAD_MAX_RADIUS_M: f64 = 0.10;
/// The largest spread of the head's points along any direction, metres (one standard
/// deviation): a face and neck about 25 cm tall spread about 7 cm, and depth noise adds to it.
/// The head's component is bounded by it ([`EmConfig::first_max_std`]).
pub const HEAD_MAX_STD_M: f64 = 0.10;
/// Components fitted besides head and hands, seeded at the points farthest from them: skin
/// the three objects do not explain (the neck, a ghost, a hand seen split in two by another
/// view's occlusion) gets a component of its own instead of pulling two hands into one.
pub const CLUTTER_COMPONENTS: usize = 2;
/// A clutter component is seeded only at a point this far from every other seed, metres
/// (farther than a hand's own extent).
pub const CLUTTER_SEED_DISTANCE_M: f64 = 0.12;

/// A face older than this says nothing about where the head is now, seconds: a seated
/// signer's head moves a few centimetres in that time, a walking person's farther.
pub const FACE_CUE_MAX_AGE_S: f64 = 2.0;
/// Distance from the centre of the face (the surface the detectors' boxes mark) to the
/// centre of the head, metres: about half an adult head's depth (19-20 cm) less the nose.
pub const FACE_TO_HEAD_CENTRE_M: f64 = 0.08;

/// Share of a tracked hand's typical mass under which its component counts as starved and
/// the mixture gets a second start (on `signer-6fps` at seed 5 the left hand's component held
/// 45 % of it in the frame the hands began to swap, 15 to 30 % in the next ones).
pub const STARVED_HAND_SHARE: f64 = 0.5;

/// Mean log-likelihood per unit weight by which a second start's fit must beat the fit from the
/// predictions, which carry the tracks' history. On `signer-6fps` the second start's fits that
/// gave a hand back its own component were 0.3 to 2 better; in the first frame after 17 lost
/// sets (`signer-3cam`, 30 fps) a fit 0.009 better put the right hand 6-7 cm off for two frames
/// more than the predictions' did.
pub const SECOND_START_MARGIN: f64 = 0.05;

/// Where the face detectors last placed the face in 3D, as the flow stage reports it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceCue {
    /// Centre of the face, world metres.
    pub centre: Vector3<f64>,
    /// Seconds between the frame the face was detected on and this one.
    pub age_s: f64,
}

impl FaceCue {
    /// A face centred at `centre`, detected `age_frames` frame sets before this one of a
    /// stream at `fps`.
    pub fn new(centre: [f64; 3], age_frames: u64, fps: f64) -> FaceCue {
        FaceCue { centre: Vector3::from(centre), age_s: age_frames as f64 / fps.max(1e-9) }
    }

    /// The cue of a particle header (`None` when it carries no face).
    pub fn from_header(header: &handflow_protocol::messages::ParticleHeader) -> Option<FaceCue> {
        (header.face_known == 1)
            .then(|| FaceCue::new(header.face_centre_m, header.face_age_frames, header.frame_rate_hz))
    }
}

/// One object after a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObjectEstimate {
    /// World position of the object's middle, metres.
    pub position: Vector3<f64>,
    /// World velocity, metres per second.
    pub velocity: Vector3<f64>,
    /// Confidence in [0, 1].
    pub confidence: f64,
    /// Tracking state.
    pub state: State,
    /// Share of the frame's particle weight in the cluster assigned to the object (0 when
    /// none was).
    pub mass: f64,
}

/// Clustering and labelling of a stream of particle sets from one reference camera.
pub struct ClusterStage {
    tracker: Tracker,
    em: EmConfig,
    points: Vec<WeightedPoint>,
    /// The frame's points within reach of the head's seed (a buffer kept between frames).
    near_points: Vec<WeightedPoint>,
    eye: Point3<f64>,
    up: Vector3<f64>,
    signer_left: Vector3<f64>,
    centre_correction: bool,
    hand_localisation: bool,
    seconds: f64,
    last_seconds: f64,
    frames: u64,
    /// The last frame's clusters, as the tracker saw them (after the centre correction).
    last_fit: Option<EmFit>,
    /// Usable points of the last frame.
    last_points: usize,
    /// What was last reported about the tracks' start (see [`ClusterStage::start_status`]),
    /// so that it is logged once per change, not once per frame.
    reported: Option<StartStatus>,
    /// Per object, the velocity it is published with ([`VelocityFilter`]).
    velocities: [VelocityFilter; 3],
    /// Per object, whether its track, since it last started, has held a hand's mass (see
    /// [`ClusterStage::small_since_start`]).
    hand_sized: [bool; 3],
}

/// Whether the tracks run, and if not why, as [`ClusterStage::start_status`] gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum StartStatus {
    /// Tracks have started (some may be predicted or lost since).
    Running,
    /// The frame held no usable point: nothing the reference camera saw was estimated as
    /// skin.
    NoSkin,
    /// Points, but the first labelling found no head and two hands in them.
    NotStarted(NotStarted),
}

impl StartStatus {
    /// The cause without its figures (one log line per change of it).
    pub fn cause(&self) -> &'static str {
        match self {
            StartStatus::Running => "running",
            StartStatus::NoSkin => "no skin",
            StartStatus::NotStarted(why) => why.cause(),
        }
    }
}

impl ClusterStage {
    /// A stage for particles on the rays of `reference` (the camera the signer faces) in a
    /// world whose up is `up` (the rig's, [`handflow_protocol::Rig::world_up`]: from the
    /// world, not from one camera's image, which a rolled or sideways-mounted camera would
    /// tilt). The signer's left is the reference camera's forward axis crossed with up: its
    /// right made horizontal, whatever its roll. `centre_correction` moves each cluster's
    /// centre from the visible surface to the object's middle ([`surface_to_centre`]).
    pub fn new(reference: &Camera, up: Vector3<f64>, centre_correction: bool) -> Self {
        let axes = reference.rotation.matrix();
        let up = up.try_normalize(1e-12).unwrap_or_else(|| -axes.row(1).transpose());
        let forward = axes.row(2).transpose();
        // A camera looking straight up or down has no horizontal right of its own: keep its
        // image right with the vertical part removed.
        let signer_left = forward.cross(&up).try_normalize(1e-9).unwrap_or_else(|| {
            let right = axes.row(0).transpose();
            (right - up * right.dot(&up)).try_normalize(1e-9).unwrap_or(right)
        });
        Self {
            tracker: Tracker::new(TrackerConfig::default(), up, signer_left),
            em: EmConfig { first_max_std: HEAD_MAX_STD_M, ..EmConfig::default() },
            points: Vec::new(),
            near_points: Vec::new(),
            eye: reference.centre(),
            up,
            signer_left,
            centre_correction,
            hand_localisation: true,
            seconds: 0.0,
            last_seconds: 0.0,
            frames: 0,
            last_fit: None,
            last_points: 0,
            reported: None,
            velocities: [HEAD_ACCELERATION_DENSITY, HAND_ACCELERATION_DENSITY, HAND_ACCELERATION_DENSITY]
                .map(VelocityFilter::new),
            hand_sized: [false; 3],
        }
    }

    /// Whether each hand is published at the distal end of its arm's skin
    /// ([`locate_hand`]; default true) or at its cluster's centre.
    pub fn with_hand_localisation(mut self, on: bool) -> Self {
        self.hand_localisation = on;
        self
    }

    /// The objects (head, left hand, right hand) after the particle set of the frame at
    /// stream time `t` seconds. `fps` converts the points' velocities from metres per frame
    /// to metres per second; `ray_spread_var` is the filter's own variance along a ray.
    /// `face`, when the detectors placed one in 3D within [`FACE_CUE_MAX_AGE_S`], anchors
    /// the head: its track starts on the cluster at the face and is brought back there when
    /// it strays (see [`crate::tracks::HeadAnchor`]).
    pub fn update(
        &mut self,
        t: f64,
        fps: f64,
        ray_spread_var: f64,
        points: &[ScenePoint],
        face: Option<FaceCue>,
    ) -> [ObjectEstimate; 3] {
        let started = Instant::now();
        self.points.clear();
        self.points.extend(points.iter().map(|p| WeightedPoint {
            position: Vector3::new(f64::from(p.position[0]), f64::from(p.position[1]), f64::from(p.position[2])),
            velocity: Vector3::new(f64::from(p.velocity[0]), f64::from(p.velocity[1]), f64::from(p.velocity[2])) * fps,
            weight: f64::from(p.weight),
        }));
        let anchor =
            face.filter(|f| f.age_s <= FACE_CUE_MAX_AGE_S && f.centre.iter().all(|v| v.is_finite())).map(|f| {
                let sight = (f.centre - self.eye.coords).try_normalize(1e-9).unwrap_or_else(Vector3::zeros);
                HeadAnchor { face: f.centre, head: f.centre + sight * FACE_TO_HEAD_CENTRE_M }
            });
        // Where each hand measured in the last frame is expected now, and how much that
        // says of which end of an arm's skin is the hand: less as the interval grows.
        let miss_m = 0.5 * self.tracker.config().max_acceleration_m_s2 * (t - self.tracker.time()).powi(2);
        let weight = continuity_weight(miss_m);
        let expected_hands: [Option<(Vector3<f64>, f64)>; 3] =
            match (self.tracker.predictions(t), self.tracker.tracks(), weight > 0.0) {
                (Some(p), Some(tracks), true) => std::array::from_fn(|k| {
                    (tracks[k].state == State::Tracked && tracks[k].unmeasured == 0).then_some((p[k].0, weight))
                }),
                _ => [None; 3],
            };
        let mut initial = match self.tracker.predictions(t) {
            Some(p) => Some(p),
            None => extremity_means(&self.points, self.up, self.signer_left),
        };
        // A head seed far from the face would grow a component on whatever skin-coloured
        // thing it sits on: seed it on the face.
        if let (Some(init), Some(a)) = (initial.as_mut(), anchor) {
            if (init[0].0 - a.face).norm() > self.tracker.config().face_anchor_m {
                init[0] = (a.face, Vector3::zeros());
            }
        }
        // A lost hand's seed goes where a hand on its side would be now, not where it was
        // lost; a hand coasting on its prediction gets that seed besides its own (the
        // prediction may be right, a hand passing behind the other, or may fly off with a
        // wrong velocity while the hand is in plain view).
        let mut returning = Vec::new();
        if let (Some(init), Some(tracks)) = (initial.as_mut(), self.tracker.tracks()) {
            for k in 1..3 {
                if tracks[k].state == State::Tracked {
                    continue;
                }
                let side = self.side_of(k);
                let reach = self.tracker.config().reach_m;
                if let Some(seed) = side_extremity(&self.points, init[0].0, reach, self.up, side) {
                    if tracks[k].state == State::Lost {
                        init[k] = seed;
                    } else {
                        returning.push(seed);
                    }
                }
            }
        }
        // EM climbs to the optimum nearest its start. At low rates a wrong velocity can
        // seed a hand on a few stray points while another component takes the hand
        // (measured on `signer-6fps`: the hands swapped at 1.5 s in one seed of six). A hand
        // whose component holds under half its usual mass gets a second start, each hand at
        // its side's end of the person's skin, and a clearly better-explaining fit is kept.
        // Only then: tried on every frame, the second start took a blob of points at a false
        // depth below a hand for the hand in some seeds of the shared real session.
        // A hand whose track has been small since it started gets a second start of its own.
        let small_from_start = self.small_since_start();
        let mut fit = initial.and_then(|init| {
            let first = self.fit_seeded(init, &returning);
            let starved = match (&first, self.tracker.tracks()) {
                (Some(fit), Some(tracks)) => (1..3).any(|k| {
                    tracks[k].state == State::Tracked
                        && fit.components[k].mass < STARVED_HAND_SHARE * tracks[k].typical_mass
                }),
                _ => false,
            };
            if starved {
                let second = self.fit_seeded(self.side_start(init), &returning);
                return better_fit(first, second);
            }
            let Some(hand_mass) = small_from_start.iter().position(|&s| s).map(|k| self.hand_mass(3 - k)) else {
                return first;
            };
            // Only the small hand is sought again, on its side of the head, away from the
            // piece it holds, from the other hand (whose track has held a hand all along) and
            // from the head; only a fit that gives it half a hand's mass beside the head (not
            // on a piece of it, nor on the neck below it) is a hand found.
            let start = self.piece_start(init, small_from_start);
            let second = self.fit_seeded(start, &returning).filter(|fit| {
                let head = &fit.components[0];
                (1..3).all(|k| {
                    let c = &fit.components[k];
                    !small_from_start[k]
                        || (c.mass >= STARVED_HAND_SHARE * hand_mass
                            && (c.position - head.position).norm() > HEAD_CLEARANCE_M
                            && (c.position - head.position).dot(&self.side_of(k)) > HEAD_MAX_RADIUS_M
                            && !behind_head(head, c, &self.eye))
                })
            });
            better_fit(first, second)
        });
        let raw = fit.clone();
        if let (Some(fit), true) = (fit.as_mut(), self.centre_correction) {
            for c in fit.components.iter_mut() {
                surface_to_centre(c, &self.eye, self.em.min_std, ray_spread_var, HAND_HALF_THICKNESS_M);
            }
        }
        let mut tracks = self.tracker.update_anchored(t, fit.as_ref(), anchor);
        if let Some(raw) = raw.as_ref().filter(|_| tracing::enabled!(tracing::Level::TRACE)) {
            for (i, c) in raw.components.iter().enumerate() {
                tracing::trace!(t, cluster = i, position = ?c.position.as_slice(), mass = c.mass, empty = c.empty, "cluster");
            }
            tracing::trace!(t, assigned = ?self.tracker.assigned(), "clusters measuring the tracks");
        }
        // The head's centre from its skin and the pieces EM split off it ([`head_centre`]).
        if let (Some(fit), Some(raw), true) = (&fit, &raw, self.centre_correction) {
            if let (State::Tracked, Some(m)) = (tracks[0].state, self.tracker.assigned()[0]) {
                let hands = [1, 2].map(|k| self.tracker.assigned()[k].map(|h| h.cluster));
                if let Some(centre) = head_centre(&raw.components, m.cluster, &hands, &self.eye, self.em.min_std) {
                    // By the share of the measurement the tracker took.
                    tracks[0].position += (centre - fit.components[m.cluster].position) * m.pull;
                    self.tracker.set_position(0, tracks[0].position);
                }
            }
        }
        // A hand's cluster in short sleeves holds the forearm too: the hand is its distal end.
        if let (Some(fit), Some(raw), true) = (&fit, &raw, self.hand_localisation) {
            for k in 1..3 {
                let (State::Tracked, Some(m)) = (tracks[k].state, self.tracker.assigned()[k]) else { continue };
                let Some(found) = locate_hand(
                    &self.points,
                    &raw.components,
                    m.cluster,
                    tracks[0].position,
                    self.up,
                    expected_hands[k],
                ) else {
                    continue;
                };
                tracing::trace!(
                    t,
                    hand = k,
                    cluster = m.cluster,
                    extent_m = found.extent_m,
                    arm = found.arm,
                    at = ?found.position.as_slice(),
                    "hand located"
                );
                if found.arm {
                    // The centroid's move to the object's middle applies to the hand's part too.
                    let at = found.position + (fit.components[m.cluster].position - raw.components[m.cluster].position);
                    tracks[k].position += (at - fit.components[m.cluster].position) * m.pull;
                    self.tracker.set_position(k, tracks[k].position);
                }
            }
        }
        let total: f64 = self.points.iter().map(|p| p.weight).sum();
        let assigned = self.tracker.assigned();
        let nominal_dt = if fps.is_finite() && fps > 0.0 { 1.0 / fps } else { REFERENCE_INTERVAL_S };
        let estimates = std::array::from_fn(|k| {
            let track = tracks[k];
            // Published with the flow's velocity fused with the published positions' motion;
            // the tracker keeps its own for its predictions.
            let velocity = if track.state == State::Lost {
                self.velocities[k].reset();
                track.velocity
            } else {
                self.velocities[k].update(t, track.position, track.velocity, nominal_dt)
            };
            let mass = match (assigned[k], &fit) {
                (Some(m), Some(fit)) if total > 0.0 => fit.components[m.cluster].mass / total,
                _ => 0.0,
            };
            ObjectEstimate {
                position: track.position,
                velocity,
                confidence: track.confidence,
                state: track.state,
                mass,
            }
        });
        self.last_points = self.points.iter().filter(|p| p.is_usable()).count();
        self.last_fit = fit;
        self.last_seconds = started.elapsed().as_secs_f64();
        self.seconds += self.last_seconds;
        self.frames += 1;
        self.report_start_status(t);
        estimates
    }

    /// Per object, whether it is a hand whose track has held less than half the other hand's
    /// usual mass ever since it started (`true`), and records which tracks have held a
    /// hand's mass. A track that starts on a piece of an arm (the forearm by the elbow at the
    /// reference view's border while the hand lies below it, on the shared real session and
    /// its half-size and lossy copies) keeps its piece when the hand rises into view: the
    /// predictions seed the fit, and the hand's skin joins the head's component. Such a hand
    /// gets the second start every frame until it holds a hand's mass; a hand that held one
    /// and then shrinks (turned edge-on, half hidden) is judged by its own usual mass.
    fn small_since_start(&mut self) -> [bool; 3] {
        let Some(tracks) = self.tracker.tracks() else {
            self.hand_sized = [false; 3];
            return [false; 3];
        };
        let mut small = [false; 3];
        for k in 1..3 {
            let other = &tracks[3 - k];
            if tracks[k].state != State::Tracked {
                self.hand_sized[k] = false;
            } else if other.state == State::Tracked && tracks[k].typical_mass < STARVED_HAND_SHARE * other.typical_mass
            {
                small[k] = !self.hand_sized[k];
            } else {
                self.hand_sized[k] = true;
            }
        }
        small
    }

    /// Seeds for head and hands with each hand at its side's end of the skin within reach
    /// of the head (where a prediction cannot be trusted to be), the head as in `init`.
    fn side_start(&self, init: [(Vector3<f64>, Vector3<f64>); 3]) -> [(Vector3<f64>, Vector3<f64>); 3] {
        let mut start = init;
        let reach = self.tracker.config().reach_m;
        for (k, seed) in start.iter_mut().enumerate().skip(1) {
            let side = self.side_of(k);
            if let Some(found) = side_extremity(&self.points, init[0].0, reach, self.up, side) {
                *seed = found;
            }
        }
        start
    }

    /// The usual mass of the track of object `k` (0 before tracks start).
    fn hand_mass(&self, k: usize) -> f64 {
        self.tracker.tracks().map_or(0.0, |tracks| tracks[k].typical_mass)
    }

    /// Seeds as in `init` except for each hand marked `small`, which goes to its side's end
    /// of the skin within reach of the head, among the points farther than a hand's length
    /// from both hands' seeds (the piece it holds, and the other hand) and clear of the head.
    fn piece_start(
        &mut self,
        init: [(Vector3<f64>, Vector3<f64>); 3],
        small: [bool; 3],
    ) -> [(Vector3<f64>, Vector3<f64>); 3] {
        let mut start = init;
        let reach = self.tracker.config().reach_m;
        let hands = [init[1].0, init[2].0];
        self.near_points.clear();
        self.near_points.extend(
            self.points
                .iter()
                .filter(|p| {
                    hands.iter().all(|h| (p.position - h).norm() > HAND_LENGTH_M)
                        && (p.position - init[0].0).norm() > HEAD_CLEARANCE_M
                })
                .copied(),
        );
        for k in (1..3).filter(|&k| small[k]) {
            let side = self.side_of(k);
            if let Some(found) = side_extremity(&self.near_points, init[0].0, reach, self.up, side) {
                start[k] = found;
            }
        }
        start
    }

    /// The direction from the head to hand `k`'s side of the body (1 left, 2 right).
    fn side_of(&self, k: usize) -> Vector3<f64> {
        if k == 1 {
            self.signer_left
        } else {
            -self.signer_left
        }
    }

    /// The mixture fitted from these seeds for head and hands, with the spare and clutter
    /// seeds added as usual.
    fn fit_seeded(
        &mut self,
        init: [(Vector3<f64>, Vector3<f64>); 3],
        returning: &[(Vector3<f64>, Vector3<f64>)],
    ) -> Option<EmFit> {
        let mut seeds = init.to_vec();
        for seed in returning {
            if seeds.iter().all(|(s, _)| (s - seed.0).norm() > CLUTTER_SEED_DISTANCE_M) {
                seeds.push(*seed);
            }
        }
        // The person's unexplained skin (a neck, a hand whose seed flew off with a wrong
        // velocity) gets a spare component before skin-like clutter across the room does.
        let reach = self.tracker.config().reach_m;
        let head = seeds[0].0;
        self.near_points.clear();
        self.near_points.extend(self.points.iter().filter(|p| (p.position - head).norm() <= reach).copied());
        let before = seeds.len();
        farthest_point_seeds(&self.near_points, &mut seeds, 1, CLUTTER_SEED_DISTANCE_M);
        let left = CLUTTER_COMPONENTS - (seeds.len() - before);
        farthest_point_seeds(&self.points, &mut seeds, left, CLUTTER_SEED_DISTANCE_M);
        fit_mixture(&self.points, &seeds, &self.em)
    }

    /// Logs the tracks' start status when its cause changed since the last report (at info:
    /// the one thing a user of new footage must see when nothing is tracked).
    fn report_start_status(&mut self, t: f64) {
        let status = self.start_status();
        if self.reported.is_some_and(|r| r.cause() == status.cause()) {
            return;
        }
        match status {
            StartStatus::Running => tracing::info!("tracks started at {t:.3} s"),
            StartStatus::NoSkin => {
                tracing::info!("tracks not started at {t:.3} s: no skin points in the reference view")
            }
            StartStatus::NotStarted(why) => {
                tracing::info!("tracks not started at {t:.3} s: {why} ({} points)", self.last_points)
            }
        }
        self.reported = Some(status);
    }

    /// Whether the tracks run after the last update, and if not why.
    pub fn start_status(&self) -> StartStatus {
        match self.tracker.not_started() {
            None => StartStatus::Running,
            Some(_) if self.last_points == 0 => StartStatus::NoSkin,
            Some(why) => StartStatus::NotStarted(why),
        }
    }

    /// The last frame's clusters (EM components, including the clutter components), with
    /// centres moved to the objects' middles when the correction is on: what the tracker
    /// labelled. `None` when the frame had no usable point or EM failed.
    pub fn last_fit(&self) -> Option<&EmFit> {
        self.last_fit.as_ref()
    }

    /// Per object (head, left hand, right hand), the cluster of [`ClusterStage::last_fit`]
    /// that measured it in the last update.
    pub fn assigned(&self) -> [Option<Measurement>; 3] {
        self.tracker.assigned()
    }

    /// Usable points (finite, positive weight) of the last update.
    pub fn last_point_count(&self) -> usize {
        self.last_points
    }

    /// Mean time per [`ClusterStage::update`], seconds.
    pub fn seconds_per_frame(&self) -> f64 {
        self.seconds / self.frames.max(1) as f64
    }

    /// Time of the last [`ClusterStage::update`], seconds.
    pub fn last_seconds(&self) -> f64 {
        self.last_seconds
    }

    /// Tracks re-initialised on a cluster far from their prediction so far.
    pub fn reinitialisations(&self) -> u64 {
        self.tracker.reinitialisations()
    }
}

/// A convex object's points spread at most this much (relative to their narrowest spread
/// across the view) in depth while they can still lie on its visible surface: 0.47 for a
/// sphere's visible half, 0.82 for points filling the whole ball, more with a little noise.
pub const SURFACE_DEPTH_RATIO: f64 = 1.0;
/// From this ratio of depth spread to narrowest width on, a cluster's depth is the engine's
/// noise, not the object's shape.
pub const NOISE_DEPTH_RATIO: f64 = 1.5;

/// Of the fit from the tracks' predictions and one from a second start, the second only if it
/// explains the points better by more than [`SECOND_START_MARGIN`].
fn better_fit(predicted: Option<EmFit>, second: Option<EmFit>) -> Option<EmFit> {
    match (predicted, second) {
        (Some(a), Some(b)) => Some(if b.log_likelihood > a.log_likelihood + SECOND_START_MARGIN { b } else { a }),
        (a, b) => a.or(b),
    }
}

/// Share (0 to 1) of the move from the visible surface to the middle that a cluster's shape
/// supports. The move assumes its points lie on the surface the reference camera sees. Where
/// the engine cannot place weakly textured skin in depth, the points spread along the line of
/// sight within what every view sees as skin: the object's inside. Their centroid is then
/// already near the middle, and moving it back overshoots. Such a cluster shows itself by a
/// depth spread wider than the object itself, which no surface or solid convex object has.
/// On the synthetic heads the ratio stays below 1.05; on the shared real session's head it
/// is 1.5 to 2.4, and the full move put the head 3.8 cm behind its reference.
pub fn surface_share(c: &Component, eye: &Point3<f64>) -> f64 {
    let Some(sight) = (c.position - eye.coords).try_normalize(1e-9) else { return 1.0 };
    let p = c.covariance.fixed_view::<3, 3>(0, 0).into_owned();
    let along = (sight.transpose() * p * sight)[(0, 0)];
    // Two directions across the view, and the smaller spread of the covariance in that plane:
    // the narrowest width, which a neck or an arm below the object does not widen.
    let helper = if sight.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    let a = sight.cross(&helper).normalize();
    let b = sight.cross(&a);
    let (aa, bb, ab) =
        ((a.transpose() * p * a)[(0, 0)], (b.transpose() * p * b)[(0, 0)], (a.transpose() * p * b)[(0, 0)]);
    let narrowest = (aa + bb) / 2.0 - (((aa - bb) / 2.0).powi(2) + ab * ab).sqrt();
    if narrowest <= 0.0 || !along.is_finite() {
        return 1.0;
    }
    let ratio = (along.max(0.0) / narrowest).sqrt();
    ((NOISE_DEPTH_RATIO - ratio) / (NOISE_DEPTH_RATIO - SURFACE_DEPTH_RATIO)).clamp(0.0, 1.0)
}

/// The centre of the head whose skin is component `head` (raw, as EM fitted it) of
/// `components`, hands' components `hands`: the head with its pieces
/// ([`head_with_its_pieces`]) moved from its visible surface to its middle by the share its
/// own component's shape supports ([`surface_share`]; the pieces lie behind it by
/// construction and would widen its depth). The head's skin is its face, a shallow cap of a
/// nearly round object: its depth spread says little about its size, so the move comes from
/// the spread across the view. `None` for an unknown component.
pub fn head_centre(
    components: &[Component],
    head: usize,
    hands: &[Option<usize>; 2],
    eye: &Point3<f64>,
    min_std: f64,
) -> Option<Vector3<f64>> {
    let bound = HEAD_MAX_RADIUS_M * surface_share(components.get(head)?, eye);
    let mut whole = head_with_its_pieces(components, head, hands, eye)?;
    surface_to_centre(&mut whole, eye, min_std, f64::INFINITY, bound);
    Some(whole.position)
}

/// The head's component `head` with the pieces EM split off it behind its visible surface.
/// A Gaussian fits the cap of skin a camera sees of a head poorly, and a spare component
/// (see [`CLUTTER_COMPONENTS`]) can take the cap's rim, which lies deeper than its middle:
/// measured alone, the head then jumps towards the camera and looks narrower, and its
/// centre lands short of the middle (`occluded-side`: 1.3 cm off with the rim, 2.9 cm
/// without, from frame to frame). A piece is a component no hand holds, lighter than the
/// head's, lying behind the head's centroid along the line of sight from `eye` by at most a
/// head's depth and within a head's radius of it across the view; a neck (below by more
/// than that) or a hand in front of the face is not. The pieces join by mass, their spread
/// about the joint centre included.
pub fn head_with_its_pieces(
    components: &[Component],
    head: usize,
    hands: &[Option<usize>; 2],
    eye: &Point3<f64>,
) -> Option<Component> {
    let &main = components.get(head)?;
    let is_piece = |j: usize, c: &Component| {
        j != head
            && !hands.contains(&Some(j))
            && !c.empty
            && c.mass > 0.0
            && c.mass < main.mass
            && behind_head(&main, c, eye)
    };
    let parts: Vec<&Component> =
        components.iter().enumerate().filter(|&(j, c)| j == head || is_piece(j, c)).map(|(_, c)| c).collect();
    let mass: f64 = parts.iter().map(|c| c.mass).sum();
    if parts.len() < 2 || mass <= 0.0 {
        return Some(main);
    }
    let mut whole = main;
    whole.position = parts.iter().map(|c| c.position * c.mass).sum::<Vector3<f64>>() / mass;
    whole.velocity = parts.iter().map(|c| c.velocity * c.mass).sum::<Vector3<f64>>() / mass;
    let spread: Matrix3<f64> = parts
        .iter()
        .map(|c| {
            let d = c.position - whole.position;
            (c.covariance.fixed_view::<3, 3>(0, 0) + d * d.transpose()) * c.mass
        })
        .sum::<Matrix3<f64>>()
        / mass;
    whole.covariance.fixed_view_mut::<3, 3>(0, 0).copy_from(&spread);
    whole.mass = mass;
    whole.mixing = parts.iter().map(|c| c.mixing).sum();
    Some(whole)
}

/// Whether component `c` lies where a piece of the head `main` would (see
/// [`head_with_its_pieces`]): behind its centroid along the line of sight from `eye` by at
/// most a head's depth, and within a head's radius of it across the view.
fn behind_head(main: &Component, c: &Component, eye: &Point3<f64>) -> bool {
    let Some(sight) = (main.position - eye.coords).try_normalize(1e-9) else { return false };
    let d = c.position - main.position;
    let along = d.dot(&sight);
    let across = (d - sight * along).norm();
    along > 0.0 && along <= 2.0 * HEAD_MAX_RADIUS_M && across <= HEAD_MAX_RADIUS_M
}

/// Moves a cluster's centre from the surface the reference camera sees to the object's
/// middle. The points of a roughly convex object (a head, a hand) seen from one side lie on
/// its front: for a sphere of radius r the visible points' centroid is 2r/3 in front of the
/// centre. The radius along the line of sight is estimated twice, from the spread across
/// the view (r/2 for a sphere) and from the spread in depth (0.236 r), and the smaller is
/// used: a flat hand facing the camera is wide but thin, and depth noise only ever widens
/// the second estimate. `min_std` is the floor EM added to every variance and
/// `ray_spread_var` the variance a ray's particles have along it (the filter's own
/// uncertainty, not the object's depth): both are taken out of the depth spread first.
/// `max_depth_radius` bounds the result by what the object can be: depth noise the
/// filter's spread does not account for still widens the depth estimate, and a hand's
/// spread across the view is its width, not its thickness.
pub fn surface_to_centre(
    c: &mut Component,
    eye: &Point3<f64>,
    min_std: f64,
    ray_spread_var: f64,
    max_depth_radius: f64,
) {
    let Some(sight) = (c.position - eye.coords).try_normalize(1e-9) else { return };
    let p = c.covariance.fixed_view::<3, 3>(0, 0);
    let floor = min_std * min_std;
    let along = (sight.transpose() * p * sight)[(0, 0)];
    let across = (p.trace() - along) / 2.0;
    let r_across = 2.0 * (across - floor).max(0.0).sqrt();
    // An infinite `ray_spread_var` leaves only the estimate across the view.
    let r_along = if ray_spread_var.is_finite() {
        (along - floor - ray_spread_var).max(0.0).sqrt() / 0.236
    } else {
        f64::INFINITY
    };
    c.position += sight * (2.0 / 3.0) * r_across.min(r_along).min(max_depth_radius);
}

/// The objects on the wire, in [`handflow_protocol::messages::OBJECT_LABELS`] order.
pub fn labelled_clusters(estimates: &[ObjectEstimate; 3]) -> [handflow_protocol::messages::LabelledCluster; 3] {
    use handflow_protocol::messages::{track_state, LabelledCluster};
    estimates.map(|e| LabelledCluster {
        position: e.position.into(),
        velocity: e.velocity.into(),
        confidence: e.confidence,
        mass: e.mass,
        state: match e.state {
            State::Tracked => track_state::TRACKED,
            State::Predicted => track_state::PREDICTED,
            State::Lost => track_state::LOST,
        },
        reserved: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use handflow_protocol::Distortion;
    use nalgebra::{Matrix3, Rotation3};

    /// A camera 2.5 m in front of the origin (+Z side, Y up) looking at it, rolled by
    /// `roll` radians about its optical axis.
    fn reference(roll: f64) -> Camera {
        let position = Vector3::new(0.3, 0.4, 2.5);
        let z = (-position).normalize();
        let x = z.cross(&Vector3::y()).normalize();
        let y = z.cross(&x);
        let upright =
            Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]));
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), roll) * upright;
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        Camera::new("ref", 640, 480, k, Distortion::default(), r, -(r * position)).expect("valid camera")
    }

    /// `n` points at rest in rows of ten, 4 mm apart, from (`x`, `y`, 0): a blob of skin.
    fn still_blob(x: f32, y: f32, n: usize) -> impl Iterator<Item = ScenePoint> {
        (0..n).map(move |i| ScenePoint {
            position: [x + (i % 10) as f32 * 0.004, y + (i / 10) as f32 * 0.004, 0.0],
            velocity: [0.0; 3],
            weight: 1.0,
            skin: 1.0,
        })
    }

    /// The component EM would fit to `points`: their mean and covariance.
    fn component_of(points: &[Vector3<f64>]) -> Component {
        let n = points.len() as f64;
        let mean = points.iter().sum::<Vector3<f64>>() / n;
        let mut covariance = nalgebra::Matrix6::identity() * 1e-6;
        let spread = points.iter().map(|p| (p - mean) * (p - mean).transpose()).sum::<Matrix3<f64>>() / n;
        covariance.fixed_view_mut::<3, 3>(0, 0).copy_from(&spread);
        Component { position: mean, velocity: Vector3::zeros(), covariance, mixing: 1.0, mass: n, empty: false }
    }

    #[test]
    fn a_visible_surface_moves_to_the_middle_and_a_cloud_deeper_than_wide_stays() {
        let eye = Point3::new(0.0, 0.0, 0.0);
        let centre = Vector3::new(0.1, -0.05, 1.5);
        let sight = centre.normalize();
        let a = sight.cross(&Vector3::y()).normalize();
        let b = sight.cross(&a);
        let radius = 0.065;
        // The half of a ball the eye sees, one point per pixel-like step across the view.
        let mut cap = Vec::new();
        for i in -20..=20 {
            for j in -20..=20 {
                let (u, v) = (f64::from(i) / 20.0, f64::from(j) / 20.0);
                if u * u + v * v <= 1.0 {
                    let depth = (1.0 - u * u - v * v).max(0.0).sqrt();
                    cap.push(centre + radius * (a * u + b * v - sight * depth));
                }
            }
        }
        let mut surface = component_of(&cap);
        assert_eq!(surface_share(&surface, &eye), 1.0);
        surface_to_centre(&mut surface, &eye, 0.0, f64::INFINITY, HEAD_MAX_RADIUS_M);
        assert!((surface.position - centre).norm() < 0.01, "{:?}", surface.position - centre);
        // The same face with depth noise filling the inside and beyond, twice as deep as wide,
        // centred on the middle: its centroid is already where the head is.
        let noisy: Vec<Vector3<f64>> = cap
            .iter()
            .enumerate()
            .map(|(k, p)| p + sight * (0.26 * ((k * 7919 % 101) as f64 / 100.0) - 0.065))
            .collect();
        let mut cloud = component_of(&noisy);
        assert!(surface_share(&cloud, &eye) == 0.0, "{}", surface_share(&cloud, &eye));
        let before = cloud.position;
        let bound = HEAD_MAX_RADIUS_M * surface_share(&cloud, &eye);
        surface_to_centre(&mut cloud, &eye, 0.0, f64::INFINITY, bound);
        assert_eq!(cloud.position, before);
        // A tall narrow object (a head with its neck) is judged by its narrowest width.
        let tall: Vec<Vector3<f64>> = cap.iter().flat_map(|p| [*p, p + b * 0.12]).collect();
        assert_eq!(surface_share(&component_of(&tall), &eye), 1.0);
    }

    #[test]
    fn a_head_whose_rim_em_split_off_is_measured_whole_and_nothing_else_joins_it() {
        let eye = Point3::new(0.0, 0.0, 0.0);
        let centre = Vector3::new(0.05, 0.1, 1.8);
        let sight = centre.normalize();
        let a = sight.cross(&Vector3::y()).normalize();
        let b = sight.cross(&a);
        let radius = 0.09;
        // The cap of a head the eye sees, split as EM split `occluded-side`'s: its middle, and
        // its rim (the deeper ring) in a component of its own.
        let (mut middle, mut rim) = (Vec::new(), Vec::new());
        for i in -20..=20 {
            for j in -20..=20 {
                let (u, v) = (f64::from(i) / 20.0, f64::from(j) / 20.0);
                if u * u + v * v <= 1.0 {
                    let depth = (1.0 - u * u - v * v).max(0.0).sqrt();
                    let p = centre + radius * (a * u + b * v - sight * depth);
                    if u * u + v * v > 0.6 {
                        rim.push(p)
                    } else {
                        middle.push(p)
                    }
                }
            }
        }
        let at = |offset: Vector3<f64>| component_of(&middle.iter().map(|p| p + offset).take(40).collect::<Vec<_>>());
        let components = vec![
            component_of(&middle),
            component_of(&rim),
            // A neck below, a hand in front of the face, and a hand's own component behind.
            at(Vector3::new(0.0, -0.17, 0.0)),
            at(-sight * 0.15),
            at(sight * 0.08 + a * 0.02),
        ];
        let hands = [None, Some(4)];
        let whole = head_with_its_pieces(&components, 0, &hands, &eye).expect("a head");
        assert_eq!(whole.mass, (middle.len() + rim.len()) as f64, "the rim joins, nothing else");
        let found = head_centre(&components, 0, &hands, &eye, 0.0).expect("a centre");
        assert!((found - centre).norm() < 0.005, "{:?}", found - centre);
        // Measured without its rim, the head lands well short of its middle.
        let alone = head_centre(&components[..1], 0, &hands, &eye, 0.0).expect("a centre");
        assert!((alone - centre).norm() > 0.02, "{:?} (whole: {:?})", alone - centre, found - centre);
        assert!(head_centre(&components, 7, &hands, &eye, 0.0).is_none());
    }

    #[test]
    fn signer_left_is_horizontal_and_independent_of_the_reference_roll() {
        let upright = ClusterStage::new(&reference(0.0), Vector3::y(), true);
        // The signer faces the camera: their left is the camera's right, here towards +X.
        assert!(upright.signer_left.x > 0.9 && upright.signer_left.y.abs() < 1e-12);
        for roll in [0.3, -1.2, std::f64::consts::FRAC_PI_2] {
            let rolled = ClusterStage::new(&reference(roll), Vector3::y(), true);
            assert!((rolled.signer_left - upright.signer_left).norm() < 1e-12, "roll {roll}");
            assert_eq!(rolled.up, Vector3::y());
        }
    }

    #[test]
    fn the_start_status_names_missing_skin_then_runs() {
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), true);
        stage.update(0.0, 30.0, 0.0, &[], None);
        assert_eq!(stage.start_status(), StartStatus::NoSkin);
        assert!(stage.last_fit().is_none());
        let blob = |x: f32, y: f32| {
            (0..200).map(move |i| ScenePoint {
                position: [x + (i % 10) as f32 * 0.004, y + (i / 10) as f32 * 0.004, 0.0],
                velocity: [0.0; 3],
                weight: 1.0,
                skin: 1.0,
            })
        };
        // Head and two hands within reach: the tracks start.
        let all: Vec<ScenePoint> = blob(0.0, 1.6).chain(blob(0.3, 1.1)).chain(blob(-0.3, 1.1)).collect();
        stage.update(1.0 / 30.0, 30.0, 0.0, &all, None);
        assert_eq!(stage.start_status(), StartStatus::Running);
        assert_eq!(stage.last_point_count(), 600);
        assert!(stage.last_fit().is_some_and(|f| f.components.len() >= 3));
        assert!(stage.assigned().iter().all(Option::is_some));
    }

    #[test]
    fn a_frame_set_without_points_coasts_every_track_on_its_prediction() {
        // A head and two hands moving sideways at 0.6 m/s; one frame set gives no points
        // (its reference camera dropped the frame): every track coasts on its prediction,
        // then the next set measures them again, each where it is, no identity swapped.
        let moving = |x: f32, y: f32, t: f64| {
            let dx = (0.6 * t) as f32;
            (0..200).map(move |i| ScenePoint {
                position: [x + dx + (i % 10) as f32 * 0.004, y + (i / 10) as f32 * 0.004, 0.0],
                velocity: [0.6 / 30.0, 0.0, 0.0],
                weight: 1.0,
                skin: 1.0,
            })
        };
        let body = |t: f64| -> Vec<ScenePoint> {
            moving(0.0, 1.6, t).chain(moving(0.3, 1.1, t)).chain(moving(-0.3, 1.1, t)).collect()
        };
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), false).with_hand_localisation(false);
        let fps = 30.0;
        let mut last = stage.update(0.0, fps, 0.0, &body(0.0), None);
        for f in 1..6 {
            last = stage.update(f as f64 / fps, fps, 0.0, &body(f as f64 / fps), None);
        }
        assert!(last.iter().all(|o| o.state == State::Tracked), "{last:?}");
        let coasted = stage.update(6.0 / fps, fps, 0.0, &[], None);
        for (k, (o, before)) in coasted.iter().zip(&last).enumerate() {
            assert_eq!(o.state, State::Predicted, "object {k}: {o:?}");
            let expected = before.position + Vector3::new(0.6 / fps, 0.0, 0.0);
            assert!((o.position - expected).norm() < 0.01, "object {k} at {:?}, expected {expected:?}", o.position);
        }
        let again = stage.update(7.0 / fps, fps, 0.0, &body(7.0 / fps), None);
        for (k, (o, before)) in again.iter().zip(&last).enumerate() {
            assert_eq!(o.state, State::Tracked, "object {k}: {o:?}");
            let expected = before.position + Vector3::new(2.0 * 0.6 / fps, 0.0, 0.0);
            assert!((o.position - expected).norm() < 0.02, "object {k} at {:?}, expected {expected:?}", o.position);
        }
    }

    #[test]
    fn a_hand_whose_prediction_flew_off_is_found_again_before_it_is_lost() {
        let blob = |x: f32, y: f32, n: usize, vx: f32| {
            (0..n).map(move |i| ScenePoint {
                position: [x + (i % 10) as f32 * 0.004, y + (i / 10) as f32 * 0.004, 0.0],
                velocity: [vx, 0.0, 0.0],
                weight: 1.0,
                skin: 1.0,
            })
        };
        let clutter = || blob(3.0, 0.5, 30, 0.0).chain(blob(-2.5, 2.5, 30, 0.0));
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), false).with_hand_localisation(false);
        let fps = 30.0;
        let body = || blob(0.0, 1.6, 200, 0.0).chain(blob(-0.3, 1.1, 200, 0.0)).chain(clutter());
        // The flow gives the left hand a wrong sideways velocity of 3 m/s (0.1 m per frame)
        // for a few frames, then the hand is hidden for a fifth of a second: its track
        // coasts half a metre away from the body.
        let mut t = 0.0;
        for f in 0..4 {
            // Without a face, the highest cluster starts the head: the clutter comes later.
            let points: Vec<ScenePoint> =
                body().filter(|p| f > 0 || p.position[0].abs() < 1.0).chain(blob(0.3, 1.1, 200, 0.1)).collect();
            stage.update(t, fps, 0.0, &points, None);
            t += 1.0 / fps;
        }
        for _ in 0..6 {
            let points: Vec<ScenePoint> = body().collect();
            stage.update(t, fps, 0.0, &points, None);
            t += 1.0 / fps;
        }
        // Back by the chin, still before the track would be lost.
        let points: Vec<ScenePoint> = body().chain(blob(0.2, 1.42, 200, 0.0)).collect();
        let mut back = stage.update(t, fps, 0.0, &points, None);
        for _ in 0..2 {
            t += 1.0 / fps;
            back = stage.update(t, fps, 0.0, &points, None);
        }
        assert_eq!(back[1].state, State::Tracked, "{back:?}");
        assert!(
            (back[1].position - Vector3::new(0.218, 1.438, 0.0)).norm() < 0.03,
            "left hand at {:?}",
            back[1].position
        );
    }

    #[test]
    fn a_lost_hand_is_found_again_beside_the_head_even_with_clutter_far_away() {
        let blob = still_blob;
        // Skin-coloured clutter out of reach takes the spare components' seeds.
        let clutter = || blob(3.0, 0.5, 30).chain(blob(-2.5, 2.5, 30));
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), false).with_hand_localisation(false);
        let fps = 30.0;
        let mut t = 0.0;
        let all: Vec<ScenePoint> = blob(0.0, 1.6, 200).chain(blob(0.3, 1.1, 200)).chain(blob(-0.3, 1.1, 200)).collect();
        let start = stage.update(t, fps, 0.0, &all, None);
        assert!(start.iter().all(|e| e.state == State::Tracked));
        // The signer's left hand (+X) sweeps out of the views and stays out for a second:
        // its track coasts on and is lost far from the body.
        for k in 0..40 {
            t += 1.0 / fps;
            let mut points: Vec<ScenePoint> =
                blob(0.0, 1.6, 200).chain(blob(-0.3, 1.1, 200)).chain(clutter()).collect();
            if k < 8 {
                points.extend(blob(0.3 + 0.05 * (k + 1) as f32, 1.1, 200));
            }
            stage.update(t, fps, 0.0, &points, None);
        }
        t += 1.0 / fps;
        let none: Vec<ScenePoint> = blob(0.0, 1.6, 200).chain(blob(-0.3, 1.1, 200)).chain(clutter()).collect();
        assert_eq!(stage.update(t, fps, 0.0, &none, None)[1].state, State::Lost);
        // It comes back up by the chin, where the head's component would swallow it.
        let mut back = None;
        for _ in 0..3 {
            t += 1.0 / fps;
            let points: Vec<ScenePoint> =
                blob(0.0, 1.6, 200).chain(blob(-0.3, 1.1, 200)).chain(blob(0.2, 1.42, 200)).chain(clutter()).collect();
            back = Some(stage.update(t, fps, 0.0, &points, None));
        }
        let back = back.expect("updated");
        assert_eq!(back[1].state, State::Tracked, "{back:?}");
        let hand = Vector3::new(0.218, 1.438, 0.0);
        assert!((back[1].position - hand).norm() < 0.03, "left hand at {:?}", back[1].position);
        assert!((back[0].position - Vector3::new(0.018, 1.638, 0.0)).norm() < 0.03, "head at {:?}", back[0].position);
    }

    #[test]
    fn a_hand_whose_track_started_on_a_piece_of_its_arm_takes_the_hand_when_it_rises() {
        let blob = still_blob;
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), false).with_hand_localisation(false);
        let fps = 6.0;
        let mut t = 0.0;
        let face = Some(FaceCue::new([0.018, 1.638, 0.02], 0, fps));
        // The signer's left hand (+X) lies below the reference view: only a piece of its
        // forearm by the elbow is seen, a fifth of a hand's skin, and its track starts there.
        let body = || {
            blob(0.0, 1.6, 200)
                .chain(blob(-0.3, 1.1, 200))
                .chain(blob(0.35, 0.95, 40))
                .chain(blob(-0.1, 2.2, 40))
                .chain(blob(3.0, 0.5, 30))
                .chain(blob(-2.5, 2.5, 30))
        };
        for _ in 0..4 {
            let points: Vec<ScenePoint> = body().collect();
            let start = stage.update(t, fps, 0.0, &points, face);
            assert_eq!(start[1].state, State::Tracked);
            assert!((start[1].position - Vector3::new(0.368, 0.958, 0.0)).norm() < 0.03, "{:?}", start[1].position);
            t += 1.0 / fps;
        }
        // The hand rises into view, nearer the head than the piece it left.
        let mut now = None;
        for _ in 0..2 {
            let points: Vec<ScenePoint> = body().chain(blob(0.2, 1.42, 200)).collect();
            now = Some(stage.update(t, fps, 0.0, &points, face));
            t += 1.0 / fps;
        }
        let now = now.expect("updated");
        let hand = Vector3::new(0.218, 1.438, 0.0);
        assert!((now[1].position - hand).norm() < 0.03, "left hand at {:?}", now[1].position);
        assert!((now[0].position - Vector3::new(0.018, 1.638, 0.0)).norm() < 0.03, "head at {:?}", now[0].position);
    }

    #[test]
    fn a_second_start_replaces_the_predictions_fit_only_when_clearly_better() {
        let fit = |log_likelihood: f64| EmFit {
            components: Vec::new(),
            iterations: 1,
            log_likelihood,
            points_used: 1,
            outlier_share: 0.0,
        };
        let kept = |a: f64, b: f64| better_fit(Some(fit(a)), Some(fit(b))).map(|f| f.log_likelihood);
        assert_eq!(kept(10.0, 10.0 + 0.5 * SECOND_START_MARGIN), Some(10.0));
        assert_eq!(kept(10.0, 9.0), Some(10.0));
        assert_eq!(kept(10.0, 10.0 + 2.0 * SECOND_START_MARGIN), Some(10.0 + 2.0 * SECOND_START_MARGIN));
        assert_eq!(better_fit(None, Some(fit(3.0))).map(|f| f.log_likelihood), Some(3.0));
        assert!(better_fit(None, None).is_none());
    }

    #[test]
    fn a_hand_whose_component_lost_it_gets_it_back_from_a_second_start() {
        // `signer-6fps` frame 6 at engine seed 5 (every fourth point), where the hands then
        // swapped: the left hand's prediction, thrown by a wrong velocity, seeds a component
        // that takes a fraction of the hand.
        let points: Vec<WeightedPoint> = include_str!("../tests/fixtures/signer-6fps-seed5-frame6.csv")
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| {
                let v: Vec<f64> = l.split(',').map(|x| x.parse().expect("a number")).collect();
                WeightedPoint {
                    position: Vector3::new(v[0], v[1], v[2]),
                    velocity: Vector3::new(v[3], v[4], v[5]),
                    weight: v[6],
                }
            })
            .collect();
        let mut stage = ClusterStage::new(&reference(0.0), Vector3::y(), false).with_hand_localisation(false);
        stage.points = points;
        let predicted = [
            (Vector3::new(0.0023, 1.6094, 0.0422), Vector3::new(-0.091, -0.115, 0.140)),
            (Vector3::new(0.2770, 1.0794, 0.2662), Vector3::new(-0.473, 0.042, 0.114)),
            (Vector3::new(-0.0982, 1.3696, 0.2458), Vector3::new(0.215, 0.053, -0.098)),
        ];
        let (left, right) = (Vector3::new(0.228, 1.094, 0.238), Vector3::new(-0.098, 1.337, 0.251));
        let total: f64 = stage.points.iter().map(|p| p.weight).sum();
        // The left hand's track's typical mass there: 14.6 % of the frame's weight.
        let typical_left = 0.146 * total;
        let from_predictions = stage.fit_seeded(predicted, &[]).expect("fit");
        let starved = &from_predictions.components[1];
        assert!(starved.mass < STARVED_HAND_SHARE * typical_left, "{:.1} of {total:.1}", starved.mass);
        let second = stage.fit_seeded(stage.side_start(predicted), &[]).expect("fit");
        assert!(second.log_likelihood > from_predictions.log_likelihood + SECOND_START_MARGIN);
        let kept = better_fit(Some(from_predictions), Some(second)).expect("fit");
        let (l, r) = (&kept.components[1], &kept.components[2]);
        assert!((l.position - left).norm() < 0.03 && l.mass > 0.8 * typical_left, "left: {l:?}");
        assert!((r.position - right).norm() < 0.03, "right: {r:?}");
    }
}
