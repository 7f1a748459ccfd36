//! Labelling and prediction: the three tracks (head, left hand, right hand) and the
//! constant-velocity model that carries them from frame to frame (section 4.2), with the
//! re-initialisation and per-track state the paper's section 6 asks for.

use nalgebra::Vector3;

use crate::em::{Component, EmFit};

/// Track labels, in track order.
pub const OBJECTS: [&str; 3] = ["head", "left_hand", "right_hand"];

/// Tracking state of one object.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum State {
    /// Measured this frame.
    Tracked,
    /// No cluster this frame: extrapolated by the constant-velocity model.
    Predicted,
    /// Unmeasured for too long; the position is the last one known.
    Lost,
}

impl State {
    /// The name used in trajectory files.
    pub fn name(self) -> &'static str {
        match self {
            State::Tracked => "tracked",
            State::Predicted => "predicted",
            State::Lost => "lost",
        }
    }
}

/// Why the first labelling did not start the tracks (see [`Tracker::not_started`]). Until
/// it succeeds every track is lost, so this is what a user needs to see first on footage
/// where nothing is tracked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NotStarted {
    /// The frame gave no clusters at all: no usable point (no skin in the reference view,
    /// or nothing estimated on it), so there is no head cluster either.
    NoClusters,
    /// Fewer than three clusters hold enough of the frame's weight
    /// ([`TrackerConfig::min_mass_share`]): a head at most, no two hands.
    TooFewClusters {
        /// Clusters kept.
        clusters: usize,
    },
    /// The highest cluster (the head) has fewer than two others within reach
    /// ([`TrackerConfig::reach_m`]).
    HandsOutOfReach {
        /// Clusters within reach of the head.
        within_reach: usize,
        /// Distance from the head of the nearest cluster beyond reach, metres.
        nearest_beyond_m: Option<f64>,
        /// The reach, metres.
        reach_m: f64,
    },
    /// Fewer than two clusters within reach of the head lie clear of it: the others are
    /// pieces of the head (a face split in two, a neck; see
    /// [`TrackerConfig::split_distance_m`]), and a hand started on one would stay there.
    HandsAtTheHead {
        /// Clusters within reach and clear of the head.
        clear: usize,
        /// Clusters closer to the head's than the clearance.
        pieces: usize,
        /// The clearance, metres.
        clearance_m: f64,
    },
}

impl NotStarted {
    /// The cause without its figures: two values with the same cause are one state to
    /// report (the figures change every frame).
    pub fn cause(&self) -> &'static str {
        match self {
            NotStarted::NoClusters => "no clusters",
            NotStarted::TooFewClusters { .. } => "too few clusters",
            NotStarted::HandsOutOfReach { .. } => "hands out of reach",
            NotStarted::HandsAtTheHead { .. } => "hands at the head",
        }
    }
}

impl std::fmt::Display for NotStarted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NotStarted::NoClusters => write!(f, "no clusters, so no head cluster"),
            NotStarted::TooFewClusters { clusters } => {
                write!(f, "{clusters} cluster(s) with enough weight, 3 needed (a head and two hands)")
            }
            NotStarted::HandsOutOfReach { within_reach, nearest_beyond_m, reach_m } => {
                write!(f, "{within_reach} cluster(s) within {reach_m} m of the head cluster (the highest), 2 needed")?;
                match nearest_beyond_m {
                    Some(d) => write!(f, "; the nearest other is {d:.2} m away"),
                    None => Ok(()),
                }
            }
            NotStarted::HandsAtTheHead { clear, pieces, clearance_m } => write!(
                f,
                "{clear} cluster(s) within reach and farther than {clearance_m} m from the head cluster, 2 needed \
                 ({pieces} closer: pieces of the head)"
            ),
        }
    }
}

/// Parameters of labelling and prediction.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerConfig {
    /// Velocity weight of the assignment cost, seconds: cost = |position error| + this x
    /// |velocity error| (default 0.1: two hands 10 cm apart moving at 1 m/s in opposite
    /// directions differ as much by motion as by place).
    pub velocity_weight_s: f64,
    /// A track whose assigned cluster is farther than its gate from its prediction is
    /// re-initialised on that cluster. The gate is this distance, metres (default 0.2, about
    /// two palm widths: what a cluster's centre jitters and a hand moves unpredictably in one
    /// frame at 30 fps), plus what the constant-velocity model can miss over the frame
    /// interval, `max_acceleration_m_s2 * dt^2 / 2` (see [`TrackerConfig::gate_m`]).
    pub reinit_distance_m: f64,
    /// Largest acceleration of a hand the gate allows for, metres per second squared
    /// (default 20: a hand reversing a 1.5 m/s stroke in 0.15 s). At 30 fps it widens the
    /// gate by 1 cm, at 6 fps by 28 cm: a hand moves 20-50 cm between frames there, and a
    /// fixed per-frame gate tuned at 30 fps re-initialised it on every turn.
    pub max_acceleration_m_s2: f64,
    /// A cluster holding less than this share of the frame's weight is no measurement
    /// (default 0.02).
    pub min_mass_share: f64,
    /// Seconds a track may be predicted before it is lost (default 0.5; at 30 fps 15 frames,
    /// at 6 fps 3).
    pub lost_after_s: f64,
    /// Seconds without any frame after which the tracks start afresh from the labelling
    /// rules; after a shorter gap longer than `lost_after_s` each track is looked for where
    /// it was last seen (default 1.0: at a signer's usual 0.3-1 m/s a hand goes farther
    /// than the 0.3-0.5 m between the hands within a second, so where it was stops saying
    /// which it is, while the signer's side still does).
    pub relabel_after_s: f64,
    /// Two tracks whose clusters are closer than this, metres, are merged in this frame (one
    /// hand passing in front of the other): both coast on their predictions instead of
    /// taking the same blob and leaving it with each other's labels (default 0.04).
    pub merge_distance_m: f64,
    /// A free cluster closer than this to another track's cluster, metres, is a piece of
    /// that object and never re-initialises a track (default 0.15, about a head's width).
    pub split_distance_m: f64,
    /// Share of a measured velocity taken into the track's velocity (default 0.5; the rest
    /// is the prediction): one frame's velocity, perhaps from a blob of two hands, cannot
    /// reverse a track.
    pub velocity_gain: f64,
    /// A cluster holding less of the weight than its track usually has is part of the
    /// object (a hand half hidden behind the other, or leaving the reference view): its
    /// centroid is biased towards the visible part. Between these shares of the track's
    /// typical mass (default 0.25 and 0.75) the measurement's pull on position and velocity
    /// rises from none (the prediction) to all.
    pub partial_mass_share: (f64, f64),
    /// Time constant with which a track's typical mass follows its measurements, seconds
    /// (default 0.32, a rate of 0.1 per frame at 30 fps: a hand turning edge-on over a third
    /// of a second is followed, a one-frame occlusion is not).
    pub typical_mass_time_s: f64,
    /// Farthest the head track may be from the face the detectors placed in 3D, metres
    /// (default 0.25, as far as a head moves between detection rounds): beyond it the
    /// track is brought back to the face ([`HeadAnchor`]).
    pub face_anchor_m: f64,
    /// Farthest a hand can be from the head, metres (default 1.0: an adult's arm and
    /// shoulder). Tracks start only on hands within this reach, so skin-like clutter or a
    /// ghost surface behind the signer never becomes a hand.
    pub reach_m: f64,
    /// Seconds after the tracks start in which the first labelling, by the signer's side,
    /// still holds once a hand track has jumped (default 1.0): after a re-initialisation of
    /// a hand in that time, two measured hands found on each other's side, farther apart
    /// across the signer than [`TrackerConfig::settle_margin_m`], trade labels. A hand track
    /// started on a forearm or a piece of the body jumps to a hand in its first frames, and
    /// can take the one its neighbour should have (measured on a fisheye rendering of the
    /// shared session: both hands on the wrong side from frame 3 to the end). Hands followed
    /// without a jump keep their labels through a crossing.
    pub settle_s: f64,
    /// How far across the signer two hands must be on each other's side to trade labels
    /// while settling, metres (default 0.15: hands held together at the middle never do).
    pub settle_margin_m: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            velocity_weight_s: 0.1,
            reinit_distance_m: 0.2,
            max_acceleration_m_s2: 20.0,
            min_mass_share: 0.02,
            lost_after_s: 0.5,
            relabel_after_s: 1.0,
            merge_distance_m: 0.04,
            split_distance_m: 0.15,
            velocity_gain: 0.5,
            partial_mass_share: (0.25, 0.75),
            typical_mass_time_s: 0.32,
            face_anchor_m: 0.25,
            reach_m: 1.0,
            settle_s: 1.0,
            settle_margin_m: 0.15,
        }
    }
}

