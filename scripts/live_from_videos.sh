#!/usr/bin/env bash
# Runs `handflow run` on live cameras that play a recording's videos at their own rate (as
# cameras deliver them), then scores the trajectories by capture time (a live run numbers its
# frame sets itself and drops what it cannot keep up with). A recording of PNG folders (a
# rendered preset) is encoded to H.264 first (ffmpeg). Prints the run's end-of-stream lines
# (samples, frames lost, glass-to-trajectory latency) and the scores.
# Usage: scripts/live_from_videos.sh [RECORDING_DIR] [FPS]
# CODEC=mjpeg encodes the PNG folders as Motion JPEG (what USB webcams send) instead of H.264.
# KEEP_OUT=1 keeps the run's folder (pipeline file, log, trajectories) and prints its path.
set -euo pipefail
cd "$(dirname "$0")/.."
rec=$(realpath "${1:-../shared/data/real/caliscope-hands}")
fps=${2:-6}
if [ ! -d "$rec" ]; then
    echo "skipped: recording $rec not found" >&2
    exit 0
fi
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q --workspace
out=$(mktemp -d)
if [ -n "${KEEP_OUT:-}" ]; then echo "run folder: $out" >&2; else trap 'rm -rf "$out"' EXIT; fi
if [ -f "$rec/camera_array.toml" ]; then calibration=$rec/camera_array.toml; else calibration=$rec/rig.toml; fi
printf 'mode = "live"\ncalibration = "%s"\nout = "%s/tracks.jsonl"\nservices = "live-videos-%s"\n' \
    "$calibration" "$out" "$$" >"$out/live.toml"
for video in "$rec"/*.mp4; do
    [ -e "$video" ] || break
    name=$(basename "$video" .mp4)
    printf '\n[[cameras]]\nname = "%s"\nsource = "file://%s"\nfps = %s\n' "$name" "$video" "$fps" >>"$out/live.toml"
done
if ! grep -q cameras "$out/live.toml"; then
    for dir in "$rec"/cam*/; do
        name=$(basename "$dir")
        if [ "${CODEC:-h264}" = mjpeg ]; then
            video=$out/$name.mkv
            ffmpeg -loglevel error -y -framerate "$fps" -i "$dir/%06d.png" -c:v mjpeg -q:v 3 -pix_fmt yuvj420p "$video"
        else
            video=$out/$name.mp4
            ffmpeg -loglevel error -y -framerate "$fps" -i "$dir/%06d.png" -c:v libx264 -crf 12 -pix_fmt yuv420p "$video"
        fi
        printf '\n[[cameras]]\nname = "%s"\nsource = "file://%s"\nfps = %s\n' "$name" "$video" "$fps" >>"$out/live.toml"
    done
fi
"$bin" run "$out/live.toml" 2>"$out/run.log" >/dev/null
grep -E "end of stream:|stream ended|frame set\(s\) dropped|frames/s" "$out/run.log" | sed 's/^.*Z *//' | tail -8
python3 - "$out" "$fps" <<'PY'
import json, sys
out, fps = sys.argv[1], float(sys.argv[2])
with open(out + "/mapped.jsonl", "w") as f:
    for line in open(out + "/tracks.jsonl"):
        r = json.loads(line)
        r["frame"] = round(r["t"] * fps)
        f.write(json.dumps(r) + "\n")
PY
if [ -f "$rec/reference.json" ]; then
    "$bin" eval tracks --recording "$rec" --tracks "$out/mapped.jsonl" --reference "$rec/reference.json" | tail -4
else
    "$bin" eval tracks --recording "$rec" --tracks "$out/mapped.jsonl" | tail -4
fi
