#!/usr/bin/env bash
# One sitting on a lent GPU machine (run from the repository root, $OUT set by the device tool):
# unpack the carried episode folders, calibrate each training job's step count on the machine
# (45 s at the longest unroll, all jobs at once, as they will run), train every job for a fixed
# wall budget with checkpoints, then time training throughput on the quiet machine. Everything
# comes back as one archive. The jobs and their options are the `JOBS` table below.
set -u
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
BUDGET_S=${BUDGET_S:-360}       # wall seconds of the real training runs
CALIB_S=${CALIB_S:-45}
python3 -c "import torch, torch_geometric; print('torch', torch.__version__, 'pyg', torch_geometric.__version__, torch.cuda.get_device_name(0))"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
for p in data/device/packs/*.pack.npz; do
  python3 benchmarks/device/pack.py unpack "$p" "data/$(basename "$p" .pack.npz)" || exit 1
done
ls data

OURS_RIGID="--model-rigid-fit true --model-ground-contact true --input-noise 0.0003 --seq-end 8"
OURS_SOFT="--model-rest-offsets true --model-ground-contact true --input-noise 0.0003 --seq-end 8"
OURS_MIXED="--model-rigid-fit true --model-rest-offsets true --model-ground-contact true --input-noise 0.0003 --seq-end 8"
# name | dataset | preset | options
JOBS=(
  "cube_collision_hrn|cube_collision|hrn|"
  "cube_collision_paper|cube_collision|ours|"
  "cube_collision_ours|cube_collision|ours|$OURS_RIGID"
  "soft_bounce_hrn|soft_bounce|hrn|"
  "soft_bounce_paper|soft_bounce|ours|"
  "soft_bounce_ours|soft_bounce|ours|$OURS_SOFT"
  "tower|tower|ours|$OURS_RIGID --train-dropout 0.1 --dropout-modules force,collision"
  "wedge|wedge|ours|$OURS_RIGID --train-dropout 0.1 --dropout-modules force,collision"
  "cube_push|cube_push|ours|$OURS_RIGID --train-dropout 0.1 --dropout-modules force"
)
DEVICE=${DEVICE:-cuda}
COMMON="--batch-size ${BATCH:-32} --workers 1 --threads 1 --device $DEVICE --no-progress --checkpoint-every 100 --eval-every 100"

launch() {  # name data preset steps time_limit_min extra... ; the job's own options come last
  local name=$1 data=$2 preset=$3 steps=$4 limit=$5; shift 5
  python3 -m hrn_pyg.cli train --preset "$preset" --data "data/$data" --out "runs/$name" \
    --train-steps "$steps" --time-limit "$limit" $COMMON "$@" > "runs/$name.log" 2>&1 &
}

mkdir -p runs calib
echo "== calibration $(date +%T)"
for job in "${JOBS[@]}"; do
  IFS='|' read -r name data preset opts <<< "$job"
  python3 -m hrn_pyg.cli train --preset "$preset" --data "data/$data" --out "calib/$name" --train-steps 100000 \
    --time-limit "$(python3 -c "print($CALIB_S/60)")" $COMMON $opts --seq-start 6 --seq-end 6 --warmup 1 \
    > "calib/$name.log" 2>&1 &
done
wait
echo "== training $(date +%T)"
for job in "${JOBS[@]}"; do
  IFS='|' read -r name data preset opts <<< "$job"
  steps=$(python3 benchmarks/device/steps_for_budget.py "calib/$name/metrics.csv" "$BUDGET_S" 200 50)
  echo "$name: $steps steps"
  launch "$name" "$data" "$preset" "$steps" "$(python3 -c "print(($BUDGET_S+30)/60)")" $opts
done
wait
echo "== done $(date +%T)"
for job in "${JOBS[@]}"; do IFS='|' read -r name _ <<< "$job"; tail -n 2 "runs/$name.log"; done
python3 -m benchmarks.train_throughput --data data/soft_bounce --devices ${BENCH_DEVICES:-cuda,cpu} --batch-sizes ${BENCH_BATCHES:-4,32,128} \
  --cpu-max-batch 4 --seq-len 1,6 --steps 5 --warmup 2 --out "$OUT/train_throughput.json"
tar czf "$OUT/runs.tar.gz" runs/*/model.pt runs/*/last.pt runs/*/metrics.csv runs/*/config.json runs/*.log \
  calib/*/metrics.csv calib/*.log 2>/dev/null
ls -la "$OUT"
