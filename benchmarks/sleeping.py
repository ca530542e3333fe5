"""Objects at rest sleep, measured: time per step and accuracy, sleeping on against all awake.

Cases (all on the CPU, shipped checkpoints, the pybullet episode's own forces):

* ``tower`` (``hrn_pyg/checkpoints/tower.pt``) and ``multi_material`` (``multi_material.pt``):
  full pybullet test episodes (``seed % 10 == 9``; ``--seeds``, default 9, 19, 29), rolled out
  from step 2 (:func:`hrn_pyg.sampling.ensemble.episode_state`) to the episode's end;
* ``field``: one pybullet world of 64 objects, sixteen of the ``tower`` scene's towers (three
  stacked cubes and a ball each, drawn as in the built-in tower scene) on a 4 x 4 grid
  ``--field-spacing`` (1.5 m) apart, rolled out with ``tower.pt`` (the model of exactly this
  neighbourhood; it sees only relative positions, so the grid offsets do not matter to it).
  Only the balls of the first ``--field-moving`` (2) towers are pushed, by the tower scene's
  random forces aimed at their own tower; the other 14 towers and balls rest from the start.
  So a few objects move (2 balls and whatever they topple) and most rest, the case sleeping
  is for. The grid is wide enough that the other towers are out of the moving balls' reach.

Both settings get the scene's declared effects (:func:`hrn_pyg.data.scene_file.scene_effects`; the
field: the tower's). For each case: a rollout with every object awake (``sleep=None``) and one with
``SleepConfig()`` (the defaults of :mod:`hrn_pyg.sim.sleeping`), ``--repeats`` >= 3 times each in one
process, the two settings interleaved so they see the same machine load (one torch thread by
default). Reported: the median over repeats of the time per step (rollout time / steps), the
ratio, the position MSE against pybullet (``hrn_pyg.evaluate``'s definition: squared error
per coordinate over the movable leaves) at ``t+15`` and at the episode's end for both settings,
the mean fraction of movable objects asleep, and whether ``SleepConfig(enabled=False)`` gives the
plain rollout bit for bit.

Errors over the whole split (``--accuracy-episodes``, default all 10 episodes per case, seeds 9,
19, ..., 99; the field: ten worlds): one episode's end error is a coin toss between two rollouts
that have both drifted or fallen apart (0.03-3 m^2 on the towers), so "not worse" is judged on
the split's mean, as ``hrn-pyg evaluate`` reports it: the ratio of the sleeping rollouts' mean
error to the awake ones', with a paired bootstrap 95 % interval over the episodes, the median
per-episode ratio and the count of episodes worse. These rollouts are not timed.

Run: ``python -m benchmarks.sleeping [--seeds 9,19,29] [--repeats 5] [--threads 1] [--model CASE=PATH]
[--accuracy-episodes 10]``; a setting of the rule on validation episodes: ``--split val --seeds
8,18,28 --field-seed 8 --threshold 1e-3 --patience 20``; a smoke run on a busy machine:
``python -m benchmarks.sleeping --quick`` (one seed, 40-step episodes, three repeats, two
episodes of errors). Prints markdown tables and writes ``benchmarks/results/sleeping.json``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time

import numpy as np
import torch
from torch_geometric.data import HeteroData
from tqdm.auto import tqdm

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import (
    SceneSpec,
    builtin_scene,
    parse_scene,
    scene_effects,
)
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.sim.sleeping import SleepConfig
from hrn_pyg.utils.files import atomic_write_json

CHECKPOINTS = {"tower": "hrn_pyg/checkpoints/tower.pt", "multi_material": "hrn_pyg/checkpoints/multi_material.pt",
               "field": "hrn_pyg/checkpoints/tower.pt"}
#: the horizon of Table 1's long error
HORIZON = 15
#: model steps of the --quick episodes (pybullet steps 0..40, the rollout starts at step 2)
QUICK_STEPS = 40


def tower_field(towers: int = 16, spacing: float = 1.5, moving: int = 2) -> SceneSpec:
    """``towers`` towers of the tower scene on a square grid ``spacing`` apart, as one scene:
    objects ``4 k .. 4 k + 2`` are tower ``k``'s cubes (bottom to top), ``4 k + 3`` its ball; the
    balls of the first ``moving`` towers are pushed as in the tower scene (each its own random
    schedule, aimed at its own tower), the rest stay at rest."""
    tower = builtin_scene("tower")
    side = math.ceil(math.sqrt(towers))
    draw = {}
    objects, pushes = [], []
    for k in range(towers):  # a few towers, each a handful of bodies
        ox, oy = spacing * (k % side), spacing * (k // side)
        draw |= {f"cube_masses_{k}": "[uniform(cube_mass_range), uniform(cube_mass_range), uniform(cube_mass_range)]",
                 f"ball_mass_{k}": "uniform(ball_mass_range)", f"yaws_{k}": "uniform(-0.2, 0.2, 3)",
                 f"ball_distance_{k}": "uniform(ball_distance_range)", f"ball_heading_{k}": "uniform(0, 2 * pi)"}
        objects += [{"mesh": "box", "material": "rigid", "size": "cube_side", "mass": f"cube_masses_{k}[{level}]",
                     "position": f"[{ox}, {oy}, cube_side * {level + 0.5}]",
                     "orientation": f"yaw_quaternion(yaws_{k}[{level}])"} for level in range(3)]
        objects.append({"mesh": "sphere", "material": "rigid", "size": "2 * ball_radius", "mass": f"ball_mass_{k}",
                        "position": f"[{ox} + ball_distance_{k} * cos(ball_heading_{k}), "
                                    f"{oy} + ball_distance_{k} * sin(ball_heading_{k}), ball_radius]"})
        if k < moving:
            pushes.append({"object": 4 * k + 3, "steps": "[0, last_push_step]",
                           "random": {"force": "force_range", "hold": "hold_range", "pause": "pause_range",
                                      "aim": 4 * k, "aim_noise": "aim_noise_range"}})
    draw["last_push_step"] = "integer(last_push_step_range)"
    settings = {key: value.tolist() if hasattr(value, "tolist") else value for key, value in tower.settings.items()}
    table = {**{f: getattr(tower.config, f) for f in ("steps", "substeps", "physics_hz", "pitch", "friction",
                                                      "rolling_friction")},
             "effects": {"forces": True, "collisions": True}, "settings": settings, "draw": draw,
             "objects": objects, "pushes": pushes}
    return parse_scene(table, name="tower_field")


def make_case(scene: str, seed: int, steps: int | None, moving: int, spacing: float) -> tuple[HeteroData, torch.Tensor]:
    """The initial graph (step 2 of the pybullet episode, with its ground truth) and the forces
    ``[S, N, 3]`` of the steps to the end."""
    if scene == "field":
        episode = simulate_episode(tower_field(moving=moving, spacing=spacing), seed, steps)
    else:
        episode = simulate_episode(scene, seed, steps)
    graph = episode_state(episode, start=2)
    return graph, graph[NODE].force_seq.transpose(0, 1).contiguous()


_CASES: dict[tuple[str, int, bool], tuple[HeteroData, torch.Tensor]] = {}


def cached_case(scene: str, seed: int, args: argparse.Namespace) -> tuple[HeteroData, torch.Tensor]:
    """:func:`make_case` once per (scene, seed) in a run: the timed cases and the accuracy pass
    share their pybullet episodes. Returns a copy (``clone``) the caller may strip."""
    key = (scene, seed, args.quick)
    if key not in _CASES:
        _CASES[key] = make_case(scene, seed, QUICK_STEPS if args.quick else None, args.field_moving, args.field_spacing)
    graph, forces = _CASES[key]
    return graph.clone(), forces


def position_mse(pred: torch.Tensor, truth: torch.Tensor, graph: HeteroData) -> float:
    """Mean squared error per coordinate over the movable leaves (``hrn_pyg.evaluate``'s)."""
    store = graph[NODE]
    moving = store.is_leaf & ~store.is_static
    return float((pred - truth)[moving].pow(2).mean())


def prepared(scene: str, seed: int, args: argparse.Namespace
             ) -> tuple[HeteroData, torch.Tensor, torch.Tensor, HRN, SceneEffects]:
    """One case ready to roll: the start graph (ground truth stripped), the forces ``[S, N, 3]``,
    pybullet's positions ``[S, N, 3]`` of the predicted steps (``x_3 .. x_S``), the case's model
    and the scene's declared effects (the same for both settings; the field: the tower's)."""
    graph, forces = cached_case(scene, seed, args)
    store = graph[NODE]
    truth = store.pos_seq[:, 3:].transpose(0, 1)
    del store.pos_seq, store.force_seq
    model = load_model(args.models.get(scene, CHECKPOINTS[scene]))
    return graph, forces, truth, model, scene_effects("tower" if scene == "field" else scene)


def errors(pred: torch.Tensor, truth: torch.Tensor, graph: HeteroData) -> dict[str, float]:
    """Position MSE at t+15 (or the last step of a shorter episode) and at the episode's end."""
    horizon = min(HORIZON, pred.shape[0])
    return {f"t+{horizon}": position_mse(pred[horizon - 1], truth[horizon - 1], graph),
            "end": position_mse(pred[-1], truth[-1], graph)}


def timed(model: HRN, graph: HeteroData, forces: torch.Tensor, sleep: SleepConfig | None,
          effects: SceneEffects | None = None) -> tuple[float, torch.Tensor]:
    steps = forces.shape[0]
    with torch.no_grad():
        t0 = time.perf_counter()
        pos = rollout(model, graph, steps, forces, sleep=sleep, effects=effects)
        return (time.perf_counter() - t0) / steps, pos


def sleeping_config(args: argparse.Namespace) -> SleepConfig:
    """The sleeping setting: the package's defaults, ``--start-from-history``, ``--threshold``
    and ``--patience`` as given."""
    default = SleepConfig()
    return SleepConfig(start_from_history=args.start_from_history == "true",
                       threshold=default.threshold if args.threshold is None else args.threshold,
                       patience=default.patience if args.patience is None else args.patience)


def bench_case(scene: str, seed: int, args: argparse.Namespace) -> dict:
    t0 = time.perf_counter()
    graph, forces, truth, model, effects = prepared(scene, seed, args)
    simulated = time.perf_counter() - t0
    store = graph[NODE]
    steps = forces.shape[0]
    settings = {"all_awake": None, "sleeping": sleeping_config(args)}

    with torch.no_grad():
        asleep = torch.stack([s.asleep for s in unroll(model, graph, steps, forces, sleep=settings["sleeping"],
                                                       effects=effects)])
        off = rollout(model, graph, steps, forces, sleep=SleepConfig(enabled=False), effects=effects)
    movable_root = store.is_root & ~store.is_static
    asleep_fraction = asleep[:, movable_root].float().mean(1)  # [steps]
    leaves_run = (~asleep[:, store.is_leaf]).float().sum(1)  # awake leaves per step

    times: dict[str, list[float]] = {k: [] for k in settings}
    preds: dict[str, torch.Tensor] = {}
    for k, sleep in settings.items():  # warm-up
        preds[k] = timed(model, graph, forces, sleep, effects)[1]
    for _ in range(args.repeats):  # interleaved: both settings see the same load
        for k, sleep in settings.items():
            times[k].append(timed(model, graph, forces, sleep, effects)[0])
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "scene": scene, "seed": seed, "steps": steps,
        "objects": int(store.is_root.sum()), "leaves": int(store.is_leaf.sum()), "nodes": int(store.num_nodes),
        "ms_per_step": {k: 1e3 * v for k, v in med.items()},
        "ms_per_step_runs": {k: [1e3 * t for t in v] for k, v in times.items()},
        "all_awake_over_sleeping": med["all_awake"] / med["sleeping"],
        "position_mse": {k: errors(p, truth, graph) for k, p in preds.items()},
        "asleep_fraction_mean": float(asleep_fraction.mean()),
        "asleep_fraction_last_step": float(asleep_fraction[-1]),
        "first_step_all_asleep": (int(torch.nonzero(asleep_fraction == 1).min())
                                  if bool((asleep_fraction == 1).any()) else None),
        "awake_leaves_per_step_mean": float(leaves_run.mean()),
        "sleep_off_bit_identical": bool(torch.equal(off, preds["all_awake"])),
        "simulate_seconds": simulated,
    }


