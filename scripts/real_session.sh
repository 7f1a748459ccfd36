#!/usr/bin/env bash
# Tracks a real recording and scores it against its reference: one table row per object
# (median 3D error, shares within 5 / 10 / 20 cm, identity switches) and the tracking speed.
# Extra arguments go to `handflow track` (for example `--set field=value` for an ablation).
# Usage: scripts/real_session.sh [RECORDING_DIR] [TRACK_ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
rec=${1:-../shared/data/real/caliscope-hands}
shift || true
if [ ! -d "$rec" ]; then
    echo "skipped: recording $rec not found" >&2
    exit 0
fi
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q -p handflow
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
start=$(date +%s.%N)
"$bin" track --recording "$rec" --out "$out/tracks.jsonl" "$@" 2>"$out/track.log"
end=$(date +%s.%N)
"$bin" eval tracks --recording "$rec" --tracks "$out/tracks.jsonl" --reference "$rec/reference.json" --json >"$out/eval.json"
python3 - "$out/eval.json" "$out/tracks.jsonl" "$start" "$end" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
frames = sum(1 for line in open(sys.argv[2]) if line.strip())
secs = float(sys.argv[4]) - float(sys.argv[3])
print("| object | median 3D | within 5 cm | within 10 cm | within 20 cm | misses |")
print("|---|---|---|---|---|---|")
for name in ("head", "left_hand", "right_hand"):
    o = report[name]
    median = "-" if o["median_3d_m"] is None else "%.3f m" % o["median_3d_m"]
    print("| %s | %s | %.1f %% | %.1f %% | %.1f %% | %d |" % (
        name, median, 100 * o["within_5cm"], 100 * o["within_10cm"], 100 * o["within_20cm"], o["misses"]))
print("identity switches: %d" % report["identity_switches"])
print("%d frames in %.1f s wall (%.2f frame sets/s, including start-up)" % (frames, secs, frames / secs))
PY
