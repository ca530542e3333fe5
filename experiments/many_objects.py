"""Many objects of meshes a model never saw: its errors and time per step against the object count.

For each object count ``N`` of ``--counts`` (default 2, 10, 20, 40) the scene is the pile of
``benchmarks/common.py`` (:func:`~benchmarks.common.pile_scene_text`): ``N`` meshes drawn per object from
``--meshes`` (default pybullet_data's duck and torus, the generalist's validation meshes; pass
the test meshes only for the one final score), standing on a grid of layers, turned by a random
yaw, falling into a pile. ``--episodes`` seeds per count (``--seed``, ``--seed`` + 1, ...) are
simulated by pybullet and kept under ``--work`` (an episode file there is reused, so a stopped
run resumes; ``experiments/episode_cache.py``).

**Errors.** The model is rolled out with the package's evaluation
(:func:`hrn_pyg.evaluate.evaluate_model`: the network alone, no object sleeps, each rollout
batched) from windows starting at step 2 and then every ``--stride`` steps of each episode; the
position and shape MSE at each horizon of ``--horizons`` (default 15 and 50) are summarised as
mean and standard error over the windows (:func:`hrn_pyg.evaluate.summarise`; a window whose
rollout left the finite numbers is counted as diverged, not averaged). Each count's errors are
also given as a ratio to those of the smallest count (2 objects by default).

**Time.** On the first episode of each count, in the same process: pybullet's median time per
model step (the episode simulated again, each ``Scene.step`` timed), and the model's seconds per
step of the rollout from step 2 to the episode's end, sleeping off (every object awake), the
median of ``--repeats`` rollouts after a warm-up, on ``--threads`` torch threads (default one).

The model's domain check runs on each count's episodes; its warning (e.g. more objects than it
was trained with) is printed and kept in the JSON.

**Rest.** With ``--rest-steps N`` (0: off) every episode of a count that ends with every object at
rest (:func:`hrn_pyg.evaluate.rest.objects_at_rest` of pybullet's positions) is rolled out ``N``
steps from its last state, the network alone, and judged by the package's stability check
(:func:`experiments.scores.rest_check`: finite, within 50 m, no leaf more than one pitch
under the ground, rigid shapes within 1 %, drift under 5 cm). An episode that has not come to
rest by its end is counted as such (give a longer ``--steps``, e.g. 240, for a pile to settle).

Run (validation meshes; time on a quiet machine)::

    python -m experiments.many_objects --model shapes --counts 2,10,20,40 --episodes 4 \\
        --out benchmarks/results/many_objects_shapes.json

Prints a markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import hashlib
import platform
import time
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.checkpoints.domain import dataset_domain, report_outside
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.evaluate import evaluate_model, summarise
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

from benchmarks.common import DEFAULT_MESHES, pile_scene_text, time_rollout
from experiments.episode_cache import cached_episodes, episode_leaves, windows_of
from experiments.scores import rest_check

ERRORS = ("position", "shape")


def absolute_mesh(mesh: str) -> str:
    """A mesh file given relative to the working folder, made absolute (the scene file is read
    from the cache folder); primitives and ``pybullet_data:`` meshes as they are."""
    path = Path(mesh)
    return str(path.resolve()) if not mesh.startswith("pybullet_data:") and path.is_file() else mesh


def run_count(model, count: int, args, meshes: tuple[str, ...]) -> dict:
    text = pile_scene_text(count, args.material, meshes, args.pitch, args.steps)
    folder = Path(args.work) / f"objects_{count}_{hashlib.sha256(text.encode()).hexdigest()[:10]}"
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "pile.toml", text)
    spec = read_scene_file(folder / "pile.toml")
    seeds = list(range(args.seed, args.seed + args.episodes))
    made = cached_episodes(spec, folder, seeds)
    outside = report_outside(model, dataset_domain(folder), prefix=f"many_objects ({count} objects): warning: ")
    windows = windows_of(folder, made["seeds"], max(args.horizons), args.stride)
    errors = summarise(evaluate_model(model, windows, args.horizons))
    episode = made["timed_episode"]
    steps = int(episode["forces"].shape[0]) - 2
    seconds, _ = time_rollout(model, episode_state(episode, start=2, steps=steps), steps, args.repeats)
    leaves = [episode_leaves(folder / f"episode_{s:06d}.npz") for s in made["seeds"]]
    rest = rest_rows(model, folder, made["seeds"], args.rest_steps) if args.rest_steps else None
    return {"rest": rest, "objects": count, "leaves": int(episode["positions"].shape[1]), "leaves_mean": float(np.mean(leaves)),
            "episodes": len(made["seeds"]), "seeds": made["seeds"], "rejected": made["rejected"],
            "made": made["made"], "windows": len(windows), "folder": str(folder),
            "pybullet_ms": 1e3 * made["pybullet_s_per_step"], "model_ms": 1e3 * seconds,
            "x_pybullet": seconds / made["pybullet_s_per_step"], "outside": outside, "errors": errors}


def rest_rows(model, folder: Path, seeds: list[int], steps: int) -> list[dict]:
    """The stability check of ``steps`` steps from the resting end of each episode of ``seeds``
    (:func:`experiments.scores.rest_check`; an episode not at rest at its end: a row saying so)."""
    rows = []
    for seed in seeds:
        report = rest_check(model, load_episode(folder / f"episode_{seed:06d}.npz"), steps)
        if report is None:
            rows.append({"seed": seed, "at_rest": False})
            continue
        rows.append({"seed": seed, "at_rest": True, **report})
        print(f"  rest, seed {seed}: holds {report['holds']}, drift {report.get('rest_drift', float('nan')):.3g} m",
              flush=True)
    return rows


def rest_summary(rows: list[dict]) -> str:
    """``held / at rest (not at rest)`` and the largest drift of the episodes at rest."""
    at_rest = [r for r in rows if r["at_rest"]]
    passed = sum(bool(r.get("holds")) for r in at_rest)
    drift = max((r.get("rest_drift", float("nan")) for r in at_rest), default=float("nan"))
    return f"{passed} / {len(at_rest)} ({len(rows) - len(at_rest)} not at rest), drift <= {drift:.3g} m"


def add_ratios(rows: list[dict], horizons: tuple[int, ...]) -> None:
    """Each row's mean errors over those of the first row (the smallest count)."""
    base = rows[0]["errors"]
    for row in rows:
        row["ratio_to"] = rows[0]["objects"]
        for m in ERRORS:
            for h in horizons:
                key = f"t+{h}"
                row[f"ratio_{m}@{h}"] = row["errors"][m][key]["mean"] / base[m][key]["mean"]


