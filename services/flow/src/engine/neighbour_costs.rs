//! Reuse of matching costs between loops: a ray's neighbour candidates whose hypothesis did
//! not change since the last loop on the same level take the cost they had then.

use super::SceneFlowEngine;
use crate::engine::particles::Particle;

/// The costs one ray's neighbour candidates had in the last loop. In a converged region a
/// neighbour's best stays the same from loop to loop, and the same hypothesis on the same ray
/// against the same images costs the same, bit for bit: it is looked up, not matched again.
#[derive(Clone, Copy)]
pub(super) struct NeighbourCosts {
    /// The `iterate` call that wrote them.
    stamp: u32,
    len: u8,
    entries: [Particle; MAX_NEIGHBOUR_CANDIDATES],
}

/// Neighbour candidates per ray: four neighbours' previous best and the sweep's updated one.
const MAX_NEIGHBOUR_CANDIDATES: usize = 5;

impl Default for NeighbourCosts {
    fn default() -> Self {
        Self { stamp: u32::MAX, len: 0, entries: [Particle::EMPTY; MAX_NEIGHBOUR_CANDIDATES] }
    }
}

impl NeighbourCosts {
    #[inline(always)]
    pub(super) fn cost_of(&self, candidate: &Particle) -> Option<f32> {
        let len = usize::from(self.len);
        self.entries[..len].iter().find(|e| same_hypothesis(e, candidate)).map(|e| e.cost)
    }

    #[inline(always)]
    pub(super) fn remember(&mut self, candidates: &[Particle], stamp: u32) {
        let len = candidates.len().min(MAX_NEIGHBOUR_CANDIDATES);
        self.entries[..len].copy_from_slice(&candidates[..len]);
        self.len = len as u8;
        self.stamp = stamp;
    }

    /// Whether these are the costs of the loop before the one numbered `loop_stamp`.
    #[inline(always)]
    pub(super) fn is_from_loop_before(&self, loop_stamp: u32) -> bool {
        self.stamp == loop_stamp.wrapping_sub(1)
    }
}

impl SceneFlowEngine {
    /// Numbers the next loop (an `iterate` call). Without reuse (tests only) a number is
    /// skipped, so no ray's costs are ever those of the loop before.
    pub(super) fn advance_loop_stamp(&mut self) {
        self.loop_stamp = self.loop_stamp.wrapping_add(if self.reuse_neighbour_costs { 1 } else { 2 });
    }
}

/// Whether two candidates of one ray are the same hypothesis (bitwise equal depth and
/// velocity), so that they have the same cost.
#[inline(always)]
pub(super) fn same_hypothesis(a: &Particle, b: &Particle) -> bool {
    a.depth.to_bits() == b.depth.to_bits() && (0..3).all(|i| a.velocity[i].to_bits() == b.velocity[i].to_bits())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::EngineConfig;
    use crate::engine::tests::{camera, textured_view};

    #[test]
    fn reusing_last_loops_neighbour_costs_changes_nothing_but_the_work() {
        let cameras = vec![camera("ref", 0.0), camera("a", 0.1), camera("b", -0.1)];
        let config = EngineConfig { pyramid_levels: 2, coarse_extra_loops: 3, ..EngineConfig::default() };
        let mut reusing = SceneFlowEngine::new(config.clone(), cameras.clone(), 0).unwrap();
        let mut matching_all = SceneFlowEngine::new(config, cameras, 0).unwrap();
        matching_all.reuse_neighbour_costs = false;
        let (mut saved, mut estimates) = (0, 0);
        for f in 0..4 {
            let views = [textured_view(f, 1), textured_view(f + 2, 1), textured_view(f + 4, 1)];
            let views: Vec<&[u8]> = views.iter().map(Vec::as_slice).collect();
            let a = reusing.push_frame(&views).unwrap().cloned();
            let b = matching_all.push_frame(&views).unwrap().cloned();
            assert_eq!(a.is_some(), b.is_some());
            if let (Some(a), Some(b)) = (a, b) {
                assert_eq!(
                    a.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
                    b.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
                    "frame {f}"
                );
                assert_eq!(a.velocity, b.velocity, "frame {f}");
                assert_eq!(a.confidence, b.confidence, "frame {f}");
                assert!(reusing.stats().evaluations <= matching_all.stats().evaluations);
                saved += matching_all.stats().evaluations - reusing.stats().evaluations;
                estimates += 1;
            }
        }
        assert!(estimates >= 2 && saved > 0, "{estimates} estimates, {saved} evaluations saved");
    }

    #[test]
    fn neighbour_costs_are_found_by_hypothesis_only() {
        let p = Particle { depth: 1.25, velocity: [0.01, -0.02, 0.0], weight: 0.1, cost: 0.3 };
        let q = Particle { depth: 1.5, cost: 0.7, ..p };
        let mut memo = NeighbourCosts::default();
        assert_eq!(memo.cost_of(&p), None);
        memo.remember(&[p, q], 7);
        assert_eq!((memo.stamp, memo.cost_of(&Particle { weight: 0.9, cost: f32::NAN, ..q })), (7, Some(0.7)));
        assert_eq!(memo.cost_of(&Particle { depth: 1.0, ..p }), None);
        // More candidates than slots: the first ones are kept.
        memo.remember(&[q; MAX_NEIGHBOUR_CANDIDATES + 2], 8);
        assert_eq!((usize::from(memo.len), memo.cost_of(&p)), (MAX_NEIGHBOUR_CANDIDATES, None));
    }

    #[test]
    fn only_bitwise_equal_hypotheses_share_a_cost() {
        let p = Particle { depth: 1.25, velocity: [0.01, -0.02, 0.0], weight: 0.1, cost: 0.3 };
        // Weight and cost are not the hypothesis.
        assert!(same_hypothesis(&p, &Particle { weight: 0.5, cost: 9.0, ..p }));
        assert!(!same_hypothesis(&p, &Particle { depth: 1.250_001, ..p }));
        assert!(!same_hypothesis(&p, &Particle { velocity: [0.01, -0.02, 1e-9], ..p }));
        // Conservative: -0 and +0 are evaluated apart.
        assert!(!same_hypothesis(&p, &Particle { velocity: [0.01, -0.02, -0.0], ..p }));
    }
}
