//! Every parser of outside input under mutated inputs: calibration files (each format),
//! `frames.csv`, caliscope's `timestamps.csv`, reference JSON, OpenPose JSON, scene and
//! pipeline files, and messages as they cross the network. Each input is a valid file (or
//! message) from the repository's fixtures with a few random mutations (bytes flipped,
//! inserted, deleted, duplicated, truncated, tokens that parsers trip on, other files spliced
//! in), written where the parser reads it. A parser may refuse an input, with a message that
//! names what is wrong; it may never panic.
//!
//! `cargo test -p handflow --test fuzz_parsers` runs a few hundred inputs per parser;
//! `scripts/fuzz.sh` runs a million each (`HANDFLOW_FUZZ_CASES`) in a release build. An input
//! that made a parser panic (or hang, over 10 s) is written to `target/fuzz-findings/<parser>/`; once fixed, it goes
//! into `tests/fixtures/fuzz/<parser>/`, which every test run replays.

#![allow(clippy::unwrap_used)]

use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};

use handflow::commands::launcher::Pipeline;
use handflow::eval::openpose::{read_openpose, OpenPosePoints};
use handflow::eval::reference::read_handflow_reference;
use handflow_ingest::recording::{read_caliscope_timestamps, read_frame_table};
use handflow_ingest::synthetic::SceneSpec;
use handflow_protocol::messages::{ClusterSet, ParticleHeader, ScenePoint, TrajectorySample, PROTOCOL_VERSION};
use handflow_protocol::{wire, Rig};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures")
}

/// A small deterministic generator (xorshift64*): a finding is reproduced by its seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Pieces of text that parsers of numbers, tables and markup trip on.
const TOKENS: &[&str] = &[
    "\"",
    "'",
    "[",
    "]",
    "{",
    "}",
    "=",
    ",",
    ":",
    "\n",
    "-",
    "0",
    "-1",
    "1e308",
    "-1e308",
    "1e-320",
    "NaN",
    "nan",
    "inf",
    "-inf",
    "18446744073709551616",
    "9223372036854775807",
    "4294967296",
    "<",
    ">",
    "</",
    "%YAML",
    "!!opencv-matrix",
    "null",
    "true",
    "[[",
    "]]",
    "\u{feff}",
    "\u{0}",
    "é",
    "\\",
    "#",
    "rows: 3",
    "cols: 3",
    "data: [",
];

/// `seed` with 1 to 4 mutations; `others` are spliced from.
fn mutate(seed: &[u8], others: &[Vec<u8>], rng: &mut Rng) -> Vec<u8> {
    let mut v = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let at = rng.below(v.len() + 1);
        match rng.below(8) {
            0 if !v.is_empty() => {
                let i = rng.below(v.len());
                v[i] ^= 1 << rng.below(8);
            }
            1 => v.insert(at, rng.next() as u8),
            2 => {
                let token = TOKENS[rng.below(TOKENS.len())].as_bytes();
                v.splice(at..at, token.iter().copied());
            }
            3 if !v.is_empty() => {
                let end = (at + 1 + rng.below(16)).min(v.len());
                v.drain(at.min(end)..end);
            }
            4 if !v.is_empty() => {
                let start = rng.below(v.len());
                let end = (start + 1 + rng.below(64)).min(v.len());
                let piece: Vec<u8> = v[start..end].to_vec();
                v.splice(at..at, piece);
            }
            5 => v.truncate(at),
            6 if !others.is_empty() => {
                let other = &others[rng.below(others.len())];
                let start = rng.below(other.len() + 1);
                let end = (start + rng.below(128)).min(other.len());
                v.splice(at..at, other[start..end].iter().copied());
            }
            _ => {
                // A digit run replaced by an extreme number.
                if let Some(i) = (at..v.len()).find(|&i| v[i].is_ascii_digit()) {
                    let end = (i..v.len()).find(|&j| !v[j].is_ascii_digit()).unwrap_or(v.len());
                    let token = ["0", "-0", "99999999999", "1e400", "-7"][rng.below(5)].as_bytes();
                    v.splice(i..end, token.iter().copied());
                }
            }
        }
    }
    v
}

