"""Effect gating measured: ``HRNConfig.skip_idle_modules`` on against every module forced on.

A module with nothing to do (no external force: the force module; no collision edge: the
collision module) is not run when ``skip_idle_modules=True``; with ``False`` it runs on empty
input. The spec promises that both give the same result; this script measures that, and what
skipping saves.

Scenes (voxelised boxes, k-means hierarchy of the package, pitch ``--pitch``):

* ``free_fall``: one cube falling freely: no collision, no force (both modules idle);
* ``apart_pushed``: two cubes far apart, one pushed: no collision (collision module idle);
* ``touching``: two cubes side by side within the collision radius, no force (force idle);
* ``touching_pushed``: the same, one pushed: nothing idle (the control: ratio ~1).

For each scene and setting: time per rollout step (:func:`hrn_pyg.sim.step.step`, median of
``--repeats`` >= 5 runs of ``--steps`` steps, one torch thread, the two settings interleaved so
they see the same machine load), the largest absolute difference of the predicted positions over
the rollout, and a per-stage breakdown of one step (``build_inputs``, each of the seven
sub-modules timed alone by forward hooks, ``decode``, and the next graph's ``set_state`` with the
collision search). The weights are random (seeded) with the normaliser fitted on a real
``soft_bounce`` window: a step's cost does not depend on the weights.

Run: ``python -m benchmarks.gating [--pitch 0.02] [--steps 10] [--repeats 11] [--threads 1]``.
Prints markdown tables and writes ``benchmarks/results/gating.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time
from collections import defaultdict

import numpy as np
import torch
from torch_geometric.data import HeteroData

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, set_state
from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.voxelise import box_mesh, voxelise
from hrn_pyg.nn.hrn import HRN, MODULE_NAMES, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.step import build_inputs, decode, run_network, step
from hrn_pyg.utils.files import atomic_write_json

#: side of each cube (m)
CUBE_SIDE = 0.2
#: seconds per model step (8 substeps at 240 Hz)
DT = 1.0 / 30.0
GRAVITY = 9.81
#: a push on every leaf of the first cube (N per leaf), the size of a scripted impulse
PUSH = (2.0, 0.0, 1.0)
#: the tolerance of the issue for "the same output"
TOLERANCE = 1e-6


def cube_leaves(pitch: float) -> np.ndarray:
    return voxelise(box_mesh(CUBE_SIDE), pitch)


def make_scene(name: str, pitch: float, radius: float) -> tuple[HeteroData, torch.Tensor]:
    """The scene's graph at ``t`` (state ``x_{t-2..t}`` of a free fall) and its force ``[N, 3]``."""
    cube = cube_leaves(pitch)
    # side by side: the facing leaf layers half a collision radius apart
    beside = float(cube[:, 0].max() - cube[:, 0].min()) + 0.5 * radius
    offsets = {"free_fall": [(0.0, 0.0, 0.5)],
               "apart_pushed": [(0.0, 0.0, 0.5), (1.0, 0.0, 0.5)],
               "touching": [(0.0, 0.0, 0.5), (beside, 0.0, 0.5)],
               "touching_pushed": [(0.0, 0.0, 0.5), (beside, 0.0, 0.5)]}[name]
    leaves = np.concatenate([cube + np.asarray(o) for o in offsets])
    leaf_object = np.repeat(np.arange(len(offsets)), len(cube))
    mass = np.full(len(leaves), 1.0 / len(cube))
    parent = torch.as_tensor(build_hierarchy(leaves, mass, leaf_object), dtype=torch.long)
    structure = build_structure(parent, torch.as_tensor(mass, dtype=torch.float32), torch.as_tensor(leaf_object),
                                torch.zeros(len(offsets), dtype=torch.long), torch.ones(len(offsets)))
    x = torch.as_tensor(leaves, dtype=torch.float32)
    drop = torch.tensor([0.0, 0.0, GRAVITY * DT * DT])  # per-step velocity change under gravity
    x1, x2 = x + 2 * drop, x + 3 * drop  # v_{t-1} = -drop, v_t = -2 drop: falling faster
    graph = set_state(structure, x2, x1, x, radius=radius)
    n = graph[NODE].num_nodes
    force = torch.zeros(n, 3)
    if name.endswith("pushed"):
        force[: len(cube)] = torch.tensor(PUSH)
    return graph, force


def realistic_normalizer(model: HRN) -> None:
    """Fit ``model``'s normaliser on a short real pybullet ``soft_bounce`` window (with its kick).

    Fitting it on the benchmark's own rigid free fall would leave the local-velocity scale at
    its fallback of 1 m per step (a rigid body has no local motion), and a random network would
    then fling the particles kilometres within a few steps.
    """
    episode = simulate_episode("soft_bounce", 0, steps=12)
    fit_normalizer([episode_state(episode, start=2, steps=8)], model.normalizer)


