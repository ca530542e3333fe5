"""Does a cloth pass through what it falls on? Cloth leaves inside other objects, model against pybullet.

For every episode of each folder (episodes ``hrn-pyg generate`` wrote, e.g. of
``data/shapes/unseen/validation_cloth.toml``), the model is rolled out from step 2 to the end
with the episode's own forces (the package's rollout, :func:`hrn_pyg.sim.rollout.rollout`;
objects at rest sleep unless ``--awake``), and at every predicted step the cloth leaves inside
another object's solid are counted (:mod:`hrn_pyg.sim.penetration`: the full lattice cells of
every object that is not cloth, moving with its leaves); the same count of pybullet's own
positions at the same steps (the ground truth in the same folder) stands beside it.

Per folder, pooled over its episodes' steps: ``mean`` leaves inside a step, ``max`` in any
step, ``share`` the mean over the cloth's leaves, ``steps with any`` the share of steps with at
least one leaf inside; a rollout that leaves the finite numbers is counted (``diverged``), not
averaged; ``ms/step`` the median over the episodes of the rollout's seconds per step (one
torch thread unless told). ``--cloth-clearance 0,0.1,0.25`` scores the same weights with
:attr:`~hrn_pyg.nn.hrn.HRNConfig.cloth_clearance` set to each value in turn (the rule of
:mod:`hrn_pyg.sim.cloth_contact`; 0: off), one row each, so what the rule buys and what it costs
are read off one run. Run::

    python -m benchmarks.cloth_pass_through --model multi_material \\
        --episodes data/unseen_val_cloth --out benchmarks/results/cloth_pass_through_val.json

Prints a markdown table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.io import load_episode
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.penetration import cloth_inside_counts, episode_solids, inside_summary
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.files import atomic_write_json

SOURCES = ("model", "pybullet")


def episode_counts(model, episode, awake: bool = False) -> dict:
    """Cloth leaves inside other objects at each step ``x_3 .. x_S`` of one episode: the model's
    rollout from step 2 (``model_counts``, None when it left the finite numbers) and pybullet's
    (``pybullet_counts``), with each one's :func:`~hrn_pyg.sim.penetration.inside_summary`."""
    solids = episode_solids(episode)
    if solids.cloth_leaves == 0:
        raise ValueError(f"episode of seed {int(episode['seed'])} has no cloth")
    positions = torch.from_numpy(np.asarray(episode["positions"], dtype=np.float32))  # [S+1, L, 3]
    truth = positions[HISTORY + 1:]
    graph = episode_state(episode, start=HISTORY)
    forces = graph[NODE].force_seq.transpose(0, 1)
    steps = forces.shape[0]
    row = {"seed": int(episode["seed"]), "steps": steps, "cloth_leaves": solids.cloth_leaves, "error": None,
           "seconds_per_step": None}
    with torch.no_grad():
        try:
            start = time.perf_counter()
            pred = rollout(model, graph, steps, forces, sleep=None if awake else DEFAULT_SLEEP)[:, :solids.leaves]
            row["seconds_per_step"] = (time.perf_counter() - start) / steps
            counts = cloth_inside_counts(pred, solids)
        except ValueError as exc:  # left the finite numbers
            counts, row["error"] = None, str(exc)
    row["model_counts"] = None if counts is None else counts.tolist()
    row["pybullet_counts"] = cloth_inside_counts(truth, solids).tolist()
    for source in SOURCES:
        values = row[f"{source}_counts"]
        row[source] = None if values is None else inside_summary(torch.tensor(values), solids.cloth_leaves)
    return row


