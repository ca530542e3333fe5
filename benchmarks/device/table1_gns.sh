#!/usr/bin/env bash
# Table 1's GNS rows from the shipped checkpoints, in one command (docs/gns.md):
#   bash benchmarks/device/table1_gns.sh            # both scenes
#   SCENES=cube_collision bash benchmarks/device/table1_gns.sh
# Needs the datasets (hrn-pyg generate --scene <scene> --episodes 200 --out data/<scene>, as
# data/recipes.toml). Scores the test split (seed % 10 == 9) at t+5/15 (windows 10 steps apart)
# and t+50/100 (one per episode), 1000 steps from rest on validation seeds, and on cube_collision
# the collisions that keep both cubes' shapes. Writes docs/results/table1_gns_<scene>/,
# benchmarks/results/rigid_collisions_cube_collision.json and
# docs/results/stability/long_rollouts_<scene>_gns.json.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
HRN="$PY -m hrn_pyg.cli"
SCENES=${SCENES:-"cube_collision soft_bounce"}
for scene in $SCENES; do
  gns=gns_$scene
  if [ "$scene" = cube_collision ]; then
    $HRN evaluate --data data/cube_collision --split test --stride 10 --no-progress \
      --model GNS=$gns --model "GNS + rigid fit=$gns" --rigid-fit "GNS + rigid fit" \
      --out docs/results/table1_gns_cube_collision
    $PY -m benchmarks.rigid_collisions --data data/cube_collision --split test \
      --model HRN=cube_collision_hrn --model "ours + rigid fit=cube_collision_ours" \
      --model GNS=$gns --model "GNS + rigid fit=$gns" --rigid-fit "GNS + rigid fit" \
      --out benchmarks/results/rigid_collisions_cube_collision.json
    $PY -m benchmarks.long_rollouts --model "cube_collision=$gns:GNS" \
      --model "cube_collision=$gns:GNS + rigid fit" --rigid-fit "GNS + rigid fit" \
      --model "cube_collision=cube_collision_ours:ours + rigid fit" --seeds 8,18 \
      --out docs/results/stability/long_rollouts_cube_collision_gns.json
  else
    $HRN evaluate --data data/$scene --split test --stride 10 --no-progress --model GNS=$gns \
      --out docs/results/table1_gns_$scene
    $PY -m benchmarks.long_rollouts --model "$scene=$gns:GNS" --model "$scene=${scene}_ours:ours (shipped)" \
      --seeds 8,18,28 --out docs/results/stability/long_rollouts_${scene}_gns.json
  fi
done
