"""The planning sweep of one task: modes x fixed scenes x planner seeds, one closed-loop pybullet
episode each (:func:`hrn_pyg.rl.planning.plan_episode`).

Modes (:data:`MODES`): the three scores of :mod:`hrn_pyg.rl.planning` and the deterministic
planner with gradient refinement. Scenes: the fixed evaluation scenes and goals of the PPO
sweeps (:func:`fixed_scenes`: the environment of :class:`~hrn_pyg.rl.success_curve.EvalConfig`,
its generator reset to ``EVAL_SEED``, one reset of ``--num-scenes`` environments), so the
planners and the PPO policies of docs/rl.md face the same starts and goals. ``--validation``
plays the validation scenes instead (:func:`validation_scenes`: other pybullet scenes, other
goals), the ones a planner's sizes are chosen on.

**Resumable.** Each finished episode is one JSON line of ``<out>/episodes.jsonl`` (the file is
rewritten atomically after every episode); a rerun skips the (mode, scene, seed) triples it
finds, and refuses a file whose planner settings differ from the command's. ``<out>/sweep.json``
records the settings. Summarise with :mod:`experiments.planning.summary`.

::

    python -m experiments.planning.sweep --task cube_push_stop --model cube_push --out runs/planning/cube_push_stop
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from experiments.command import script_main
from hrn_pyg.rl.tasks import TASKS, get_task
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

DESCRIPTION = "closed-loop planning episodes of a task in pybullet over planners, fixed scenes and planner seeds"
#: the planners compared: a score, with or without gradient refinement
MODES = ("deterministic", "mean", "risk", "deterministic_refine")
#: the baseline every mode is compared with
BASELINE = "deterministic"


def mode_config(base, mode: str):
    """The :class:`~hrn_pyg.rl.planning.PlannerConfig` of a mode from the shared sizes ``base``."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    refine = mode.endswith("_refine")
    return replace(base, score=mode.removesuffix("_refine"), refine_steps=base.refine_steps if refine else 0)


def fixed_scenes(task, dynamics, count: int) -> list[dict]:
    """The first ``count`` fixed evaluation scenes of the PPO sweeps: ``{"scene", "pool_index",
    "scene_seed", "goal"}`` each (``count`` <= 32 gives the first of the same 32)."""
    from hrn_pyg.rl.success_curve import EvalConfig, evaluation_env

    config = EvalConfig()
    if not 1 <= count <= config.episodes:
        raise ValueError(f"--num-scenes must lie in [1, {config.episodes}], got {count}")
    env = evaluation_env(task, dynamics, config)
    env.rng.manual_seed(config.seed)
    td = env.reset()
    _, index = dynamics.leaf_history(td["state"])
    seeds = dynamics.scene_seeds(td["state"])
    return [{"scene": i, "pool_index": int(index[i]), "scene_seed": int(seeds[i]),
             "goal": [float(v) for v in td["goal"][i]]} for i in range(count)]


def validation_scenes(task, dynamics, count: int) -> list[dict]:
    """The first ``count`` validation scenes: pool entry ``i`` of ``dynamics`` (built on
    :data:`~hrn_pyg.rl.hrn_dynamics.VALIDATION_SEEDS`, pybullet scenes 20000 + i, apart from the
    evaluation pool) against the goal :func:`~hrn_pyg.rl.planning.episode_goal` draws from a
    generator seeded with the scene's seed (the scene and goal ``hrn-pyg plan --episode-seed``
    plays)."""
    from hrn_pyg.rl.planning import episode_goal

    if not 1 <= count <= len(dynamics.pool_seeds):
        raise ValueError(f"--num-scenes must lie in [1, {len(dynamics.pool_seeds)}], got {count}")
    out = []
    for i in range(count):  # a loop over scenes
        seed = int(dynamics.pool_seeds[i])
        goal = episode_goal(task, dynamics, i, seed)
        out.append({"scene": i, "pool_index": i, "scene_seed": seed, "goal": [float(v) for v in goal]})
    return out


