#!/usr/bin/env bash
# Every parser of outside input under a million mutated inputs each (deploy/tests/fuzz_parsers.rs),
# in a release build. Not part of CI: about ten minutes on 2 cores.
#
#   scripts/fuzz.sh                 # 1,000,000 inputs per parser, seed 1
#   CASES=100000 SEED=7 scripts/fuzz.sh
#   ONLY=rig scripts/fuzz.sh        # one parser: rig, frames_csv, caliscope_timestamps,
#                                   # reference_json, openpose_json, scene, pipeline, wire
#
# An input that makes a parser panic is saved under target/fuzz-findings/<parser>/; once the
# parser is fixed, copy it into tests/fixtures/fuzz/<parser>/ so that `cargo test` replays it.
set -euo pipefail
cd "$(dirname "$0")/.."
export HANDFLOW_FUZZ_CASES="${CASES:-1000000}"
export HANDFLOW_FUZZ_SEED="${SEED:-1}"
if [ -n "${ONLY:-}" ]; then export HANDFLOW_FUZZ_ONLY="$ONLY"; fi
cargo test --release -p handflow --test fuzz_parsers -- --nocapture --test-threads 1 \
    no_parser_panics_on_mutated_inputs_and_every_refusal_says_why