/// One parser under test: where its input goes and what reads it.
struct Target {
    name: &'static str,
    /// Valid (and a few invalid) inputs to mutate, each with its file name.
    seeds: Vec<(String, Vec<u8>)>,
    /// Writes `input` where the parser reads it (below `dir`, as `name` where the name
    /// matters) and parses it.
    run: Box<Parse>,
}

/// A parser as the fuzzer calls it: scratch folder, file name, input.
type Parse = dyn Fn(&Path, &str, &[u8]) -> Result<(), String>;

fn read_all(paths: impl IntoIterator<Item = PathBuf>) -> Vec<(String, Vec<u8>)> {
    paths
        .into_iter()
        .filter_map(|p| {
            let name = p.file_name()?.to_string_lossy().into_owned();
            std::fs::read(&p).ok().map(|bytes| (name, bytes))
        })
        .collect()
}

fn named(name: &str, bytes: Vec<u8>) -> (String, Vec<u8>) {
    (name.to_owned(), bytes)
}

fn files_in(dir: &Path, suffix: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(suffix))
        .collect();
    v.sort();
    v
}

/// Parses `input` written as `dir/name`: errors must name the file.
fn as_file(
    dir: &Path,
    name: &str,
    input: &[u8],
    parse: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), String> {
    let path = dir.join(name);
    std::fs::write(&path, input).unwrap();
    parse(&path)
}

fn rig3() -> Rig {
    Rig::load(fixtures().join("rig_formats/anipose.toml")).unwrap()
}

