"""Partial-hit share: how often the ``k`` sampled futures of a step straddle the goal.

Reward relaxation rewards a step when *any* of the ``k`` samples meets the goal. It can only
change a reward at a step where some samples meet the goal and others do not; when the spread
of the samples is small against the goal tolerance, every step has either all or none of them
in the goal and the stochastic environment trains exactly like the deterministic one. The
*partial-hit share* of a task, rate and tolerance is the fraction of environment steps at
which

.. math::
    0 < h_t < k, \\qquad h_t = \\sum_{j=1}^k \\mathbb 1\\big[\\mathrm{goal}(s^{(j)}_{t+1})\\big],

counted over every step of every episode (an episode ends at the goal or at the step limit).
The *near-miss share* counts the same steps among the goal-reaching ones (:math:`h_t > 0`),
:func:`~hrn_pyg.rl.env.near_miss_share`: under relaxation the share over all steps is capped
near ``hold_steps`` over the episode length, this one is not (a task that must hold its goal
for several steps, ``cube_push_hold``, lifts that cap). PPO logs both per update over the
batch it collected (``partial_hit_share`` and ``near_miss_share`` in ``log.csv``);
:func:`partial_hit_share` measures it for a uniformly random policy, which is the policy at
update 0, and :func:`partial_hit_table` for a grid of rates and goal tolerances, so that a rate
and tolerance with a useful share (say 10-30 % of steps) can be chosen before any training run.

Measure on scenes the agent does not train on:
:data:`~hrn_pyg.rl.hrn_dynamics.VALIDATION_SEEDS` (``experiments/rl/score_partial_hits.py`` builds its
learned dynamics on them).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import torch
from torch import Tensor
from torchrl.envs.utils import step_mdp

from experiments.rl.planners import Planner
from hrn_pyg.rl.dynamics import StochasticDynamics
from hrn_pyg.rl.env import HRNEnv, partial_hits
from hrn_pyg.rl.tasks import TaskConfig, get_task


def random_actions(task: TaskConfig, batch: int, generator: torch.Generator) -> Tensor:
    """Actions drawn uniformly inside the force bounds, ``(B, A)`` on the generator's device:
    the action distribution of an untrained policy, without its network."""
    u = torch.rand(batch, task.action_dim, generator=generator, device=generator.device)
    return (2 * u - 1) * task.max_force


def with_tolerance(task: TaskConfig, tolerance: float | None) -> TaskConfig:
    """``task`` with goal radius ``tolerance`` metres (None: unchanged). The task's own checks
    apply (a displaced goal needs ``tolerance > goal_margin``)."""
    if tolerance is None:
        return task
    if not tolerance > 0:
        raise ValueError(f"goal tolerance must be positive, got {tolerance}")
    return dataclasses.replace(task, goal_radius=float(tolerance))


@torch.no_grad()
def partial_hit_share(task: str | TaskConfig, dynamics: StochasticDynamics, rate: float,
                      episodes: int, *, num_samples: int | None = None, num_envs: int = 32,
                      relax: bool = True, seed: int = 0, policy: Planner | None = None,
                      action_noise_std: float = 0.0) -> dict[str, float | int]:
    r"""The partial-hit share of a policy at dropout ``rate``, over ``episodes`` episodes.

    ``policy``: None, a uniformly random policy (the policy at update 0); else a planner
    (:mod:`experiments.rl.planners`) called on each observation, e.g. the task's scripted planner,
    with Gaussian action noise of ``action_noise_std`` times the force bound added by the
    environment (the ``action_noise`` mode's exploration, closer to what PPO tries than a
    random policy), or a policy with a ``manual_seed`` method that draws its own actions
    (:class:`~experiments.rl.clone.ActorPolicy` sampling a cloned actor, PPO's update 0 when it
    starts from the clone): it is reseeded with ``seed + 2`` first.

    Runs rounds of ``num_envs`` environments (:class:`~hrn_pyg.rl.env.HRNEnv`, seeded with
    ``seed``; the actions from a second generator seeded with ``seed + 1``) until ``episodes``
    episodes have ended; in the last round only the first environments needed are counted. The
    result depends only on its arguments.

    Returns ``steps`` (counted), ``partial_steps``, ``partial_hit_share``
    (``partial_steps / steps``), ``any_hit_steps`` (steps with at least one sample in the
    goal), ``near_miss_share`` (``partial_steps / any_hit_steps``, None without a hit; also
    under its older name ``partial_of_hit_steps``),
    ``success_rate`` and ``mean_length`` of the episodes (relaxed or not, as ``relax``), and the
    settings: ``rate``, ``tolerance`` (the task's goal radius), ``k``, ``episodes``,
    ``action_noise_std``.

    **A bound.** With relaxation the ``hold_steps``-th goal-reaching step in a row (:math:`H`)
    ends the episode, so an episode whose goal-reaching steps all come in a row has at most
    :math:`H` of them and
    :math:`\text{share} \le \text{any\_hit\_steps} / \text{steps} \lesssim H / \bar T` for
    a mean episode length :math:`\bar T`: with :math:`H = 1` a policy that needs 10 steps
    cannot exceed 10 % whatever the spread. ``near_miss_share`` says how the spread compares
    with the goal where it matters (1: every goal-reaching step is straddled).
    """
    task = get_task(task)
    if episodes < 1 or num_envs < 1:
        raise ValueError(f"episodes and num_envs must be >= 1, got {episodes}, {num_envs}")
    B = min(num_envs, episodes)
    env = HRNEnv(task, dynamics, batch_size=B, num_samples=num_samples, dropout_rate=rate,
                 relax=relax, seed=seed, action_noise_std=action_noise_std)
    k = env.num_samples
    actions = torch.Generator(device=env.rng.device).manual_seed(seed + 1)
    if hasattr(policy, "manual_seed"):
        policy.manual_seed(seed + 2)
    steps = partial = any_hit = successes = length_sum = 0
    for start in range(0, episodes, B):  # a loop over rounds of B episodes
        counted = torch.arange(B, device=env.device) < min(B, episodes - start)
        alive = counted.clone()
        td = env.reset()
        for _ in range(task.max_steps):  # a loop over time steps
            drawn = random_actions(task, B, actions).to(env.device)  # drawn either way: one stream
            td["action"] = drawn if policy is None else policy(task, td["observation"])
            td = env.step(td)
            hits = td["next", "goal_hits"].squeeze(-1)
            steps += int(alive.sum())
            partial += int((partial_hits(hits, k) & alive).sum())
            any_hit += int(((hits > 0) & alive).sum())
            done = td["next", "done"].squeeze(-1) & alive
            successes += int((done & td["next", "terminated"].squeeze(-1)).sum())
            length_sum += int(td["next", "t"].squeeze(-1)[done].sum())
            alive &= ~done
            if not alive.any():
                break
            td = step_mdp(td)
    return {"rate": float(rate), "tolerance": task.goal_radius, "k": k, "episodes": episodes,
            "steps": steps, "partial_steps": partial, "partial_hit_share": partial / steps,
            "any_hit_steps": any_hit, "success_rate": successes / episodes,
            "mean_length": length_sum / episodes, "action_noise_std": float(action_noise_std),
            "partial_of_hit_steps": partial / any_hit if any_hit else None,
            "near_miss_share": partial / any_hit if any_hit else None}


def partial_hit_table(task: str | TaskConfig, dynamics: StochasticDynamics, rates: Sequence[float],
                      tolerances: Sequence[float | None], episodes: int, **kwargs) -> list[dict]:
    """:func:`partial_hit_share` for every rate and goal tolerance (rows in the order
    ``tolerance`` major, ``rate`` minor); ``kwargs`` go to it, the same seed for every cell, so
    that the cells differ only by rate and tolerance."""
    task = get_task(task)
    if not rates or not tolerances:
        raise ValueError("need at least one rate and one tolerance")
    rows = []
    for tolerance in tolerances:  # a small grid; each cell is a batch of episodes
        cell_task = with_tolerance(task, tolerance)
        for rate in rates:
            rows.append(partial_hit_share(cell_task, dynamics, rate, episodes, **kwargs))
    return rows


def in_band(rows: list[dict], low: float = 0.1, high: float = 0.3) -> list[dict]:
    """The rows whose partial-hit share lies in ``[low, high]``."""
    if not 0 <= low <= high <= 1 or math.isnan(low + high):
        raise ValueError(f"need 0 <= low <= high <= 1, got {low}, {high}")
    return [r for r in rows if low <= r["partial_hit_share"] <= high]
