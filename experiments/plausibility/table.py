"""The plausibility table: K sampled futures and the network alone, every scene of a set at every
pitch, through :mod:`hrn_pyg.sim.plausibility`, beside pybullet's own episode.

A set is a TOML file (``data/plausibility/validation.toml``): the scene files, pitches, episode
seeds, K and the horizon. For each (scene, pitch, seed) the pybullet episode is simulated once and
kept under ``--work``; the model's K futures at its calibrated rate (sleeping on, as
``hrn_pyg.sample`` runs them) and its deterministic rollout with every object running at every
step (the network alone) are rolled out from step 2 and reported. Each cell is written to its
own JSON file as soon as it is done, so a stopped run resumes where it stopped; the table is
made from every cell file there is.

    python -m experiments.plausibility.table --set data/plausibility/validation.toml \\
        --model shapes --out docs/results/plausibility/validation
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import time
import tomllib
import warnings
from pathlib import Path

import torch

from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.data.episodes import DivergedEpisode, simulate_episode_alone
from hrn_pyg.data.io import load_episode, save_episode
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.plausibility import ENERGY_TOLERANCE, FutureReport, Scene, plausibility
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

#: the step the futures start from (the episode's third frame: two frames of history)
START = 2


def read_set(path: Path) -> dict:
    """The set's settings, scene paths made absolute."""
    settings = tomllib.loads(path.read_text())
    settings["scenes"] = [str((path.parent / s).resolve()) for s in settings["scenes"]]
    return settings


def cells_tag(model: str, applied: dict, rate: float) -> str:
    """The folder name (one path part, under ``--work``'s ``cells``) of a model's cells: its name or
    path with every separator made ``_``, the options applied and the rate."""
    name = re.sub(r"[^\w.=+-]+", "_", model).strip("_") or "model"
    return name + "".join(f"_{k}={v}" for k, v in sorted(applied.items())) + f"_rate{rate:g}"


def cell_name(scene: str, pitch: float, seed: int) -> str:
    return f"{Path(scene).stem}_p{pitch:g}_s{seed}"


def episode_of(scene: str, pitch: float, seed: int, steps: int, work: Path) -> dict | None:
    """The pybullet episode of a cell (kept under ``work``), or None when pybullet loses it."""
    path = work / "episodes" / f"{cell_name(scene, pitch, seed)}.npz"
    if path.is_file():
        return load_episode(path)
    spec = read_scene_file(scene)
    spec = dataclasses.replace(spec, config=dataclasses.replace(spec.config, pitch=pitch, steps=steps + START + 1))
    try:
        episode = simulate_episode_alone(spec, seed)  # soft bodies and cloth: as in a fresh process
    except (DivergedEpisode, ValueError) as exc:  # lost by pybullet, or no scene at this pitch
        print(f"{cell_name(scene, pitch, seed)}: {str(exc).splitlines()[0]}", file=sys.stderr, flush=True)
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    save_episode(path, episode)
    return episode


def score_cell(model, scene: str, pitch: float, seed: int, settings: dict, work: Path, rate: float) -> dict:
    """One cell: pybullet's row, the network alone and K futures, each as report dictionaries."""
    steps, k = int(settings["steps"]), int(settings["k"])
    t0 = time.perf_counter()
    episode = episode_of(scene, pitch, seed, steps, work)
    if episode is None:
        return {"scene": Path(scene).stem, "pitch": pitch, "seed": seed, "lost_by_pybullet": True}  # or not made
    simulated = time.perf_counter() - t0
    truth = torch.as_tensor(episode["positions"], dtype=torch.float64)
    scene_info = Scene.of_episode(episode)
    start = truth[START - 1 : START + 1]
    forces = torch.as_tensor(episode["forces"][START:], dtype=torch.float64)
    state = episode_state(episode, start=START, steps=steps)
    reference = plausibility(truth[START + 1 : START + 1 + steps], start, scene_info, forces)[0]
    t1 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a failed future is counted below
        alone = sample(model, state, k=1, steps=steps, rate=0.0, sleep=None)
        futures = sample(model, state, k=k, steps=steps, rate=rate, generator=torch.Generator().manual_seed(seed))
    rolled = time.perf_counter() - t1
    return {
        "scene": Path(scene).stem, "pitch": pitch, "seed": seed, "leaves": int(truth.shape[1]),
        "pybullet": reference.to_dict(),
        "alone": plausibility(alone, start, scene_info, forces)[0].to_dict(),
        "futures": [r.to_dict() for r in plausibility(futures, start, scene_info, forces)],
        "end_error_alone": float((alone[0, -1].double() - truth[START + steps]).norm(dim=-1).mean()),
        "seconds": {"pybullet": simulated, "model": rolled},
    }


