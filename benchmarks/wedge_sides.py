"""Which side of the wedge does the ball end on? Sampled futures against pybullet ensembles.

The seed paper's Figure 1: a ball dropped on the ridge of a wedge can roll off either side.
For each ridge episode (balls dropped within a few millimetres of the ridge, the
``wedge_ridge`` dataset's settings read from its ``meta.json``), this script compares

* the model's probability of ending at ``x < 0``: the share of ``k`` dropout samples whose ball
  centre ends there (:func:`~benchmarks.common.side_fractions`), at each ``--rates``
  (default: the checkpoint's calibrated rate), and the deterministic rollout's side (0 or 1);
* two pybullet ensembles of the same episode whose start is shifted by a Gaussian in x and y
  (``--fine-std``, 2 mm, and ``--coarse-std``, 1 cm): the share of members ending at ``x < 0``.

Scores, over the episodes (issue 13's wedge criteria):

* **Brier score** against the fine ensemble: mean of :math:`(p_{model} - p_{2mm})^2`;
  the constant forecast 1/2 is printed beside it as the reference;
* **split difference** against the coarse ensemble: mean of :math:`|p_{model} - p_{1cm}|`;
* **energy score** of the ball's final centre (m), samples against the fine ensemble's
  members, and the deterministic rollout's (its distance to the members).

``--scene-file`` scores another ridge instead, e.g. a roof the model never saw
(``data/shapes/unseen/roof_drop.toml``; its ball is object 0 and its ridge runs along y at x = 0).

Select settings with ``--split val`` (seeds with ``seed % 10 == 8``); ``--split test``
(``== 9``) is the held-out report. Run: ``python -m benchmarks.wedge_sides [--model
hrn_pyg/checkpoints/wedge.pt] [--data data/wedge_ridge] [--split val] [--episodes 20]
[--k 32] [--members 16] [--rates 0.05,0.1] [--out benchmarks/results/wedge_sides.json]``.
Prints markdown tables and writes JSON atomically. The pybullet ensembles (most of the run time)
are kept under ``--cache`` (default ``runs/cache/wedge_sides``, one small ``.npz`` per episode,
ensemble and setting), so scoring another model on the same episodes simulates nothing again;
``--cache ""`` turns that off.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    episode_state,
    ground_truth_ensemble,
)
from hrn_pyg.sampling.metrics import energy_score
from hrn_pyg.sampling.sample import sample
from benchmarks.sides import (
    RIDGE_X,
    ball_centres,
    brier_score,
    ridge_config,
    share_below,
    split_difference,
)
from hrn_pyg.utils.files import atomic_write, atomic_write_json

#: seed residues of the splits (hrn_pyg.data.dataset)
SPLITS = {"val": 8, "test": 9}


def split_seeds(split: str, count: int, first: int = 0) -> list[int]:
    """The first ``count`` seeds from ``first`` on whose residue mod 10 marks ``split``."""
    residue = SPLITS[split]
    start = first + (residue - first) % 10
    return list(range(start, start + 10 * count, 10))


def ensemble_end(cache: str, seed: int, members: int, steps: int, std: float, config,
                 from_file: bool = False) -> np.ndarray:
    """Leaf positions ``[members, L, 3]`` of a pybullet ensemble at step ``steps``, from ``cache``
    when an earlier run stored them for the same scene settings (and, for a scene file, the same
    text), seed, size and spread."""
    fields = {"scene": config.settings_dict(), "seed": seed, "members": members, "steps": steps, "std": std}
    if from_file:
        fields["scene_file_sha256"] = hashlib.sha256(config.text.encode()).hexdigest()
    key = json.dumps(fields, sort_keys=True)
    path = Path(cache) / f"{hashlib.sha256(key.encode()).hexdigest()[:20]}.npz" if cache else None
    if path is not None and path.is_file():
        with np.load(path, allow_pickle=False) as stored:
            if str(stored["key"]) == key:
                return stored["end"]
    runs = ground_truth_ensemble(config.name, seed, members, steps, PerturbationConfig(position_std=std), config)
    end = np.asarray(runs[:, steps], dtype=np.float32)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)

        def write(f) -> None:
            buffer = io.BytesIO()
            np.savez(buffer, end=end, key=np.array(key))
            f.write(buffer.getvalue())

        atomic_write(path, write)
    return end


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="hrn_pyg/checkpoints/wedge.pt")
    parser.add_argument("--data", default="data/wedge_ridge",
                        help="folder whose meta.json holds the ridge-drop scene settings")
    parser.add_argument("--scene-file", default=None,
                        help="a ridge-drop scene file instead (ball: object 0; ridge along y at x = 0)")
    parser.add_argument("--split", choices=sorted(SPLITS), default="val")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--k", type=int, default=32)
    parser.add_argument("--members", type=int, default=16)
    parser.add_argument("--fine-std", type=float, default=0.002)
    parser.add_argument("--coarse-std", type=float, default=0.01)
    parser.add_argument("--rates", default=None,
                        help="comma-separated dropout rates (default: the checkpoint's calibrated rate)")
    parser.add_argument("--steps", type=int, default=None,
                        help="predicted steps (default: to the episode's end)")
    parser.add_argument("--sample-seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--cache", default="runs/cache/wedge_sides",
                        help="folder for the pybullet ensembles ('' : simulate them every run)")
    parser.add_argument("--out", default="benchmarks/results/wedge_sides.json")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.k < 2 or args.members < 2:
        raise ValueError("--episodes must be >= 1, --k and --members >= 2")
    torch.set_num_threads(args.threads)
    config = read_scene_file(args.scene_file) if args.scene_file else ridge_config(args.data)
    steps = args.steps or config.config.steps - HISTORY
    if not 1 <= steps <= config.config.steps - HISTORY:
        raise ValueError(f"--steps must be in [1, {config.config.steps - HISTORY}], got {steps}")
    model = load_model(args.model)
    if args.rates:
        rates = [float(r) for r in args.rates.split(",") if r]
    elif float(model.config.dropout_rate) > 0:
        rates = [float(model.config.dropout_rate)]
    else:
        raise ValueError(f"{args.model} is not calibrated: pass --rates")
    seeds = split_seeds(args.split, args.episodes, args.first_seed)
    rows = []
    start = time.perf_counter()
    for i, seed in enumerate(seeds):
        episode = simulate_episode(config, seed, steps=HISTORY + steps)
        fine_end = torch.as_tensor(ensemble_end(args.cache, seed, args.members, HISTORY + steps,
                                                args.fine_std, config, bool(args.scene_file)))
        coarse_end = torch.as_tensor(ensemble_end(args.cache, seed, args.members, HISTORY + steps,
                                                  args.coarse_std, config, bool(args.scene_file)))
        graph = episode_state(episode, start=HISTORY, steps=steps)
        forces = graph[NODE].force_seq.transpose(0, 1)
        def centres(positions):  # [T, L, 3] -> [T, 3]
            return ball_centres(positions, episode["leaf_object"], episode["leaf_mass"])

        truth_x = float(centres(torch.as_tensor(episode["positions"][HISTORY + steps]).float()[None])[0, 0])
        fine_centres = centres(fine_end)  # [M, 3]
        row = {"seed": seed, "truth_below": truth_x < RIDGE_X,
               "fine_below": share_below(fine_centres[:, 0]),
               "coarse_below": share_below(centres(coarse_end)[:, 0])}
        det = centres(sample(model, graph, 1, steps, 0.0, forces=forces)[:, -1])
        row["deterministic_below"] = share_below(det[:, 0])
        row["deterministic_es_m"] = float(energy_score(det, fine_centres))
        for rate in rates:
            gen = torch.Generator().manual_seed(args.sample_seed)
            futures = centres(sample(model, graph, args.k, steps, rate, forces=forces, generator=gen)[:, -1])
            row[f"below@{rate:g}"] = share_below(futures[:, 0])
            row[f"es_m@{rate:g}"] = float(energy_score(futures, fine_centres))
            row[f"final_x@{rate:g}"] = futures[:, 0].tolist()
        row["fine_final_x"] = fine_centres[:, 0].tolist()
        row["coarse_final_x"] = centres(coarse_end)[:, 0].tolist()
        rows.append(row)
        print(f"[{i + 1}/{len(seeds)}] seed {seed}: p(x<0) fine {row['fine_below']:.2f} coarse "
              f"{row['coarse_below']:.2f} det {row['deterministic_below']:.0f} "
              + " ".join(f"@{r:g} {row[f'below@{r:g}']:.2f}" for r in rates)
              + f" ({time.perf_counter() - start:.0f} s)", file=sys.stderr, flush=True)
    fine_p = np.array([r["fine_below"] for r in rows])
    coarse_p = np.array([r["coarse_below"] for r in rows])
    results = [{"model": "constant 1/2", "rate": None, "brier_fine": brier_score(np.full_like(fine_p, 0.5), fine_p),
                "split_difference_coarse": split_difference(np.full_like(coarse_p, 0.5), coarse_p),
                "energy_score_m": None}]
    det_p = np.array([r["deterministic_below"] for r in rows])
    results.append({"model": "deterministic", "rate": 0.0, "brier_fine": brier_score(det_p, fine_p),
                    "split_difference_coarse": split_difference(det_p, coarse_p),
                    "energy_score_m": float(np.mean([r["deterministic_es_m"] for r in rows]))})
    for rate in rates:
        p = np.array([r[f"below@{rate:g}"] for r in rows])
        results.append({"model": "samples", "rate": rate, "brier_fine": brier_score(p, fine_p),
                        "split_difference_coarse": split_difference(p, coarse_p),
                        "energy_score_m": float(np.mean([r[f"es_m@{rate:g}"] for r in rows])),
                        "share_below": float(p.mean())})
    lines = [f"{config.name} ridge drops, {args.split} split, {len(seeds)} episodes, {steps} steps, k = {args.k}, "
             f"{args.members} members per ensemble ({1e3 * args.fine_std:g} mm / {1e3 * args.coarse_std:g} mm); "
             f"share of episodes' members at x < 0: fine {fine_p.mean():.2f}, coarse {coarse_p.mean():.2f}",
             "", "| model | rate | Brier vs fine (<= 0.12) | split diff. vs coarse (<= 0.1) | energy score (mm) |",
             "|---|---:|---:|---:|---:|"]
    for r in results:
        es = "-" if r["energy_score_m"] is None else f"{1e3 * r['energy_score_m']:.1f}"
        lines.append(f"| {r['model']} | {'-' if r['rate'] is None else r['rate']} | {r['brier_fine']:.3f} | "
                     f"{r['split_difference_coarse']:.3f} | {es} |")
    table = "\n".join(lines)
    print(table)
    out = {"what": "wedge ridge drops: probability of ending at x < 0, samples vs pybullet ensembles",
           "model": args.model, "data": None if args.scene_file else args.data,
           "scene_file": args.scene_file, "scene_config": config.settings_dict(),
           "split": args.split, "seeds": seeds, "steps": steps, "k": args.k, "members": args.members,
           "fine_std": args.fine_std, "coarse_std": args.coarse_std, "rates": rates,
           "sample_seed": args.sample_seed, "results": results, "episodes": rows, "markdown": table,
           "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
           "seconds": time.perf_counter() - start}
    atomic_write_json(args.out, out)
    return out


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:
        raise SystemExit(f"wedge_sides.py: error: {exc}") from None