def models(graph: HeteroData, force: torch.Tensor, hidden: int, radius: float) -> dict[str, HRN]:
    """Two HRNs with the same weights: gating on and every module forced on."""
    torch.manual_seed(0)
    on = HRN(HRNConfig(hidden=hidden, collision_radius=radius, skip_idle_modules=True))
    realistic_normalizer(on)
    off = HRN(dataclasses.replace(on.config, skip_idle_modules=False))
    off.load_state_dict(on.state_dict())
    return {"gated": on.eval(), "forced_on": off.eval()}


def run_steps(model: HRN, graph: HeteroData, force: torch.Tensor, steps: int) -> torch.Tensor:
    """``[steps, N, 3]`` positions; the force acts at the first step only (an impulse)."""
    out = []
    zero = torch.zeros_like(force)
    with torch.no_grad():
        for t in range(steps):  # time steps
            result = step(model, graph, force if t == 0 else zero)
            out.append(result.pos)
            graph = result.graph
    return torch.stack(out)


def stage_times(model: HRN, graph: HeteroData, force: torch.Tensor, repeats: int) -> dict[str, float]:
    """Median seconds of each stage of one step (modules timed alone by forward hooks)."""
    spent: dict[str, list[float]] = defaultdict(list)
    started: dict[str, float] = {}
    handles = []
    for name in MODULE_NAMES:
        module = getattr(model, name)
        handles.append(module.register_forward_pre_hook(lambda m, a, n=name: started.__setitem__(n, time.perf_counter())))
        handles.append(module.register_forward_hook(
            lambda m, a, o, n=name: spent[n].append(time.perf_counter() - started[n])))
    try:
        with torch.no_grad():
            for r in range(repeats + 1):  # first pass warms up
                t0 = time.perf_counter()
                inputs = build_inputs(model, graph, force)
                t1 = time.perf_counter()
                out = run_network(model, inputs)
                t2 = time.perf_counter()
                pos = decode(model, graph, out).pos
                t3 = time.perf_counter()
                store = graph[NODE]
                set_state(graph, store.prev_pos, store.pos, pos, radius=model.config.collision_radius)
                t4 = time.perf_counter()
                if r == 0:
                    spent.clear()
                    continue
                for key, dt in (("build_inputs", t1 - t0), ("network", t2 - t1), ("decode", t3 - t2),
                                ("set_state+collision_search", t4 - t3)):
                    spent[key].append(dt)
    finally:
        for h in handles:
            h.remove()
    medians = {k: statistics.median(v) for k, v in spent.items()}
    for name in MODULE_NAMES:
        medians.setdefault(name, 0.0)  # a module that never ran cost nothing
    return medians


def bench_scene(name: str, args: argparse.Namespace) -> dict:
    graph, force = make_scene(name, args.pitch, args.radius)
    pair = models(graph, force, args.hidden, args.radius)
    preds = {k: run_steps(m, graph, force, args.steps) for k, m in pair.items()}
    max_diff = float((preds["gated"] - preds["forced_on"]).abs().max())
    times: dict[str, list[float]] = {k: [] for k in pair}
    for k, m in pair.items():
        run_steps(m, graph, force, args.steps)  # warm-up
    for _ in range(args.repeats):  # interleaved: both settings see the same load
        for k, m in pair.items():
            t0 = time.perf_counter()
            run_steps(m, graph, force, args.steps)
            times[k].append((time.perf_counter() - t0) / args.steps)
    store = graph[NODE]
    stages = {k: stage_times(m, graph, force, args.repeats) for k, m in pair.items()}
    med = {k: statistics.median(v) for k, v in times.items()}
    fastest = {k: min(v) for k, v in times.items()}
    # the same ratio from one run's stage times: the idle modules' cost when forced on
    s = stages["forced_on"]
    total = s["build_inputs"] + s["network"] + s["decode"] + s["set_state+collision_search"]
    idle = [m for m, busy in (("force", bool((force != 0).any())),
                              ("collision", graph[COLLISION].edge_index.size(1) > 0)) if not busy]
    idle_cost = sum(s[m] for m in idle)
    return {
        "scene": name,
        "leaves": int(store.is_leaf.sum()), "nodes": int(store.num_nodes),
        "collision_edges_at_t": int(graph[COLLISION].edge_index.size(1)),
        "force_rows": int((force != 0).any(-1).sum()),
        "ms_per_step": {k: 1e3 * v for k, v in med.items()},
        "ms_per_step_runs": {k: [1e3 * t for t in v] for k, v in times.items()},
        "ms_per_step_min": {k: 1e3 * v for k, v in fastest.items()},
        "forced_on_over_gated": med["forced_on"] / med["gated"],
        "forced_on_over_gated_min": fastest["forced_on"] / fastest["gated"],
        "idle_modules": idle,
        "idle_modules_ms_forced_on": 1e3 * idle_cost,
        "ratio_from_stage_times": total / (total - idle_cost),
        "max_abs_position_difference": max_diff,
        "identical": max_diff <= TOLERANCE,
        "stage_ms": {k: {s: 1e3 * t for s, t in v.items()} for k, v in stages.items()},
    }


