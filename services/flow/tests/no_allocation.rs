//! The engine allocates nothing per frame once it has seen its first frames: every buffer
//! (pyramids, particles, estimates, the dense field) is reused.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, MutexGuard};

use handflow_flow::{EngineConfig, SceneFlowEngine, Temporal, Variant};
use handflow_protocol::{Camera, Distortion};
use nalgebra::{Matrix3, Rotation3, Vector3};

struct CountingAllocator;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// Counting wrapper around the system allocator; `unsafe` is what GlobalAlloc requires.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        // SAFETY: forwarded unchanged to the system allocator.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// The count is process-wide and the engine allocates on rayon's threads too, so the tests of
/// this file run one at a time, each whole: side by side, each would count the other's set-up.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn alone() -> MutexGuard<'static, ()> {
    // A test that failed while holding the lock leaves it poisoned; the count is still sound.
    ONE_AT_A_TIME.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn camera(name: &str, x: f64) -> Camera {
    Camera::new(
        name,
        64,
        48,
        Matrix3::new(60.0, 0.0, 31.5, 0.0, 60.0, 23.5, 0.0, 0.0, 1.0),
        Distortion::default(),
        Rotation3::identity(),
        Vector3::new(-x, 0.0, 0.0),
    )
    .expect("valid camera")
}

fn frame(k: usize) -> Vec<Vec<u8>> {
    (0..2).map(|cam| (0..64 * 48 * 3).map(|i| ((i * 7 + k * 13 + cam * 3) % 251) as u8).collect()).collect()
}

/// Allocations during ten steady-state frames (the last two of `frames`, alternating), after
/// the first four sized every buffer. Each of the ten must complete an estimate.
fn steady_state_allocations(engine: &mut SceneFlowEngine, frames: &[Vec<Vec<u8>>]) -> usize {
    let views: Vec<Vec<&[u8]>> = frames.iter().map(|f| f.iter().map(Vec::as_slice).collect()).collect();
    for v in &views[..4] {
        engine.push_frame(v).expect("push");
    }
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    for k in 0..10 {
        assert!(engine.push_frame(&views[4 + k % 2]).expect("push").is_some());
    }
    ALLOCATIONS.load(Ordering::Relaxed) - before
}

#[test]
fn steady_state_frames_allocate_nothing() {
    let _alone = alone();
    for variant in [Variant::Handflow, Variant::Paper] {
        for temporal in [Temporal::TwoFrame, Temporal::ForwardsBackwards] {
            let config = EngineConfig {
                temporal,
                depth_range: (2.0, 20.0),
                speed_bound: 0.2,
                ..EngineConfig::for_variant(variant)
            };
            let mut engine = SceneFlowEngine::new(config, vec![camera("a", 0.0), camera("b", 0.5)], 0).expect("engine");
            let frames: Vec<Vec<Vec<u8>>> = (0..6).map(frame).collect();
            // rayon's global job queue allocates one block per 63 jobs sent into its pool
            // from outside (about two per frame), so at most one such allocation may fall in
            // the window; nothing of the engine's own.
            let during = steady_state_allocations(&mut engine, &frames);
            assert!(during <= 1, "{variant:?} {temporal:?}: {during} allocations in ten steady-state frames");
        }
    }
}

#[test]
fn a_second_reference_on_lent_images_allocates_nothing_either() {
    let _alone = alone();
    let config = EngineConfig {
        temporal: Temporal::ForwardsBackwards,
        coverage: handflow_flow::Coverage::Skin,
        second_reference: true,
        depth_range: (2.0, 20.0),
        speed_bound: 0.2,
        ..EngineConfig::for_variant(Variant::Handflow)
    };
    let cameras = vec![camera("a", 0.0), camera("b", 0.5), camera("c", -0.5)];
    let mut engine = SceneFlowEngine::new(config, cameras, 0).expect("engine");
    assert!(engine.companion().is_some());
    let frames: Vec<Vec<Vec<u8>>> = (0..6)
        .map(|k| {
            let mut views = frame(k);
            views.push(views[0].clone());
            views
        })
        .collect();
    let during = steady_state_allocations(&mut engine, &frames);
    assert!(during <= 2, "{during} allocations in ten steady-state frames");
}
