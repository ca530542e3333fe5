"""Scripted planners of the tasks with room to learn: episode lengths in the learned model and in
pybullet, and the length thresholds they set.

For each policy (the greedy push and the task's planner, :mod:`experiments.rl.planners`) it runs
``--episodes`` episodes in the learned model at rate 0 from the RL pool scenes
(:data:`hrn_pyg.rl.hrn_dynamics.POOL_SEEDS`, the scenes PPO trains on) and replays each episode's
actions open loop in pybullet from the same scene against the same goal
(:func:`hrn_pyg.rl.evaluate.ground_truth_success`); the planner also runs with the
``action_noise`` mode's noise (sigma = 0.1 x max force) in the model. A failed episode counts as
``max_steps`` long. The same policy also runs closed loop in pybullet (it sees pybullet's
states), from the same scenes and goals: what the policy can do in physics, apart from the
open-loop replay's drift. The planner's mean in-model length ``L`` sets the task's thresholds
(:func:`experiments.rl.planners.length_thresholds`).

Run: ``python -m experiments.rl.score_planners --task tower_aside [--episodes 64]
[--out benchmarks/results/planners_tower_aside.json]``. Prints a table and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch


from experiments.rl.planners import (
    PLANNERS,
    Planner,
    greedy_push,
    length_thresholds,
    planner_policy,
)
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import (
    closed_loop_in_pybullet,
    evaluate_policy,
    ground_truth_success,
)
from hrn_pyg.rl.hrn_dynamics import POOL_SEEDS, HRNDynamics
from hrn_pyg.rl.tasks import TaskConfig, get_task
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.files import atomic_write_json


def closed_loop_rates(task: TaskConfig, planner: Planner, env: HRNEnv, episodes: int) -> dict:
    """Success rate and mean length (failures count ``max_steps``) of the planner run closed loop
    in pybullet from the scenes and goals of ``episodes`` learned-model episodes' starts."""
    from hrn_pyg.rl.evaluate import record_episodes

    records = record_episodes(planner_policy(task, planner), env, episodes)
    runs = [closed_loop_in_pybullet(lambda obs: planner(task, obs), task, r["seed"], r["goal"]) for r in records]
    return {"pybullet_closed_loop_success_rate": sum(r["success"] for r in runs) / len(runs),
            "pybullet_closed_loop_mean_length": sum(r["steps"] for r in runs) / len(runs)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(PLANNERS), default="tower_aside")
    parser.add_argument("--model", default=None, help="default hrn_pyg/checkpoints/<scene>.pt")
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--noise", type=float, default=0.1, help="action noise, fraction of max force")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="default benchmarks/results/planners_<task>.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    task = get_task(args.task)
    model = args.model or f"hrn_pyg/checkpoints/{task.scene_name}.pt"
    start = time.perf_counter()
    dynamics = HRNDynamics.from_checkpoint(model, task, "cpu", pool_seeds=POOL_SEEDS, sleep=DEFAULT_SLEEP)
    rows = []
    for name, planner in (("greedy_push", greedy_push), ("planner", PLANNERS[task.name])):
        env = HRNEnv(task, dynamics, batch_size=args.num_envs, dropout_rate=0.0, seed=args.seed)
        row = {"policy": name, **ground_truth_success(planner_policy(task, planner), env, args.episodes)}
        env = HRNEnv(task, dynamics, batch_size=args.num_envs, dropout_rate=0.0, seed=args.seed,
                     action_noise_std=args.noise)
        success, length = evaluate_policy(planner_policy(task, planner), env, args.episodes)
        row.update(noisy_model_success_rate=success, noisy_model_mean_length=length)
        env = HRNEnv(task, dynamics, batch_size=args.num_envs, dropout_rate=0.0, seed=args.seed)
        row.update(closed_loop_rates(task, planner, env, args.episodes))
        rows.append(row)
    seconds = time.perf_counter() - start
    planner_length = rows[1]["model_mean_length"]
    thresholds = length_thresholds(planner_length)
    print(f"{task.name}: {args.episodes} episodes from the RL pool, rate 0, max_steps {task.max_steps} "
          f"({seconds:.0f} s)")
    print("| policy | model success | model length | pybullet replay success | pybullet replay length "
          f"| agreement | model success, noise {args.noise:g} | model length, noise "
          "| pybullet closed-loop success | pybullet closed-loop length |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['policy']} | {r['model_success_rate']:.2f} | {r['model_mean_length']:.2f} | "
              f"{r['pybullet_success_rate']:.2f} | {r['pybullet_mean_length']:.2f} | {r['agreement']:.2f} | "
              f"{r['noisy_model_success_rate']:.2f} | {r['noisy_model_mean_length']:.2f} | "
              f"{r['pybullet_closed_loop_success_rate']:.2f} | {r['pybullet_closed_loop_mean_length']:.2f} |")
    print(f"thresholds from the planner's length {planner_length:.2f}: {thresholds}")
    out = args.out or f"benchmarks/results/planners_{task.name}.json"
    meta = {
        "what": "greedy push and scripted planner: episodes in the learned model (rate 0) and replayed in pybullet",
        "task": task.to_dict(), "model": model, "pool_seeds": [POOL_SEEDS[0], POOL_SEEDS[-1]],
        "episodes": args.episodes, "num_envs": args.num_envs, "seed": args.seed,
        "action_noise_std": args.noise, "seconds": seconds, "planner_length": planner_length,
        "thresholds": thresholds,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
        "rows": rows,
    }
    atomic_write_json(out, meta)
    print(f"wrote {out}")
    return meta


if __name__ == "__main__":
    main()
