"""What does a sampled future cost? Time per rollout step of ``hrn_pyg.sampling.sample`` for
k = 1, 2, 4, 8, 16, 32 trajectories run as one batched graph, against a sequential loop of k
single-trajectory rollouts.

The model is randomly initialised (its normaliser fitted on the window itself), so no trained
checkpoint is needed: the cost of a step does not depend on the weights. The scene is a real
``soft_bounce`` window from pybullet (the soft cube with its k-means hierarchy; the kick falls
inside the window, so the force module runs at one step), dropout on force + collision. The
rollouts get the scene's declared effects (``scene_effects("soft_bounce")``: one body, so no
collision search; what ``hrn-pyg sample`` passes) unless ``--no-effects``.

Run: ``python -m benchmarks.sampling [--steps 8] [--repeats 5] [--threads 1] [--profile]
[--ks 1,16,64,256] [--out benchmarks/results/sampling.json]``. Median over repeats, one process,
torch intra-op threads fixed by ``--threads``. Prints a markdown table and writes JSON
(atomically). Two goals: ``batched k=8 <= 2.5 x k=1``, and from k = 16 on the cost per copy
stays flat or falls (a planner's hundreds of copies cost no more each than 16 sampled futures;
:mod:`hrn_pyg.sim.copy_groups`). ``--profile`` adds a cProfile of one batched k=8 rollout;
``--compile`` times the network after ``Module.compile()`` (the compile happens in the warm-up,
whose length is recorded), e.g. ``--compile --out benchmarks/results/sampling_compiled.json``.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import platform
import pstats
import statistics
import time

import torch

from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import scene_effects
from hrn_pyg.sampling.sample import sample
from hrn_pyg.utils.files import atomic_write_json

from benchmarks.common import SAMPLING_RATE, SAMPLING_SCENE, SAMPLING_SEED, sampling_setup

KS = (1, 2, 4, 8, 16, 32)
#: batched k = 8 costs at most this multiple of k = 1
GOAL_RATIO = 2.5
#: from this k on, the batched cost per copy must not rise with k
FLAT_FROM = 16


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--ks", default=",".join(map(str, KS)))
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--no-effects", action="store_true",
                        help="no declared effects: the data decide (a collision search every step)")
    parser.add_argument("--compile", action="store_true",
                        help="time the network through torch.compile (compiled during the warm-up)")
    parser.add_argument("--one-pass", action="store_true",
                        help="run the network over all copies in one pass, not in cache-sized groups of copies "
                             "(what grouping gains; hrn_pyg.sim.copy_groups)")
    parser.add_argument("--out", default="benchmarks/results/sampling.json")
    args = parser.parse_args(argv)
    if args.one_pass:
        import hrn_pyg.sim.step as step_module

        step_module.copy_groups = lambda inputs: None
    effects = None if args.no_effects else scene_effects(SAMPLING_SCENE)
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5 (median of at least 5 runs)")
    torch.set_num_threads(args.threads)
    ks = [int(k) for k in args.ks.split(",") if k]
    model, window, forces = sampling_setup(args.steps)
    if args.compile:
        model.compile()
    n_nodes = window[NODE].num_nodes
    n_leaves = int(window[NODE].is_leaf.sum())

    def batched(k: int):
        gen = torch.Generator().manual_seed(0)
        return lambda: sample(model, window, k, args.steps, SAMPLING_RATE, forces=forces, generator=gen, effects=effects)

    def sequential(k: int):
        gen = torch.Generator().manual_seed(0)

        def run():
            for _ in range(k):  # the baseline: one rollout per sample
                sample(model, window, 1, args.steps, SAMPLING_RATE, forces=forces, generator=gen, effects=effects)

        return run

    # interleaved: every round times each k once, batched then sequential, so a slow phase of a
    # shared machine lands on all of them alike; the k = 8 / k = 1 ratio is taken per round
    calls = {(k, mode): make(k) for k in ks for mode, make in (("batched", batched), ("sequential", sequential))}
    warm_start = time.perf_counter()
    for fn in calls.values():
        fn()  # warm-up (allocator, lazy imports, and the compile with --compile)
    warm_up_seconds = time.perf_counter() - warm_start
    runs: dict[tuple[int, str], list[float]] = {key: [] for key in calls}
    for _ in range(args.repeats):
        for key, fn in calls.items():
            start = time.perf_counter()
            fn()
            runs[key].append((time.perf_counter() - start) / args.steps)
    rows = []
    for k in ks:
        b, s = statistics.median(runs[k, "batched"]), statistics.median(runs[k, "sequential"])
        rows.append({"k": k, "batched_ms_per_step": 1e3 * b, "sequential_ms_per_step": 1e3 * s,
                     "batched_ms_per_step_runs": [1e3 * t for t in runs[k, "batched"]]})
        rows[-1]["batched_ms_per_copy_step"] = 1e3 * b / k
        print(f"k={k:3d}  batched {1e3 * b:8.2f} ms/step ({1e3 * b / k:6.3f} per copy)   "
              f"sequential {1e3 * s:8.2f} ms/step", flush=True)
    base = next((r["batched_ms_per_step"] for r in rows if r["k"] == 1), None)
    for r in rows:
        r["batched_over_k1"] = r["batched_ms_per_step"] / base if base else None
        r["sequential_over_batched"] = r["sequential_ms_per_step"] / r["batched_ms_per_step"]
        if base:
            r["batched_over_k1_per_round"] = [t / t1 for t, t1 in zip(runs[r["k"], "batched"], runs[1, "batched"])]
            r["batched_over_k1_median_of_rounds"] = statistics.median(r["batched_over_k1_per_round"])
    ratio8 = next((r.get("batched_over_k1_median_of_rounds") for r in rows if r["k"] == 8), None)

    print()
    print(f"{SAMPLING_SCENE} seed {SAMPLING_SEED}: {n_leaves} leaves, {n_nodes} nodes; {args.steps} steps; dropout {SAMPLING_RATE} "
          f"on force+collision; torch threads {args.threads}; median of {args.repeats}")
    print()
    print("| k | batched ms/step | batched ms per copy and step | sequential ms/step | batched / batched k=1 "
          "| same, median of rounds | sequential / batched |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['k']} | {r['batched_ms_per_step']:.2f} | {r['batched_ms_per_copy_step']:.3f} | "
              f"{r['sequential_ms_per_step']:.2f} | "
              f"{r['batched_over_k1']:.2f} | {r.get('batched_over_k1_median_of_rounds', float('nan')):.2f} | "
              f"{r['sequential_over_batched']:.2f} |")
    if ratio8 is not None:
        verdict = "meets" if ratio8 <= GOAL_RATIO else "misses"
        spread = sorted(next(r["batched_over_k1_per_round"] for r in rows if r["k"] == 8))
        print(f"\nbatched k=8 / k=1 = {ratio8:.2f}, median of {args.repeats} interleaved rounds "
              f"(range {spread[0]:.2f}-{spread[-1]:.2f}; {verdict} the goal <= {GOAL_RATIO})")

    per_copy = {r["k"]: r["batched_ms_per_copy_step"] for r in rows if r["k"] >= FLAT_FROM}
    flat = None
    if FLAT_FROM in per_copy and len(per_copy) > 1:
        flat = all(v <= per_copy[FLAT_FROM] for v in per_copy.values())
        listed = ", ".join(f"k={k} {v:.3f}" for k, v in per_copy.items())
        print(f"batched ms per copy and step from k={FLAT_FROM}: {listed} "
              f"({'meets' if flat else 'misses'} the goal: none above k={FLAT_FROM}'s)")

    profile = None
    if args.profile:
        prof = cProfile.Profile()
        run8 = batched(8)
        run8()
        prof.enable()
        run8()
        prof.disable()
        text = io.StringIO()
        pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(20)
        profile = text.getvalue()
        print(profile)

    result = {
        "what": "time per rollout step of hrn_pyg.sampling.sample, batched k copies vs k sequential rollouts",
        "scene": SAMPLING_SCENE, "seed": SAMPLING_SEED, "leaves": n_leaves, "nodes": n_nodes,
        "effects": None if effects is None else effects.to_dict(),
        "steps": args.steps, "repeats": args.repeats, "statistic": "median over interleaved rounds (each k once a round), divided by steps; the goal ratio is the median of the per-round ratios",
        "rate": SAMPLING_RATE, "dropout_modules": list(model.config.dropout_modules),
        "compiled": bool(args.compile), "warm_up_seconds": warm_up_seconds,
        "copy_groups": not args.one_pass,
        "model": model.config.to_dict(), "weights": "random init (seed 0), normaliser fitted on the window",
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0],
                    "note": "2 shared cores; other jobs may run at the same time"},
        "goal": f"batched k=8 <= {GOAL_RATIO} x batched k=1", "batched_k8_over_k1": ratio8,
        "meets_goal": None if ratio8 is None else ratio8 <= GOAL_RATIO,
        "goal_per_copy": f"batched ms per copy and step at every k >= {FLAT_FROM} <= that at k={FLAT_FROM}",
        "meets_goal_per_copy": flat,
        "rows": rows,
        "profile_k8_top": profile,
    }
    atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