impl TrackerConfig {
    /// The re-initialisation gate for a prediction `dt` seconds ahead, metres.
    pub fn gate_m(&self, dt: f64) -> f64 {
        let dt = dt.max(0.0);
        self.reinit_distance_m + 0.5 * self.max_acceleration_m_s2 * dt * dt
    }
}

/// Where the face detectors say the head is. Skin-coloured clutter (a bookshelf, a sunlit
/// door frame) can hold a cluster that the head track drifts onto once a hand covers the
/// face; the detectors' face, confirmed by several views, cannot. With an anchor, the head
/// track starts on the cluster nearest the face, and a head track farther than
/// [`TrackerConfig::face_anchor_m`] from it is re-initialised on the cluster nearest the
/// face, or on the face itself when no cluster is near it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeadAnchor {
    /// The face's centre (on its surface), world metres: what a head cluster is compared with.
    pub face: Vector3<f64>,
    /// The head's centre behind it, world metres: where the track goes when no cluster is
    /// near the face.
    pub head: Vector3<f64>,
}

/// One object's estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Track {
    /// World position, metres.
    pub position: Vector3<f64>,
    /// World velocity, metres per second.
    pub velocity: Vector3<f64>,
    /// Confidence in [0, 1]: high for a clear, predicted measurement, decaying while predicted.
    pub confidence: f64,
    /// Tracking state.
    pub state: State,
    /// Frames since the last measurement.
    pub unmeasured: u32,
    /// Seconds since the last measurement.
    pub unmeasured_s: f64,
    /// The weight the track's clusters usually hold (a running mean).
    pub typical_mass: f64,
    /// False once the velocity foretold a measurement worse than rest did, until it foretells
    /// one better (a new track's velocity is trusted). Only a trusted velocity moves the
    /// prediction (and the EM seed placed there): at low rates a wrong velocity throws the
    /// prediction a third of a metre off, and the cluster seeded there loses the object
    /// (measured on `signer-6fps`: a left hand moving at 0.25 m/s started at -2 m/s by a
    /// cold start's flow, its prediction 20 cm off and its cluster lost for four frames).
    pub velocity_trusted: bool,
}

/// How a cluster measured a track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Measurement {
    /// Index into the fit's components.
    pub cluster: usize,
    /// Share of the way from the prediction to the cluster the track moved (below 1 for a
    /// partly hidden object, see [`TrackerConfig::partial_mass_share`]).
    pub pull: f64,
}

/// Labels clusters into the three tracks and predicts them.
#[derive(Clone, Debug)]
pub struct Tracker {
    config: TrackerConfig,
    up: Vector3<f64>,
    signer_left: Vector3<f64>,
    tracks: Option<[Track; 3]>,
    time: f64,
    reinitialisations: u64,
    /// Per track, the cluster that measured it in the last update.
    assigned: [Option<Measurement>; 3],
    /// Why the last update's first labelling failed (`None` once tracks run).
    not_started: Option<NotStarted>,
    /// When the tracks last started from the labelling rules.
    started_at: f64,
    /// Whether a hand track was re-initialised since then.
    hand_jumped: bool,
}

impl Tracker {
    /// A tracker for a scene whose world `up` direction and signer's-left direction (the
    /// camera's right, for a signer facing the camera) are given.
    pub fn new(config: TrackerConfig, up: Vector3<f64>, signer_left: Vector3<f64>) -> Self {
        Self {
            config,
            up: up.try_normalize(1e-12).unwrap_or_else(Vector3::y),
            signer_left: signer_left.try_normalize(1e-12).unwrap_or_else(Vector3::x),
            tracks: None,
            time: 0.0,
            reinitialisations: 0,
            assigned: [None; 3],
            not_started: None,
            started_at: f64::NEG_INFINITY,
            hand_jumped: false,
        }
    }

    /// Why the last update started no track: `Some` while no track has started (or every
    /// track is lost) and the last update's clusters could not be labelled; `None` when the
    /// last update measured or predicted tracks.
    pub fn not_started(&self) -> Option<NotStarted> {
        self.not_started
    }

    /// Per track (head, left hand, right hand), the cluster that measured it in the last
    /// update (`None`: predicted or lost).
    pub fn assigned(&self) -> [Option<Measurement>; 3] {
        self.assigned
    }

    /// The tracks after the last update (`None` before the first measurement).
    pub fn tracks(&self) -> Option<&[Track; 3]> {
        self.tracks.as_ref()
    }

    /// Replaces track `k`'s current position (a caller refining the measurement, e.g. with
    /// knowledge of the object's shape); the next prediction starts from it.
    pub fn set_position(&mut self, k: usize, position: Vector3<f64>) {
        if let Some(track) = self.tracks.as_mut().and_then(|t| t.get_mut(k)) {
            track.position = position;
        }
    }

    /// The configuration.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// Re-initialisations so far (a track jumping to a cluster far from its prediction).
    pub fn reinitialisations(&self) -> u64 {
        self.reinitialisations
    }

    /// Time of the last update, seconds.
    pub fn time(&self) -> f64 {
        self.time
    }

    /// Constant-velocity predictions at time `t` (seconds), in track order, to initialise
    /// the next EM fit; `None` before the first measurement or when every track is lost.
    pub fn predictions(&self, t: f64) -> Option<[(Vector3<f64>, Vector3<f64>); 3]> {
        let tracks = self.tracks.as_ref()?;
        if tracks.iter().all(|k| k.state == State::Lost) {
            return None;
        }
        let dt = t - self.time;
        Some(tracks.map(|k| match k.state {
            State::Lost => (k.position, Vector3::zeros()),
            _ if !k.velocity_trusted => (k.position, k.velocity),
            _ => (k.position + k.velocity * dt, k.velocity),
        }))
    }

    /// Takes the clusters of the frame at time `t` (or none, when the frame had no usable
    /// point) and returns the three tracks.
    pub fn update(&mut self, t: f64, fit: Option<&EmFit>) -> [Track; 3] {
        self.update_anchored(t, fit, None)
    }

