#!/usr/bin/env bash
# Tracks a session played forwards, backwards, forwards... (ROUNDS times each way, default 4:
# the shared 111-frame session becomes 888 frame sets) and scores it per pass against the
# session's reference mapped frame by frame: what minutes of tracking do to memory, speed and the
# skin models' and tracks' state, on footage whose every frame has a reference. The videos are
# re-encoded (H.264 CRF 18, the source's rate) into OUT and the calibration copied; the copy has no
# capture times (frame i of every video is one instant). Prints `track`'s peak memory and speed
# and, per pass, the shares within 5 / 10 cm per object.
# Usage: [ROUNDS=4] [SEED=0] scripts/long_replay.sh [SESSION_DIR] [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
session=${1:-../shared/data/real/caliscope-hands}
out=${2:-out/long-replay}
rounds=${ROUNDS:-4}
seed=${SEED:-0}
if [ ! -f "$session/reference.json" ] || [ ! -f "$session/camera_array.toml" ]; then
    echo "skipped: $session has no reference.json and camera_array.toml (a caliscope session is needed)" >&2
    exit 0
fi
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q -p handflow
mkdir -p "$out"
cp "$session/camera_array.toml" "$out/"
for video in "$session"/cam_*.mp4; do
    name=$(basename "$video")
    [ -f "$out/$name" ] && continue
    rate=$(ffprobe -v error -select_streams v:0 -show_entries stream=r_frame_rate -of csv=p=0 "$video")
    # One pass forwards and one backwards, that pair ROUNDS times (`reverse` holds the whole
    # video in memory: fine for a session of seconds, not for one of minutes).
    copies=$(for ((k = 0; k < rounds; k++)); do printf '[c%d]' "$k"; done)
    graph="[0:v]split[a][b];[b]reverse[r];[a][r]concat=n=2:v=1,split=$rounds$copies;"
    graph+="${copies}concat=n=$rounds:v=1,setpts=N/($rate)/TB[o]"
    ffmpeg -loglevel error -y -i "$video" -filter_complex "$graph" -map "[o]" -r "$rate" \
        -c:v libx264 -crf 18 -pix_fmt yuv420p "$out/$name"
done
python3 - "$session/reference.json" "$out" <<'EOF'
import json, subprocess, sys
from pathlib import Path
reference, out = Path(sys.argv[1]), Path(sys.argv[2])
frames = int(subprocess.run(
    ["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
     "stream=nb_read_frames", "-of", "csv=p=0", str(next(out.glob("cam_*.mp4")))],
    check=True, capture_output=True, text=True).stdout.strip())
ref = json.loads(reference.read_text())
by_frame = {f["frame"]: f for f in ref["frames"]}
n = max(by_frame) + 1
order = []
while len(order) < frames:
    order += list(range(n)) + list(range(n - 1, -1, -1))
ref["frames"] = [dict(by_frame[src], frame=i) for i, src in enumerate(order[:frames]) if src in by_frame]
(out / "reference.json").write_text(json.dumps(ref))
(out / "passes.json").write_text(json.dumps({"frames_per_pass": n, "frames": frames}))
EOF
# GNU time gives the peak memory; without it (Debian's `time` package) the run goes on unmeasured.
measure=()
if [ -x /usr/bin/time ]; then
    measure=(/usr/bin/time -f "track: peak memory %M KB, %e s wall, %U s user")
else
    echo "long_replay: /usr/bin/time not found (apt-get install time): peak memory not measured" >&2
fi
"${measure[@]}" "$bin" track --recording "$out" --out "$out/tracks-$seed.jsonl" --seed "$seed" 2>"$out/track-$seed.log" \
    || { tail -5 "$out/track-$seed.log" >&2; exit 1; }
tail -2 "$out/track-$seed.log"
"$bin" eval tracks --recording "$out" --tracks "$out/tracks-$seed.jsonl" --reference "$out/reference.json" \
    --per-frame "$out/per-frame-$seed.csv"
python3 - "$out" "$seed" <<'EOF'
import csv, json, sys
from pathlib import Path
out, seed = Path(sys.argv[1]), sys.argv[2]
n = json.loads((out / "passes.json").read_text())["frames_per_pass"]
rows = [r for r in csv.DictReader(open(out / f"per-frame-{seed}.csv")) if r["error_3d_m"]]
objects = ["head", "left_hand", "right_hand"]
print("| pass | " + " | ".join(f"{o}: within 5 / 10 cm" for o in objects) + " |")
print("|---|" + "---|" * len(objects))
for k in range(max(int(r["frame"]) for r in rows) // n + 1):
    cells = []
    for o in objects:
        e = [float(r["error_3d_m"]) for r in rows if r["object"] == o and int(r["frame"]) // n == k]
        cells.append(f"{100 * sum(x < 0.05 for x in e) / len(e):.1f} / {100 * sum(x < 0.1 for x in e) / len(e):.1f} %"
                     if e else "no reference")
    way = "forwards" if k % 2 == 0 else "backwards"
    print(f"| {k} ({way}) | " + " | ".join(cells) + " |")
EOF
