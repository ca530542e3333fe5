"""The soft cube at a fine resolution: the learned step beside pybullet's FEM, at its reported error.

Issue 15 asks for speed where accuracy is known: a ``soft_bounce`` model trained at pitch 0.025
m (729 leaves per cube) by the recipe (``soft_bounce_fine`` in ``data/recipes.toml``), its error
on the held-out **test** episodes of its own dataset, and its step time next to the time
pybullet takes for the same simulated time (one model step = ``substeps`` physics steps) on the
same machine, in one process. The errors are :func:`hrn_pyg.evaluate.evaluate_model`'s (position
and shape MSE at t+5 and t+15, windows every 10 steps), the step time the median over
``--repeats`` of a 15-step deterministic rollout of one test window (sleeping off, the scene's
declared effects: no collision search for a lone body), pybullet's the median over
``--repeats`` seeds of 20 scripted model steps; both on ``--threads`` torch / one pybullet
thread. Goal: the learned step at least 5x faster than pybullet.

Run: ``python -m benchmarks.soft_speed [--model hrn_pyg/checkpoints/soft_bounce_fine.pt]
[--data data/soft_bounce_fine] [--repeats 5] [--threads 1]``. Prints a table and writes
``benchmarks/results/soft_speed.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch
from torch_geometric.data import Batch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import scene_effects
from hrn_pyg.evaluate import evaluate_model, select_windows, summarise
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.utils.files import atomic_write_json

from benchmarks.common import HORIZONS, STRIDE, pybullet_ms_per_step

SCENE = "soft_bounce"
GOAL_SPEEDUP = 5.0


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="hrn_pyg/checkpoints/soft_bounce_fine.pt")
    parser.add_argument("--data", default="data/soft_bounce_fine")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/soft_speed.json")
    args = parser.parse_args(argv)
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5 (median of at least 5 runs)")
    meta = json.loads((Path(args.data) / "meta.json").read_text())
    if meta["scene"] != SCENE:
        raise SystemExit(f"--data holds {meta['scene']!r} episodes, not {SCENE!r}")
    pitch = float(meta["config"]["pitch"])
    torch.set_num_threads(args.threads)

    model = load_model(args.model)
    steps = max(HORIZONS)
    test = EpisodeWindows(args.data, "test", horizon=steps)
    windows = select_windows(test, STRIDE, None)
    errors = summarise(evaluate_model(model, windows, HORIZONS))
    one = windows[0]
    store = one[NODE]
    forces = store.force_seq[:, :steps].transpose(0, 1).contiguous()
    graph = Batch.from_data_list([one])
    effects = scene_effects(SCENE)

    def run_once() -> None:
        with torch.no_grad():
            rollout(model, graph, steps, forces, sleep=None, effects=effects)

    run_once()  # warm-up
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        run_once()
        times.append((time.perf_counter() - start) / steps)
    model_ms = 1e3 * statistics.median(times)
    pybullet_ms, pybullet_leaves = pybullet_ms_per_step(SCENE, pitch, args.repeats)
    leaves = int(store.is_leaf.sum())
    speedup = pybullet_ms / model_ms
    print("| model | pitch | leaves | ms/step | pybullet ms/step | speed-up | pos MSE t+5 | pos MSE t+15 | shape MSE t+15 |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    pos, shape = errors["position"], errors["shape"]
    print(f"| {args.model} | {pitch:g} | {leaves} | {model_ms:.2f} | {pybullet_ms:.2f} | x{speedup:.1f} | "
          f"{pos['t+5']['mean']:.3g} | {pos['t+15']['mean']:.3g} ± {pos['t+15']['sem']:.2g} | "
          f"{shape['t+15']['mean']:.3g} |")
    print(f"\ngoal: learned step >= {GOAL_SPEEDUP:g}x faster than pybullet: {'met' if speedup >= GOAL_SPEEDUP else 'missed'}")
    result = {
        "what": "learned soft-cube step beside pybullet's FEM at the same pitch, with the model's test error",
        "model": args.model, "data": args.data, "pitch": pitch, "leaves": leaves,
        "pybullet_leaves": pybullet_leaves, "ms_per_step": model_ms, "ms_per_step_runs": [1e3 * t for t in times],
        "pybullet_ms_per_step": pybullet_ms, "speedup": speedup, "goal_speedup": GOAL_SPEEDUP,
        "errors": errors, "test_windows": len(windows), "test_episodes": len(test.seeds),
        "statistic": "model: median of repeats of a 15-step rollout / 15; pybullet: median over seeds of 20 steps",
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch": torch.__version__,
                    "torch_threads": args.threads, "load_average_1m": os.getloadavg()[0]},
    }
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
