r"""Evaluation apart from training: the success curve of a PPO run on fixed evaluation scenes.

Every ``every`` updates the policy is judged the same way whatever the training mode: its
deterministic action, in the learned model at rate 0 without noise, on the same ``episodes``
scenes and goals (a generator reset to ``seed``), each episode replayed open loop and run closed
loop in pybullet (:func:`~hrn_pyg.rl.evaluate.ground_truth_success`). It draws nothing from the
training's random streams. One row per evaluation goes to ``eval.csv`` (:data:`EVAL_FIELDS`).

From a curve of success :math:`s_i` at frames :math:`f_0 < \dots < f_n`: frames to level
:math:`\ell`, :math:`\min\{f_i : s_i \ge \ell\}` (:func:`frames_to_level`, :data:`LEVELS`), and

.. math::
    \mathrm{AUC} = \frac{1}{f_n - f_0} \sum_{i=0}^{n-1} (f_{i+1} - f_i)\,\frac{s_i + s_{i+1}}{2}

(:func:`success_auc`).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule

from hrn_pyg.rl.dynamics import StochasticDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import evaluate_policy, ground_truth_success
from hrn_pyg.rl.tasks import TaskConfig

#: generator seed of the evaluation environment: the fixed evaluation scenes and goals; the same
#: for every mode, seed and evaluation, and apart from the training seeds (small integers)
EVAL_SEED = 900_001
#: success levels whose first crossing (in frames) measures learning speed
LEVELS = (0.5, 0.8)
#: columns of ``eval.csv``
EVAL_FIELDS = ["step", "update", "frames", "model_success_rate", "model_mean_length",
               "pybullet_success_rate", "pybullet_mean_length", "agreement",
               "closed_loop_success_rate", "closed_loop_mean_length"]
#: the judges of a curve: in the learned model, the open-loop replay in pybullet, the policy
#: closed loop in pybullet (columns ``<judge>_success_rate``)
JUDGES = ("model", "pybullet", "closed_loop")


@dataclass(frozen=True)
class EvalConfig:
    """When and on what a run is evaluated.

    Attributes:
        every: updates between evaluations (0: none); update 0 and the last are evaluated too.
        episodes: fixed evaluation scenes, one environment each.
        seed: generator seed of the scenes and goals (:data:`EVAL_SEED`).
        pybullet: replay every episode in pybullet when the dynamics has scenes.
        closed_loop: with ``pybullet``, also run the policy closed loop.
    """

    every: int = 0
    episodes: int = 32
    seed: int = EVAL_SEED
    pybullet: bool = True
    closed_loop: bool = True

    def __post_init__(self) -> None:
        if self.every < 0 or self.episodes < 1:
            raise ValueError(f"need every >= 0 and episodes >= 1, got {self.every}, {self.episodes}")

    def due(self, updates_done: int, total: int) -> bool:
        """Whether to evaluate after ``updates_done`` of ``total`` updates."""
        return self.every > 0 and (updates_done % self.every == 0 or updates_done == total)


def evaluation_env(task: TaskConfig, dynamics: StochasticDynamics, config: EvalConfig,
                   device: str | torch.device | None = None) -> HRNEnv:
    """The environment of the fixed evaluation scenes: ``config.episodes`` environments, rate 0,
    no action noise."""
    return HRNEnv(task, dynamics, batch_size=config.episodes, dropout_rate=0.0,
                  action_noise_std=0.0, seed=config.seed, device=device)


def evaluate_point(policy: TensorDictModule, env: HRNEnv, config: EvalConfig) -> dict[str, float]:
    """One evaluation on the fixed scenes (``env``'s generator reset to ``config.seed``): the keys of
    :func:`~hrn_pyg.rl.evaluate.ground_truth_success`, or only the model's without pybullet scenes."""
    env.rng.manual_seed(config.seed)
    if config.pybullet and hasattr(env.dynamics, "scene_seeds"):
        out = ground_truth_success(policy, env, config.episodes, closed_loop=config.closed_loop)
        out.pop("ground_truth_episodes", None)
        return out
    saved = env.dropout_rate, env.action_noise_std
    env.dropout_rate, env.action_noise_std = 0.0, 0.0
    try:
        success, length = evaluate_policy(policy, env, config.episodes)
    finally:
        env.dropout_rate, env.action_noise_std = saved
    return {"model_success_rate": success, "model_mean_length": length}


def read_eval(path: str | Path) -> dict[str, list[float]]:
    """The columns of an ``eval.csv`` as floats (NaN where a cell is empty), in row order."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {name: [float(r[name]) if r.get(name) not in (None, "") else math.nan for r in rows]
            for name in EVAL_FIELDS}


def _check_curve(frames: Sequence[float], success: Sequence[float]) -> None:
    if len(frames) != len(success) or not frames:
        raise ValueError(f"need as many frames as success values, at least one; got {len(frames)}, "
                         f"{len(success)}")
    if any(b <= a for a, b in zip(frames, frames[1:])):
        raise ValueError("frames must increase strictly")
    if any(math.isnan(s) for s in success):
        raise ValueError("success values must not be NaN")


def frames_to_level(frames: Sequence[float], success: Sequence[float], level: float) -> float:
    """The first frame count at which ``success >= level``; ``math.inf`` when never."""
    _check_curve(frames, success)
    for f, s in zip(frames, success):
        if s >= level:
            return float(f)
    return math.inf


def success_auc(frames: Sequence[float], success: Sequence[float]) -> float:
    """Area under the success curve over its span of frames, in ``[0, 1]`` for rates in
    ``[0, 1]`` (trapezoid rule); a single evaluation gives its own value."""
    _check_curve(frames, success)
    if len(frames) == 1:
        return float(success[0])
    area = sum((f1 - f0) * (s0 + s1) / 2
               for f0, f1, s0, s1 in zip(frames, frames[1:], success, success[1:]))
    return float(area / (frames[-1] - frames[0]))


def curve_summary(curve: dict[str, list[float]], levels: Sequence[float] = LEVELS) -> dict[str, float]:
    """Per judge (``model``; ``pybullet`` and ``closed_loop`` when present, :data:`JUDGES`):
    frames to each level, AUC and the last
    evaluation's success, keyed ``<judge>_frames_to_<level%>``, ``<judge>_success_auc``,
    ``<judge>_final_success``; plus ``eval_points``, ``eval_frames`` (the last)."""
    frames = curve["frames"]
    out: dict[str, float] = {"eval_points": len(frames), "eval_frames": frames[-1] if frames else math.nan}
    for judge in JUDGES:
        success = curve.get(f"{judge}_success_rate", [])
        if not success or any(math.isnan(s) for s in success):
            continue
        for level in levels:
            out[f"{judge}_frames_to_{round(100 * level)}"] = frames_to_level(frames, success, level)
        out[f"{judge}_success_auc"] = success_auc(frames, success)
        out[f"{judge}_final_success"] = success[-1]
    return out
