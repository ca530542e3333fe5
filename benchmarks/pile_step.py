"""A step of a pile against pybullet's: time per model step as the object count grows.

For each object count ``N`` in ``--counts`` a scene of ``N`` meshes the generalist never trained
on (``--meshes``, default pybullet_data's duck and torus, the validation meshes of
docs/generalist.md) is written as a scene file: the objects stand on a square grid 0.4 m apart
in layers 0.4 m apart, each turned by a random yaw and scaled to a drawn size, and fall into a
pile. pybullet runs one episode of it (``--steps`` model steps); its time per model step is the
median over those steps of one ``Scene.step`` (``substeps`` physics steps, the leaves read
back). The model rolls out the same episode from step 2 for ``--steps - 2`` steps, sleeping off
(every object awake, the network alone), one torch thread; its time per step is the median over
``--repeats`` rollouts of the rollout's seconds per step. Each model of ``--model`` is timed as
it is loaded and, when it averages over the lattice's symmetries (``mirror_average``), also as
one pass (the same weights, ``mirror_average`` off), so the cost of the average is read off one
run. The position MSE of the one-pass rollout against the averaged one at the last step says
how far apart they are on this scene. With ``--compile`` each model is also timed in one pass
as fixed-shape steps compiled by ``torch.compile``
(:class:`hrn_pyg.sim.fixed_shape.FixedShapeSimulator`, ``compile=True``): the seconds of its
first rollout (the compilation) are reported beside its median time per step, and its largest
difference from the eager one-pass rollout says it computes the same positions.

Run: ``python benchmarks/pile_step.py [--counts 2,5,10,20,40] [--material rigid] [--model shapes]
[--compile] [--out benchmarks/results/pile_step_rigid.json]``. Prints a markdown table and writes JSON
atomically. Time only on a quiet machine.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from pathlib import Path

import torch

import hrn_pyg
from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.fixed_shape import FixedShapeConfig, FixedShapeSimulator
from hrn_pyg.utils.files import atomic_write_json

DEFAULT_MESHES = ("pybullet_data:duck_vhacd.obj", "pybullet_data:torus/torus_textured.obj")
#: grid spacing and layer height of the starting arrangement (m); with sizes up to
#: :data:`MAX_SIZE` and yaw-only turns no two bounding boxes overlap
SPACING = 0.4
MAX_SIZE = 0.25


def pile_scene_text(count: int, material: str, meshes: tuple[str, ...], pitch: float, steps: int) -> str:
    """A scene file of ``count`` objects on a grid of layers that fall into a pile."""
    side = max(1, math.ceil(math.sqrt(count / 2)))  # two layers or more
    lines = [f"steps = {steps}", f"pitch = {pitch}", "rolling_friction = 0.03", ""]
    mesh_list = "[" + ", ".join(f'"{m}"' for m in meshes) + "]"
    for i in range(count):
        layer, cell = divmod(i, side * side)
        row, col = divmod(cell, side)
        x = (col - (side - 1) / 2) * SPACING
        y = (row - (side - 1) / 2) * SPACING
        z = 0.15 + layer * SPACING
        lines += ["[[objects]]", f"mesh = {mesh_list}", f'material = "{material}"',
                  f"size = {{ min = 0.15, max = {MAX_SIZE} }}", "mass = { min = 0.3, max = 1.5 }",
                  f"position = [{x:.3f}, {y:.3f}, {z:.3f}]", "yaw = { min = 0, max = 360 }"]
        if material == "soft":
            lines.append("stiffness = { min = 0.4, max = 0.7 }")
        lines.append("")
    return "\n".join(lines)


def time_pybullet(spec, seed: int) -> tuple[dict, float]:
    """One episode and pybullet's median seconds per model step."""
    durations: list[float] = []

    def timed(sim) -> None:
        step = sim.step

        def wrapped(*args, **kwargs):
            start = time.perf_counter()
            out = step(*args, **kwargs)
            durations.append(time.perf_counter() - start)
            return out

        sim.step = wrapped

    episode = simulate_episode(spec, seed, after_reset=timed)
    return episode, statistics.median(durations)


def time_rollout(model, state, steps: int, repeats: int) -> tuple[float, torch.Tensor]:
    """Median seconds per step of a ``steps``-step rollout (sleeping off) and its positions."""
    seconds = []
    with torch.no_grad():
        hrn_pyg.rollout(model, state, 2, sleep=None)  # warm-up
        for _ in range(repeats):
            start = time.perf_counter()
            pos = hrn_pyg.rollout(model, state, steps, sleep=None)
            seconds.append((time.perf_counter() - start) / steps)
    return statistics.median(seconds), pos