def summarise(cells: list[dict]) -> list[dict]:
    """One row per (scene, pitch): counts and extremes over its seeds."""
    rows: dict[tuple, dict] = {}
    for cell in cells:
        if cell.get("lost_by_pybullet"):
            continue
        key = (cell["scene"], cell["pitch"])
        row = rows.setdefault(key, {"scene": cell["scene"], "pitch": cell["pitch"], "runs": 0, "futures": 0,
                                    "blow_ups": 0, "gaining": 0, "largest_gain": 0.0, "depth": 0.0,
                                    "pybullet_depth": 0.0, "unsupported": 0, "alone_gain": 0.0,
                                    "alone_depth": 0.0, "alone_blow_ups": 0, "over_depth": 0})
        reports = [FutureReport(**r) for r in cell["futures"]]
        alone, reference = FutureReport(**cell["alone"]), FutureReport(**cell["pybullet"])
        floor = reference.depth + cell["pitch"]
        row["runs"] += 1
        row["futures"] += len(reports)
        row["blow_ups"] += sum(r.first_non_finite > 0 for r in reports)
        row["gaining"] += sum(r.gains_energy for r in reports) + int(alone.gains_energy)
        row["largest_gain"] = max(row["largest_gain"], *(r.energy_share for r in reports))
        row["depth"] = max(row["depth"], *(r.depth for r in reports))
        row["pybullet_depth"] = max(row["pybullet_depth"], reference.depth)
        row["over_depth"] += sum(r.depth > floor for r in reports) + int(alone.depth > floor)
        row["unsupported"] += sum(r.unsupported for r in reports)
        row["alone_gain"] = max(row["alone_gain"], alone.energy_share)
        row["alone_depth"] = max(row["alone_depth"], alone.depth)
        row["alone_blow_ups"] += int(alone.first_non_finite > 0)
    return sorted(rows.values(), key=lambda r: (r["scene"], r["pitch"]))


def markdown(rows: list[dict], title: str) -> str:
    head = ("| scene | pitch (m) | runs | futures | blow-ups (K / alone) | gaining > 5 % | largest gain (K / alone) "
            "| deepest (cm): K / alone / pybullet | deeper than pybullet + 1 pitch | unsupported at rest |\n"
            "|---|---|---|---|---|---|---|---|---|---|\n")
    body = "".join(
        f"| {r['scene']} | {r['pitch']:g} | {r['runs']} | {r['futures']} | {r['blow_ups']} / {r['alone_blow_ups']} "
        f"| {r['gaining']} | {r['largest_gain']:+.1%} / {r['alone_gain']:+.1%} "
        f"| {100 * r['depth']:.1f} / {100 * r['alone_depth']:.1f} / {100 * r['pybullet_depth']:.1f} "
        f"| {r['over_depth']} | {r['unsupported']} |\n" for r in rows)
    totals = {key: sum(r[key] for r in rows) for key in ("futures", "blow_ups", "alone_blow_ups", "gaining",
                                                            "over_depth", "unsupported")}
    foot = (f"\nIn all: {totals['futures']} futures and {sum(r['runs'] for r in rows)} runs of the network alone; "
            f"{totals['blow_ups']} + {totals['alone_blow_ups']} blow-ups, {totals['gaining']} gaining more than "
            f"{ENERGY_TOLERANCE:.0%} energy, {totals['over_depth']} deeper than pybullet's plus one pitch, "
            f"{totals['unsupported']} objects unsupported at rest.\n")
    return f"# {title}\n\n" + head + body + foot


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", type=Path, default=Path("data/plausibility/validation.toml"))
    parser.add_argument("--model", default="shapes")
    parser.add_argument("--apply", default="", help="applied options, e.g. energy_limit=true,cloth_clearance=0.3")
    parser.add_argument("--rate", type=float, default=None, help="default: the model's calibrated rate")
    parser.add_argument("--work", type=Path, default=Path("runs/plausibility"))
    parser.add_argument("--out", type=Path, default=None, help="folder for table.md and cells.json")
    parser.add_argument("--only", default="", help="comma-separated scene stems")
    parser.add_argument("--pitches", default="", help="comma-separated pitches (default: the set's)")
    parser.add_argument("--seeds", default="", help="comma-separated episode seeds (default: the set's)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    settings = read_set(args.set)
    model = load_model(args.model)
    applied = {}
    for item in filter(None, args.apply.split(",")):
        name, value = item.split("=")
        applied[name] = {"true": True, "false": False}.get(value.lower(), None)
        if applied[name] is None:
            applied[name] = float(value)
    if applied:
        model = with_applied_options(model, **applied)
    model.eval()
    rate = model.config.dropout_rate if args.rate is None else args.rate
    tag = cells_tag(args.model, applied, rate)
    cells_dir = args.work / "cells" / tag
    cells_dir.mkdir(parents=True, exist_ok=True)
    only = set(filter(None, args.only.split(",")))
    pitches = [float(p) for p in args.pitches.split(",")] if args.pitches else settings["pitches"]
    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else settings["seeds"]
    for seed in seeds:
        for pitch in pitches:
            for scene in settings["scenes"]:
                if only and Path(scene).stem not in only:
                    continue
                path = cells_dir / f"{cell_name(scene, pitch, seed)}.json"
                if path.is_file():
                    continue
                cell = score_cell(model, scene, pitch, seed, settings, args.work, rate)
                atomic_write_json(path, cell)
                summary = summarise([cell])
                line = (f"{path.stem}: lost by pybullet" if not summary else
                        f"{path.stem}: blow-ups {summary[0]['blow_ups']}/{summary[0]['alone_blow_ups']}, gaining "
                        f"{summary[0]['gaining']}, largest {summary[0]['largest_gain']:+.1%} / alone "
                        f"{summary[0]['alone_gain']:+.1%}, depth {100 * summary[0]['depth']:.1f} cm "
                        f"(pybullet {100 * summary[0]['pybullet_depth']:.1f}), {cell.get('seconds')}")
                print(line, file=sys.stderr, flush=True)
    cells = [json.loads(p.read_text()) for p in sorted(cells_dir.glob("*.json"))]
    rows = summarise(cells)
    table = markdown(rows, f"Plausibility of {tag} on {args.set}")
    print(table)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.out / "cells.json", {"set": str(args.set), "model": args.model, "applied": applied,
                                                     "rate": rate, "cells": cells, "rows": rows})
        atomic_write_text(args.out / "table.md", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
