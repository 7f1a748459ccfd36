#!/usr/bin/env bash
# Sensitivity of the handflow variant to its main parameters: each line moves one default
# by roughly +-50% and reports the mean over 3 seeds of both layouts (optical flow px,
# Z flow, structure px, AAE deg, s/frame). Usage: scripts/sensitivity.sh [SCENE_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
scene=${1:-../shared/data/middlebury/teddy}
cargo build --release -q -p handflow
for setting in "" temperature=0.07 temperature=0.15 local_normalisation_radius=2 local_normalisation_radius=4 \
    view_keep_fraction=0.5 truncation=0.7 refine_colour_sigma=0.2 refine_colour_sigma=0.5 diffusion_shrink=0.7 \
    fresh_fraction=0.1; do
    echo "== ${setting:-defaults}"
    if [ -n "$setting" ]; then
        target/release/handflow bench accuracy --scene "$scene" --set "$setting"
    else
        target/release/handflow bench accuracy --scene "$scene"
    fi
done
