"""Are the sampled futures calibrated? Dropout samples scored against a ground-truth ensemble.

For each scene, one test episode (``--seed``) gives the model's start state at step 2; the
ground truth is an ensemble of ``--members`` pybullet replays of that episode whose initial
objects were shifted by a 2 mm Gaussian in x and y
(:func:`hrn_pyg.sampling.ensemble.ground_truth_ensemble`). The deterministic model (k = 1, no
dropout) and k dropout samples at each ``--rates`` are scored at the last predicted step with

* energy score per particle (:func:`~hrn_pyg.sampling.metrics.energy_score` on each leaf's
  3-D position, mean over leaves; metres, lower is better),
* best-of-k error (:func:`~benchmarks.common.best_of_k_error`: mean leaf distance of the
  closest sample, averaged over members; metres),
* coverage (:func:`~benchmarks.common.coverage`, per coordinate: fraction of the
  members' leaf coordinates inside the samples' [min, max]),
Leaves of static objects are left out of every score.

* spread: RMS distance of each moving leaf from its mean, for the samples and for the ensemble
  (:func:`~hrn_pyg.sampling.metrics.root_spread`, mean over leaves; metres),
* shape error: for each sample, the mean squared difference of its pairwise leaf distances within
  each moving object from the unperturbed pybullet episode's at the same step, mean over objects
  and samples (m^2; the seed's claim is that sampling does not spoil roll-out quality: issue 13
  asks for at most 1.5x the deterministic rollout's),
* wedge only: fraction of trajectories whose ball centre ends at ``x < 0`` / ``x >= 0``
  (:func:`~benchmarks.common.side_fractions`), samples against the ensemble.

Run: ``python -m benchmarks.uncertainty [--scenes wedge,soft_bounce,cube_collision]
[--k 16] [--rates 0.05,0.1,0.3] [--members 16] [--steps 20] [--seeds 9,19,29]
[--out benchmarks/results/uncertainty.json]`` with ``--model-dir`` (default
``hrn_pyg/checkpoints``, one ``<scene>.pt`` each); ``--model SCENE=PATH`` (repeatable) scores
another checkpoint for that scene, e.g. ``cube_collision=hrn_pyg/checkpoints/cube_collision_dropout.pt``.
``--random-init``: untrained models, a
pipeline check whose numbers mean nothing. Prints a markdown table, writes JSON atomically.

``--calibrated``: each model is scored at its own calibrated setting (the rate and modules
``hrn-pyg calibrate`` wrote into the checkpoint; model ``calibrated``) instead of ``--rates``;
a model never calibrated is an error naming the command. ``--quick``: a smoke run (k = 4,
4 members, 5 steps, the first seed only; JSON to ``uncertainty_quick.json`` unless ``--out``).
Samples mask the model's ``dropout_modules`` (after calibration: the chosen ones).
"""

from __future__ import annotations

import argparse
import os
import platform
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import best_of_k_error, coverage, model_for, object_centres, side_fractions
from hrn_pyg.checkpoints import CHECKPOINT_DIR
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE, STATIC
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.sampling.ensemble import (
    PerturbationConfig,
    episode_state,
    ground_truth_ensemble,
)
from hrn_pyg.sampling.metrics import energy_score, root_spread
from hrn_pyg.sampling.sample import sample
from hrn_pyg.utils.files import atomic_write_json

#: the wedge's ball is object 0; its ridge runs along y at x = 0
WEDGE_BALL, WEDGE_RIDGE_X = 0, 0.0


def shape_error(futures: torch.Tensor, truth: torch.Tensor, obj: torch.Tensor, moving: torch.Tensor) -> float:
    """Mean over the samples ``[K, L, 3]`` and the moving objects of the squared error of the
    pairwise leaf distances within each object, against ``truth`` ``[L, 3]`` (m^2)."""
    errors = []
    for o in torch.unique(obj[moving]).tolist():  # a few objects per scene
        rows = obj == o
        pred = torch.cdist(futures[:, rows], futures[:, rows])  # [K, n, n]
        true = torch.cdist(truth[rows][None], truth[rows][None])  # [1, n, n]
        errors.append((pred - true).pow(2).flatten(1).mean(dim=1))  # [K]
    return float(torch.stack(errors).mean())


def score(futures: torch.Tensor, members: torch.Tensor, episode: dict, scene: str,
          truth: torch.Tensor | None = None) -> dict:
    """Scores of futures ``[K, L, 3]`` against members ``[M, L, 3]`` (one time step).

    Leaves of static objects (the wedge) never move in either, so they are left out: they would
    only dilute every score. ``truth`` ``[L, 3]``: the unperturbed episode at the same step, for
    the shape error (left out when None).
    """
    obj, mass = torch.as_tensor(episode["leaf_object"]), torch.as_tensor(episode["leaf_mass"])
    moving = torch.as_tensor(episode["object_material"])[obj] != STATIC
    row = {
        # per leaf, then the mean over the moving leaves
        "energy_score_m": float(energy_score(futures[:, moving], members[:, moving]).mean()),
        "best_of_k_m": float(best_of_k_error(futures[:, moving], members[:, moving])),
        "coverage": float(coverage(futures[:, moving].flatten(1), members[:, moving].flatten(1))),
        # RMS distance of each moving leaf from its mean, samples against ensemble members
        "spread_m": float(root_spread(futures[:, moving]).mean()),
        "ensemble_spread_m": float(root_spread(members[:, moving]).mean()),
    }
    if truth is not None:
        row["shape_mse_m2"] = shape_error(futures, truth, obj, moving)
    if scene == "wedge":
        x = object_centres(futures, obj, mass)[:, WEDGE_BALL, 0]
        row["side_fractions"] = side_fractions(x, WEDGE_RIDGE_X).tolist()
    return row


