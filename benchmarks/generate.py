"""How fast is ground-truth generation? pybullet model steps per second per scene, and the
graph-building cost per step split by stage (k-means hierarchy, collision edges).

Run: ``python -m benchmarks.generate [--steps 40] [--repeats 3] [--out benchmarks/results/generate.json]``.
Median over repeats. Prints a markdown table and writes JSON (atomically).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.radius import collision_edges
from hrn_pyg.data.scene_file import SCENES, make_scene
from hrn_pyg.utils.files import atomic_write_json

#: Collision radius for the edge-search timing (m): about one voxel pitch, as the model uses.
COLLISION_RADIUS = 0.06


def bench_scene(name: str, steps: int, repeats: int) -> dict:
    step_rates, kmeans_s, edge_s, edge_counts = [], [], [], []
    for r in range(repeats):
        scene = make_scene(name, seed=r)
        try:
            x = scene.reset()
            leaf_mass, leaf_object = scene.leaf_mass.astype(np.float64), scene.leaf_object
            frames = [x]
            start = time.perf_counter()
            for t in range(steps):
                action, spins = scene.scripted_action(t)
                frames.append(scene.step(action, spins))
            step_rates.append(steps / (time.perf_counter() - start))
        finally:
            scene.close()
        start = time.perf_counter()
        parent = build_hierarchy(x, leaf_mass, leaf_object)
        kmeans_s.append(time.perf_counter() - start)
        obj = torch.as_tensor(leaf_object)
        start = time.perf_counter()
        counts = [collision_edges(torch.as_tensor(f, dtype=torch.float32), obj, COLLISION_RADIUS).shape[1]
                  for f in frames]
        edge_s.append((time.perf_counter() - start) / len(frames))
        edge_counts.append(float(np.mean(counts)))
    return {
        "scene": name,
        "leaves": int(len(x)),
        "nodes": int(len(parent)),
        "objects": int(leaf_object.max() + 1),
        "model_steps_per_s": float(np.median(step_rates)),
        "kmeans_hierarchy_ms": 1e3 * float(np.median(kmeans_s)),
        "collision_edges_ms_per_step": 1e3 * float(np.median(edge_s)),
        "mean_collision_edges": float(np.median(edge_counts)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="*", default=list(SCENES))
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="benchmarks/results/generate.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [bench_scene(name, args.steps, args.repeats) for name in args.scenes]
    header = ("| scene | leaves | nodes | model steps/s | k-means hierarchy (ms, once) "
              "| collision edges (ms/step) | edges/step |")
    print(header)
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['scene']} | {r['leaves']} | {r['nodes']} | {r['model_steps_per_s']:.0f} "
              f"| {r['kmeans_hierarchy_ms']:.1f} | {r['collision_edges_ms_per_step']:.2f} "
              f"| {r['mean_collision_edges']:.0f} |")
    payload = {
        "what": "pybullet generation speed and graph-building cost per stage",
        "steps": args.steps, "repeats": args.repeats, "statistic": "median over repeats",
        "substeps": 8, "physics_hz": 240, "collision_radius": COLLISION_RADIUS,
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version(),
                    "torch_threads": torch.get_num_threads()},
        "rows": rows,
    }
    atomic_write_json(args.out, payload)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
