#!/usr/bin/env bash
# Ablation of the handflow variant on a Middlebury scene: each row turns one choice off
# (or changes it) and reports the mean over 3 seeds of both layouts. Figures go in
# BENCHMARKS.md. Usage: scripts/ablation.sh [SCENE_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
scene=${1:-../shared/data/middlebury/teddy}
cargo build --release -q -p handflow
bin=target/release/handflow
row() {
    local name=$1
    shift
    "$bin" bench accuracy --scene "$scene" --seeds 3 --json "$@" | python3 -c '
import json, sys
name = sys.argv[1]
rows = [json.loads(line) for line in sys.stdin if line.strip()]
cells = []
for r in rows:
    cells.append("%.3f / %.3f / %.2f" % (r["of_rmse_px"], r["structure_rmse_px"], r["aae_deg"]))
secs = sum(r["seconds_per_frame"] for r in rows) / len(rows)
print("| %s | %s | %.2f |" % (name, " | ".join(cells), secs))
' "$name"
}
echo "| configuration | multiview: flow / structure px / AAE deg | fb: flow / structure px / AAE deg | s/frame |"
echo "|---|---|---|---|"
row "handflow defaults"
row "paper variant (reference)" --variant paper
row "no local contrast normalisation" --set local_normalisation_radius=0
row "no propagation (independent rays)" --set propagation=false
row "no robust view selection (all views count)" --set view_keep_fraction=1.0
row "single-pixel likelihood (no support window)" --set window_radius=0 --set coarse_window_radius=0
row "3x3 window on coarse levels too" --set coarse_window_radius=1
row "no weighted-median refinement" --set refine_radius=0
row "isotropic velocity prior (no depth-motion prior)" --set velocity_prior_depth=1.0
row "no extra coarsest-level loops" --set coarse_extra_loops=0
row "3 loops per level (as the paper)" --set noise_loops=3
row "no exploration particles" --set exploration_particles=0
row "best particle as estimate instead of weighted mean" --set mean_estimate=false
row "with velocity smoothness term" --set smoothness_px=0.5