    /// [`Tracker::update`] with the head anchored to where the face detectors place it.
    pub fn update_anchored(&mut self, t: f64, fit: Option<&EmFit>, anchor: Option<HeadAnchor>) -> [Track; 3] {
        let (indices, clusters): (Vec<usize>, Vec<&Component>) = match fit {
            Some(f) => {
                let total: f64 = f.components.iter().map(|c| c.mass).sum();
                f.components
                    .iter()
                    .enumerate()
                    .filter(|(_, c)| !c.empty && total > 0.0 && c.mass / total >= self.config.min_mass_share)
                    .unzip()
            }
            None => (Vec::new(), Vec::new()),
        };
        self.assigned = [None; 3];
        self.not_started = None;
        // No frame at all for longer than a track may coast (a live stage that fell behind,
        // a stream that stalled): the constant-velocity predictions over that gap say
        // nothing of where each hand is now, and following them swaps hands. After a gap up
        // to `relabel_after_s`, each track is looked for where it was last seen, its
        // velocity forgotten (labelled afresh instead, a 6 fps live run took a stray cluster
        // by the left hand for a hand and swapped the hands for the rest of the session);
        // after a longer one, the tracks start again from the labelling rules.
        let gap_s = t - self.time;
        let long_gap = gap_s > self.config.lost_after_s;
        if let (true, Some(tracks)) = (long_gap, self.tracks.as_mut()) {
            for k in tracks.iter_mut() {
                k.velocity = Vector3::zeros();
                k.velocity_trusted = false;
                if gap_s > self.config.relabel_after_s {
                    k.state = State::Lost;
                }
            }
        }
        let tracks = match self.predictions(t) {
            Some(predicted) => self.follow(gap_s, predicted, &clusters, anchor).map(|tracks| {
                if long_gap {
                    self.uncrossed(tracks, 0.0)
                } else if self.hand_jumped
                    && t - self.started_at <= self.config.settle_s
                    && self.assigned[1].is_some()
                    && self.assigned[2].is_some()
                {
                    self.uncrossed(tracks, self.config.settle_margin_m)
                } else {
                    tracks
                }
            }),
            None => match self.start(&clusters, anchor) {
                Ok(tracks) => {
                    self.started_at = t;
                    self.hand_jumped = false;
                    Some(tracks)
                }
                Err(why) => {
                    self.not_started = Some(why);
                    None
                }
            },
        };
        self.time = t;
        self.assigned = self.assigned.map(|a| a.map(|m| Measurement { cluster: indices[m.cluster], ..m }));
        if let Some(tracks) = tracks {
            self.tracks = Some(tracks);
        }
        self.tracks.unwrap_or(
            [Track {
                position: Vector3::zeros(),
                velocity: Vector3::zeros(),
                confidence: 0.0,
                state: State::Lost,
                unmeasured: 0,
                unmeasured_s: 0.0,
                typical_mass: 0.0,
                velocity_trusted: false,
            }; 3],
        )
    }

    /// First labelling: head is the highest cluster, the hands are the two largest within
    /// reach of it, told apart by the signer's left. Needs three such clusters (until then
    /// no track starts, and the error says which is missing).
    fn start(&mut self, clusters: &[&Component], anchor: Option<HeadAnchor>) -> Result<[Track; 3], NotStarted> {
        let highest = (0..clusters.len())
            .max_by(|&a, &b| clusters[a].position.dot(&self.up).total_cmp(&clusters[b].position.dot(&self.up)))
            .ok_or(NotStarted::NoClusters)?;
        // With a face known, the head is the cluster on it, not whatever is highest (a
        // raised hand, a lamp).
        let head = anchor.and_then(|a| self.nearest_within(clusters, a.face)).unwrap_or(highest);
        if clusters.len() < 3 {
            return Err(NotStarted::TooFewClusters { clusters: clusters.len() });
        }
        let distance = |k: usize| (clusters[k].position - clusters[head].position).norm();
        let mut hands: Vec<usize> =
            (0..clusters.len()).filter(|&k| k != head && distance(k) <= self.config.reach_m).collect();
        if hands.len() < 2 {
            let nearest_beyond_m = (0..clusters.len())
                .filter(|&k| k != head && distance(k) > self.config.reach_m)
                .map(distance)
                .min_by(f64::total_cmp);
            return Err(NotStarted::HandsOutOfReach {
                within_reach: hands.len(),
                nearest_beyond_m,
                reach_m: self.config.reach_m,
            });
        }
        // A cluster by the head is a piece of it (a face EM split in two): a hand started
        // there would follow the face. Wait for a frame with both hands clear of it.
        let clearance = self.config.split_distance_m;
        let pieces = hands.iter().filter(|&&k| distance(k) < clearance).count();
        hands.retain(|&k| distance(k) >= clearance);
        if hands.len() < 2 {
            return Err(NotStarted::HandsAtTheHead { clear: hands.len(), pieces, clearance_m: clearance });
        }
        // Of the remaining, the two largest are the hands.
        hands.sort_by(|&a, &b| clusters[b].mass.total_cmp(&clusters[a].mass));
        hands.truncate(2);
        let side = |k: usize| clusters[k].position.dot(&self.signer_left);
        let (left, right) = if side(hands[0]) >= side(hands[1]) { (hands[0], hands[1]) } else { (hands[1], hands[0]) };
        self.assigned = [head, left, right].map(|cluster| Some(Measurement { cluster, pull: 1.0 }));
        Ok([head, left, right].map(|k| self.fresh(clusters[k], 1.0)))
    }

    /// After a gap longer than a track may coast: hands followed from where they were last
    /// seen that come out on each other's side of the signer moved past each other unseen
    /// (each took the other), so they trade places. Arms held crossed through a gap are
    /// rarer than hands that swapped sides during it. The same while the first labelling
    /// settles ([`TrackerConfig::settle_s`]), for hands more than `margin_m` across.
    fn uncrossed(&mut self, mut tracks: [Track; 3], margin_m: f64) -> [Track; 3] {
        let side = |k: &Track| k.position.dot(&self.signer_left);
        if side(&tracks[2]) - side(&tracks[1]) > margin_m {
            tracks.swap(1, 2);
            self.assigned.swap(1, 2);
        }
        tracks
    }

