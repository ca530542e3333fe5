"""The warm start measured: a planner cloned into the PPO actor (``python -m experiments.rl.clone``), in the
learned model and in pybullet, and what its spread leaves to relaxation at update 0.

For one task and one clone checkpoint:

- **validation scenes** (:data:`hrn_pyg.rl.hrn_dynamics.VALIDATION_SEEDS`, ``--episodes``
  episodes; no clone or PPO run sees them): the clone's deterministic (mean) action at rate 0,
  success and mean length in the learned model, beside the planner's; then the policy PPO
  collects with at update 0 (actions drawn from the clone's TanhNormal) at each ``--rates``
  with ``k`` samples and relaxation: the partial-hit share over all steps and over the
  goal-reaching steps (near-miss share), success and length
  (:func:`experiments.rl.partial_hits.partial_hit_share`);
- **evaluation scenes** (the fixed scenes of ``hrn-pyg rl --eval-every``:
  :func:`hrn_pyg.rl.success_curve.evaluation_env`, ``--eval-scenes`` of them drawn from the
  training pool by :data:`~hrn_pyg.rl.success_curve.EVAL_SEED`): the clone's mean action in the
  model at rate 0 and its episodes replayed open loop in pybullet
  (:func:`~hrn_pyg.rl.success_curve.evaluate_point`, as a run's ``eval.csv`` rows), and the clone
  run closed loop in pybullet from the same scenes and goals (``planners.closed_loop_rates``);
  the planner's the same way, for reference.

Failed episodes count as ``max_steps`` long.

Run: ``python -m experiments.rl.score_clone --task cube_push_stop --policy runs/clones/cube_push_stop.pt
[--rates 0 0.1 0.3] [--episodes 64] [--eval-scenes 32] [--out benchmarks/results/clone_<task>.json]``, the
policy made by ``python -m experiments.rl.clone --task cube_push_stop --out runs/clones/cube_push_stop.pt``.
Prints tables and writes JSON atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import torch


from experiments.rl.clone import ActorPolicy, load_policy_actor
from experiments.rl.partial_hits import partial_hit_share
from experiments.rl.planners import PLANNERS, planner_policy
from experiments.rl.score_planners import closed_loop_rates
from hrn_pyg.rl.hrn_dynamics import POOL_SEEDS, VALIDATION_SEEDS, HRNDynamics
from hrn_pyg.rl.success_curve import EvalConfig, evaluate_point, evaluation_env
from hrn_pyg.rl.tasks import get_task
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP
from hrn_pyg.utils.checkpoint import load_checkpoint
from hrn_pyg.utils.files import atomic_write_json, file_sha256


def evaluation_scenes(task, dynamics, policy_module, planner_fn, scenes: int) -> dict:
    """Model and open-loop replay (``evaluate_point``) and closed loop in pybullet on the fixed
    evaluation scenes."""
    config = EvalConfig(every=1, episodes=scenes)
    env = evaluation_env(task, dynamics, config)
    row = evaluate_point(policy_module, env, config)
    env.rng.manual_seed(config.seed)  # the same scenes and goals again
    row.update(closed_loop_rates(task, planner_fn, env, scenes))
    return row


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(PLANNERS), default="cube_push_stop")
    parser.add_argument("--policy", required=True, help="clone checkpoint (python -m experiments.rl.clone)")
    parser.add_argument("--model", default=None, help="default hrn_pyg/checkpoints/<scene>.pt")
    parser.add_argument("--rates", type=float, nargs="+", default=[0.0, 0.1, 0.3])
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--num-envs", type=int, default=32)
    parser.add_argument("--eval-scenes", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=None, help="default benchmarks/results/clone_<task>.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    task = get_task(args.task)
    model = args.model or f"hrn_pyg/checkpoints/{task.scene_name}.pt"
    start = time.perf_counter()

    val = HRNDynamics.from_checkpoint(model, task, "cpu", pool_seeds=VALIDATION_SEEDS, sleep=DEFAULT_SLEEP)
    actor = load_policy_actor(args.policy, task, val)
    mean, sampled = ActorPolicy(actor), ActorPolicy(actor, sample=True)
    common = {"episodes": args.episodes, "num_envs": args.num_envs, "seed": args.seed}
    validation = {"clone_mean_rate0": partial_hit_share(task, val, 0.0, policy=mean, **common),
                  "planner_rate0": partial_hit_share(task, val, 0.0, policy=PLANNERS[task.name], **common),
                  "update0": [partial_hit_share(task, val, rate, policy=sampled, **common)
                              for rate in args.rates]}

    pool = HRNDynamics.from_checkpoint(model, task, "cpu", pool_seeds=POOL_SEEDS, sleep=DEFAULT_SLEEP)
    pool_actor = load_policy_actor(args.policy, task, pool)
    evaluation = {"clone": evaluation_scenes(task, pool, pool_actor, ActorPolicy(pool_actor), args.eval_scenes),
                  "planner": evaluation_scenes(task, pool, planner_policy(task), PLANNERS[task.name],
                                               args.eval_scenes)}
    seconds = time.perf_counter() - start

    print(f"{task.name}: clone {args.policy} ({seconds:.0f} s)")
    print(f"validation scenes, rate 0, mean action: clone success {validation['clone_mean_rate0']['success_rate']:.2f} "
          f"length {validation['clone_mean_rate0']['mean_length']:.2f}; planner "
          f"{validation['planner_rate0']['success_rate']:.2f} / {validation['planner_rate0']['mean_length']:.2f}")
    print("| update-0 policy (sampled) | rate | steps | partial-hit share (all steps) | goal-reaching steps "
          "| near-miss share | success | mean length |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in validation["update0"]:
        near = "-" if r["near_miss_share"] is None else f"{r['near_miss_share']:.3f}"
        print(f"| clone | {r['rate']:.2f} | {r['steps']} | {r['partial_hit_share']:.3f} | {r['any_hit_steps']} | "
              f"{near} | {r['success_rate']:.2f} | {r['mean_length']:.2f} |")
    print(f"evaluation scenes ({args.eval_scenes}), rate 0:")
    print("| policy | model success | model length | replay success | replay length | closed-loop success "
          "| closed-loop length |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, r in evaluation.items():
        print(f"| {name} | {r['model_success_rate']:.2f} | {r['model_mean_length']:.2f} | "
              f"{r['pybullet_success_rate']:.2f} | {r['pybullet_mean_length']:.2f} | "
              f"{r['pybullet_closed_loop_success_rate']:.2f} | {r['pybullet_closed_loop_mean_length']:.2f} |")
    out = args.out or f"benchmarks/results/clone_{task.name}.json"
    meta = {
        "what": "the planner cloned into the PPO actor: in-model success on validation scenes, partial-hit "
                "shares of the update-0 (sampled) policy, and pybullet success on the evaluation scenes",
        "task": task.to_dict(), "model": model, "policy": args.policy, "policy_sha256": file_sha256(args.policy),
        "clone": json.loads(load_checkpoint(args.policy)["config"]),
        "validation_seeds": [VALIDATION_SEEDS[0], VALIDATION_SEEDS[-1]], "k": task.num_samples,
        "relax": True, **common, "eval_scenes": args.eval_scenes, "seconds": seconds,
        "machine": {"cpu": platform.machine(), "cpus": os.cpu_count(), "torch_threads": args.threads},
        "validation": validation, "evaluation": evaluation,
    }
    atomic_write_json(out, meta)
    print(f"wrote {out}")
    return meta


if __name__ == "__main__":
    main()