fn targets() -> Vec<Target> {
    let fx = fixtures();
    let mut rig_seeds = read_all(files_in(&fx.join("rig_formats"), ""));
    rig_seeds.extend(read_all(files_in(&fx.join("bad"), "")));
    let frames_csv = b"frame,timestamp\n0,0.0\n1,0.0333333\n2,0.0666667\n3,0.1\n".to_vec();
    let caliscope = b"sync_index,cam_id,frame_index,frame_time\n0,0,10,123.30\n0,1,12,123.301\n1,0,11,123.47\n1,1,13,123.468\n2,1,14,123.634\n"
        .to_vec();
    let sample = {
        let mut s =
            TrajectorySample { protocol_version: PROTOCOL_VERSION, frame: 3, sequence: 3, ..Default::default() };
        s.objects[1].position = [0.2, 1.1, 1.9];
        s.objects[1].confidence = 0.5;
        wire::encode_trajectory_sample(&s)
    };
    let clusters = wire::encode_cluster_set(&ClusterSet { protocol_version: PROTOCOL_VERSION, ..Default::default() });
    let particles = {
        let points = vec![ScenePoint { weight: 1.0, ..Default::default() }; 3];
        let header = ParticleHeader { protocol_version: PROTOCOL_VERSION, point_count: 3, ..Default::default() };
        wire::encode_particle_set(&header, &points)
    };
    let scene = toml::to_string(&SceneSpec::preset("signer-3cam").unwrap()).unwrap().into_bytes();
    let pipelines = read_all(files_in(&Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines"), ".toml"));
    vec![
        Target {
            name: "rig",
            seeds: rig_seeds,
            // The format is told by the file's name and content: every name a rig file has.
            run: Box::new(|dir, name, input| {
                as_file(dir, name, input, |p| Rig::load_detected(p).map(|_| ()).map_err(|e| e.to_string()))
            }),
        },
        Target {
            name: "frames_csv",
            seeds: vec![named("frames.csv", frames_csv)],
            run: Box::new(|dir, _, input| {
                as_file(dir, "frames.csv", input, |p| read_frame_table(p).map(|_| ()).map_err(|e| e.to_string()))
            }),
        },
        Target {
            name: "caliscope_timestamps",
            seeds: vec![named("timestamps.csv", caliscope)],
            run: Box::new(|dir, _, input| {
                as_file(dir, "timestamps.csv", input, |p| {
                    read_caliscope_timestamps(p).map(|_| ()).map_err(|e| e.to_string())
                })
            }),
        },
        Target {
            name: "reference_json",
            seeds: read_all(files_in(&fx.join("reference"), ".json")),
            run: Box::new({
                let rig = rig3();
                move |dir, _, input| {
                    as_file(dir, "reference.json", input, |p| {
                        read_handflow_reference(p, &rig).map(|_| ()).map_err(|e| format!("{e:#}"))
                    })
                }
            }),
        },
        Target {
            name: "openpose_json",
            seeds: read_all(
                ["body25b", "coco"].iter().flat_map(|k| files_in(&fx.join("openpose").join(k).join("cam_1"), ".json")),
            ),
            // One camera's file mutated among the fixture's others.
            run: Box::new({
                let rig = rig3();
                let fx = fx.clone();
                move |dir, _, input| {
                    let root = dir.join("openpose");
                    if !root.exists() {
                        for cam in ["cam_0", "cam_1", "cam_2"] {
                            std::fs::create_dir_all(root.join(cam)).unwrap();
                            let from =
                                fx.join("openpose/body25b").join(cam).join(format!("{cam}_000000_keypoints.json"));
                            std::fs::copy(from, root.join(cam).join(format!("{cam}_000000_keypoints.json"))).unwrap();
                        }
                    }
                    std::fs::write(root.join("cam_1/cam_1_000000_keypoints.json"), input).unwrap();
                    read_openpose(&root, &rig, None, OpenPosePoints::Centres, None)
                        .map(|_| ())
                        .map_err(|e| format!("{e:#}"))
                }
            }),
        },
        Target {
            name: "scene",
            seeds: vec![named("scene.toml", scene)],
            run: Box::new(|_, _, input| {
                let text = std::str::from_utf8(input).map_err(|e| e.to_string())?;
                let spec: SceneSpec = toml::from_str(text).map_err(|e| e.to_string())?;
                spec.validate()
            }),
        },
        Target {
            name: "pipeline",
            seeds: pipelines,
            run: Box::new(|dir, _, input| {
                as_file(dir, "pipeline.toml", input, |p| Pipeline::load(p).map(|_| ()).map_err(|e| format!("{e:#}")))
            }),
        },
        Target {
            name: "wire",
            seeds: vec![named("sample", sample), named("clusters", clusters), named("particles", particles)],
            // Every decoder sees every input (a message of one kind sent as another); the
            // input is refused when none takes it.
            run: Box::new(|_, _, input| {
                let a = wire::decode_trajectory_sample(input).map(|_| ()).map_err(|e| e.to_string());
                let b = wire::decode_cluster_set(input).map(|_| ()).map_err(|e| e.to_string());
                let c = wire::decode_particle_set(input).map(|_| ()).map_err(|e| e.to_string());
                match (a, b, c) {
                    (Err(a), Err(b), Err(c)) => Err(format!("{a}; {b}; {c}")),
                    _ => Ok(()),
                }
            }),
        },
    ]
}

/// A parser that takes longer than this on one input hangs: the input is saved and the run
/// ends (a thread cannot be stopped from outside).
const HANG: std::time::Duration = std::time::Duration::from_secs(10);

/// The input being parsed and since when, for the watchdog.
type Current = std::sync::Arc<std::sync::Mutex<(std::time::Instant, Vec<u8>)>>;

/// Saves the input of a parser that hangs and ends the process.
fn watchdog(
    name: &'static str,
    findings_dir: PathBuf,
    current: Current,
    done: std::sync::Arc<std::sync::atomic::AtomicBool>,
) {
    std::thread::spawn(move || {
        while !done.load(std::sync::atomic::Ordering::Relaxed) {
            std::thread::sleep(std::time::Duration::from_millis(500));
            let (since, input) = current.lock().unwrap().clone();
            if since.elapsed() > HANG {
                std::fs::create_dir_all(&findings_dir).unwrap();
                let path = findings_dir.join("hang");
                std::fs::write(&path, &input).unwrap();
                eprintln!("{name}: an input hangs the parser (over {HANG:?}); saved as {}", path.display());
                std::process::exit(3);
            }
        }
    });
}

/// What fuzzing `target` with `cases` inputs found: panics (their inputs saved) and refusals
/// without a message.
fn fuzz(target: &Target, cases: u64, seed: u64) -> (u64, Vec<String>) {
    let dir = tempfile::tempdir().unwrap();
    let findings_dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("../fuzz-findings").join(target.name);
    let current: Current = std::sync::Arc::new(std::sync::Mutex::new((std::time::Instant::now(), Vec::new())));
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    watchdog(target.name, findings_dir.clone(), current.clone(), done.clone());
    let mut rng = Rng(seed | 1);
    let mut problems = Vec::new();
    let mut refused = 0u64;
    // `HANDFLOW_FUZZ_SHOW=N` prints every N-th refusal, to read what users would be told.
    let show: u64 = std::env::var("HANDFLOW_FUZZ_SHOW").ok().and_then(|v| v.parse().ok()).unwrap_or(0);
    assert!(!target.seeds.is_empty(), "{}: no seed inputs", target.name);
    let others: Vec<Vec<u8>> = target.seeds.iter().map(|(_, bytes)| bytes.clone()).collect();
    for case in 0..cases {
        let (name, base) = &target.seeds[rng.below(target.seeds.len())];
        let input = mutate(base, &others, &mut rng);
        *current.lock().unwrap() = (std::time::Instant::now(), input.clone());
        let outcome = std::panic::catch_unwind(AssertUnwindSafe(|| (target.run)(dir.path(), name, &input)));
        match outcome {
            Ok(Ok(())) => {}
            Ok(Err(message)) => {
                refused += 1;
                if show > 0 && refused.is_multiple_of(show) {
                    println!("  {}: {}", target.name, message.replace('\n', " / "));
                }
                // A message, and one whose reason is not cut off after its colon.
                if message.trim().is_empty() || message.trim_end().ends_with(':') {
                    problems.push(format!("{} case {case}: refused without a reason: `{message}`", target.name));
                }
            }
            Err(_) => {
                std::fs::create_dir_all(&findings_dir).unwrap();
                let path = findings_dir.join(format!("seed{seed}-case{case}"));
                std::fs::write(&path, &input).unwrap();
                problems.push(format!("{} case {case}: panicked; input saved as {}", target.name, path.display()));
            }
        }
        if problems.len() >= 20 {
            break;
        }
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    (refused, problems)
}

#[test]
fn no_parser_panics_on_mutated_inputs_and_every_refusal_says_why() {
    let cases: u64 = std::env::var("HANDFLOW_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(300);
    let seed: u64 = std::env::var("HANDFLOW_FUZZ_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
    let only = std::env::var("HANDFLOW_FUZZ_ONLY").ok();
    // Panics are caught and counted; their messages would drown the report.
    std::panic::set_hook(Box::new(|_| {}));
    let mut problems = Vec::new();
    for target in targets().iter().filter(|t| only.as_deref().is_none_or(|o| o == t.name)) {
        let started = std::time::Instant::now();
        let (refused, found) = fuzz(target, cases, seed);
        println!(
            "{:22} {cases} inputs, {refused} refused, {} problems, {:.1} s",
            target.name,
            found.len(),
            started.elapsed().as_secs_f64()
        );
        problems.extend(found);
    }
    let _ = std::panic::take_hook();
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn inputs_that_once_made_a_parser_panic_are_refused_with_a_message() {
    let root = fixtures().join("fuzz");
    let targets = targets();
    let dir = tempfile::tempdir().unwrap();
    for target in &targets {
        for path in files_in(&root.join(target.name), "") {
            let input = std::fs::read(&path).unwrap();
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            match (target.run)(dir.path(), &name, &input) {
                Ok(()) => {}
                Err(message) => assert!(!message.trim().is_empty(), "{}: refused without a message", path.display()),
            }
        }
    }
}

#[test]
fn every_parser_takes_some_of_its_seeds_as_they_are() {
    let dir = tempfile::tempdir().unwrap();
    for target in targets() {
        let taken: Vec<&str> = target
            .seeds
            .iter()
            .filter(|(name, bytes)| (target.run)(dir.path(), name, bytes).is_ok())
            .map(|(name, _)| name.as_str())
            .collect();
        assert!(!taken.is_empty(), "{}: no seed parses, so the mutations explore only errors", target.name);
    }
}
