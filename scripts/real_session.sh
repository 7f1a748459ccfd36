#!/usr/bin/env bash
# Tracks a real recording and scores it against its reference: one table row per object
# (median 3D error, shares within 5 / 10 / 20 cm, identity switches) and the tracking speed.
# Extra arguments go to `handflow track` (for example `--set field=value` for an ablation).
# SEEDS="0 1 2" tracks once per engine seed and adds the mean row per object: on a session of
# about a hundred frames one seed's shares move by up to ten points, so compare means.
# The reference is REFERENCE when set (a `handflow-reference/1` file or an OpenPose folder), else
# the recording's `reference.json`, else its OpenPose folder (`pose/`, as Pose2Sim lays one out,
# or `openpose/`).
# Usage: [SEEDS="0 1 2"] [REFERENCE=PATH] scripts/real_session.sh [RECORDING_DIR] [TRACK_ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
rec=${1:-../shared/data/real/caliscope-hands}
shift || true
if [ ! -d "$rec" ]; then
    echo "skipped: recording $rec not found" >&2
    exit 0
fi
reference=${REFERENCE:-}
if [ -z "$reference" ]; then
    for candidate in "$rec/reference.json" "$rec/pose" "$rec/openpose"; do
        if [ -e "$candidate" ]; then
            reference=$candidate
            break
        fi
    done
fi
if [ -z "$reference" ]; then
    echo "real_session: $rec has no reference.json, pose/ or openpose/ folder; set REFERENCE=PATH" >&2
    exit 2
fi
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q -p handflow
seeds=${SEEDS:-0}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
for seed in $seeds; do
    start=$(date +%s.%N)
    "$bin" track --recording "$rec" --out "$out/tracks-$seed.jsonl" --seed "$seed" "$@" 2>"$out/track-$seed.log"
    end=$(date +%s.%N)
    "$bin" eval tracks --recording "$rec" --tracks "$out/tracks-$seed.jsonl" --reference "$reference" \
        --json >"$out/eval-$seed.json"
    frames=$(grep -c . "$out/tracks-$seed.jsonl")
    echo "$seed $frames $start $end" >>"$out/runs.txt"
done
python3 - "$out" <<'PY'
import json, sys
out = sys.argv[1]
runs = [line.split() for line in open(out + "/runs.txt")]
names = ("head", "left_hand", "right_hand")
print("| object | seed | median 3D | within 5 cm | within 10 cm | within 20 cm | misses |")
print("|---|---|---|---|---|---|---|")
reports = []
for seed, frames, start, end in runs:
    report = json.load(open("%s/eval-%s.json" % (out, seed)))
    reports.append(report)
    for name in names:
        o = report[name]
        median = "-" if o["median_3d_m"] is None else "%.3f m" % o["median_3d_m"]
        print("| %s | %s | %s | %.1f %% | %.1f %% | %.1f %% | %d |" % (
            name, seed, median, 100 * o["within_5cm"], 100 * o["within_10cm"], 100 * o["within_20cm"], o["misses"]))
if len(reports) > 1:
    for name in names:
        mean = lambda key: 100 * sum(r[name][key] for r in reports) / len(reports)
        print("| %s | mean | | %.1f %% | %.1f %% | %.1f %% | |" % (
            name, mean("within_5cm"), mean("within_10cm"), mean("within_20cm")))
for (seed, frames, start, end), report in zip(runs, reports):
    secs = float(end) - float(start)
    print("seed %s: identity switches %d; %s frames in %.1f s wall (%.2f frame sets/s, including start-up)" % (
        seed, report["identity_switches"], frames, secs, int(frames) / secs))
PY
