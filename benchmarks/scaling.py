"""How a rollout step scales: time and peak memory against particle count and object count,
with the edge counts beside them, and the memory of the chunked fully-connected shape loss.

Three experiments, each measurement in its own fresh subprocess (so one measurement's freed
memory cannot hide the next one's peak):

1. **particles**: two rigid cubes of side 0.2 m side by side, voxelised with ``n`` leaves per
   side (pitch ``0.2 / (n - 1)``, ``2 n^3`` leaves from ~10^2 to ~2.10^4), collision radius
   ``1.6 x pitch`` (the facing layers, one pitch apart, collide, as a model trained at that
   resolution would be configured);
2. **objects**: ``O`` cubes of 5^3 leaves (pitch 0.05 m, radius 0.08 m) on a grid, neighbours
   one pitch apart, ``O`` from 1 to 64;
3. **shape loss**: :func:`hrn_pyg.losses.full_shape_loss` forward + backward on one object of
   ``L`` leaves, against the chunk size (and against ``L`` at a fixed chunk), next to a naive
   unchunked pairwise-distance loss.

The hierarchy is an octree over the voxel lattice (every node groups the 2x2x2 blocks of the
level below): the same shape of tree as the package's k-means hierarchy with branching 8 and
leaf groups of 8 (:mod:`hrn_pyg.data.hierarchy`), built in a vectorised way because thousands of
k-means calls would dominate the set-up of the large scenes. Weights are random (seed 0), with
the normaliser fitted on a real pybullet ``soft_bounce`` window; cost does not depend on them.

**Time**: median over ``--repeats`` (>= 5) of a ``--steps``-step rollout (:func:`hrn_pyg.sim.step.step`,
no gradient), per step, one torch thread. **Peak memory**: the growth of the process's resident
set during one step (or one loss forward + backward) after a warm-up: Linux's high-water mark
``VmHWM`` is reset to the current ``VmRSS`` by writing ``5`` to ``/proc/self/clear_refs``, the work
runs, and ``VmHWM - VmRSS(before)`` is the peak (page granularity). Each child runs with
glibc's ``MALLOC_MMAP_THRESHOLD_=65536``, so every tensor of 64 KiB or more is mapped on
allocation and unmapped on free: the resident set then follows the live tensors (the cost of
Python objects and small tensors is below this method's resolution). The shape loss is timed as
the median of 3 runs (its memory is the point).

Run: ``python -m benchmarks.scaling [--repeats 5] [--steps 3] [--threads 1]
[--sections particles,objects,shape]``. Prints markdown tables, writes
``benchmarks/results/scaling.json`` and ``benchmarks/results/scaling.png``. With ``--sections``
naming some of the three experiments, only those run; the others' rows are kept from the JSON
already at ``--out``, and ``measured`` in the JSON says when and under what load each section
was measured.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.viz import save_figure

from benchmarks.common import cubes_scene, lattice

#: cube side (m) of the particle-count experiment
CUBE_SIDE = 0.2
#: collision radius as a multiple of the pitch (face neighbours and in-plane diagonals)
RADIUS_OVER_PITCH = 1.6
#: leaves per side of each cube in the particle-count experiment (2 n^3 leaves)
SIDES = (4, 6, 8, 11, 14, 18, 22)
#: object counts of the object experiment (cubes of OBJECT_SIDE^3 leaves)
OBJECTS = (1, 2, 4, 8, 16, 32, 64)
OBJECT_SIDE, OBJECT_PITCH, OBJECT_RADIUS = 5, 0.05, 0.08
#: the three experiments, as ``--sections`` names them
SECTIONS = ("particles", "objects", "shape")
#: shape loss: leaves per side of the big object, chunk sizes, and sides at a fixed chunk
SHAPE_SIDE = 16
CHUNKS = (32, 128, 512, 2048, 4096)
SHAPE_SIDES = (8, 12, 16, 20)
#: timed runs of the shape loss (after a warm-up); its memory, not its time, is the point here
SHAPE_REPEATS = 3
#: glibc setting of every child: allocations of 64 KiB and more are mmapped and returned to the
#: system when freed, so the resident set follows the live tensors and its high-water mark is
#: the peak (with the default dynamic threshold, freed blocks stay in the heap and hide peaks)
CHILD_ENV = {"MALLOC_MMAP_THRESHOLD_": "65536"}
FIXED_CHUNK = 512
#: the naive loss holds [L, L, 3] tensors; skip it above this many leaves
NAIVE_MAX_LEAVES = 4096


# ---------------------------------------------------------------------------------------------
# measurement helpers (run inside the child process)


def _status() -> dict[str, int]:
    text = Path("/proc/self/status").read_text()
    return {k: int(re.search(rf"{k}:\s+(\d+)", text).group(1)) for k in ("VmRSS", "VmHWM")}


def peak_growth_mb(fn) -> float:
    """MB by which the resident set peaks above its level before ``fn()`` runs."""
    Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current VmRSS
    before = _status()["VmRSS"]
    fn()
    return (_status()["VmHWM"] - before) / 1024.0


def median_seconds(fn, repeats: int) -> tuple[float, list[float]]:
    fn()  # warm-up
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs), runs


def child_step(args: argparse.Namespace) -> dict:
    from hrn_pyg.data.graph import (
        ANCESTOR_TO_DESCENDANT,
        COLLISION,
        LEAF_TO_ANCESTOR,
        NODE,
        WITHIN_SIBLINGS,
        build_structure,
        set_state,
    )
    from hrn_pyg.nn.hrn import HRN, HRNConfig
    from hrn_pyg.sim.step import build_inputs, run_network, step

    leaves, leaf_object, parent = cubes_scene(args.n, args.objects, args.pitch,
                                              per_row=args.objects if args.row else None)
    n_obj = args.objects
    structure = build_structure(torch.as_tensor(parent), torch.full((len(leaves),), 1.0 / args.n**3),
                                torch.as_tensor(leaf_object), torch.zeros(n_obj, dtype=torch.long), torch.ones(n_obj))
    x = torch.as_tensor(leaves, dtype=torch.float32)
    drop = torch.tensor([0.0, 0.0, 9.81 / 900.0])
    graph = set_state(structure, x + 3 * drop, x + 2 * drop, x, radius=args.radius)
    torch.manual_seed(0)
    model = HRN(HRNConfig(collision_radius=args.radius)).eval()
    model.normalizer.load_state_dict(torch.load(args.normalizer, weights_only=True))

    def rollout_steps() -> None:
        g = graph
        with torch.no_grad():
            for _ in range(args.steps):  # time steps
                g = step(model, g).graph

    def network_only() -> None:
        with torch.no_grad():
            run_network(model, build_inputs(model, graph))

    seconds, runs = median_seconds(rollout_steps, args.repeats)
    net_seconds, _ = median_seconds(network_only, args.repeats)
    with torch.no_grad():
        peak = peak_growth_mb(lambda: step(model, graph))
    store = graph[NODE]
    edges = {"collision": graph[COLLISION].edge_index.size(1),
             "l2a": graph[LEAF_TO_ANCESTOR].edge_index.size(1),
             "ws": graph[WITHIN_SIBLINGS].edge_index.size(1),
             "a2d": graph[ANCESTOR_TO_DESCENDANT].edge_index.size(1)}
    return {"n_side": args.n, "objects": n_obj, "pitch": args.pitch, "radius": args.radius,
            "leaves": len(leaves), "nodes": int(store.num_nodes), "edges": edges, "edges_total": sum(edges.values()),
            "depth": int(store.depth.max()), "ms_per_step": 1e3 * seconds / args.steps,
            "ms_per_step_runs": [1e3 * t / args.steps for t in runs],
            "network_ms": 1e3 * net_seconds, "peak_mb_per_step": peak}


def naive_shape_loss(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """All pairs at once: the ``[L, L]`` distance matrices (what chunking avoids)."""
    d_pred = (pred[:, None] - pred[None]).pow(2).sum(-1).add(1e-12).sqrt()
    d_true = (true[:, None] - true[None]).pow(2).sum(-1).add(1e-12).sqrt()
    n = pred.size(0)
    return (d_pred - d_true).pow(2).sum() / (n * (n - 1))


def child_shape(args: argparse.Namespace) -> dict:
    from hrn_pyg.losses import full_shape_loss

    true = torch.as_tensor(lattice(args.n) * 0.01, dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    base = true + 1e-3 * torch.randn(true.shape, generator=gen)
    group = torch.zeros(len(true), dtype=torch.long)

    def forward_backward() -> None:
        pred = base.clone().requires_grad_(True)
        loss = naive_shape_loss(pred, true) if args.chunk == 0 else full_shape_loss(pred, true, group, args.chunk)
        loss.backward()

    seconds, _ = median_seconds(forward_backward, SHAPE_REPEATS)
    peak = peak_growth_mb(forward_backward)
    return {"leaves": len(true), "chunk": args.chunk or "naive", "ms": 1e3 * seconds, "peak_mb": peak,
            "pairs": len(true) * (len(true) - 1)}


# ---------------------------------------------------------------------------------------------
# parent: run the children, report


def run_child(extra: list[str], args: argparse.Namespace) -> dict:
    cmd = [sys.executable, "-m", "benchmarks.scaling", "--threads", str(args.threads), "--repeats", str(args.repeats),
           "--steps", str(args.steps), *extra]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, env={**os.environ, **CHILD_ENV},
                          cwd=Path(__file__).resolve().parents[1])  # the checkout, where benchmarks/ is a package
    if done.returncode != 0:
        raise RuntimeError(f"child {' '.join(extra)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def fit_normalizer_file(path: str) -> None:
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.nn.normalizer import Normalizer, fit_normalizer
    from hrn_pyg.sampling.ensemble import episode_state

    norm = fit_normalizer([episode_state(simulate_episode("soft_bounce", 0, steps=12), start=2, steps=8)], Normalizer())
    torch.save(norm.state_dict(), path)


def kept_sections(path: Path, names: list[str]) -> dict:
    """The rows of the sections ``names`` (and their ``measured`` records) from the JSON at
    ``path``, for a run that measures the other sections only."""
    if not names:
        return {}
    if not path.is_file():
        raise SystemExit(f"--sections leaves out {', '.join(names)}, but {path} holds no earlier rows to keep")
    old = json.loads(path.read_text())
    keys = {"particles": ("particles",), "objects": ("objects",), "shape": ("shape_loss_chunks", "shape_loss_sizes")}
    kept = {key: old[key] for name in names for key in keys[name]}
    kept["measured"] = {name: old.get("measured", {}).get(name, "with the other sections") for name in names}
    return kept


def loglog_slope(x: list[float], y: list[float]) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def plot(particles: list[dict], objects: list[dict], chunks: list[dict], sizes: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    ax = axes[0]
    L = np.array([r["leaves"] for r in particles], dtype=float)
    t = np.array([r["ms_per_step"] for r in particles])
    E = np.array([r["edges_total"] for r in particles], dtype=float)
    ax.loglog(L, t, "o-", label="time per step (ms)")
    ax.loglog(L, [r["peak_mb_per_step"] for r in particles], "s-", label="peak memory growth (MB)")
    ax.loglog(L, t[0] * L / L[0], "k:", lw=0.8, label="∝ L")
    ax.loglog(L, t[0] * (L / L[0]) ** 2, "k--", lw=0.8, label="∝ L²")
    ax.loglog(L, t[0] * E / E[0], "g-.", lw=0.8, label="∝ edges")
    ax.set_xlabel("leaves L (two cubes, pitch shrinking)")
    ax.set_title("particle count")
    ax.legend(fontsize=7)
    ax2 = ax.twinx()
    for key, style in (("collision", "c"), ("l2a", "m"), ("ws", "y")):
        ax2.loglog(L, [r["edges"][key] for r in particles], style + "x", ms=4, alpha=0.6, label=f"{key} edges")
    ax2.set_ylabel("edges")
    ax2.legend(fontsize=7, loc="lower right")

    ax = axes[1]
    O = [r["objects"] for r in objects]
    ax.loglog(O, [r["ms_per_step"] for r in objects], "o-", label="time per step (ms)")
    ax.loglog(O, [r["peak_mb_per_step"] for r in objects], "s-", label="peak memory growth (MB)")
    ax.loglog(O, [objects[0]["ms_per_step"] * o for o in O], "k:", lw=0.8, label="∝ objects")
    ax.set_xlabel(f"objects ({OBJECT_SIDE}³ leaves each)")
    ax.set_title("object count")
    ax.legend(fontsize=7)

    ax = axes[2]
    ch = [r for r in chunks if r["chunk"] != "naive"]
    ax.loglog([r["chunk"] for r in ch], [r["peak_mb"] for r in ch], "o-",
              label=f"chunked, L={ch[0]['leaves']}: peak MB")
    naive = [r for r in chunks if r["chunk"] == "naive"]
    if naive:
        ax.axhline(naive[0]["peak_mb"], color="r", ls="--", label=f"naive [L, L], L={naive[0]['leaves']}")
    ax.set_xlabel("chunk size (rows)")
    ax.set_ylabel("peak memory growth, forward + backward (MB)")
    ax.set_title("fully-connected shape loss")
    ax3 = ax.twiny()
    sz = [r for r in sizes if r["chunk"] != "naive"]
    ax3.loglog([r["leaves"] for r in sz], [r["peak_mb"] for r in sz], "g^-", label=f"chunk {FIXED_CHUNK}, against L (top axis)")
    nz = [r for r in sizes if r["chunk"] == "naive"]
    ax3.loglog([r["leaves"] for r in nz], [r["peak_mb"] for r in nz], "rv:", label="naive, against L (top axis)")
    ax3.set_xlabel("leaves L of the object")
    lines = ax.get_legend_handles_labels()
    lines3 = ax3.get_legend_handles_labels()
    ax.legend(lines[0] + lines3[0], lines[1] + lines3[1], fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> dict | None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sides", default=",".join(map(str, SIDES)))
    parser.add_argument("--objects", default=",".join(map(str, OBJECTS)))
    parser.add_argument("--chunks", default=",".join(map(str, CHUNKS)), help="shape-loss chunk sizes")
    parser.add_argument("--shape-sides", default=",".join(map(str, SHAPE_SIDES)),
                        help=f"leaves per side of the shape-loss object at chunk {FIXED_CHUNK}")
    parser.add_argument("--out", default="benchmarks/results/scaling.json")
    parser.add_argument("--plot", default="benchmarks/results/scaling.png")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help="experiments to run (particles, objects, shape); the others' rows are kept "
                             "from the JSON at --out")
    parser.add_argument("--child", choices=("step", "shape"), help=argparse.SUPPRESS)
    parser.add_argument("--n", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--n-objects", type=int, dest="n_objects", help=argparse.SUPPRESS)
    parser.add_argument("--pitch", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--radius", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--row", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--chunk", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--normalizer", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats < 5:
        raise SystemExit("--repeats must be >= 5 (median of at least 5 runs)")
    torch.set_num_threads(args.threads)
    if args.child == "step":
        args.objects = args.n_objects
        print(json.dumps(child_step(args)))
        return None
    if args.child == "shape":
        print(json.dumps(child_shape(args)))
        return None

    sections = [x for x in args.sections.split(",") if x]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown or not sections:
        raise SystemExit(f"--sections: choose from {', '.join(SECTIONS)}, got {args.sections!r}")
    kept = kept_sections(Path(args.out), [x for x in SECTIONS if x not in sections])
    if "particles" not in sections:
        args.sides = ""
    if "objects" not in sections:
        args.objects = ""
    if "shape" not in sections:
        args.chunks = args.shape_sides = ""
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        norm_path = os.path.join(tmp, "normalizer.pt")
        fit_normalizer_file(norm_path)
        particles = []
        for n in (int(s) for s in args.sides.split(",") if s):
            pitch = CUBE_SIDE / (n - 1)
            r = run_child(["--child", "step", "--n", str(n), "--n-objects", "2", "--row", "--pitch", f"{pitch:.9g}",
                           "--radius", f"{RADIUS_OVER_PITCH * pitch:.9g}", "--normalizer", norm_path], args)
            particles.append(r)
            print(f"particles: {r['leaves']:6d} leaves {r['edges_total']:8d} edges {r['ms_per_step']:9.2f} ms/step "
                  f"{r['peak_mb_per_step']:8.1f} MB", flush=True)
        objects = []
        for o in (int(s) for s in args.objects.split(",") if s):
            r = run_child(["--child", "step", "--n", str(OBJECT_SIDE), "--n-objects", str(o), "--pitch",
                           str(OBJECT_PITCH), "--radius", str(OBJECT_RADIUS), "--normalizer", norm_path], args)
            objects.append(r)
            print(f"objects: {o:3d} ({r['leaves']:6d} leaves, {r['edges']['collision']} collision edges) "
                  f"{r['ms_per_step']:9.2f} ms/step {r['peak_mb_per_step']:8.1f} MB", flush=True)
    chunks = []
    for c in (*(int(c) for c in args.chunks.split(",") if c), 0):
        r = run_child(["--child", "shape", "--n", str(SHAPE_SIDE), "--chunk", str(c)], args)
        chunks.append(r)
        print(f"shape loss L={r['leaves']} chunk {r['chunk']}: {r['ms']:.1f} ms, {r['peak_mb']:.1f} MB", flush=True)
    sizes = []
    for n in (int(x) for x in args.shape_sides.split(",") if x):
        for c in (FIXED_CHUNK, 0):
            if c == 0 and n**3 > NAIVE_MAX_LEAVES:
                continue
            r = run_child(["--child", "shape", "--n", str(n), "--chunk", str(c)], args)
            sizes.append(r)
            print(f"shape loss L={r['leaves']} chunk {r['chunk']}: {r['ms']:.1f} ms, {r['peak_mb']:.1f} MB", flush=True)

    particles = kept.get("particles", particles)
    objects = kept.get("objects", objects)
    chunks, sizes = kept.get("shape_loss_chunks", chunks), kept.get("shape_loss_sizes", sizes)
    L = [r["leaves"] for r in particles]
    slopes = {
        "time_vs_leaves": loglog_slope(L, [r["ms_per_step"] for r in particles]),
        "edges_vs_leaves": loglog_slope(L, [r["edges_total"] for r in particles]),
        "time_vs_edges": loglog_slope([r["edges_total"] for r in particles], [r["ms_per_step"] for r in particles]),
        "memory_vs_leaves": loglog_slope(L, [max(r["peak_mb_per_step"], 1e-3) for r in particles]),
        "time_vs_objects": loglog_slope([r["objects"] for r in objects], [r["ms_per_step"] for r in objects]),
    }
    for r in particles + objects:
        r["us_per_edge"] = 1e3 * r["ms_per_step"] / r["edges_total"]
    print()
    print("| leaves | nodes | depth | collision | L2A | WS | A2D | ms/step | network ms | µs/edge | peak MB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in particles:
        e = r["edges"]
        print(f"| {r['leaves']} | {r['nodes']} | {r['depth']} | {e['collision']} | {e['l2a']} | {e['ws']} | {e['a2d']} | "
              f"{r['ms_per_step']:.1f} | {r['network_ms']:.1f} | {r['us_per_edge']:.2f} | {r['peak_mb_per_step']:.1f} |")
    print()
    print("| objects | leaves | collision | L2A | WS | A2D | ms/step | µs/edge | peak MB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in objects:
        e = r["edges"]
        print(f"| {r['objects']} | {r['leaves']} | {e['collision']} | {e['l2a']} | {e['ws']} | {e['a2d']} | "
              f"{r['ms_per_step']:.1f} | {r['us_per_edge']:.2f} | {r['peak_mb_per_step']:.1f} |")
    print()
    print("| shape loss: leaves | chunk | forward+backward ms | peak MB |")
    print("|---:|---:|---:|---:|")
    for r in chunks + sizes:
        print(f"| {r['leaves']} | {r['chunk']} | {r['ms']:.1f} | {r['peak_mb']:.1f} |")
    print()
    print("log-log slopes: " + ", ".join(f"{k} {v:.2f}" for k, v in slopes.items()))
    result = {
        "what": "time and peak memory of a rollout step against particles and objects; chunked shape loss memory",
        "statistic": "median over repeats of a `steps`-step rollout, per step; one subprocess per measurement",
        "memory": "peak growth of VmRSS during one step / one loss forward+backward (VmHWM reset via "
                  "/proc/self/clear_refs), MB",
        "hierarchy": "octree over the voxel lattice (branching 8, leaf group 8)",
        "weights": "random init (seed 0), normaliser fitted on a pybullet soft_bounce window",
        "repeats": args.repeats, "steps": args.steps,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0],
                    "note": "2 shared cores, loaded by other jobs while this ran"},
        "measured": {**kept.get("measured", {}),
                     **{x: {"utc": time.strftime("%Y-%m-%dT%H:%MZ", time.gmtime()),
                            "load_average_1m": os.getloadavg()[0]} for x in sections}},
        "particles": particles, "objects": objects, "shape_loss_chunks": chunks, "shape_loss_sizes": sizes,
        "loglog_slopes": slopes, "total_seconds": round(time.perf_counter() - t_start, 1),
    }
    from hrn_pyg.utils.files import atomic_write_json

    atomic_write_json(args.out, result)
    plot(particles, objects, chunks, sizes, Path(args.plot))
    return result


if __name__ == "__main__":
    main()
