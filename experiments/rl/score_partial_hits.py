"""How often do the k sampled futures straddle the goal? The partial-hit share of a random
policy (the policy at PPO update 0) for a grid of dropout rates and goal tolerances.

A step is a partial hit when some but not all of the k samples meet the goal; only then can
reward relaxation change a reward (:mod:`experiments.rl.partial_hits`). The share is counted over
every step of ``--episodes`` episodes started from the validation scenes
(:data:`hrn_pyg.rl.hrn_dynamics.VALIDATION_SEEDS`, apart from the RL training pool), so that a
rate and a tolerance can be chosen (e.g. 10-30 % of steps) without looking at training scenes.

Run: ``python -m experiments.rl.score_partial_hits --task tower [--model PATH] [--rates 0.1 0.3 0.5]
[--tolerances 0.06 0.1] [--episodes 64] [--policy random|planner|clone:PATH] [--noise 0.1]
[--out benchmarks/results/partial_hits_tower.json]`` (the model defaults to
``hrn_pyg/checkpoints/<scene>.pt``; the output to ``partial_hits_<task>.json`` for the random
policy, ``partial_hits_<task>_<policy>_noise<noise>.json`` otherwise, ``_clone[_noise<noise>]``
for a clone). ``--policy planner`` runs the task's scripted planner
(:data:`experiments.rl.planners.PLANNERS`) with ``--noise`` action noise: near the goal more often
than a random policy, as PPO is once it learns. ``--policy clone:PATH`` runs a policy
checkpoint (``python -m experiments.rl.clone``) as PPO collects with it at update 0: actions drawn from its
TanhNormal (``--deterministic``: its mean action). Each row holds the share over all steps
(``partial_hit_share``) and over the goal-reaching steps (``near_miss_share``). Prints a table
and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import torch


from experiments.rl.clone import ActorPolicy, load_policy_actor
from experiments.rl.partial_hits import partial_hit_table
from experiments.rl.planners import PLANNERS
from hrn_pyg.rl.hrn_dynamics import VALIDATION_SEEDS, HRNDynamics
from hrn_pyg.rl.tasks import TASKS, get_task
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.files import atomic_write_json, file_sha256


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(TASKS), default="tower")
    parser.add_argument("--model", default=None, help="default hrn_pyg/checkpoints/<task>.pt")
    parser.add_argument("--rates", type=float, nargs="+", default=[0.1, 0.3, 0.5])
    parser.add_argument("--tolerances", type=float, nargs="+", default=None,
                        help="goal radii, metres (default: the task's)")
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--k", type=int, default=None, help="samples per step (default: the task's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--pool", type=int, default=len(VALIDATION_SEEDS),
                        help="validation scenes used (the first N of VALIDATION_SEEDS)")
    parser.add_argument("--no-relax", action="store_true", help="episodes without reward relaxation")
    parser.add_argument("--policy", default="random",
                        help="random: uniform actions (update 0 from scratch); planner: the task's scripted "
                             "planner; clone:PATH: a policy checkpoint, sampled (update 0 from it)")
    parser.add_argument("--deterministic", action="store_true",
                        help="with clone:PATH: the policy's mean action instead of a draw")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="Gaussian action noise, fraction of max force (0.1: the action_noise mode)")
    parser.add_argument("--no-sleep", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="default benchmarks/results/partial_hits_<task>.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    task = get_task(args.task)
    model = args.model or f"hrn_pyg/checkpoints/{task.scene_name}.pt"
    kind, _, policy_path = args.policy.partition(":")
    if kind not in ("random", "planner", "clone") or (kind == "clone") != bool(policy_path):
        parser.error(f"--policy must be random, planner or clone:PATH, got {args.policy!r}")
    if kind == "planner" and task.name not in PLANNERS:
        parser.error(f"no planner for task {task.name!r}; known: {', '.join(PLANNERS)}")
    seeds = VALIDATION_SEEDS[:args.pool]
    start = time.perf_counter()
    dynamics = HRNDynamics.from_checkpoint(model, task, "cpu", pool_seeds=seeds,
                                           sleep=None if args.no_sleep else DEFAULT_SLEEP)
    policy, policy_sha = {"random": None, "planner": PLANNERS.get(task.name)}.get(kind), None
    if kind == "clone":
        policy = ActorPolicy(load_policy_actor(policy_path, task, dynamics), sample=not args.deterministic)
        policy_sha = file_sha256(policy_path)
    rows = partial_hit_table(task, dynamics, args.rates, args.tolerances or [None], args.episodes,
                             num_samples=args.k, num_envs=args.num_envs, relax=not args.no_relax,
                             seed=args.seed, policy=policy, action_noise_std=args.noise)
    seconds = time.perf_counter() - start
    print(f"{task.name}: {args.policy} policy, action noise {args.noise:g}, {args.episodes} episodes on {len(seeds)} validation scenes, "
          f"k = {rows[0]['k']}, relax = {not args.no_relax} ({seconds:.0f} s)")
    print("| tolerance (m) | rate | steps | partial-hit share (all steps) | steps with any hit "
          "| near-miss share (partial / any hit) | success | mean length |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        of_hits = "-" if r["near_miss_share"] is None else f"{r['near_miss_share']:.2f}"
        print(f"| {r['tolerance']:.3f} | {r['rate']:.2f} | {r['steps']} | {r['partial_hit_share']:.3f} | "
              f"{r['any_hit_steps']} | {of_hits} | {r['success_rate']:.2f} | {r['mean_length']:.2f} |")
    if kind == "clone":
        suffix = "_clone" + ("_mean" if args.deterministic else "") + (f"_noise{args.noise:g}" if args.noise else "")
    else:
        suffix = "" if kind == "random" and args.noise == 0 else f"_{kind}_noise{args.noise:g}"
    out = args.out or f"benchmarks/results/partial_hits_{task.name}{suffix}.json"
    meta = {
        "what": f"share of steps at which some but not all of the k samples meet the goal, {kind} policy; "
                "near_miss_share: the same share among the steps with at least one sample in the goal",
        "policy": kind, "policy_checkpoint": policy_path or None, "policy_sha256": policy_sha,
        "policy_sampled": kind == "clone" and not args.deterministic,
        "action_noise_std": args.noise, "task_config": task.to_dict(),
        "task": task.name, "model": model, "validation_seeds": list(seeds), "episodes": args.episodes,
        "num_envs": args.num_envs, "seed": args.seed, "relax": not args.no_relax,
        "sleep": not args.no_sleep, "seconds": seconds,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
        "rows": rows,
    }
    atomic_write_json(out, meta)
    print(f"wrote {out}")
    return meta


if __name__ == "__main__":
    main()
