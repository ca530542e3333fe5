"""``hrn-pyg rl``'s arguments (the work: :mod:`hrn_pyg.rl.ppo`), the defaults read from
:class:`~hrn_pyg.rl.ppo.PPOConfig`'s source (:mod:`hrn_pyg.commands.configs`)."""

from __future__ import annotations

import argparse

from hrn_pyg.commands.configs import config_fields, source_constant
from hrn_pyg.utils.options import add_moved, add_no_progress, add_strict

#: the names of :data:`hrn_pyg.rl.tasks.TASKS` (``tests/commands/test_configs.py`` holds them equal)
TASK_NAMES = ("cube_push", "tower", "cube_push_stop", "cube_push_hold", "tower_aside", "tower_top_aside")


def add_training_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a run's training and scoring, apart from its mode, seed and output:
    shared by ``hrn-pyg rl`` and the sweeps over modes and seeds."""
    d = {f.name: f.default for f in config_fields("hrn_pyg.rl.ppo", "PPOConfig")}
    parser.add_argument("--task", choices=sorted(TASK_NAMES), default="cube_push", help="the task")
    parser.add_argument("--updates", type=int, default=d["updates"], help="PPO updates per run")
    parser.add_argument("--frames-per-batch", type=int, default=d["frames_per_batch"],
                        help="frames collected per update, over all environments")
    parser.add_argument("--num-envs", type=int, default=d["num_envs"], help="environments stepped together")
    parser.add_argument("--epochs", type=int, default=d["epochs"], help="passes over each batch")
    parser.add_argument("--minibatch", type=int, default=d["minibatch"], help="frames per gradient step")
    parser.add_argument("--lr", type=float, default=d["lr"], help="Adam's learning rate")
    parser.add_argument("--threads", type=int, default=d["threads"], help="torch threads per run")
    parser.add_argument("--action-noise-std", type=float, default=d["action_noise_std"],
                        help="action_noise mode: noise std as a fraction of the force bound")
    parser.add_argument("--dropout-rate", type=float, default=None,
                        help="stochastic modes: dropout rate (default: the model's calibrated rate, "
                             "else the task's)")
    parser.add_argument("--anneal-updates", type=int, default=None,
                        help="stochastic_annealed: updates to reach rate 0 (default: the task's)")
    parser.add_argument("--eval-episodes", type=int, default=d["eval_episodes"],
                        help="episodes scoring the final policy in the model")
    parser.add_argument("--ground-truth-episodes", type=int, default=d["ground_truth_episodes"],
                        help="with --model: final-policy episodes replayed in pybullet (0: none)")
    parser.add_argument("--eval-every", type=int, default=d["eval_every"],
                        help="every N updates: the deterministic policy at rate 0 on fixed evaluation "
                             "scenes, in the model and (with --model) replayed in pybullet; eval.csv (0: none)")
    parser.add_argument("--eval-scenes", type=int, default=d["eval_scenes"],
                        help="fixed evaluation scenes of --eval-every")
    parser.add_argument("--model", default=None,
                        help="learned HRN checkpoint, a path or a shipped model's name (e.g. cube_push); "
                             "absent: point-mass development dynamics")
    add_strict(parser, "with --model: a task scene")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    add_no_progress(parser)
    parser.add_argument("--no-sleep", action="store_true",
                        help="with --model: every object runs at every step (default: objects the state "
                             "shows at rest sleep until pushed or touched)")
    parser.add_argument("--restart", action="store_true",
                        help="start afresh (default: continue a run from its policy.pt)")
    parser.add_argument("--init-policy", default=None,
                        help="policy checkpoint the actor starts from (another run's policy.pt, or a "
                             "planner's clone); the critic starts fresh")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_training_arguments(parser)
    parser.add_argument("--mode", choices=source_constant("hrn_pyg.rl.tasks", "MODES"), default="stochastic",
                        help="the run's mode")
    parser.add_argument("--seed", type=int, default=0,
                        help="seeds the run's initialisation, batches, noise and environments")
    parser.add_argument("--out", default=None, help="the run's folder (default: runs/rl/<task>/<mode>/seed<seed>)")
    add_moved(parser, ("--num-seeds", "--seeds", "--first-seed", "--seed-start", "--modes"),
              "the sweep over seeds and modes, `python -m experiments.rl.sweep` in a checkout; "
              "`hrn-pyg rl` trains one run (--mode, --seed)")
