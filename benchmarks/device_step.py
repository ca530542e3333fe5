"""Time per rollout step against scene size on one device: the CPU (small sizes) or a GPU.

The scene is a grid of rigid cubes of ``--side``^3 leaves (pitch 0.05 m, neighbouring faces one
pitch apart, collision radius 0.08 m; the octree hierarchy of ``benchmarks/scaling.py``), as many
cubes as it takes to reach each ``--leaves`` target. The model is a random-init
:class:`~hrn_pyg.nn.hrn.HRN` (default config, seed 0) whose normaliser is fitted on a real
pybullet ``soft_bounce`` window: the cost of a step does not depend on the weights. Each size is
timed as the median over ``--repeats`` of ``--steps`` steps of :func:`hrn_pyg.sim.rollout.unroll`
(sleeping off, every object moving: the worst case), with the device synchronised before the
clock starts and stops, after one warm-up run; the network pass alone is timed the same way.
Beside it, the same rollout from fixed-shape steps (:mod:`hrn_pyg.sim.fixed_shape`: a collision
candidate list with a skin, no host read inside a step, one read per look-ahead), and on CUDA
the same again with every step recorded as a CUDA graph; each row says how many collision
searches and host reads the fixed-shape rollout made, and how far its positions are from the
plain rollout's (0 on the CPU: the same numbers bit for bit). Falling, every object speeds up
by 1.1 cm a step and the random-weight model moves leaves 8 cm to 1.3 m a step, so the candidate
list is stale at once and searched every step: the fixed-shape path's worst case. Its best case,
a scene whose list lasts, is timed in parts: one fixed-shape step with the start's list reused
(``fixed_step_ms``; recorded as a CUDA graph on CUDA, ``graphed_step_ms``) and one search
(``search_ms``); a list that lasts ``L`` steps costs a step plus ``1 / L`` of a search.

Goals of issue 15 on an H100: at most 1.5 ms per step up to 10 000 leaves, and a step of a
million leaves under 50 ms (28 ms at 250 000 leaves was measured by hand with the earlier code).
Without a GPU the script runs on the CPU with the default (smaller) sizes, which checks it end
to end; the CPU numbers say nothing about the GPU goals.

Run: ``python -m benchmarks.device_step [--device cpu|cuda] [--leaves 250,2000,...]
[--repeats 5] [--steps 20] [--threads 1]``. Prints a markdown table and writes
``benchmarks/results/device_step_<device type>.json``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time

import torch

from hrn_pyg.data.candidates import build_candidates
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, set_state
from hrn_pyg.nn.hrn import HRN, HRNConfig, StepOptions
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.fixed_shape import (
    FixedShapeConfig,
    FixedShapeSimulator,
    RecordedStep,
    make_step,
)
from hrn_pyg.sim.rollout import unroll
from hrn_pyg.sim.step import build_inputs, run_network
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json

from benchmarks.common import cubes_scene

PITCH, RADIUS = 0.05, 0.08
CPU_LEAVES = (250, 2_000, 16_000)
GPU_LEAVES = (250, 2_000, 10_000, 65_000, 250_000, 1_000_000)
#: the goals of issue 15 (H100): ms per step up to SMALL_LEAVES leaves, and at a million
SMALL_LEAVES, SMALL_GOAL_MS, MILLION_GOAL_MS = 10_000, 1.5, 50.0


def scene(target_leaves: int, side: int, device: torch.device):
    """Enough ``side``^3 cubes to reach ``target_leaves``, all falling, as a graph on ``device``."""
    objects = max(1, math.ceil(target_leaves / side**3))
    leaves, leaf_object, parent = cubes_scene(side, objects, PITCH)
    structure = build_structure(torch.as_tensor(parent), torch.full((len(leaves),), 0.01),
                                torch.as_tensor(leaf_object), torch.zeros(objects, dtype=torch.long),
                                torch.ones(objects))
    x = torch.as_tensor(leaves, dtype=torch.float32)
    drop = torch.tensor([0.0, 0.0, 9.81 / 900.0])  # falling: every object moves
    return set_state(structure, x + 2 * drop, x + drop, x, radius=RADIUS).to(device), objects


def timed(fn, device: torch.device, repeats: int) -> list[float]:
    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fn()  # warm-up: allocator, kernels, lazy imports
    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def step_parts(model: HRN, graph, device: torch.device, steps: int, repeats: int) -> dict:
    """ms of one fixed-shape step with the start state's candidate list reused (eager, and on
    CUDA recorded as a graph), each step fed the last one's output with no host read, and of
    one candidate search."""
    radius = model.config.collision_radius
    skin = FixedShapeConfig().skin * radius
    with torch.no_grad():
        candidates = build_candidates(graph, graph[NODE].pos, radius, skin)
        search = timed(lambda: build_candidates(graph, graph[NODE].pos, radius, skin), device, repeats)
        store = graph[NODE]
        fn = make_step(model, graph, StepOptions(force_active=False), radius, skin, ())
        start = (store.pos, store.prev_pos, store.prev_prev_pos, torch.zeros_like(store.pos), (),
                 candidates.edge_index, candidates.valid, candidates.reference)

        def run(step_fn) -> None:
            pos, prev, prev2 = start[:3]
            for _ in range(steps):
                nxt, since, _ = step_fn(pos, prev, prev2, *start[3:])
                pos, prev, prev2 = nxt, since, prev

        parts = {"candidate_pairs": candidates.pairs, "search_ms": 1e3 * statistics.median(search),
                 "fixed_step_ms": 1e3 * statistics.median(timed(lambda: run(fn), device, repeats)) / steps}
        if device.type == "cuda":
            recorded = RecordedStep(fn, start)
            parts["graphed_step_ms"] = 1e3 * statistics.median(timed(lambda: run(recorded), device, repeats)) / steps
    return parts


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--leaves", default=None, help="comma-separated leaf counts (default by device)")
    parser.add_argument("--side", type=int, default=5, help="leaves per side of each cube")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.repeats < 3 or args.steps < 1 or args.side < 2:
        raise SystemExit("need --repeats >= 3, --steps >= 1 and --side >= 2")
    device = resolve_device(args.device)
    torch.set_num_threads(args.threads)
    default = GPU_LEAVES if device.type == "cuda" else CPU_LEAVES
    targets = [int(n) for n in args.leaves.split(",")] if args.leaves else list(default)
    out = args.out or f"benchmarks/results/device_step_{device.type}.json"

    torch.manual_seed(0)
    model = HRN(HRNConfig(collision_radius=RADIUS))
    fit_normalizer([episode_state(simulate_episode("soft_bounce", 0, steps=12), start=2, steps=8)], model.normalizer)
    model = model.to(device).eval()
    rows = []
    for target in targets:
        graph, objects = scene(target, args.side, device)
        store = graph[NODE]
        with torch.no_grad():
            steps = timed(lambda: unroll(model, graph, args.steps, sleep=None), device, args.repeats)
            inputs = build_inputs(model, graph)
            network = timed(lambda: run_network(model, inputs), device, args.repeats)
            reference = torch.stack([s.pos for s in unroll(model, graph, args.steps, sleep=None)])
        row = {"target_leaves": target, "leaves": int(store.is_leaf.sum()), "nodes": int(store.num_nodes),
               "objects": objects, "collision_edges": int(graph[COLLISION].edge_index.size(1)),
               "ms_per_step": 1e3 * statistics.median(steps) / args.steps,
               "ms_per_step_runs": [1e3 * t / args.steps for t in steps],
               "network_ms": 1e3 * statistics.median(network)}
        variants = [("fixed_shape", FixedShapeConfig())]
        if device.type == "cuda":
            variants.append(("cuda_graph", FixedShapeConfig(cuda_graph=True)))
        for name, config in variants:
            simulator = FixedShapeSimulator(model, graph, config)
            runs = timed(lambda: simulator.rollout(args.steps), device, args.repeats)  # warm-up records
            result = simulator.rollout(args.steps)
            row[f"{name}_ms_per_step"] = 1e3 * statistics.median(runs) / args.steps
            row[f"{name}_ms_per_step_runs"] = [1e3 * t / args.steps for t in runs]
            row[f"{name}_searches"], row[f"{name}_host_reads"] = result.searches, result.host_reads
            row[f"{name}_repeated_steps"] = result.repeated_steps
            row[f"{name}_max_abs_diff_m"] = float((result.pos - reference).abs().max())
        row.update(step_parts(model, graph, device, args.steps, args.repeats))
        rows.append(row)
        print(f"{row['leaves']} leaves ({objects} cubes): {row['ms_per_step']:.2f} ms/step, "
              f"network {row['network_ms']:.2f} ms, fixed-shape {row['fixed_shape_ms_per_step']:.2f} ms/step "
              f"({row['fixed_shape_searches']} searches, {row['fixed_shape_host_reads']} reads in {args.steps} steps)"
              + (f", CUDA graph {row['cuda_graph_ms_per_step']:.2f} ms/step" if "cuda_graph_ms_per_step" in row else "")
              + f"; one step with a kept list {row['fixed_step_ms']:.2f} ms"
              + (f" (graphed {row['graphed_step_ms']:.2f} ms)" if "graphed_step_ms" in row else "")
              + f", one search {row['search_ms']:.2f} ms", flush=True)

    graphed = device.type == "cuda"
    print("\n| leaves | objects | collision edges | ms / step | network ms | fixed-shape ms / step | searches / reads"
          + (" | CUDA graph ms / step" if graphed else "") + " | step, kept list ms" + (" | graphed ms" if graphed else "")
          + " | search ms |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if graphed else ""))
    for r in rows:
        print(f"| {r['leaves']} | {r['objects']} | {r['collision_edges']} | {r['ms_per_step']:.2f} | {r['network_ms']:.2f} "
              f"| {r['fixed_shape_ms_per_step']:.2f} | {r['fixed_shape_searches']} / {r['fixed_shape_host_reads']} |"
              + (f" {r['cuda_graph_ms_per_step']:.2f} |" if graphed else "")
              + f" {r['fixed_step_ms']:.2f} |" + (f" {r['graphed_step_ms']:.2f} |" if graphed else "")
              + f" {r['search_ms']:.2f} |")
    goals = {}
    if device.type == "cuda":  # the fastest of the three ways per size
        best = [min(r["ms_per_step"], r["fixed_shape_ms_per_step"], r["cuda_graph_ms_per_step"]) for r in rows]
        kept = [min(r["fixed_step_ms"], r["graphed_step_ms"]) for r in rows]  # a list that lasts
        small = [b for r, b in zip(rows, best) if r["leaves"] <= SMALL_LEAVES]
        million = [b for r, b in zip(rows, best) if r["leaves"] >= 1_000_000]
        goals = {f"max_ms_up_to_{SMALL_LEAVES}_leaves": max(small) if small else None,
                 "meets_small_goal": bool(small) and max(small) <= SMALL_GOAL_MS,
                 "ms_at_a_million": million[0] if million else None,
                 "meets_million_goal": bool(million) and million[0] < MILLION_GOAL_MS,
                 "kept_list_step_ms": {r["leaves"]: k for r, k in zip(rows, kept)}}
        print(f"\ngoals: <= {SMALL_GOAL_MS} ms up to {SMALL_LEAVES} leaves, < {MILLION_GOAL_MS} ms at 1M: {goals}")
    result = {
        "what": "time per rollout step (sleeping off, every object falling) against leaf count",
        "device": str(device), "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
        "statistic": f"median of {args.repeats} runs of {args.steps} steps, device synchronised around each run",
        "side": args.side, "pitch": PITCH, "radius": RADIUS,
        "machine": {"cpus": os.cpu_count(), "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0]},
        "goals": goals, "rows": rows,
    }
    atomic_write_json(out, result)
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