def pooled(rows: list[dict]) -> dict:
    """One folder's summary of both sources over every step of its episodes (model: of the
    rollouts that stayed finite)."""
    out = {"episodes": len(rows), "diverged": sum(r["model_counts"] is None for r in rows)}
    timed = [r["seconds_per_step"] for r in rows if r.get("seconds_per_step") is not None]
    out["model_ms_per_step"] = 1e3 * float(np.median(timed)) if timed else None
    for source in SOURCES:
        kept = [r for r in rows if r[f"{source}_counts"] is not None]
        if not kept:
            out[source] = None
            continue
        counts = torch.tensor([c for r in kept for c in r[f"{source}_counts"]], dtype=torch.float64)
        leaves = torch.tensor([r["cloth_leaves"] for r in kept for _ in r[f"{source}_counts"]], dtype=torch.float64)
        out[source] = {"mean": float(counts.mean()), "max": int(counts.max()),
                       "mean_share": float((counts / leaves).mean()), "steps_with_any": float((counts > 0).double().mean()),
                       "episodes_with_any": sum(max(r[f"{source}_counts"]) > 0 for r in kept)}
    return out


def score_folders(model, folders: list[Path], limit: int | None = None, awake: bool = False) -> dict:
    """Per folder: every episode's row (:func:`episode_counts`) and the pooled summary."""
    result = {}
    for folder in folders:
        paths = sorted(Path(folder).glob("episode_*.npz"))[:limit]
        if not paths:
            raise FileNotFoundError(f"{folder}: no episode_*.npz")
        rows = []
        for path in paths:
            rows.append(episode_counts(model, load_episode(path), awake))
            m, b = rows[-1]["model"], rows[-1]["pybullet"]
            said = "diverged" if m is None else f"{m['mean']:.2f} (max {m['max']})"
            print(f"  {Path(folder).name} seed {rows[-1]['seed']}: model {said}, pybullet "
                  f"{b['mean']:.2f} (max {b['max']}) leaves inside", flush=True)
        result[Path(folder).name] = {"summary": pooled(rows), "episodes": rows}
    return result


def markdown(result: dict) -> str:
    lines = ["| folder | clearance | episodes | model: mean inside (share) | max | steps with any "
             "| pybullet: mean inside (share) | max | steps with any | diverged | model ms/step |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for run in result["runs"]:
        for name, folder in run["folders"].items():
            s = folder["summary"]
            cells = []
            for source in SOURCES:
                v = s[source]
                cells += ["-", "-", "-"] if v is None else [
                    f"{v['mean']:.2f} ({100 * v['mean_share']:.2f} %)", str(v["max"]),
                    f"{100 * v['steps_with_any']:.0f} %"]
            ms = "-" if s.get("model_ms_per_step") is None else f"{s['model_ms_per_step']:.1f}"
            lines.append(f"| {name} | {run['cloth_clearance']:g} | {s['episodes']} | {' | '.join(cells)} "
                         f"| {s['diverged']} | {ms} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name or a checkpoint path")
    parser.add_argument("--episodes", action="append", required=True, type=Path,
                        help="a folder of episodes with cloth (repeatable)")
    parser.add_argument("--limit", type=int, default=None, help="the first N episodes of each folder")
    parser.add_argument("--awake", action="store_true", help="no object sleeps (the network alone)")
    parser.add_argument("--cloth-clearance", default=None,
                        help="comma-separated values of HRNConfig.cloth_clearance (pitches; 0: the rule off) to "
                             "score the model with, one row each (default: the model's own)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    model = load_model(args.model)
    try:
        clearances = ([float(getattr(model.config, "cloth_clearance", 0.0))] if args.cloth_clearance is None
                      else [float(v) for v in args.cloth_clearance.split(",")])
    except ValueError:
        parser.error(f"--cloth-clearance expects numbers separated by commas, got {args.cloth_clearance!r}")
    runs = []
    for clearance in clearances:
        print(f"cloth_clearance {clearance:g}", flush=True)
        applied = model if args.cloth_clearance is None else with_applied_options(model, cloth_clearance=clearance)
        folders = score_folders(applied, args.episodes, args.limit, args.awake)
        runs.append({"cloth_clearance": clearance, "folders": folders})
    result = {"model": str(args.model), "awake": args.awake, "threads": args.threads, "runs": runs,
              "machine": platform.platform(), "seconds": time.perf_counter() - t0}
    atomic_write_json(args.out, result)
    print(markdown(result), end="")
    print(f"wrote {args.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