def evaluate_scene(model: HRN, scene: str, seed: int, steps: int, members: np.ndarray, episode: dict,
                   k: int, rates: tuple[float, ...], sample_seed: int, label: str = "dropout") -> list[dict]:
    graph = episode_state(episode, start=HISTORY, steps=steps)
    forces = graph[NODE].force_seq.transpose(0, 1)
    truth = torch.as_tensor(members[:, HISTORY + steps]).float()  # [M, L, 3] at the last step
    unperturbed = torch.as_tensor(episode["positions"][HISTORY + steps]).float()  # [L, 3]
    rows = []
    modules = list(model.config.dropout_modules)
    for name, kk, rate in [("deterministic", 1, 0.0)] + [(label, k, r) for r in rates]:
        gen = torch.Generator().manual_seed(sample_seed)
        futures = sample(model, graph, kk, steps, rate, forces=forces, generator=gen)[:, -1]  # [K, L, 3]
        rows.append({"scene": scene, "episode_seed": seed, "model": name, "k": kk, "rate": rate,
                     "modules": modules if rate > 0 else [], **score(futures, truth, episode, scene, unperturbed)})
    if scene == "wedge":
        obj, mass = torch.as_tensor(episode["leaf_object"]), torch.as_tensor(episode["leaf_mass"])
        ens_x = object_centres(truth, obj, mass)[:, WEDGE_BALL, 0]
        for r in rows:
            r["ensemble_side_fractions"] = side_fractions(ens_x, WEDGE_RIDGE_X).tolist()
    return rows


def _split(fractions) -> str:
    return f"{fractions[0]:.2f} / {fractions[1]:.2f}" if fractions else "-"


def markdown(rows: list[dict]) -> str:
    """One line per (scene, episode seed, model, rate)."""
    lines = ["| scene | seed | model | k | rate | energy score (mm) | best-of-k (mm) | coverage | spread samples / ensemble (mm) | side split samples | side split ensemble |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r.get('episode_seed', '-')} | {r['model']} | {r['k']} | {r['rate']} | "
                     f"{1e3 * r['energy_score_m']:.1f} | {1e3 * r['best_of_k_m']:.1f} | {r['coverage']:.2f} | "
                     f"{1e3 * r['spread_m']:.1f} / {1e3 * r['ensemble_spread_m']:.1f} | "
                     f"{_split(r.get('side_fractions'))} | {_split(r.get('ensemble_side_fractions'))} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> list[dict]:
    """Mean of every score over the episode seeds, per (scene, model, rate)."""
    keys = ("energy_score_m", "best_of_k_m", "coverage", "spread_m", "ensemble_spread_m", "shape_mse_m2")
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["model"], r["k"], r["rate"]), []).append(r)
    out = []
    for (scene, model, k, rate), group in groups.items():
        row = {"scene": scene, "model": model, "k": k, "rate": rate, "seeds": len(group)}
        row.update({key: float(np.mean([g[key] for g in group])) for key in keys if key in group[0]})
        for key in ("side_fractions", "ensemble_side_fractions"):
            if key in group[0]:
                row[key] = np.mean([g[key] for g in group], axis=0).tolist()
        out.append(row)
    return out