    /// Later frames: the assignment of clusters to tracks that best matches the predicted
    /// positions and velocities (all permutations; three tracks make six).
    fn follow(
        &mut self,
        dt: f64,
        predicted: [(Vector3<f64>, Vector3<f64>); 3],
        clusters: &[&Component],
        anchor: Option<HeadAnchor>,
    ) -> Option<[Track; 3]> {
        let previous = self.tracks?;
        let gate = self.config.gate_m(dt);
        let cost = |track: usize, c: &Component| {
            let (p, v) = predicted[track];
            (c.position - p).norm() + self.config.velocity_weight_s * (c.velocity - v).norm()
        };
        // A track left without a cluster pays the gate and the velocity change the largest
        // acceleration allows over the interval: better unmeasured than matched to a
        // cluster farther than that in position and motion.
        let miss = gate + self.config.velocity_weight_s * self.config.max_acceleration_m_s2 * dt.max(0.0);
        let mut best: ([Option<usize>; 3], f64) = ([None; 3], f64::INFINITY);
        let options: Vec<Option<usize>> = (0..clusters.len()).map(Some).chain(std::iter::once(None)).collect();
        for &a in &options {
            for &b in &options {
                for &c in &options {
                    let pick = [a, b, c];
                    let distinct = (0..3).all(|i| (0..i).all(|j| pick[i].is_none() || pick[i] != pick[j]));
                    if !distinct {
                        continue;
                    }
                    let total: f64 = (0..3).map(|k| pick[k].map_or(miss, |i| cost(k, clusters[i]))).sum();
                    if total < best.1 {
                        best = (pick, total);
                    }
                }
            }
        }
        // The head strayed from the face: back onto the cluster at the face, taken from a
        // hand if need be (a hand in front of the face is one blob with it; the hand coasts),
        // or onto the face itself.
        let mut head_to_face = None;
        if let Some(a) = anchor {
            let head_now = best.0[0].map_or(predicted[0].0, |i| clusters[i].position);
            if (head_now - a.face).norm() > self.config.face_anchor_m {
                let near = self.nearest_within(clusters, a.face);
                for k in 1..3 {
                    if near.is_some() && best.0[k] == near {
                        best.0[k] = None;
                    }
                }
                best.0[0] = near;
                head_to_face = Some(near.map_or(a.head, |i| clusters[i].position));
            }
        }
        // The head split into pieces (EM gives a face two components when its points are
        // few): of the pieces, the head is the one at the face, not whichever the track
        // happened to follow onto the top of the head; before the face is placed in 3D, the
        // heaviest piece.
        if let (None, Some(held)) = (head_to_face, best.0[0]) {
            let piece = |i: usize| {
                i != held
                    && !best.0[1..].contains(&Some(i))
                    && (clusters[i].position - clusters[held].position).norm() < self.config.split_distance_m
            };
            let head = match anchor {
                Some(a) => self.nearest_within(clusters, a.face).filter(|&i| piece(i)),
                None => (0..clusters.len())
                    .filter(|&i| piece(i) && clusters[i].mass > clusters[held].mass)
                    .max_by(|&a, &b| clusters[a].mass.total_cmp(&clusters[b].mass)),
            };
            if let Some(i) = head {
                best.0[0] = Some(i);
            }
        }
        // Merged clusters: two tracks on (nearly) one blob coast through it.
        let mut merged = [false; 3];
        for a in 0..3 {
            for b in a + 1..3 {
                if let (Some(i), Some(j)) = (best.0[a], best.0[b]) {
                    if (clusters[i].position - clusters[j].position).norm() < self.config.merge_distance_m {
                        merged[a] = true;
                        merged[b] = true;
                    }
                }
            }
        }
        let taken: Vec<usize> = best.0.iter().flatten().copied().collect();
        for (k, m) in merged.iter().enumerate() {
            if *m {
                best.0[k] = None;
            }
        }
        // A track its prediction no longer explains (no cluster within the re-initialisation
        // distance for a second frame running) is re-initialised on the cluster nearest to
        // its prediction that no other track took: the object reappeared somewhere the
        // constant-velocity model did not expect.
        for (k, track) in previous.iter().enumerate() {
            if best.0[k].is_some() || track.unmeasured == 0 || merged[k] || (k == 0 && head_to_face.is_some()) {
                continue;
            }
            // Not a piece of an object another track holds: a cluster that close to another
            // track's measurement is that object split in two.
            let others: Vec<Vector3<f64>> =
                (0..3).filter(|&o| o != k).filter_map(|o| best.0[o].map(|i| clusters[i].position)).collect();
            // A hand comes back within reach of the head, as tracks start (skin-like
            // clutter across the room never becomes a hand).
            let head = best.0[0].map_or(predicted[0].0, |i| clusters[i].position);
            let free = (0..clusters.len())
                .filter(|i| !best.0.contains(&Some(*i)) && !taken.contains(i))
                .filter(|&i| others.iter().all(|p| (clusters[i].position - p).norm() > self.config.split_distance_m))
                .filter(|&i| k == 0 || (clusters[i].position - head).norm() <= self.config.reach_m)
                .min_by(|&a, &b| cost(k, clusters[a]).total_cmp(&cost(k, clusters[b])));
            if let Some(i) = free {
                best.0[k] = Some(i);
            }
        }
        // A hand EM split in pieces (its points few, or two fingers' worth apart): the free
        // pieces by the one the track took are the same hand, and measure it together. Alone,
        // the piece the track took looks like a hand half hidden, and the track would coast on
        // its prediction beside the very hand it lost.
        let whole: [Option<Component>; 3] = std::array::from_fn(|k| {
            let i = best.0[k].filter(|_| k > 0 && !merged[k])?;
            let typical = previous[k].typical_mass;
            if typical <= 0.0 || clusters[i].mass >= self.config.partial_mass_share.1 * typical {
                return None;
            }
            let held: Vec<Vector3<f64>> =
                (0..3).filter(|&o| o != k).filter_map(|o| best.0[o].map(|j| clusters[j].position)).collect();
            let near = |j: usize| (clusters[j].position - clusters[i].position).norm();
            let pieces: Vec<usize> = (0..clusters.len())
                .filter(|&j| j != i && !best.0.contains(&Some(j)) && !taken.contains(&j))
                .filter(|&j| near(j) < self.config.split_distance_m)
                .filter(|&j| held.iter().all(|h| (clusters[j].position - h).norm() > near(j)))
                .collect();
            (!pieces.is_empty()).then(|| merge_pieces(clusters[i], pieces.iter().map(|&j| clusters[j])))
        });
        self.assigned = [None; 3];
        let mut out = previous;
        for k in 0..3 {
            let (p, v) = predicted[k];
            if let (0, Some(at)) = (k, head_to_face) {
                self.reinitialisations += 1;
                out[0] = match best.0[0] {
                    Some(i) => {
                        self.assigned[0] = Some(Measurement { cluster: i, pull: 1.0 });
                        self.fresh(clusters[i], 0.5)
                    }
                    None => Track {
                        position: at,
                        velocity: Vector3::zeros(),
                        confidence: 0.3,
                        state: State::Tracked,
                        unmeasured: 0,
                        unmeasured_s: 0.0,
                        typical_mass: previous[0].typical_mass,
                        velocity_trusted: false,
                    },
                };
                continue;
            }
            out[k] = match best.0[k] {
                Some(i) => {
                    let c = whole[k].as_ref().unwrap_or(clusters[i]);
                    let distance = (c.position - p).norm();
                    if distance > gate {
                        self.reinitialisations += 1;
                        self.hand_jumped |= k > 0;
                        self.assigned[k] = Some(Measurement { cluster: i, pull: 1.0 });
                        self.fresh(c, 0.5)
                    } else {
                        let agreement = (-0.5 * (distance / (0.5 * gate)).powi(2)).exp();
                        let typical = previous[k].typical_mass;
                        let (low, high) = self.config.partial_mass_share;
                        let share = if typical > 0.0 { c.mass / typical } else { 1.0 };
                        let pull = ((share - low) / (high - low).max(1e-9)).clamp(0.0, 1.0);
                        let mut track = measured(c, agreement * (0.5 + 0.5 * pull));
                        let g = self.config.velocity_gain.clamp(0.0, 1.0);
                        track.position = p + (c.position - p) * pull;
                        track.velocity = v + (c.velocity - v) * g * pull;
                        let rate = 1.0 - (-dt.max(0.0) / self.config.typical_mass_time_s.max(1e-9)).exp();
                        track.typical_mass = typical + (c.mass - typical) * rate;
                        // Did the velocity foretell this measurement better than rest? A
                        // partial one (pull 0) says little of where the object is.
                        let from = previous[k].position;
                        let moving = (c.position - (from + previous[k].velocity * dt.max(0.0))).norm();
                        track.velocity_trusted =
                            if pull > 0.0 { moving < (c.position - from).norm() } else { previous[k].velocity_trusted };
                        self.assigned[k] = Some(Measurement { cluster: i, pull });
                        track
                    }
                }
                None => {
                    let unmeasured = previous[k].unmeasured + 1;
                    let unmeasured_s = previous[k].unmeasured_s + dt.max(0.0);
                    // A hair's tolerance: 15 frames at 30 fps are 0.5 s give or take rounding.
                    if unmeasured_s > self.config.lost_after_s + 1e-6 || previous[k].state == State::Lost {
                        Track {
                            position: previous[k].position,
                            velocity: Vector3::zeros(),
                            confidence: 0.0,
                            state: State::Lost,
                            unmeasured,
                            unmeasured_s,
                            typical_mass: previous[k].typical_mass,
                            velocity_trusted: false,
                        }
                    } else {
                        Track {
                            position: p,
                            velocity: v,
                            confidence: previous[k].confidence * 0.8,
                            state: State::Predicted,
                            unmeasured,
                            unmeasured_s,
                            typical_mass: previous[k].typical_mass,
                            velocity_trusted: previous[k].velocity_trusted,
                        }
                    }
                }
            };
        }
        Some(out)
    }
}