def markdown(rows: list[dict], horizons: tuple[int, ...]) -> str:
    first = rows[0]["objects"]
    head = ["objects", "leaves", "pybullet ms/step", "model ms/step", "model / pybullet"]
    for h in horizons:
        head += [f"position MSE t+{h}", f"x {first} objects"]
    head.append("diverged")
    if any(row.get("rest") is not None for row in rows):
        head.append("rest: holds / at rest, largest drift")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [str(r["objects"]), str(r["leaves"]), f"{r['pybullet_ms']:.2f}", f"{r['model_ms']:.2f}",
                 f"{r['x_pybullet']:.2f}x"]
        for h in horizons:
            s = r["errors"]["position"][f"t+{h}"]
            sem = f" ± {s['sem']:.2g}" if np.isfinite(s["sem"]) else ""
            cells += [f"{s['mean']:.3g}{sem}", f"{r[f'ratio_position@{h}']:.2f}x"]
        cells.append(str(r["errors"]["position"][f"t+{max(horizons)}"]["diverged"]))
        if any(row.get("rest") is not None for row in rows):
            cells.append(rest_summary(r["rest"]) if r.get("rest") is not None else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="shapes", help="a shipped model's name or a checkpoint path")
    parser.add_argument("--counts", default="2,10,20,40", help="object counts, comma-separated; the first is "
                        "the one the others' errors are divided by")
    parser.add_argument("--meshes", default=",".join(DEFAULT_MESHES),
                        help="meshes drawn per object, comma-separated (default: the validation meshes)")
    parser.add_argument("--material", choices=("rigid", "soft"), default="rigid")
    parser.add_argument("--pitch", type=float, default=0.05)
    parser.add_argument("--steps", type=int, default=60, help="model steps per episode (at least the longest "
                        "horizon + 2)")
    parser.add_argument("--episodes", type=int, default=4, help="episodes per object count")
    parser.add_argument("--seed", type=int, default=0, help="the first episode's seed")
    parser.add_argument("--horizons", default="15,50")
    parser.add_argument("--stride", type=int, default=10, help="steps between window starts in an episode")
    parser.add_argument("--repeats", type=int, default=5, help="timed rollouts per count (median)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--work", default="runs/many_objects", help="where the episodes are kept")
    parser.add_argument("--rest-steps", type=int, default=0,
                        help="steps of the stability check from each episode's resting end (0: no rest section)")
    parser.add_argument("--out", default="benchmarks/results/many_objects.json")
    args = parser.parse_args(argv)
    args.horizons = tuple(int(h) for h in args.horizons.split(",") if h)
    counts = [int(c) for c in args.counts.split(",") if c]
    meshes = tuple(absolute_mesh(m) for m in args.meshes.split(",") if m)
    if not counts or min(counts) < 1 or not meshes:
        parser.error("--counts needs positive counts and --meshes at least one mesh")
    if not args.horizons or min(args.horizons) < 1 or args.steps < max(args.horizons) + 2:
        parser.error(f"--steps must be at least the longest horizon + 2 (got {args.steps}, horizons {args.horizons})")
    if args.episodes < 1 or args.repeats < 1 or args.stride < 1:
        parser.error("--episodes, --repeats and --stride must be >= 1")
    if args.rest_steps < 0:
        parser.error("--rest-steps must be >= 0")
    torch.set_num_threads(args.threads)
    model = load_model(args.model)
    started = time.perf_counter()
    rows = []
    for count in counts:
        row = run_count(model, count, args, meshes)
        rows.append(row)
        pos = row["errors"]["position"]
        print(f"{count} objects, {row['leaves']} leaves, {row['windows']} windows ({row['made']} episodes made): "
              f"pybullet {row['pybullet_ms']:.2f} ms, model {row['model_ms']:.2f} ms; position MSE "
              + ", ".join(f"t+{h} {pos[f't+{h}']['mean']:.3g}" for h in args.horizons), flush=True)
    add_ratios(rows, args.horizons)
    table = markdown(rows, args.horizons)
    print()
    print(table, end="")
    result = {"model": args.model, "meshes": list(meshes), "material": args.material, "pitch": args.pitch,
              "steps": args.steps, "episodes": args.episodes, "seed": args.seed, "horizons": list(args.horizons),
              "stride": args.stride, "repeats": args.repeats, "threads": args.threads,
              "rest_steps": args.rest_steps,
              "statistics": "errors: mean and standard error over windows (from step 2, then every --stride "
                            "steps), the network alone; model_ms: median over --repeats of one rollout from "
                            "step 2 to the first episode's end, sleeping off; pybullet_ms: median over the "
                            "model steps of the same episode",
              "machine": f"{platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} thread(s)",
              "seconds": time.perf_counter() - started, "rows": rows, "table": table}
    atomic_write_json(args.out, result)
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return result


if __name__ == "__main__":
    main()
