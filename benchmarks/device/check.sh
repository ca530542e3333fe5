#!/usr/bin/env bash
# The GPU checks in one sitting on a lent machine (run from the repository root with the device
# tool, which sets $OUT; carry data/device/packs): the CUDA-only tests (the fixed-shape step runs
# with no synchronisation, a CUDA-graph rollout equals the plain one), the step time against
# leaf count (plain, fixed-shape, CUDA graph; the goals <= 1.5 ms to 10k leaves and < 50 ms at
# 1M), then the shipped models on real episodes with fixed-shape steps recorded as CUDA graphs.
set -u
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-runs/device_check}
mkdir -p "$OUT"
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0))"
for scene in tower cube_collision cube_push soft_bounce; do
  [ -d "data/$scene" ] || python3 benchmarks/device/pack.py unpack "data/device/packs/$scene.pack.npz" "data/$scene"
done
timeout 120 python3 -m pytest -q -p no:warnings tests/sim/test_fixed_shape.py -k cuda 2>&1 | tee "$OUT/cuda_tests.log"
timeout 300 python3 -m benchmarks.device_step --device cuda --out "$OUT/device_step_cuda.json" 2>&1 | tee "$OUT/device_step.log"
timeout 200 python3 -m benchmarks.fixed_shape --device cuda --cuda-graph --scenes tower,cube_collision,cube_push,soft_bounce \
  --out "$OUT/fixed_shape_cuda.json" 2>&1 | tee "$OUT/fixed_shape.log"