impl Tracker {
    /// A track starting (or starting again) on cluster `c`: its velocity is the cluster's
    /// taken with [`TrackerConfig::velocity_gain`] against a prior of rest, as every later
    /// measurement is taken against the prediction. A first frame's flow velocity is the
    /// least settled of all (measured on `signer-6fps`: a left hand moving at 0.4 m/s started
    /// at 2 m/s), and at low rates a wrong velocity throws the next prediction, and the EM
    /// seed placed there, a third of a metre off.
    fn fresh(&self, c: &Component, confidence: f64) -> Track {
        let mut track = measured(c, confidence);
        track.velocity *= self.config.velocity_gain.clamp(0.0, 1.0);
        track
    }

    /// The cluster nearest `at` within [`TrackerConfig::face_anchor_m`].
    fn nearest_within(&self, clusters: &[&Component], at: Vector3<f64>) -> Option<usize> {
        (0..clusters.len())
            .map(|i| (i, (clusters[i].position - at).norm()))
            .filter(|(_, d)| *d <= self.config.face_anchor_m)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, _)| i)
    }
}

/// One component for an object EM split in pieces: their masses summed, position and
/// velocity their mass-weighted means (the rest as `main`'s).
fn merge_pieces<'a>(main: &Component, pieces: impl Iterator<Item = &'a Component>) -> Component {
    let mut whole = *main;
    let (mut position, mut velocity) = (main.position * main.mass, main.velocity * main.mass);
    for piece in pieces {
        position += piece.position * piece.mass;
        velocity += piece.velocity * piece.mass;
        whole.mass += piece.mass;
        whole.mixing += piece.mixing;
    }
    if whole.mass > 0.0 {
        whole.position = position / whole.mass;
        whole.velocity = velocity / whole.mass;
    }
    whole
}

