"""Reinforcement learning over the stochastic HRN: a TorchRL environment and PPO."""

from hrn_pyg.rl.dynamics import PointMassDynamics, StochasticDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.policy import load_policy
from hrn_pyg.rl.tasks import CUBE_PUSH, TASKS, TOWER, TaskConfig, get_task

__all__ = ["HRNEnv", "StochasticDynamics", "PointMassDynamics", "TaskConfig", "TASKS", "CUBE_PUSH", "TOWER", "get_task", "load_policy"]
