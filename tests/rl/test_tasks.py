"""Goals that need a policy: no goal is met at reset, for every task and every mode."""

import dataclasses
import math

import pytest
import torch

from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.ppo import PPOConfig, mode_relaxes, mode_settings
from hrn_pyg.rl.tasks import (
    CUBE_PUSH,
    MODES,
    TOWER,
    goal_clearance,
    goal_reached,
    sample_goal,
)

#: goals drawn per task (rounds of ``BATCH`` environments)
DRAWS, BATCH = 8192, 1024
#: half width of the square the scattered cubes start in: it covers the whole goal ring
#: (0.15-0.3 m from the origin, plus the 0.1 m disc), so a goal drawn without the rule is often
#: met at reset
SCATTER = 0.4


class ScatteredDynamics:
    """Two cubes scattered over the cube_push goal ring at reset; a step leaves them where they
    are, whatever the action (k copies of the state)."""

    num_objects, object_dim, state_dim = 2, 6, 12

    def reset_states(self, batch, generator):
        s = torch.zeros(batch, 2, 6)
        s[..., :2] = (torch.rand(batch, 2, 2, generator=generator) * 2 - 1) * SCATTER
        return s.reshape(batch, 12)

    def roots(self, states):
        return states.reshape(*states.shape[:-1], 2, 6)

    def sample_next(self, states, forces, k, rate, generator):
        return states[:, None].repeat(1, k, 1)


def _naive_goals(n: int, generator: torch.Generator) -> torch.Tensor:
    """cube_push goals drawn as before the rule: uniform in the ring, no look at the cubes."""
    lo, hi = CUBE_PUSH.goal_distance
    angle = torch.rand(n, generator=generator) * 2 * math.pi
    dist = lo + (hi - lo) * torch.rand(n, generator=generator)
    return torch.stack([dist * torch.cos(angle), dist * torch.sin(angle)], -1)


def test_sample_goal_never_met_at_reset_thousands_of_draws():
    gen = torch.Generator().manual_seed(0)
    dyn = {"cube_push": ScatteredDynamics(), "tower": PointMassDynamics.for_task("tower")}
    for name, task in (("cube_push", CUBE_PUSH), ("tower", TOWER)):  # the new tasks: test_room_tasks.py
        roots = torch.cat([dyn[name].roots(dyn[name].reset_states(BATCH, gen))
                           for _ in range(DRAWS // BATCH)])                       # (DRAWS, O, 6)
        goal = sample_goal(task, roots, gen)
        assert goal.shape == (DRAWS, 2)
        assert not goal_reached(task, roots, goal).any(), name
        assert (goal_clearance(task, roots, goal) > task.goal_margin).all(), name
        if task.goal_kind == "region":  # still drawn in the ring, and not just one spot
            radius = goal.norm(dim=-1)
            lo, hi = task.goal_distance
            assert (radius >= lo - 1e-6).all() and (radius <= hi + 1e-6).all()
            assert goal.std(0).min() > 0.1
            # the test scenes matter: goals drawn without the rule are often met at reset
            assert goal_reached(task, roots, _naive_goals(DRAWS, gen)).float().mean() > 0.05
        else:
            assert torch.equal(goal, roots[:, task.goal_objects[0], :2])


def test_sample_goal_by_hand():
    # cube 0 at the origin's right on the ring, cube 1 far away: a goal may not lie within
    # 0.15 m of cube 0, and the first candidate that does not is kept
    roots = torch.zeros(1, 2, 6)
    roots[0, 0, :2] = torch.tensor([0.2, 0.0])
    roots[0, 1, :2] = 5.0
    goals = torch.cat([sample_goal(CUBE_PUSH, roots, torch.Generator().manual_seed(s)) for s in range(200)])
    assert ((goals - roots[0, 0, :2]).norm(dim=-1) > 0.15).all()
    clear = torch.tensor([[0.0, 0.0]])  # clearance: nearest cube 0.2 m away -> 0.1 m
    torch.testing.assert_close(goal_clearance(CUBE_PUSH, roots, clear), torch.tensor([0.1]))
    tower = torch.zeros(1, 4, 6)
    tower[0, 1, :2] = torch.tensor([0.03, 0.04])  # middle cube 5 cm off the goal point
    torch.testing.assert_close(goal_clearance(TOWER, tower, torch.zeros(1, 2)), torch.tensor([0.05]))


def test_sample_goal_raises_when_no_goal_can_need_a_policy():
    roots = torch.zeros(3, 2, 6)  # both cubes at the origin, goals drawn within 5 cm of it
    tight = dataclasses.replace(CUBE_PUSH, goal_distance=(0.0, 0.05))
    with pytest.raises(ValueError, match="needs acting"):
        sample_goal(tight, roots, torch.Generator().manual_seed(0))
    apart = dataclasses.replace(TOWER, goal_objects=(0, 3))  # the ball starts off the axis
    roots = torch.zeros(2, 4, 6)
    roots[:, 3, 0] = 0.3
    with pytest.raises(ValueError, match="met at reset"):
        sample_goal(apart, roots, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="goal_margin"):
        dataclasses.replace(TOWER, goal_margin=0.1)
    with pytest.raises(ValueError, match="goal_margin"):
        dataclasses.replace(CUBE_PUSH, goal_margin=-0.01)


def _mode_env(task, dynamics, mode: str, seed: int, batch: int) -> HRNEnv:
    """An environment set up as PPO sets it up for ``mode`` at its first update."""
    schedule, noise = mode_settings(mode, task, PPOConfig())
    return HRNEnv(task, dynamics, batch_size=batch, dropout_rate=schedule(0),
                  action_noise_std=noise, relax=mode_relaxes(mode), seed=seed)


@pytest.mark.parametrize("mode", MODES)
def test_env_reset_never_starts_in_the_goal(mode):
    for task, dyn in ((CUBE_PUSH, ScatteredDynamics()), (CUBE_PUSH, PointMassDynamics.for_task("cube_push")),
                      (TOWER, PointMassDynamics.for_task("tower"))):
        env = _mode_env(task, dyn, mode, seed=MODES.index(mode), batch=512)
        for _ in range(4):  # 2048 resets per task and dynamics
            td = env.reset()
            roots = dyn.roots(td["state"])
            assert not goal_reached(task, roots, td["goal"]).any()
            assert (goal_clearance(task, roots, td["goal"]) > task.goal_margin).all()
            torch.testing.assert_close(td["observation"][:, -2:], td["goal"])


@pytest.mark.parametrize("mode", ["deterministic", "stochastic", "stochastic_annealed", "stochastic_unrelaxed"])
def test_zero_action_for_a_whole_episode_never_succeeds(mode):
    """Point-mass dynamics: with no force the objects stay put, at any dropout rate (the force
    noise scales with the force), so the episode runs to ``max_steps`` with reward 0. The
    action-noise mode is left out: its noise pushes the objects even under a zero action."""
    for task in (CUBE_PUSH, TOWER):
        env = _mode_env(task, PointMassDynamics.for_task(task.name), mode, seed=1, batch=256)
        td = env.rollout(task.max_steps, policy=lambda td: td.set("action", torch.zeros(env.action_spec.shape)),
                         break_when_any_done=False)
        assert td.shape == (256, task.max_steps)
        assert not td["next", "terminated"].any() and (td["next", "reward"] == 0).all()
        assert td["next", "truncated"][:, -1].all()  # every episode ran its full length
        success = td["next", "terminated"][:, -1].float().mean()
        assert success == 0.0