fn measured(c: &Component, confidence: f64) -> Track {
    Track {
        position: c.position,
        velocity: c.velocity,
        confidence: confidence.clamp(0.0, 1.0),
        state: State::Tracked,
        unmeasured: 0,
        unmeasured_s: 0.0,
        typical_mass: c.mass,
        velocity_trusted: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix6;

    fn cluster(x: f64, y: f64, vx: f64, mass: f64) -> Component {
        Component {
            position: Vector3::new(x, y, 0.0),
            velocity: Vector3::new(vx, 0.0, 0.0),
            covariance: Matrix6::identity() * 1e-4,
            mixing: mass,
            mass,
            empty: false,
        }
    }

    fn fit(components: Vec<Component>) -> EmFit {
        EmFit { components, iterations: 1, log_likelihood: 0.0, points_used: 100, outlier_share: 0.0 }
    }

    fn tracker() -> Tracker {
        Tracker::new(TrackerConfig::default(), Vector3::y(), Vector3::x())
    }

    #[test]
    fn the_first_frame_labels_head_on_top_and_hands_by_the_signers_side() {
        let mut t = tracker();
        assert!(t.predictions(0.0).is_none());
        // Given in a scrambled order: right hand (-x), head, left hand (+x).
        let tracks = t.update(
            0.0,
            Some(&fit(vec![cluster(-0.2, 1.0, 0.0, 1.0), cluster(0.0, 1.6, 0.0, 2.0), cluster(0.25, 1.1, 0.0, 1.0)])),
        );
        assert_eq!(tracks[0].position.y, 1.6);
        assert_eq!(tracks[1].position.x, 0.25, "left hand on the signer's left");
        assert_eq!(tracks[2].position.x, -0.2);
        assert!(tracks.iter().all(|k| k.state == State::Tracked));
    }

    /// Head still at the top, the right hand still, the left hand at `x` moving at `vx`.
    fn signer(x: f64, vx: f64) -> EmFit {
        fit(vec![cluster(0.0, 1.6, 0.0, 2.0), cluster(x, 1.1, vx, 1.0), cluster(-0.25, 1.0, 0.0, 1.0)])
    }

    #[test]
    fn a_velocity_that_foretold_a_measurement_worse_than_rest_stops_moving_the_prediction() {
        let dt = 1.0 / 6.0;
        let mut t = tracker();
        // A cold start's flow: the left hand at 2 m/s the wrong way.
        t.update(0.0, Some(&signer(0.25, -2.0)));
        let left = t.tracks().expect("started")[1];
        assert!(left.velocity_trusted, "a new track's velocity is trusted");
        let (p, _) = t.predictions(dt).expect("tracks")[1];
        assert!((p.x - (0.25 + left.velocity.x * dt)).abs() < 1e-12, "moved by its velocity: {p}");
        // The hand moved 4 cm the other way: rest foretold it better.
        t.update(dt, Some(&signer(0.29, -2.0)));
        let left = t.tracks().expect("tracks")[1];
        assert_eq!(left.state, State::Tracked);
        assert!(!left.velocity_trusted);
        assert!(left.velocity.x < 0.0, "the velocity itself is still the flow's");
        let (p, _) = t.predictions(2.0 * dt).expect("tracks")[1];
        assert_eq!(p, left.position, "an untrusted velocity does not move the prediction");
    }

    #[test]
    fn a_velocity_that_foretells_its_measurements_keeps_moving_the_prediction() {
        let dt = 1.0 / 6.0;
        let mut t = tracker();
        t.update(0.0, Some(&signer(0.25, 0.3)));
        // Moved 5 cm: its velocity (0.15 m/s after the start's gain) foretold 2.5 cm of it.
        t.update(dt, Some(&signer(0.30, 0.3)));
        let left = t.tracks().expect("tracks")[1];
        assert!(left.velocity_trusted);
        let (p, _) = t.predictions(2.0 * dt).expect("tracks")[1];
        assert!((p.x - (left.position.x + left.velocity.x * dt)).abs() < 1e-12);
        assert!(p.x > left.position.x);
    }

    #[test]
    fn after_a_gap_longer_than_a_track_may_coast_each_hand_is_looked_for_where_it_was() {
        let hands = |left: (f64, f64), right: (f64, f64)| {
            fit(vec![
                cluster(0.0, 1.6, 0.0, 2.0),
                cluster(left.0, 1.1, left.1, 1.0),
                cluster(right.0, 1.1, right.1, 1.0),
            ])
        };
        let dt = 1.0 / 15.0;
        let mut t = tracker();
        // The hands sweep towards each other at 1 m/s.
        t.update(0.0, Some(&hands((0.25, -1.0), (-0.25, 1.0))));
        t.update(dt, Some(&hands((0.25 - dt, -1.0), (-0.25 + dt, 1.0))));
        // No frame for a second; the hands are back at their sides. Followed over the gap,
        // each hand's prediction lies beyond the other hand, which it would take; where
        // each was last seen, it is its own.
        let tracks = t.update(dt + 1.0, Some(&hands((0.25, 0.0), (-0.25, 0.0))));
        assert!(tracks.iter().all(|k| k.state == State::Tracked), "{tracks:?}");
        assert!((tracks[1].position.x - 0.25).abs() < 1e-9, "left hand on the signer's left: {tracks:?}");
        assert!((tracks[2].position.x + 0.25).abs() < 1e-9, "{tracks:?}");
        // A short gap is followed as before.
        let tracks = t.update(dt + 1.2, Some(&hands((0.2, 0.0), (-0.25, 0.0))));
        assert!((tracks[1].position.x - 0.2).abs() < 0.03, "{tracks:?}");
        // Hands that swapped depths unseen (the left from in front of the body to behind
        // the right hand's old place): the nearest each would take is the other hand, on the
        // wrong side of the signer.
        let at = |x: f64, z: f64| Component { position: Vector3::new(x, 1.1, z), ..cluster(0.0, 0.0, 0.0, 1.0) };
        let frame = |l: (f64, f64), r: (f64, f64)| fit(vec![cluster(0.0, 1.6, 0.0, 2.0), at(l.0, l.1), at(r.0, r.1)]);
        let mut t = tracker();
        t.update(0.0, Some(&frame((0.1, 0.5), (-0.1, -0.5))));
        t.update(dt, Some(&frame((0.1, 0.5), (-0.1, -0.5))));
        let tracks = t.update(dt + 1.0, Some(&frame((0.2, -0.5), (-0.2, 0.5))));
        assert!((tracks[1].position.x - 0.2).abs() < 1e-9, "left hand on the signer's left: {tracks:?}");
        assert!((tracks[2].position.x + 0.2).abs() < 1e-9, "{tracks:?}");
    }

    #[test]
    fn tracks_start_only_on_hands_within_reach_of_the_head() {
        let mut t = tracker();
        // Both hands in one blob below the head, and a larger skin-like ghost 1.4 m behind:
        // the ghost is out of reach, so there is no second hand and no start.
        let blob = cluster(0.0, 1.15, 0.0, 1.0);
        let ghost = Component { position: Vector3::new(0.2, 1.45, 1.4), ..cluster(0.0, 0.0, 0.0, 1.5) };
        let head = cluster(0.0, 1.6, 0.0, 2.0);
        let tracks = t.update(0.0, Some(&fit(vec![head, blob, ghost])));
        assert!(t.tracks().is_none(), "no track may start on the ghost");
        assert!(tracks.iter().all(|k| k.state == State::Lost));
        // The hands part: the start takes them, not the larger ghost.
        let (left, right) = (cluster(0.1, 1.15, 0.0, 0.5), cluster(-0.1, 1.15, 0.0, 0.5));
        let tracks = t.update(1.0 / 30.0, Some(&fit(vec![head, left, ghost, right])));
        assert_eq!(tracks[1].position.x, 0.1);
        assert_eq!(tracks[2].position.x, -0.1);
    }

    #[test]
    fn a_starting_track_takes_half_its_first_velocity_as_later_measurements_are_taken() {
        let mut t = tracker();
        let tracks = t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 2.0), cluster(0.2, 1.1, 2.0, 1.0), cluster(-0.2, 1.1, 0.0, 1.0)])),
        );
        // A first frame's flow velocity is the least settled: half of it, against rest.
        assert_eq!(tracks[1].velocity.x, 1.0);
        assert_eq!(tracks[2].velocity.x, 0.0);
        // The next measurement of the same velocity takes it half the rest of the way.
        let dt = 1.0 / 6.0;
        let tracks = t.update(
            dt,
            Some(&fit(vec![
                cluster(0.0, 1.6, 0.0, 2.0),
                cluster(0.2 + 2.0 * dt, 1.1, 2.0, 1.0),
                cluster(-0.2, 1.1, 0.0, 1.0),
            ])),
        );
        assert!((tracks[1].velocity.x - 1.5).abs() < 1e-9, "{:?}", tracks[1].velocity);
    }

    #[test]
    fn crossing_hands_keep_their_labels_through_the_crossing() {
        let mut t = tracker();
        let dt = 1.0 / 30.0;
        // Left hand from +0.15 moving -1.5 m/s, right hand from -0.15 moving +1.5 m/s: they
        // meet at x = 0 at frame 3, 3 cm apart in height, and pass.
        for f in 0..8 {
            let time = f as f64 * dt;
            let left = cluster(0.15 - 1.5 * time, 1.0, -1.5, 1.0);
            let right = cluster(-0.15 + 1.5 * time, 1.03, 1.5, 1.0);
            let head = cluster(0.0, 1.6, 0.0, 2.0);
            // The clusters come in any order.
            let order = if f % 2 == 0 { vec![right, head, left] } else { vec![left, right, head] };
            let tracks = t.update(time, Some(&fit(order)));
            // Velocities start at half the first measurement's and approach it.
            assert!(tracks[1].velocity.x < -0.7, "frame {f}: left hand keeps moving left");
            assert!(tracks[2].velocity.x > 0.7, "frame {f}: right hand keeps moving right");
            // On its own hand, coasting a little behind it while the two are one blob.
            assert!((tracks[1].position.x - (0.15 - 1.5 * time)).abs() < 0.03, "frame {f}: {:?}", tracks[1].position);
            assert!((tracks[2].position.x - (-0.15 + 1.5 * time)).abs() < 0.03, "frame {f}: {:?}", tracks[2].position);
            if f == 7 {
                assert!((tracks[1].velocity.x + 1.5).abs() < 0.1 && (tracks[2].velocity.x - 1.5).abs() < 0.1);
            }
        }
        assert_eq!(t.reinitialisations(), 0);
    }

    /// At 30 fps: hand tracks started on two pieces near the middle of the body (the left
    /// one higher, 0.5 m apart), held for `still_s`, then the pieces gone and the hands seen where each
    /// piece's nearest cluster is the other hand, farther than the gate: the left hand low
    /// on the signer's left (+x), the right hand high on their right. Returns the tracks of
    /// that frame and the number of re-initialisations.
    fn pieces_then_hands(still_s: f64) -> ([Track; 3], u64) {
        let mut t = tracker();
        let head = cluster(0.0, 1.6, 0.0, 2.0);
        let pieces = fit(vec![head, cluster(0.05, 1.25, 0.0, 1.0), cluster(-0.05, 0.75, 0.0, 1.0)]);
        let dt = 1.0 / 30.0;
        let mut time = 0.0;
        while time <= still_s {
            let tracks = t.update(time, Some(&pieces));
            assert!((tracks[1].position.x - 0.05).abs() < 1e-9, "started by side: {:?}", tracks[1].position);
            assert!((tracks[2].position.x + 0.05).abs() < 1e-9, "started by side: {:?}", tracks[2].position);
            time += dt;
        }
        let hands = fit(vec![head, cluster(0.3, 0.7, 0.0, 1.0), cluster(-0.3, 1.3, 0.0, 1.0)]);
        // Beyond the gate, a track coasts one frame and is re-initialised in the next.
        t.update(time, Some(&hands));
        (t.update(time + dt, Some(&hands)), t.reinitialisations())
    }

    #[test]
    fn hands_that_jump_onto_each_others_side_while_the_tracks_settle_trade_labels() {
        let (tracks, jumps) = pieces_then_hands(0.1);
        assert_eq!(jumps, 2, "both hand tracks jumped past their gates");
        assert_eq!(tracks[1].position.x, 0.3, "the left hand is the one on the signer's left");
        assert_eq!(tracks[2].position.x, -0.3);
    }

    #[test]
    fn once_the_tracks_have_settled_a_jump_keeps_the_labels_it_gives() {
        // Past the first second the labels followed so far are the evidence, not the side
        // (arms held crossed).
        let (tracks, jumps) = pieces_then_hands(1.5);
        assert_eq!(jumps, 2);
        assert_eq!(tracks[1].position.x, -0.3);
        assert_eq!(tracks[2].position.x, 0.3);
    }

    #[test]
    fn hands_held_together_at_the_middle_while_settling_keep_their_labels() {
        let mut t = tracker();
        let head = cluster(0.0, 1.6, 0.0, 2.0);
        t.update(0.0, Some(&fit(vec![head, cluster(0.05, 1.25, 0.0, 1.0), cluster(-0.05, 0.75, 0.0, 1.0)])));
        // Both jump, 36 cm forwards, to hands 10 cm apart across the middle, each on the
        // other's side.
        let forwards = |x: f64, y: f64| Component { position: Vector3::new(x, y, 0.35), ..cluster(x, y, 0.0, 1.0) };
        let hands = fit(vec![head, forwards(0.05, 0.75), forwards(-0.05, 1.25)]);
        t.update(1.0 / 30.0, Some(&hands));
        let tracks = t.update(2.0 / 30.0, Some(&hands));
        assert_eq!(t.reinitialisations(), 2);
        assert_eq!(tracks[1].position.x, -0.05, "within the margin: no trade");
        assert_eq!(tracks[2].position.x, 0.05);
    }

    #[test]
    fn a_vanishing_hand_is_predicted_then_lost_then_reinitialised_where_it_reappears() {
        let mut t = tracker();
        let dt = 1.0 / 30.0;
        let head = || cluster(0.0, 1.6, 0.0, 2.0);
        let left = |time: f64| cluster(0.2 + 0.3 * time, 1.0, 0.3, 1.0);
        t.update(0.0, Some(&fit(vec![head(), left(0.0), cluster(-0.2, 1.0, 0.0, 1.0)])));
        // The right hand disappears (behind the torso): its cluster is gone.
        let mut confidence = 1.0;
        for f in 1..=5 {
            let time = f as f64 * dt;
            let tracks = t.update(time, Some(&fit(vec![head(), left(time)])));
            assert_eq!(tracks[2].state, State::Predicted, "frame {f}");
            assert!(tracks[2].confidence < confidence);
            confidence = tracks[2].confidence;
            assert_eq!(tracks[1].state, State::Tracked);
        }
        // It comes back near its prediction: tracked again, no re-initialisation.
        let tracks = t.update(6.0 * dt, Some(&fit(vec![head(), left(6.0 * dt), cluster(-0.21, 1.0, 0.0, 1.0)])));
        assert_eq!(tracks[2].state, State::Tracked);
        assert_eq!(t.reinitialisations(), 0);
        // Gone for longer than `lost_after`: lost.
        let mut last = tracks;
        for f in 7..30 {
            let time = f as f64 * dt;
            last = t.update(time, Some(&fit(vec![head(), left(time)])));
        }
        assert_eq!(last[2].state, State::Lost);
        assert_eq!(last[2].confidence, 0.0);
        // Reappearing far away (0.4 m from where it was lost): re-initialised there.
        let back = cluster(-0.2, 1.4, 0.0, 1.0);
        let tracks = t.update(30.0 * dt, Some(&fit(vec![head(), left(30.0 * dt), back])));
        assert_eq!(tracks[2].state, State::Tracked);
        assert!((tracks[2].position - back.position).norm() < 1e-12);
        assert_eq!(t.reinitialisations(), 1);
    }

    #[test]
    fn tracks_start_in_a_z_up_world_and_a_face_picks_the_head_over_a_raised_hand() {
        // Z up, the signer's left along -Y (a calibration board's world, as caliscope's).
        let z_cluster = |x: f64, y: f64, z: f64, mass: f64| Component {
            position: Vector3::new(x, y, z),
            ..cluster(0.0, 0.0, 0.0, mass)
        };
        let head = z_cluster(0.0, 0.0, 1.6, 2.0);
        let left = z_cluster(0.1, -0.25, 1.1, 1.0);
        let right = z_cluster(0.1, 0.25, 1.1, 1.0);
        let mut t = Tracker::new(TrackerConfig::default(), Vector3::z(), -Vector3::y());
        let tracks = t.update(0.0, Some(&fit(vec![right, head, left])));
        assert!(tracks.iter().all(|k| k.state == State::Tracked));
        assert_eq!(tracks[0].position, head.position);
        assert_eq!(tracks[1].position, left.position);
        assert_eq!(tracks[2].position, right.position);
        // A hand raised above the head at the first frame: the highest cluster is the hand,
        // but the face the detectors placed says which one is the head.
        let raised = z_cluster(0.1, 0.2, 1.75, 1.0);
        let anchor = HeadAnchor { face: head.position, head: head.position + Vector3::x() * 0.08 };
        let mut t = Tracker::new(TrackerConfig::default(), Vector3::z(), -Vector3::y());
        let tracks = t.update_anchored(0.0, Some(&fit(vec![raised, head, left])), Some(anchor));
        assert_eq!(tracks[0].position, head.position);
        assert_eq!(tracks[2].position, raised.position);
        let mut unanchored = Tracker::new(TrackerConfig::default(), Vector3::z(), -Vector3::y());
        let tracks = unanchored.update(0.0, Some(&fit(vec![raised, head, left])));
        assert_eq!(tracks[0].position, raised.position, "without a face the highest cluster is the head");
    }

    #[test]
    fn a_head_drifting_onto_clutter_is_brought_back_to_the_face() {
        let mut t = tracker();
        let head = cluster(0.0, 1.6, 0.0, 2.0);
        let (left, right) = (cluster(0.25, 1.1, 0.0, 1.0), cluster(-0.25, 1.1, 0.0, 1.0));
        let anchor = HeadAnchor { face: head.position, head: head.position - Vector3::z() * 0.08 };
        t.update_anchored(0.0, Some(&fit(vec![head, left, right])), Some(anchor));
        // The head track wandered onto a bookshelf 0.4 m away (as on the shared real
        // session once a hand covered the face): the face brings it back, onto its cluster.
        t.set_position(0, Vector3::new(-0.4, 1.7, 0.0));
        let shelf = cluster(-0.4, 1.7, 0.0, 1.5);
        let tracks = t.update_anchored(1.0 / 30.0, Some(&fit(vec![shelf, left, right, head])), Some(anchor));
        assert_eq!(tracks[0].position, head.position);
        assert_eq!(t.assigned()[0].map(|m| m.cluster), Some(3));
        // No cluster at the face at all (the hand covers it, one blob elsewhere): the head
        // goes to the face's own estimate of the head's centre.
        t.set_position(0, Vector3::new(-0.4, 1.7, 0.0));
        let tracks = t.update_anchored(2.0 / 30.0, Some(&fit(vec![shelf, left, right])), Some(anchor));
        assert!((tracks[0].position - anchor.head).norm() < 1e-12);
        assert_eq!(tracks[0].state, State::Tracked);
    }

    #[test]
    fn gates_and_timeouts_follow_the_frame_rate() {
        let config = TrackerConfig::default();
        assert!((config.gate_m(1.0 / 30.0) - config.reinit_distance_m).abs() < 0.02);
        assert!(config.gate_m(1.0 / 6.0) > 0.45);
        // A hand moving at 1.5 m/s turns back within one frame interval: 0.3 m from the
        // constant-velocity prediction. At 6 fps that is a turn the hand makes between two
        // frames and the track follows it; at 30 fps no hand gets that far off in one frame,
        // so that cluster is no measurement of it.
        for (fps, followed) in [(6.0, true), (30.0, false)] {
            let dt = 1.0 / fps;
            let mut t = tracker();
            let head = || cluster(0.0, 1.6, 0.0, 2.0);
            let left = |x: f64, vx: f64| cluster(x, 1.0, vx, 1.0);
            let right = || cluster(-0.3, 1.0, 0.0, 1.0);
            t.update(0.0, Some(&fit(vec![head(), left(0.2, 1.5), right()])));
            t.update(dt, Some(&fit(vec![head(), left(0.2 + 1.5 * dt, 1.5), right()])));
            let predicted = 0.2 + 2.0 * 1.5 * dt;
            t.update(2.0 * dt, Some(&fit(vec![head(), left(predicted - 0.3, -1.5), right()])));
            assert_eq!(t.assigned()[1].is_some(), followed, "{fps} fps");
            assert_eq!(t.reinitialisations(), 0, "{fps} fps");
        }
        // Lost after half a second, whatever the rate: 4 unmeasured frames at 6 fps, 16 at 30.
        for (fps, frames) in [(6.0, 4), (30.0, 16)] {
            let dt = 1.0 / fps;
            let mut t = tracker();
            let head = || cluster(0.0, 1.6, 0.0, 2.0);
            t.update(0.0, Some(&fit(vec![head(), cluster(0.2, 1.0, 0.0, 1.0), cluster(-0.2, 1.0, 0.0, 1.0)])));
            let mut states = Vec::new();
            for f in 1..=frames {
                let tracks = t.update(f as f64 * dt, Some(&fit(vec![head(), cluster(0.2, 1.0, 0.0, 1.0)])));
                states.push(tracks[2].state);
            }
            assert_eq!(states[frames - 2], State::Predicted, "{fps} fps");
            assert_eq!(states[frames - 1], State::Lost, "{fps} fps");
        }
    }

    #[test]
    fn a_half_hidden_hand_follows_its_prediction_not_its_biased_fragment() {
        let mut t = tracker();
        let dt = 1.0 / 30.0;
        let head = || cluster(0.0, 1.6, 0.0, 2.0);
        // The right hand moves at 0.3 m/s along x; five frames establish mass and velocity.
        let right = |time: f64, dx: f64, mass: f64| cluster(-0.2 + 0.3 * time + dx, 1.0, 0.3, mass);
        for f in 0..5 {
            let time = f as f64 * dt;
            t.update(time, Some(&fit(vec![head(), cluster(0.2, 1.0, 0.0, 1.0), right(time, 0.0, 1.0)])));
        }
        // Half of it disappears behind the other hand: its fragment's centroid is 3 cm off.
        let time = 5.0 * dt;
        let tracks = t.update(time, Some(&fit(vec![head(), cluster(0.2, 1.0, 0.0, 1.0), right(time, 0.03, 0.3)])));
        let truth = -0.2 + 0.3 * time;
        let pull = t.assigned()[2].expect("the fragment measures the right hand").pull;
        assert!(pull < 0.2, "a 30 % fragment should barely pull, pulled {pull}");
        assert!((tracks[2].position.x - truth).abs() < 0.01, "{} vs {truth}", tracks[2].position.x);
        assert_eq!(tracks[2].state, State::Tracked);
        // Whole again: measured in full.
        let time = 6.0 * dt;
        t.update(time, Some(&fit(vec![head(), cluster(0.2, 1.0, 0.0, 1.0), right(time, 0.0, 1.0)])));
        assert_eq!(t.assigned()[2].map(|m| m.pull), Some(1.0));
    }

    #[test]
    fn a_hand_split_in_pieces_is_measured_whole_where_its_prediction_went_astray() {
        // At 6 fps, the left hand started with a wrong velocity (1.2 m/s towards the body):
        // its prediction lands 20 cm inside, by no cluster.
        let mut t = tracker();
        let dt = 1.0 / 6.0;
        let head = || cluster(0.0, 1.6, 0.0, 2.0);
        let right = || cluster(-0.3, 1.3, 0.0, 1.0);
        t.update(0.0, Some(&fit(vec![head(), cluster(0.25, 1.2, -2.4, 1.0), right()])));
        // Next frame EM splits the hand (which barely moved) in two pieces 4 cm apart, the
        // nearer to the prediction a fifth of the hand.
        let tracks = t.update(
            dt,
            Some(&fit(vec![head(), right(), cluster(0.27, 1.16, 0.0, 0.75), cluster(0.24, 1.19, 0.0, 0.2)])),
        );
        let pull = t.assigned()[1].expect("the left hand is measured").pull;
        assert_eq!(pull, 1.0, "both pieces together are the whole hand");
        let whole_x = (0.27 * 0.75 + 0.24 * 0.2) / 0.95;
        assert!((tracks[1].position.x - whole_x).abs() < 1e-9, "left hand at {:?}", tracks[1].position);
        assert_eq!(tracks[1].state, State::Tracked);
        // A piece by another track's cluster is that object's, not this hand's.
        let mut t = tracker();
        t.update(0.0, Some(&fit(vec![head(), cluster(0.25, 1.2, 0.0, 1.0), right()])));
        t.update(dt, Some(&fit(vec![head(), cluster(-0.05, 1.3, 0.0, 0.2), right(), cluster(-0.19, 1.3, 0.0, 0.3)])));
        assert!(t.assigned()[1].expect("measured").pull < 1e-9, "the right hand's piece joined the left hand");
    }

    #[test]
    fn tiny_clusters_are_not_measurements_and_nothing_is_not_a_panic() {
        let mut t = tracker();
        let tracks = t.update(0.0, None);
        assert!(tracks.iter().all(|k| k.state == State::Lost));
        let tracks = t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 0.001), cluster(-0.2, 1.0, 0.0, 1.0)])),
        );
        assert!(tracks.iter().all(|k| k.state == State::Lost), "two real clusters cannot start three tracks");
    }

    #[test]
    fn of_a_head_split_in_pieces_the_head_is_the_piece_at_the_face() {
        let (left, right) = (cluster(0.25, 1.1, 0.0, 1.0), cluster(-0.2, 1.0, 0.0, 1.0));
        // The track starts on the top of the head, 7 cm above the face.
        let face = Vector3::new(0.0, 1.59, 0.03);
        let anchor = HeadAnchor { face, head: face - Vector3::z() * 0.08 };
        let at_face = cluster(0.0, 1.58, 0.03, 1.5);
        // Without a face placed in 3D, the heaviest piece.
        for (anchored, top_mass, expected) in [(true, 2.0, 1), (false, 2.0, 0), (false, 0.5, 1)] {
            let top = cluster(0.0, 1.66, 0.0, top_mass);
            let mut t = tracker();
            t.update_anchored(0.0, Some(&fit(vec![top, left, right])), anchored.then_some(anchor));
            // Next frame the head comes in two pieces: the prediction sits on the top one.
            t.update_anchored(1.0 / 30.0, Some(&fit(vec![top, at_face, left, right])), anchored.then_some(anchor));
            let head = t.assigned()[0].map(|m| m.cluster);
            assert_eq!(head, Some(expected), "anchored {anchored}, top {top_mass}: the head on cluster {head:?}");
            assert_eq!(t.assigned()[1].map(|m| m.cluster), Some(2), "the hands keep theirs");
        }
    }

    #[test]
    fn the_start_says_why_it_failed() {
        let mut t = tracker();
        t.update(0.0, None);
        assert_eq!(t.not_started(), Some(NotStarted::NoClusters), "no points: no head cluster");
        t.update(0.0, Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 1.0)])));
        assert_eq!(t.not_started(), Some(NotStarted::TooFewClusters { clusters: 2 }));
        // A cluster below the weight floor is not counted.
        t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 1.0), cluster(-0.2, 1.0, 0.0, 1e-4)])),
        );
        assert_eq!(t.not_started(), Some(NotStarted::TooFewClusters { clusters: 2 }));
        // One hand within reach, the other (a skin-coloured object) 1.5 m to the side.
        t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 1.0), cluster(1.5, 1.4, 0.0, 1.0)])),
        );
        match t.not_started() {
            Some(NotStarted::HandsOutOfReach { within_reach: 1, nearest_beyond_m: Some(d), reach_m }) => {
                assert!((d - 2.29f64.sqrt()).abs() < 1e-12, "{d}");
                assert_eq!(reach_m, 1.0);
            }
            other => panic!("expected hands out of reach, got {other:?}"),
        }
        assert_eq!(t.not_started().map(|w| w.cause()), Some("hands out of reach"));
        assert!(t.not_started().is_some_and(|w| w.to_string().contains("1.51 m")));
        // The face split in two: its second piece, 6 cm from the first, is no hand.
        t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 1.0), cluster(0.03, 1.65, 0.03, 0.5)])),
        );
        assert_eq!(t.not_started(), Some(NotStarted::HandsAtTheHead { clear: 1, pieces: 1, clearance_m: 0.15 }));
        assert!(t.not_started().is_some_and(|w| w.to_string().contains("pieces of the head")));
        // A good frame starts the tracks and clears the reason.
        t.update(
            0.0,
            Some(&fit(vec![cluster(0.0, 1.6, 0.0, 1.0), cluster(0.2, 1.0, 0.0, 1.0), cluster(-0.2, 1.0, 0.0, 1.0)])),
        );
        assert_eq!(t.not_started(), None);
        assert!(t.tracks().is_some());
    }
}
