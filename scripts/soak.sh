#!/usr/bin/env bash
# One hour of the live pipeline on a looped recording (`handflow bench soak`, release build):
# each stage's resident memory and open descriptors, rate and latency per five minutes, as a
# table (stdout), a CSV and a plot. Not part of CI.
#
#   scripts/soak.sh                                   # the demo recording, 60 minutes
#   MINUTES=10 RECORDING=../shared/data/real/caliscope-hands scripts/soak.sh
#
# Writes out/soak.csv and docs/images/soak.png (matplotlib, installed with pip if missing).
set -euo pipefail
cd "$(dirname "$0")/.."
minutes="${MINUTES:-60}"
window="${WINDOW:-5}"
args=(bench soak --minutes "$minutes" --window "$window" --csv out/soak.csv)
if [ -n "${RECORDING:-}" ]; then args+=(--recording "$RECORDING"); fi
mkdir -p out docs/images
cargo build --release --workspace
./target/release/handflow "${args[@]}" 2> out/soak.log
if ! python3 -c "import matplotlib" >/dev/null 2>&1; then
    python3 -m pip install --quiet matplotlib || python3 -m pip install --quiet --break-system-packages matplotlib
fi
python3 scripts/soak_plot.py out/soak.csv docs/images/soak.png
