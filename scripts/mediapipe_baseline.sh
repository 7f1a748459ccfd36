#!/usr/bin/env bash
# Measures, in one run, `handflow track` against the pipeline users would pick instead: MediaPipe
# Holistic on every view plus triangulation, as caliscope and FreeMoCap run it
# (scripts/mediapipe_baseline.py). Alternates the two, twice each, on one recording and prints
# frame sets per second of every run and the ratio handflow / MediaPipe of the medians.
# handflow's seconds are its process's wall clock, start-up included; MediaPipe's are the
# script's own, from opening the videos to the last triangulated frame set (Python's start-up
# and imports, about a second, left out). handflow's frame sets are the records it wrote (one
# per frame set read), MediaPipe's the frame sets it read.
# Usage: [HANDFLOW_BIN=...] [PYTHON=python3.12] scripts/mediapipe_baseline.sh [RECORDING_DIR] [--frames N]
set -euo pipefail
cd "$(dirname "$0")/.."
rec=../shared/data/real/caliscope-hands
if [ $# -gt 0 ] && [ "${1#--}" = "$1" ]; then
    rec=$1
    shift
fi
frames=()
while [ $# -gt 0 ]; do
    case $1 in
        --frames) [ $# -ge 2 ] || { echo "--frames needs a number" >&2; exit 2; }; frames=(--frames "$2"); shift 2 ;;
        *) echo "usage: scripts/mediapipe_baseline.sh [RECORDING_DIR] [--frames N]" >&2; exit 2 ;;
    esac
done
if [ ! -d "$rec" ]; then
    echo "skipped: recording $rec not found" >&2
    exit 0
fi
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q -p handflow

# mediapipe 0.10.14 is the last release whose wheel bundles the Holistic models, so it runs
# offline; later ones download them at run time. Its wheels are for Python 3.8 to 3.12, and the
# script reads TOML with tomllib (3.11 on). OpenCV headless: no GUI libraries needed.
venv=target/mediapipe-venv
if ! "$venv/bin/python" -c 'import cv2, mediapipe' 2>/dev/null; then
    python=${PYTHON:-python3}
    if ! "$python" -c 'import sys; sys.exit(not (3, 11) <= sys.version_info[:2] <= (3, 12))'; then
        echo "$python is not Python 3.11 or 3.12, which mediapipe 0.10.14 and the script need: set PYTHON" >&2
        exit 1
    fi
    echo "making $venv (mediapipe 0.10.14, OpenCV), once" >&2
    rm -rf "$venv"
    "$python" -m venv "$venv"
    "$venv/bin/pip" install -q mediapipe==0.10.14 opencv-python-headless
    "$venv/bin/python" -c 'import cv2, mediapipe'
fi

out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
# Prints a failed run's log and stops.
failed() {
    echo "$1 failed; its log:" >&2
    tail -n 20 "$2" >&2
    exit 1
}
for run in 1 2; do
    start=$(date +%s.%N)
    "$bin" track --recording "$rec" --out "$out/tracks-$run.jsonl" "${frames[@]}" 2>"$out/handflow-$run.log" ||
        failed "handflow track (run $run)" "$out/handflow-$run.log"
    end=$(date +%s.%N)
    echo "handflow $run $(grep -c . "$out/tracks-$run.jsonl") $start $end" >>"$out/runs.txt"
    "$venv/bin/python" scripts/mediapipe_baseline.py "$rec" --json "${frames[@]}" >"$out/mediapipe-$run.json" \
        2>"$out/mediapipe-$run.log" || failed "scripts/mediapipe_baseline.py (run $run)" "$out/mediapipe-$run.log"
    echo "mediapipe $run $out/mediapipe-$run.json" >>"$out/runs.txt"
done
python3 - "$out/runs.txt" <<'PY'
import json, statistics, sys
names = {"handflow": "handflow track", "mediapipe": "MediaPipe Holistic + triangulation"}
rates = {"handflow": [], "mediapipe": []}
print("| pipeline | run | frame sets | seconds | frame sets/s |")
print("|---|---|---|---|---|")
for line in open(sys.argv[1]):
    pipeline, run, *rest = line.split()
    if pipeline == "handflow":
        frame_sets, seconds = int(rest[0]), float(rest[2]) - float(rest[1])
    else:
        report = json.load(open(rest[0]))
        frame_sets, seconds = report["frame_sets"], report["seconds"]
    rates[pipeline].append(frame_sets / seconds)
    print("| %s | %s | %d | %.1f | %.2f |" % (names[pipeline], run, frame_sets, seconds, frame_sets / seconds))
handflow, mediapipe = statistics.median(rates["handflow"]), statistics.median(rates["mediapipe"])
print("handflow / MediaPipe (medians): %.2f / %.2f frame sets/s = %.2fx" % (handflow, mediapipe, handflow / mediapipe))
PY