def episode_errors(scene: str, seed: int, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """Position MSE at t+15 (or the episode's last step, if sooner) and at the end, all awake and
    sleeping, of one episode (untimed)."""
    graph, forces, truth, model, effects = prepared(scene, seed, args)
    with torch.no_grad():
        return {name: errors(rollout(model, graph, forces.shape[0], forces, sleep=sleep, effects=effects), truth, graph)
                for name, sleep in (("all_awake", None), ("sleeping", sleeping_config(args)))}


def paired_summary(awake: list[float], sleeping: list[float], draws: int = 2000) -> dict:
    r"""Sleeping against all awake over episodes, one error per episode each.

    ``ratio_of_means`` :math:`\bar e_\mathrm{sleep} / \bar e_\mathrm{awake}` (the mean is the
    split's error, as ``hrn-pyg evaluate`` averages episodes), its 95 % interval from ``draws``
    paired bootstrap resamples of the episodes (a fixed seed, so a rerun prints the same), the
    median of the per-episode ratios and how many episodes are worse with sleeping.
    """
    a, b = np.asarray(awake, dtype=np.float64), np.asarray(sleeping, dtype=np.float64)
    pick = np.random.default_rng(0).integers(0, a.size, size=(draws, a.size))
    boot = b[pick].mean(1) / a[pick].mean(1)
    per_episode = b / a
    return {"mean_all_awake": float(a.mean()), "mean_sleeping": float(b.mean()),
            "ratio_of_means": float(b.mean() / a.mean()),
            "ratio_interval_95": [float(np.quantile(boot, 0.025)), float(np.quantile(boot, 0.975))],
            "median_episode_ratio": float(np.median(per_episode)),
            "episodes_worse": int((per_episode > 1).sum()), "episodes": int(a.size)}


def accuracy_over_split(scenes: list[str], args: argparse.Namespace) -> dict:
    """Errors of both settings over the first ``--accuracy-episodes`` episodes of the split of
    every case (the field: that many field worlds), with :func:`paired_summary` per horizon."""
    residue = 9 if args.split == "test" else 8
    seeds = [residue + 10 * i for i in range(args.accuracy_episodes)]
    result = {}
    for scene in scenes:
        per_seed = {}
        for seed in tqdm(seeds, desc=f"accuracy {scene}", leave=False, disable=args.no_progress):
            per_seed[seed] = episode_errors(scene, seed, args)
        summary = {h: paired_summary([e["all_awake"][h] for e in per_seed.values()],
                                     [e["sleeping"][h] for e in per_seed.values()])
                   for h in next(iter(per_seed.values()))["all_awake"]}
        result[scene] = {"seeds": seeds, "per_episode": {str(k): v for k, v in per_seed.items()}, "summary": summary}
    return result


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="9,19,29", help="test seeds (seed %% 10 == 9) of tower and multi_material")
    parser.add_argument("--split", default="test", choices=("test", "val"),
                        help="val: validation seeds (seed %% 10 == 8), for choosing settings")
    parser.add_argument("--start-from-history", default="true", choices=("true", "false"),
                        help="SleepConfig.start_from_history of the sleeping setting (default: the package default, true)")
    parser.add_argument("--threshold", type=float, default=None,
                        help="SleepConfig.threshold of the sleeping setting, m per step (default: the package's)")
    parser.add_argument("--patience", type=int, default=None,
                        help="SleepConfig.patience of the sleeping setting, steps (default: the package's)")
    parser.add_argument("--field-seed", type=int, default=9)
    parser.add_argument("--field-moving", type=int, default=2, help="towers whose ball is pushed (of 16)")
    parser.add_argument("--field-spacing", type=float, default=1.5, help="distance between towers (m)")
    parser.add_argument("--cases", default="tower,multi_material,field")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke run: first seed only, {QUICK_STEPS}-step episodes, 3 repeats")
    parser.add_argument("--model", action="append", default=[], metavar="CASE=PATH",
                        help="score this checkpoint in CASE instead of the shipped one (repeatable), "
                             "e.g. a candidate on --split val")
    parser.add_argument("--accuracy-episodes", type=int, default=10,
                        help="errors of both settings (untimed) over this many episodes of the split per case, "
                             "seeds 9, 19, ... (val: 8, 18, ...); 0: none")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--out", default="benchmarks/results/sleeping.json")
    args = parser.parse_args(argv)
    args.models = {}
    for spec in args.model:
        case, _, path = spec.partition("=")
        if case not in CHECKPOINTS or not path:
            raise SystemExit(f"--model {spec!r}: need CASE=PATH with CASE one of {sorted(CHECKPOINTS)}")
        if not os.path.isfile(path):
            raise SystemExit(f"--model {spec!r}: no file {path}")
        args.models[case] = path
    if args.quick:
        args.repeats = 3
        args.accuracy_episodes = min(args.accuracy_episodes, 2)
    try:
        sleeping_config(args)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    if not 0 <= args.accuracy_episodes <= 10:
        raise SystemExit(f"--accuracy-episodes must be 0..10 (the split has 10 episodes per scene), got {args.accuracy_episodes}")
    if args.repeats < 3:
        raise SystemExit("--repeats must be >= 3 (median of at least 3 runs)")
    seeds = [int(s) for s in args.seeds.split(",") if s]
    residue = 9 if args.split == "test" else 8
    if any(s % 10 != residue for s in seeds + [args.field_seed]):
        raise SystemExit(f"--seeds and --field-seed must be {args.split} seeds (seed % 10 == {residue}), "
                         f"got {seeds} and {args.field_seed}")
    if args.quick:
        seeds = seeds[:1]
    torch.set_num_threads(args.threads)

    scenes = [c for c in args.cases.split(",") if c]
    for scene in scenes:
        if scene not in CHECKPOINTS:
            raise SystemExit(f"unknown case {scene!r}; choose from {sorted(CHECKPOINTS)}")
    rows = []
    for scene in scenes:
        for seed in ([args.field_seed] if scene == "field" else seeds):
            row = bench_case(scene, seed, args)
            rows.append(row)
            ms = row["ms_per_step"]
            print(f"{scene} seed {seed}: all awake {ms['all_awake']:.2f} ms, sleeping {ms['sleeping']:.2f} ms "
                  f"(x{row['all_awake_over_sleeping']:.2f}), asleep {100 * row['asleep_fraction_mean']:.0f}% of "
                  f"object-steps", flush=True)

    print()
    print("| case | seed | objects | leaves | steps | all awake ms/step | sleeping ms/step | speed-up | "
          "asleep (mean) | pos MSE t+15 awake / sleeping | pos MSE end awake / sleeping | off = plain |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|")
    for r in rows:
        ms, err = r["ms_per_step"], r["position_mse"]
        h = next(k for k in err["all_awake"] if k != "end")
        print(f"| {r['scene']} | {r['seed']} | {r['objects']} | {r['leaves']} | {r['steps']} | "
              f"{ms['all_awake']:.2f} | {ms['sleeping']:.2f} | x{r['all_awake_over_sleeping']:.2f} | "
              f"{100 * r['asleep_fraction_mean']:.0f}% | {err['all_awake'][h]:.3g} / {err['sleeping'][h]:.3g} | "
              f"{err['all_awake']['end']:.3g} / {err['sleeping']['end']:.3g} | "
              f"{'yes' if r['sleep_off_bit_identical'] else 'NO'} |")
    accuracy = accuracy_over_split(scenes, args) if args.accuracy_episodes else {}
    if accuracy:
        print()
        print(f"Errors over {args.accuracy_episodes} {args.split} episodes per case (untimed; mean of the per-episode "
              "position MSE, sleeping / all awake with a paired bootstrap 95 % interval):")
        print()
        print("| case | horizon | mean awake | mean sleeping | ratio of means | 95 % interval | median episode ratio | episodes worse |")
        print("|---|---|---:|---:|---:|---|---:|---:|")
        for scene, acc in accuracy.items():
            for h, sm in acc["summary"].items():
                lo, hi = sm["ratio_interval_95"]
                print(f"| {scene} | {h} | {sm['mean_all_awake']:.4g} | {sm['mean_sleeping']:.4g} | "
                      f"{sm['ratio_of_means']:.3f} | {lo:.3f}-{hi:.3f} | {sm['median_episode_ratio']:.3f} | "
                      f"{sm['episodes_worse']} of {sm['episodes']} |")
    result = {
        "what": "objects at rest sleep: rollout with SleepConfig() against every object awake",
        "sleep_config": sleeping_config(args).to_dict(), "split": args.split,
        "quick": args.quick, "repeats": args.repeats,
        "statistic": "median over repeats of (rollout time / steps); settings interleaved, one process",
        "error": "position MSE per coordinate over movable leaves against pybullet, at t+15 and the episode end",
        "field": {"towers": 16, "moving": args.field_moving, "spacing": args.field_spacing,
                  "model": args.models.get("field", CHECKPOINTS["field"])},
        "models": {case: args.models.get(case, path) for case, path in CHECKPOINTS.items()},
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                    "torch": torch.__version__, "numpy": np.__version__, "torch_threads": args.threads,
                    "load_average_1m": os.getloadavg()[0]},
        "rows": rows,
        "accuracy": accuracy,
    }
    atomic_write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