def time_compiled(model, state, steps: int, repeats: int) -> tuple[float, float, torch.Tensor]:
    """Seconds of the first compiled fixed-shape rollout, the median seconds per step of
    ``repeats`` more, and their positions."""
    torch._dynamo.reset()  # each count compiles afresh, as in a new process (not past the recompile limit)
    simulator = FixedShapeSimulator(model, state, FixedShapeConfig(compile=True))
    with torch.no_grad():
        start = time.perf_counter()
        simulator.rollout(steps)
        first = time.perf_counter() - start
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            pos = simulator.rollout(steps).pos
            seconds.append((time.perf_counter() - start) / steps)
    return first, statistics.median(seconds), pos


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", default="2,5,10,20,40", help="object counts, comma-separated")
    parser.add_argument("--material", choices=("rigid", "soft"), default="rigid")
    parser.add_argument("--model", action="append", default=None, help="shipped name or path (repeatable; default shapes)")
    parser.add_argument("--meshes", default=",".join(DEFAULT_MESHES), help="meshes drawn per object, comma-separated")
    parser.add_argument("--pitch", type=float, default=0.05)
    parser.add_argument("--steps", type=int, default=40, help="model steps of the episode")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--compile", action="store_true",
                        help="also time one pass as compiled fixed-shape steps (a minute or so to compile per count)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    if args.repeats < 1 or args.steps < 4:
        raise SystemExit("--repeats must be >= 1 and --steps >= 4")
    torch.set_num_threads(args.threads)
    counts = [int(c) for c in args.counts.split(",") if c]
    meshes = tuple(m for m in args.meshes.split(",") if m)
    models = {name: load_model(name) for name in (args.model or ["shapes"])}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for count in counts:
            path = Path(tmp) / f"pile_{count}.toml"
            path.write_text(pile_scene_text(count, args.material, meshes, args.pitch, args.steps))
            spec = read_scene_file(path)
            episode, bullet_s = time_pybullet(spec, args.seed)
            leaves = int(episode["positions"].shape[1])
            state = episode_state(episode, start=2, steps=args.steps - 2)
            row = {"objects": count, "leaves": leaves, "pybullet_ms": 1e3 * bullet_s, "models": {}}
            for name, model in models.items():
                variants = {"as loaded": model}
                if getattr(model.config, "mirror_average", False):
                    variants["one pass"] = with_applied_options(model, mirror_average=False).eval()
                results, positions = {}, {}
                for label, variant in variants.items():
                    seconds, positions[label] = time_rollout(variant.eval(), state, args.steps - 2, args.repeats)
                    results[label] = {"ms": 1e3 * seconds, "x_pybullet": seconds / bullet_s}
                one_pass = "one pass" if "one pass" in variants else "as loaded"
                if one_pass == "one pass":
                    results["one pass"]["mse_to_averaged_last_step"] = float(
                        ((positions["one pass"][-1] - positions["as loaded"][-1]) ** 2).sum(-1).mean())
                if args.compile:
                    eager = positions[one_pass]
                    first, seconds, pos = time_compiled(variants[one_pass].eval(), state, args.steps - 2, args.repeats)
                    results["compiled"] = {"ms": 1e3 * seconds, "x_pybullet": seconds / bullet_s,
                                           "compile_s": first,
                                           "max_abs_diff_to_eager_m": float((pos - eager).abs().max())}
                row["models"][name] = results
            rows.append(row)
            print(f"{count} objects, {leaves} leaves: pybullet {row['pybullet_ms']:.2f} ms; "
                  + "; ".join(f"{n} {lab} {r['ms']:.2f} ms" for n, res in row["models"].items() for lab, r in res.items()),
                  flush=True)
    header = "| objects | leaves | pybullet (ms) | " + " | ".join(
        f"{n} {lab} (ms, x pybullet)" for n, res in rows[0]["models"].items() for lab in res) + " |"
    print()
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for row in rows:
        cells = [f"{r['ms']:.2f} ({r['x_pybullet']:.2f}x)" for res in row["models"].values() for r in res.values()]
        print(f"| {row['objects']} | {row['leaves']} | {row['pybullet_ms']:.2f} | " + " | ".join(cells) + " |")
    if args.out:
        atomic_write_json(args.out, {"material": args.material, "pitch": args.pitch, "steps": args.steps,
                                     "repeats": args.repeats, "threads": args.threads, "seed": args.seed,
                                     "meshes": list(meshes), "torch": torch.__version__, "rows": rows})


if __name__ == "__main__":
    main()