def module_shares(stage_ms: dict[str, float]) -> dict[str, float]:
    total = sum(stage_ms[k] for k in ("build_inputs", "network", "decode", "set_state+collision_search"))
    return {k: v / total for k, v in stage_ms.items()}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pitch", type=float, default=0.02, help="voxel pitch (m): 11^3 leaves per cube at 0.02")
    parser.add_argument("--radius", type=float, default=0.08, help="collision radius (m)")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=11)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--scenes", default="free_fall,apart_pushed,touching,touching_pushed")
    parser.add_argument("--out", default="benchmarks/results/gating.json")
    args = parser.parse_args(argv)
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5 (median of at least 5 runs)")
    torch.set_num_threads(args.threads)
    rows = []
    for name in (s for s in args.scenes.split(",") if s):
        row = bench_scene(name, args)
        rows.append(row)
        print(f"{name}: gated {row['ms_per_step']['gated']:.2f} ms, forced on {row['ms_per_step']['forced_on']:.2f} ms, "
              f"max diff {row['max_abs_position_difference']:.3g}", flush=True)

    print()
    print("| scene | leaves | nodes | collision edges | forced rows | idle modules | gated ms/step | "
          "forced-on ms/step | forced-on / gated (median) | (fastest run) | (stage times) | max abs diff (m) |")
    print("|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['scene']} | {r['leaves']} | {r['nodes']} | {r['collision_edges_at_t']} | {r['force_rows']} | "
              f"{', '.join(r['idle_modules']) or 'none'} | "
              f"{r['ms_per_step']['gated']:.2f} | {r['ms_per_step']['forced_on']:.2f} | "
              f"{r['forced_on_over_gated']:.3f} | {r['forced_on_over_gated_min']:.3f} | "
              f"{r['ratio_from_stage_times']:.3f} | {r['max_abs_position_difference']:.3g} |")
    stages = ["build_inputs", *MODULE_NAMES, "decode", "set_state+collision_search"]
    print()
    print("Per-stage ms of one step (forced-on model; 0 = not run):")
    print()
    print("| scene | " + " | ".join(stages) + " |")
    print("|---|" + "---:|" * len(stages))
    for r in rows:
        s = r["stage_ms"]["forced_on"]
        print(f"| {r['scene']} | " + " | ".join(f"{s[k]:.3f}" for k in stages) + " |")
    # the module that dominates, and the saving gating could give at most where a module is idle
    active = next((r for r in rows if r["scene"] == "touching_pushed"), rows[-1])
    s = active["stage_ms"]["forced_on"]
    dominant = max(MODULE_NAMES, key=lambda k: s[k])
    total = sum(s[k] for k in ("build_inputs", "network", "decode", "set_state+collision_search"))
    bound = total / (total - s["force"] - s["collision"])
    summary = {
        "dominant_module": dominant,
        "dominant_share_of_step": s[dominant] / total,
        "module_ms_all_active": {k: s[k] for k in MODULE_NAMES},
        "largest_possible_saving_ratio": bound,
        "note": ("forced_on / gated in an idle scene is bounded by the cost of running the idle modules "
                 "on empty input; largest_possible_saving_ratio is (step) / (step - force - collision) "
                 "with both modules busy, i.e. what skipping them would save if they cost the same idle"),
    }
    print()
    print(f"dominant module (all active): {dominant} ({100 * summary['dominant_share_of_step']:.0f}% of a step); "
          f"force + collision busy cost {s['force'] + s['collision']:.3f} ms of {total:.3f} ms: "
          f"skipping both could save at most x{bound:.2f}")
    result = {
        "what": "effect gating: skip_idle_modules=True vs every module forced on",
        "pitch": args.pitch, "radius": args.radius, "hidden": args.hidden, "steps": args.steps,
        "repeats": args.repeats, "statistic": "median over repeats of a rollout of `steps` steps, per step; "
                                             "settings interleaved",
        "weights": "random init (seed 0), normaliser fitted on a pybullet soft_bounce window",
        "tolerance": TOLERANCE,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0],
                    "note": "2 shared cores, loaded by other jobs while this ran"},
        "rows": rows, "summary": summary,
    }
    atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
