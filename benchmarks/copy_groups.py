"""How large should a group of copies be? Cost per copy and step of ``hrn_pyg.sample`` at k = 16,
64, 256 for several node budgets of :mod:`hrn_pyg.sim.copy_groups`, and for one pass over all copies.

Same scene, model and rate as ``benchmarks/sampling.py`` (soft_bounce, random weights, dropout
0.3 on force + collision, the scene's effects). Every round times every (budget, k) once, so a slow
phase of the machine lands on all of them alike; the table gives the median over rounds.

Run: ``python -m benchmarks.copy_groups [--rounds 6] [--budgets 2048,4096,8192,16384]
[--out benchmarks/results/copy_groups.json]``. Prints a markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import hrn_pyg.sim.step as step_module
from hrn_pyg.data.scene_file import scene_effects
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim import copy_groups
from hrn_pyg.utils.files import atomic_write_json

from benchmarks.common import SAMPLING_RATE, SAMPLING_SCENE, sampling_setup

KS = (16, 64, 256)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--budgets", default="2048,4096,8192,16384", help="nodes per group (comma-separated)")
    parser.add_argument("--out", default="benchmarks/results/copy_groups.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    model, window, forces = sampling_setup(args.steps)
    effects = scene_effects(SAMPLING_SCENE)
    budgets: list[int | None] = [None] + [int(b) for b in args.budgets.split(",") if b]

    def grouping(budget: int | None):
        if budget is None:
            return lambda inputs: None
        return lambda inputs: copy_groups.copy_groups(inputs, max_nodes=budget)

    def run(k: int) -> None:
        gen = torch.Generator().manual_seed(0)
        sample(model, window, k, args.steps, SAMPLING_RATE, forces=forces, generator=gen, effects=effects)

    times: dict[tuple[int | None, int], list[float]] = {(b, k): [] for b in budgets for k in KS}
    for round_index in range(args.rounds + 1):  # round 0 warms up
        for budget in budgets:
            step_module.copy_groups = grouping(budget)
            for k in KS:
                start = time.perf_counter()
                run(k)
                if round_index:
                    times[budget, k].append(1e3 * (time.perf_counter() - start) / args.steps / k)
    step_module.copy_groups = copy_groups.copy_groups
    rows = [{"budget": b, **{f"k{k}_ms_per_copy_step": statistics.median(times[b, k]) for k in KS}} for b in budgets]
    print(f"{SAMPLING_SCENE}: ms per copy and step, one thread, median of {args.rounds} interleaved rounds")
    print()
    print("| nodes per group | " + " | ".join(f"k={k}" for k in KS) + " |")
    print("|---|" + "---:|" * len(KS))
    for r in rows:
        label = "one pass" if r["budget"] is None else str(r["budget"])
        print(f"| {label} | " + " | ".join(f"{r[f'k{k}_ms_per_copy_step']:.3f}" for k in KS) + " |")
    result = {"what": "cost per copy and step by the node budget of a group of copies", "scene": SAMPLING_SCENE,
              "rounds": args.rounds, "steps": args.steps, "default_budget": copy_groups.MAX_NODES_PER_GROUP,
              "rows": rows, "runs": {f"{b}/{k}": v for (b, k), v in times.items()}}
    atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