def markdown_summary(rows: list[dict]) -> str:
    lines = ["| scene | model | k | rate | seeds | energy score (mm) | best-of-k (mm) | coverage | spread samples / ensemble (mm) | shape MSE (mm^2) | shape / deterministic |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    deterministic = {r["scene"]: r.get("shape_mse_m2") for r in rows if r["model"] == "deterministic"}
    for r in rows:
        shape, base = r.get("shape_mse_m2"), deterministic.get(r["scene"])
        ratio = f"{shape / base:.2f}" if shape is not None and base else "-"
        lines.append(f"| {r['scene']} | {r['model']} | {r['k']} | {r['rate']} | {r['seeds']} | "
                     f"{1e3 * r['energy_score_m']:.1f} | {1e3 * r['best_of_k_m']:.1f} | {r['coverage']:.2f} | "
                     f"{1e3 * r['spread_m']:.1f} / {1e3 * r['ensemble_spread_m']:.1f} | "
                     f"{'-' if shape is None else f'{1e6 * shape:.3g}'} | {ratio} |")
    return "\n".join(lines)


def calibrated_rate(model: HRN, scene: str, path: str | None) -> float:
    """The rate ``hrn-pyg calibrate`` wrote into the model's config; ValueError if it has none."""
    rate = float(model.config.dropout_rate)
    if not rate > 0:
        raise ValueError(f"--calibrated: the {scene} model {path or '(random init)'} is not calibrated; run "
                         f"`hrn-pyg calibrate --scene {scene} --model {path} --in-place` first")
    return rate


def chosen_models(specs: list[str], scenes: list[str]) -> dict[str, str]:
    """``--model SCENE=PATH`` options as ``{scene: path}``; a scene not in ``scenes``, a repeated
    scene or a missing file is a ``ValueError``."""
    chosen: dict[str, str] = {}
    for spec in specs:
        scene, sep, path = spec.partition("=")
        if not sep or not path:
            raise ValueError(f"--model wants SCENE=PATH, got {spec!r}")
        if scene not in scenes:
            raise ValueError(f"--model {spec!r}: {scene!r} is not one of --scenes {','.join(scenes)}")
        if scene in chosen:
            raise ValueError(f"--model names {scene!r} twice")
        if not Path(path).is_file():
            raise ValueError(f"--model {spec!r}: no such file")
        chosen[scene] = path
    return chosen


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="wedge,soft_bounce,cube_collision")
    parser.add_argument("--model-dir", default=str(CHECKPOINT_DIR))
    parser.add_argument("--model", action="append", default=[], metavar="SCENE=PATH",
                        help="this checkpoint for SCENE instead of <model-dir>/<scene>.pt (repeatable)")
    parser.add_argument("--k", type=int, default=16)
    parser.add_argument("--rates", default="0.05,0.1,0.3")
    parser.add_argument("--members", type=int, default=16)
    parser.add_argument("--position-std", type=float, default=PerturbationConfig().position_std)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--seeds", default="9",
                        help="comma-separated episode seeds (test-split seeds: seed %% 10 == 9)")
    parser.add_argument("--sample-seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--random-init", action="store_true", help="untrained models: pipeline check only")
    parser.add_argument("--calibrated", action="store_true",
                        help="score each model at its calibrated rate and modules instead of --rates")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: k 4, 4 members, 5 steps, first seed only")
    parser.add_argument("--out", default=None,
                        help="JSON (default benchmarks/results/uncertainty.json, uncertainty_quick.json with --quick)")
    args = parser.parse_args(argv)
    if args.quick:
        args.k, args.members, args.steps = 4, 4, 5
        args.seeds = args.seeds.split(",")[0]
    if args.out is None:
        args.out = f"benchmarks/results/uncertainty{'_quick' if args.quick else ''}.json"
    if args.calibrated and args.random_init:
        raise ValueError("--calibrated needs trained, calibrated checkpoints, not --random-init")
    torch.set_num_threads(args.threads)
    rates = tuple(float(r) for r in args.rates.split(",") if r)
    perturbation = PerturbationConfig(position_std=args.position_std)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    if not seeds:
        raise ValueError("--seeds must name at least one episode seed")
    scenes = [s for s in args.scenes.split(",") if s]
    model_paths = {scene: str(Path(args.model_dir) / f"{scene}.pt") for scene in scenes}
    model_paths.update(chosen_models(args.model, scenes))
    rows = []
    calibrated: dict[str, dict] = {}
    for scene in scenes:
        model = None
        scene_rates = rates
        for seed in seeds:  # a few test episodes; each is one batched rollout per rate
            episode = simulate_episode(scene, seed, steps=HISTORY + args.steps)
            if model is None:
                model_path = None if args.random_init else model_paths[scene]
                model = model_for(scene, model_path, args.random_init, episode_state(episode, HISTORY, args.steps))
                if args.calibrated:  # before the ensemble: an uncalibrated model fails fast
                    scene_rates = (calibrated_rate(model, scene, model_path),)
                    calibrated[scene] = {"rate": scene_rates[0], "modules": list(model.config.dropout_modules)}
            members = ground_truth_ensemble(scene, seed, args.members, HISTORY + args.steps, perturbation)
            rows += evaluate_scene(model, scene, seed, args.steps, members, episode, args.k, scene_rates,
                                   args.sample_seed, "calibrated" if args.calibrated else "dropout")
            print(markdown(rows[-1 - len(scene_rates):]), flush=True)
    table = markdown(rows)
    means = summary(rows)
    mean_table = markdown_summary(means)
    print("\nall rows:\n" + table + "\n\nmean over episode seeds:\n" + mean_table)
    result = {
        "what": "dropout samples vs a ground-truth ensemble of perturbed pybullet replays, at the last step",
        "steps": args.steps, "start_step": HISTORY, "episode_seeds": seeds, "members": args.members,
        "perturbation": perturbation.to_dict(), "k": args.k,
        "rates": None if args.calibrated else list(rates),
        "calibrated": calibrated if args.calibrated else None, "quick": args.quick,
        "sample_seed": args.sample_seed, "random_init": args.random_init,
        "models": None if args.random_init else model_paths,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
        "rows": rows, "markdown": table, "mean_over_seeds": means, "markdown_mean": mean_table,
    }
    atomic_write_json(args.out, result)
    return result


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:  # one line, like the hrn-pyg commands
        raise SystemExit(f"uncertainty.py: error: {exc}") from None
