"""Fixed-shape steps on real scenes: time per step against the plain rollout, and what it took.

For each scene, the shipped checkpoint rolls out full pybullet validation episodes (``seed % 10
== 8``, ``--seeds``, from step 2 with the episode's own forces, the scene's declared effects,
sleeping off) two ways in one process, interleaved ``--repeats`` times so both see the same
load: :func:`hrn_pyg.sim.rollout.rollout` (``sleep=None``) and a kept
:class:`hrn_pyg.sim.fixed_shape.FixedShapeSimulator` (no host read inside a step; a collision
candidate list with a skin, searched again only when a leaf has moved half the skin; on CUDA,
with ``--cuda-graph``, every step recorded as a CUDA graph). Reported per scene: the median time
per step of each, their ratio, the collision searches, flag reads and repeated steps per
100 steps, and whether the positions are the same bit for bit (they are on the CPU; a GPU's
atomic sums may differ in the last bits).

On one CPU thread the fixed-shape step does more arithmetic (its candidates include the skin)
and fewer searches and reads; the reads are what it removes on a GPU.

Run: ``python -m benchmarks.fixed_shape [--scenes tower,cube_collision,...] [--seeds 8,18]
[--repeats 3] [--device cpu|cuda] [--cuda-graph] [--threads 1]``. Prints a markdown table and
writes ``benchmarks/results/fixed_shape_<device type>.json``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import read_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import scene_effects
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.fixed_shape import FixedShapeConfig, FixedShapeSimulator
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.utils.device import resolve_device
from hrn_pyg.utils.files import atomic_write_json

#: scene -> shipped checkpoint
CHECKPOINTS = {"tower": "tower.pt", "cube_collision": "cube_collision_ours.pt", "cube_push": "cube_push.pt",
               "multi_material": "multi_material.pt", "soft_bounce": "soft_bounce.pt"}
START = 2


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def clock(fn, device: torch.device) -> float:
    sync(device)
    start = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - start


def run_scene(scene: str, seeds: list[int], repeats: int, device: torch.device, config: FixedShapeConfig) -> dict:
    model = load_model(Path("hrn_pyg/checkpoints") / CHECKPOINTS[scene], device).eval()
    effects = scene_effects(scene)
    plain_s, fixed_s, steps_total = [], [], 0
    searches = reads = repeated = 0
    identical, max_diff = True, 0.0
    for seed in seeds:
        graph = episode_state(read_episode(Path("data") / scene / f"episode_{seed:06d}.npz"), start=START).to(device)
        forces = graph[NODE].force_seq.transpose(0, 1).contiguous()
        steps = forces.shape[0]
        simulator = FixedShapeSimulator(model, graph, config)

        def plain():
            with torch.no_grad():
                return rollout(model, graph, steps, forces, sleep=None, effects=effects)

        reference, result = plain(), simulator.rollout(steps, forces, effects=effects)  # warm-up (and recording)
        identical &= bool(torch.equal(reference, result.pos))
        max_diff = max(max_diff, float((reference - result.pos).abs().max()))
        searches, reads, repeated = searches + result.searches, reads + result.host_reads, repeated + result.repeated_steps
        seed_plain, seed_fixed = [], []
        for _ in range(repeats):  # interleaved
            seed_plain.append(clock(plain, device) / steps)
            seed_fixed.append(clock(lambda: simulator.rollout(steps, forces, effects=effects), device) / steps)
        plain_s.append(statistics.median(seed_plain))
        fixed_s.append(statistics.median(seed_fixed))
        steps_total += steps
    per100 = 100.0 / steps_total
    row = {"scene": scene, "checkpoint": CHECKPOINTS[scene], "seeds": seeds, "steps": steps_total,
           "leaves": int(graph[NODE].is_leaf.sum()), "plain_ms_per_step": 1e3 * statistics.median(plain_s),
           "fixed_ms_per_step": 1e3 * statistics.median(fixed_s),
           "plain_ms_per_step_by_seed": [1e3 * t for t in plain_s], "fixed_ms_per_step_by_seed": [1e3 * t for t in fixed_s],
           "searches_per_100_steps": searches * per100, "reads_per_100_steps": reads * per100,
           "repeated_per_100_steps": repeated * per100, "identical": identical, "max_abs_diff_m": max_diff}
    row["plain_over_fixed"] = row["plain_ms_per_step"] / row["fixed_ms_per_step"]
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="tower,cube_collision,cube_push,multi_material,soft_bounce")
    parser.add_argument("--seeds", default="8,18", help="validation seeds (seed %% 10 == 8)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cuda-graph", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    if any(s % 10 != 8 for s in seeds):
        raise SystemExit(f"--seeds must be validation seeds (seed % 10 == 8), got {seeds}")
    if args.repeats < 3:
        raise SystemExit("need --repeats >= 3")
    device = resolve_device(args.device)
    torch.set_num_threads(args.threads)
    config = FixedShapeConfig(cuda_graph=args.cuda_graph)
    rows = []
    for scene in args.scenes.split(","):
        if scene not in CHECKPOINTS:
            raise SystemExit(f"unknown scene {scene!r}; choose from {sorted(CHECKPOINTS)}")
        rows.append(run_scene(scene, seeds, args.repeats, device, config))
        r = rows[-1]
        print(f"{scene}: plain {r['plain_ms_per_step']:.2f} ms/step, fixed-shape {r['fixed_ms_per_step']:.2f} "
              f"({r['plain_over_fixed']:.2f}x), {r['searches_per_100_steps']:.0f} searches / "
              f"{r['reads_per_100_steps']:.0f} reads / {r['repeated_per_100_steps']:.0f} repeated per 100 steps, "
              f"identical {r['identical']}", flush=True)
    print("\n| scene | leaves | steps | plain ms / step | fixed-shape ms / step | plain / fixed | searches / 100 steps "
          "| reads / 100 steps | repeated / 100 steps | identical |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['leaves']} | {r['steps']} | {r['plain_ms_per_step']:.2f} | {r['fixed_ms_per_step']:.2f} "
              f"| {r['plain_over_fixed']:.2f} | {r['searches_per_100_steps']:.0f} | {r['reads_per_100_steps']:.0f} "
              f"| {r['repeated_per_100_steps']:.0f} | {r['identical']} |")
    out = args.out or f"benchmarks/results/fixed_shape_{device.type}.json"
    result = {
        "what": "shipped models on full validation episodes: plain rollout (sleep off) against fixed-shape steps",
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor(),
        "config": {"skin": config.skin, "check_every": config.check_every, "cuda_graph": config.cuda_graph},
        "statistic": f"median over seeds of the median of {args.repeats} interleaved runs, time / steps",
        "machine": {"cpus": os.cpu_count(), "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0]},
        "rows": rows,
    }
    atomic_write_json(out, result)
    print(f"wrote {out}")
    return result


if __name__ == "__main__":
    main()
