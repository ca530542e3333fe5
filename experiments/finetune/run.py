"""The fine-tuning table of docs/data.md: the generalist (``shapes``) on MuJoCo episodes of a
scene it never saw (``throw.toml``: meshes no scene of the package uses), zero-shot, fine-tuned on
10, 30 and 100 episodes, and a model trained from scratch on the same episodes for the same
number of optimiser steps; beside it, pybullet against MuJoCo on the same seeds, the floor of what
a model of one engine can match in the other.

Every stage is skipped when its output exists, so running the same command again continues a
killed run (training resumes from ``last.pt``). Each training records the CPU seconds of its
process (``budget.json``, summed over sittings). One process, one torch thread::

    nice -n 10 python -m experiments.finetune.run --out runs/finetune

Windows start at step 2 of each test episode (``--stride 100``: one per episode), so the models'
errors and the engines' divergence are over the same steps.
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np

from experiments.command import script_main
from hrn_pyg.cli import main as hrn_pyg
from hrn_pyg.data.dataset import split_of_seed
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.kinds import STATIC
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

DESCRIPTION = __doc__.splitlines()[0]
SCENE = Path(__file__).with_name("throw.toml")
HORIZONS = (15, 50)
#: the window start of every score (``HISTORY``: the first step with two past states)
START = 2
#: training options both arms share (the generalist's recipe where it applies)
COMMON = ("--preset", "ours", "--batch-size", "8", "--seq-end", "4", "--warmup", "20", "--w-rest", "10",
          "--input-noise", "0.0003", "--augment-symmetry", "true", "--checkpoint-every", "25", "--seed", "0",
          "--no-progress")
#: per arm: the options that differ
ARMS = {"finetune": ("--init-from", "shapes", "--lr", "0.0003"), "scratch": ("--lr", "0.001")}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="runs/finetune", help="the experiment's folder")
    parser.add_argument("--episodes", type=int, default=150, help="MuJoCo episodes generated (seeds 0..n-1)")
    parser.add_argument("--counts", default="10,30,100", help="training episodes of each cell, comma-separated")
    parser.add_argument("--train-steps", type=int, default=150, help="optimiser steps of every training")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _call(argv: list[str]) -> None:
    code = hrn_pyg(argv)
    if code != 0:
        raise ValueError(f"hrn-pyg {' '.join(argv)}: exit code {code}")


def generate(out: Path, episodes: int) -> None:
    """The MuJoCo episodes, and pybullet's of the test seeds (the same draws)."""
    base = ["generate", "--scene-file", str(SCENE), "--episodes", str(episodes), "--no-progress"]
    _call([*base, "--engine", "mujoco", "--out", str(out / "mujoco")])
    _call([*base, "--engine", "pybullet", "--shard", "9/10", "--out", str(out / "pybullet")])


def cell_folder(out: Path, count: int) -> Path:
    """A folder of links to the first ``count`` training-split MuJoCo episodes and every validation one."""
    source = (out / "mujoco").resolve()
    seeds = sorted(int(p.stem.split("_")[1]) for p in source.glob("episode_*.npz"))
    train = [s for s in seeds if split_of_seed(s) == "train"]
    if len(train) < count:
        raise ValueError(f"{count} training episodes asked, {len(train)} generated: raise --episodes")
    folder = out / "cells" / f"mujoco_{count}"
    folder.mkdir(parents=True, exist_ok=True)
    for seed in train[:count] + [s for s in seeds if split_of_seed(s) == "val"]:
        link = folder / f"episode_{seed:06d}.npz"
        if not link.exists():
            link.symlink_to(source / link.name)
    return folder