def read_episodes(path: Path) -> list[dict]:
    """The finished episodes of a sweep (none when the file does not exist)."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hrn_pyg.rl.planning import add_search_arguments

    parser.add_argument("--task", required=True, choices=sorted(TASKS), help="an RL task's name")
    parser.add_argument("--model", required=True, help="a model checkpoint: a path or a shipped model's name")
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES), help="planners to run")
    parser.add_argument("--num-scenes", type=int, default=32, help="fixed evaluation scenes (the first N of 32)")
    parser.add_argument("--num-seeds", type=int, default=5, help="planner seeds per mode and scene")
    parser.add_argument("--first-seed", type=int, default=0, help="the first planner seed")
    add_search_arguments(parser)
    parser.add_argument("--validation", action="store_true",
                        help="play the validation scenes (pybullet seeds 20000+), not the 32 evaluation scenes")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", required=True, help="the sweep's folder")


def run(args: argparse.Namespace) -> int:
    from hrn_pyg.rl.hrn_dynamics import VALIDATION_SEEDS, HRNDynamics
    from hrn_pyg.rl.planning import MPCPlanner, PlannerConfig, plan_episode

    if args.num_seeds < 1 or args.threads < 1:
        raise ValueError(f"--num-seeds and --threads must be >= 1, got {args.num_seeds}, {args.threads}")
    task = get_task(args.task)
    base = PlannerConfig(candidates=args.candidates, elites=args.elites, iterations=args.iterations,
                         horizon=args.horizon, futures=args.k, refine_steps=args.refine_steps,
                         action_repeat=args.action_repeat, reach_weight=args.reach_weight,
                         horizontal=args.horizontal, route_proposal=args.route_proposal)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"task": task.name, "model": args.model, "planner": asdict(base)}
    if args.validation:
        settings["scenes"] = "validation"
    record = out / "sweep.json"
    if record.exists() and json.loads(record.read_text()) != settings:
        raise ValueError(f"{record} holds other settings ({record.read_text().strip()}); use another --out")
    atomic_write_json(record, settings)
    torch.set_num_threads(args.threads)
    if args.validation:
        dynamics = HRNDynamics.from_checkpoint(args.model, task, pool_seeds=VALIDATION_SEEDS[:args.num_scenes])
        scenes = validation_scenes(task, dynamics, args.num_scenes)
    else:
        dynamics = HRNDynamics.from_checkpoint(args.model, task)
        scenes = fixed_scenes(task, dynamics, args.num_scenes)
    path = out / "episodes.jsonl"
    lines = path.read_text().splitlines() if path.exists() else []
    done = {(e["mode"], e["scene"], e["seed"]) for e in read_episodes(path)}
    seeds = range(args.first_seed, args.first_seed + args.num_seeds)
    for mode in args.modes:
        config = mode_config(base, mode)
        for seed in seeds:
            for scene in scenes:
                if (mode, scene["scene"], seed) in done:
                    continue
                start = time.perf_counter()
                planner = MPCPlanner(dynamics, config, seed=seed)
                result = plan_episode(planner, scene["scene_seed"], torch.tensor(scene["goal"]),
                                      scene["pool_index"])
                plan_s, physics_s = result["plan_seconds"], result["physics_seconds"]
                entry = {"mode": mode, "seed": seed, **scene, "success": result["success"],
                         "steps": result["steps"], "rate": planner.rate,
                         "plan_seconds": sum(plan_s) / len(plan_s),
                         "physics_seconds": sum(physics_s) / len(physics_s),
                         "episode_seconds": time.perf_counter() - start}
                lines.append(json.dumps(entry, sort_keys=True))
                atomic_write_text(path, "\n".join(lines) + "\n")
                print(f"{mode} seed {seed} scene {scene['scene']}: "
                      f"{'success' if entry['success'] else 'failure'} in {entry['steps']} steps, "
                      f"{entry['plan_seconds']:.3f} s per plan, {entry['episode_seconds']:.1f} s",
                      file=sys.stderr, flush=True)
    return 0


def main(argv=None) -> int:
    return script_main("python -m experiments.planning.sweep", DESCRIPTION, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
