#!/usr/bin/env bash
# Renders each synthetic preset or scene file (once, into out/presets/NAME), tracks it and
# prints its agreement and 3D error per object against the exact truth (with VELOCITY=1, the
# published velocity's RMS error and the share of the true velocity it carries instead). Extra
# arguments go to `handflow track`.
# Usage: [VELOCITY=1] scripts/presets.sh [PRESET|SCENE.toml...] [-- TRACK_ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${HANDFLOW_BIN:-target/release/handflow}
[ -x "$bin" ] || cargo build --release -q -p handflow
presets=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do presets+=("$1"); shift; done
[ "${1:-}" = "--" ] && shift
[ ${#presets[@]} -gt 0 ] || presets=(signer-3cam signer-2cam-narrow hands-cross occluded-side)
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
if [ "${VELOCITY:-0}" = 1 ]; then
    echo "| preset | head: velocity rmse / gain | left hand | right hand | switches |"
else
    echo "| preset | head: agreement / 3D rmse | left hand | right hand | switches |"
fi
echo "|---|---|---|---|---|"
for p in "${presets[@]}"; do
    name=$(basename "$p" .toml)
    rec=out/presets/$name
    if [ ! -f "$rec/frames.csv" ]; then
        case $p in
            *.toml) "$bin" render --scene "$p" --out "$rec" >/dev/null ;;
            *) "$bin" render --preset "$p" --out "$rec" >/dev/null ;;
        esac
    fi
    "$bin" track --recording "$rec" --out "$out/$name.jsonl" "$@" 2>/dev/null
    "$bin" eval tracks --recording "$rec" --tracks "$out/$name.jsonl" --json | python3 -c '
import json, sys
r = json.load(sys.stdin)
velocity = sys.argv[2] == "1"
def cell(o):
    if velocity:
        if o["rmse_velocity_m_s"] is None:
            return "-"
        return "%.3f m/s / %.2f" % (o["rmse_velocity_m_s"], o["velocity_gain"] if o["velocity_gain"] is not None else float("nan"))
    rmse = "-" if o["rmse_3d_m"] is None else "%.1f cm" % (100 * o["rmse_3d_m"])
    lost = " (%d lost)" % o["misses"] if o["misses"] else ""
    return "%.1f %% / %s%s" % (100 * o["agreement"], rmse, lost)
cells = [cell(r[o]) for o in ("head", "left_hand", "right_hand")]
print("| %s | %s | %d |" % (sys.argv[1], " | ".join(cells), r["identity_switches"]))
' "$name" "${VELOCITY:-0}"
done