def train(out: Path, arm: str, count: int, steps: int, threads: int) -> Path:
    """One training (resumed when a sitting was killed); its model and its CPU seconds."""
    run = out / "runs" / f"{arm}_{count}"
    model = run / "model.pt"
    if model.exists():
        return model
    budget_path = run / "budget.json"
    budget = json.loads(budget_path.read_text()) if budget_path.exists() else {"cpu_seconds": 0.0, "wall_seconds": 0.0}
    resume = ["--resume"] if (run / "last.pt").exists() else []
    cpu, wall = _cpu_seconds(), time.perf_counter()
    _call(["train", *COMMON, *ARMS[arm], "--data", str(cell_folder(out, count)), "--out", str(run),
           "--train-steps", str(steps), "--eval-every", str(steps), "--threads", str(threads), *resume])
    budget["cpu_seconds"] += _cpu_seconds() - cpu
    budget["wall_seconds"] += time.perf_counter() - wall
    atomic_write_json(budget_path, budget)
    return model


def evaluate(out: Path, name: str, model: str, engine: str = "mujoco") -> dict:
    """The test windows' position and shape errors of ``model`` on ``engine``'s episodes."""
    folder = out / "eval" / f"{name}_{engine}"
    if not (folder / "results.json").exists():
        _call(["evaluate", "--data", str(out / engine), "--model", f"{name}={model}", "--out", str(folder),
               "--horizons", ",".join(map(str, HORIZONS)), "--stride", "100", "--split", "test", "--no-figure",
               "--no-progress"])
    return json.loads((folder / "results.json").read_text())["results"][name]


def engine_floor(out: Path) -> dict:
    """Position MSE of pybullet's leaves against MuJoCo's (the same seed and draw) at steps
    ``START + h``, over the moving leaves, as evaluate's ``position``: mean and standard error
    over the test episodes."""
    errors: dict[int, list[float]] = {h: [] for h in HORIZONS}
    for path in sorted((out / "pybullet").glob("episode_*.npz")):
        pb, mj = load_episode(path), load_episode(out / "mujoco" / path.name)
        moving = pb["object_material"][pb["leaf_object"]] != STATIC
        for h in HORIZONS:
            diff = pb["positions"][START + h, moving] - mj["positions"][START + h, moving]
            errors[h].append(float((diff.astype(np.float64) ** 2).mean()))
    return {"position": {f"t+{h}": {"mean": float(np.mean(v)), "sem": float(np.std(v, ddof=1) / np.sqrt(len(v))),
                                    "n": len(v)} for h, v in errors.items()}}


def _cell(result: dict, metric: str, horizon: int) -> str:
    value = result.get(metric, {}).get(f"t+{horizon}")
    if value is None:
        return "-"
    return f"{value['mean']:.3g} ± {value['sem']:.2g}"


def table(rows: list[tuple[str, str, dict]]) -> str:
    """The markdown table: one row per model, position and shape MSE at each horizon."""
    head = ["model", "CPU min"] + [f"{m} MSE t+{h}" for m in ("position", "shape") for h in HORIZONS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, cpu, result in rows:
        cells = [name, cpu] + [_cell(result, m, h) for m in ("position", "shape") for h in HORIZONS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    counts = [int(c) for c in args.counts.split(",") if c]
    generate(out, args.episodes)
    rows = [("pybullet against MuJoCo (same draw)", "-", engine_floor(out)),
            ("shapes zero-shot", "0", evaluate(out, "shapes", "shapes")),
            ("shapes on pybullet's episodes (its own engine)", "0", evaluate(out, "shapes", "shapes", "pybullet"))]
    atomic_write_text(out / "table.md", table(rows))
    for count in counts:
        for arm in ARMS:
            model = train(out, arm, count, args.train_steps, args.threads)
            cpu = json.loads((model.parent / "budget.json").read_text())["cpu_seconds"] / 60
            rows.append((f"{arm}, {count} episodes", f"{cpu:.1f}", evaluate(out, f"{arm}_{count}", str(model))))
            atomic_write_text(out / "table.md", table(rows))
    atomic_write_json(out / "results.json", {name: {"cpu_minutes": cpu, **result} for name, cpu, result in rows})
    print(table(rows), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(script_main("python -m experiments.finetune.run", DESCRIPTION, add_arguments, run))
