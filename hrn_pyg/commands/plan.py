"""``hrn-pyg plan``'s arguments (the work: :mod:`hrn_pyg.rl.planning`), the defaults read from
:class:`~hrn_pyg.rl.planning.PlannerConfig`'s source (:mod:`hrn_pyg.commands.configs`)."""

from __future__ import annotations

import argparse

from hrn_pyg.commands.configs import config_fields, source_constant
from hrn_pyg.commands.rl import TASK_NAMES

PLANNING = "hrn_pyg.rl.planning"


def add_search_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the planner's search, shared by ``hrn-pyg plan`` and the planning sweep."""
    defaults = {f.name: f.default for f in config_fields(PLANNING, "PlannerConfig")}
    parser.add_argument("--refine-steps", type=int, default=3, help="Adam steps of a gradient refinement")
    parser.add_argument("--candidates", type=int, default=defaults["candidates"], help="CEM candidates N")
    parser.add_argument("--elites", type=int, default=defaults["elites"], help="CEM elites E")
    parser.add_argument("--iterations", type=int, default=defaults["iterations"], help="CEM iterations")
    parser.add_argument("--horizon", type=int, default=defaults["horizon"], help="model steps predicted from a start")
    parser.add_argument("--k", type=int, default=defaults["futures"], help="sampled futures per start")
    parser.add_argument("--action-repeat", type=int, default=defaults["action_repeat"],
                        help="model steps each planned action is held (the plan is redone as often)")
    parser.add_argument("--reach-weight", type=float, default=defaults["reach_weight"],
                        help="weight of the pushed object's route length (tasks whose goal object is not pushed)")
    parser.add_argument("--horizontal", action="store_true",
                        help="forces in the ground plane, at most the task's bound in magnitude")
    parser.add_argument("--route-proposal", action="store_true",
                        help="add the full-force push along the reach route to the first CEM draw")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = {f.name: f.default for f in config_fields(PLANNING, "PlannerConfig")}
    parser.add_argument("--task", required=True, choices=sorted(TASK_NAMES), help="an RL task's name")
    parser.add_argument("--model", required=True,
                        help="a model checkpoint: a path or a shipped model's name")
    parser.add_argument("--score", choices=source_constant(PLANNING, "SCORES"), default=defaults["score"],
                        help="how a candidate is scored")
    parser.add_argument("--refine", action="store_true", help="gradient refinement of each plan")
    add_search_arguments(parser)
    parser.add_argument("--rate", type=float, default=None,
                        help="dropout rate of the futures (default: the model's calibrated rate, else the task's)")
    parser.add_argument("--risk-std", type=float, default=defaults["risk_std"], help="c of the risk score")
    parser.add_argument("--control-steps", type=int, default=None,
                        help="stop after this many control steps (default: the task's limit)")
    parser.add_argument("--episode-seed", type=int, default=10_000, help="the pybullet episode simulated")
    parser.add_argument("--seed", type=int, default=0, help="seeds the planner's candidates and masks")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: cuda if available, else cpu)")
    parser.add_argument("--out", default=None,
                        help="output folder: episode.png (the picture) and episode.json (default: runs/plan/<task>)")
