import dataclasses

import pytest
import torch

from experiments.rl.partial_hits import (
    in_band,
    partial_hit_share,
    partial_hit_table,
    random_actions,
    with_tolerance,
)
from experiments.rl.planners import greedy_push
from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.tasks import CUBE_PUSH, TOWER

#: cube_push with its goal disc at the origin
AT_ORIGIN = dataclasses.replace(CUBE_PUSH, goal_distance=(0.0, 0.0))


class Offsets:
    """Sample j puts cube 0 at x = offsets[j] (cube 1 stays 5 m away), whatever the state."""

    num_objects, object_dim, state_dim = 2, 6, 12

    def __init__(self, offsets):
        self.offsets = torch.tensor(offsets, dtype=torch.float32)

    def reset_states(self, batch, generator):
        return torch.full((batch, 12), 5.0)

    def roots(self, states):
        return states.reshape(*states.shape[:-1], 2, 6)

    def sample_next(self, states, forces, k, rate, generator):
        out = states[:, None].repeat(1, k, 1)
        out[..., 0] = self.offsets[:k]
        out[..., 1] = 0.0
        return out


class Steered(Offsets):
    """Cube 0 starts 0.3 m from the goal and moves 1 cm per newton of x force, the same in every
    sample: only the actions decide when it arrives."""

    def __init__(self):
        pass

    def reset_states(self, batch, generator):
        states = torch.full((batch, 12), 5.0)
        states[:, :2] = torch.tensor([0.3, 0.0])
        return states

    def sample_next(self, states, forces, k, rate, generator):
        out = states.clone()
        out[:, 0] += 0.01 * forces[:, 0, 0]
        return out[:, None].repeat(1, k, 1)


def test_one_sample_of_five_in_the_goal_is_a_partial_hit_at_every_step():
    relaxed = partial_hit_share(AT_ORIGIN, Offsets([0.0, 5, 5, 5, 5]), 0.1, episodes=10, num_envs=4)
    # relaxation: every episode ends at its first step, rewarded
    assert relaxed["steps"] == 10 and relaxed["partial_steps"] == 10 and relaxed["partial_hit_share"] == 1.0
    assert relaxed["success_rate"] == 1.0 and relaxed["mean_length"] == 1.0 and relaxed["any_hit_steps"] == 10
    # without relaxation an episode ends only when the drawn sample is the one in the goal
    plain = partial_hit_share(AT_ORIGIN, Offsets([0.0, 5, 5, 5, 5]), 0.1, episodes=200, relax=False)
    assert plain["partial_hit_share"] == 1.0
    assert plain["steps"] == round(plain["mean_length"] * 200)  # every step of every episode counted
    expected = (1 - 0.8 ** 10) / 0.2                             # truncated geometric, p = 1/5
    assert abs(plain["mean_length"] - expected) < 0.8
    assert 0.8 < plain["success_rate"] < 0.95                    # 1 - 0.8^10 = 0.89


def test_all_or_none_in_the_goal_is_never_partial_and_the_last_round_is_cut():
    none = partial_hit_share(AT_ORIGIN, Offsets([5.0] * 5), 0.1, episodes=10, num_envs=4)
    assert none["steps"] == 10 * CUBE_PUSH.max_steps  # rounds of 4, 4 and 2 counted episodes
    assert none["partial_steps"] == none["any_hit_steps"] == 0 and none["success_rate"] == 0.0
    assert none["mean_length"] == CUBE_PUSH.max_steps
    every = partial_hit_share(AT_ORIGIN, Offsets([0.0] * 5), 0.1, episodes=3)
    assert every["partial_hit_share"] == 0.0 and every["any_hit_steps"] == every["steps"] == 3
    assert (every["tolerance"], every["k"], every["rate"]) == (0.1, 5, 0.1)


def test_share_is_deterministic_given_the_seed():
    dyn = PointMassDynamics.for_task("tower")
    loose = with_tolerance(TOWER, 0.06)
    a = partial_hit_share(loose, dyn, 0.5, episodes=6, num_envs=3, seed=4)
    b = partial_hit_share(loose, dyn, 0.5, episodes=6, num_envs=3, seed=4)
    assert a == b and a["steps"] > 0


def test_share_differs_between_seeds():
    # the scripted push reaches the goal in about five steps, so the share is neither 0 nor 1;
    # with a planner only the environment's seed draws (its starts and its samples)
    dyn = PointMassDynamics.for_task("cube_push")
    planned = [partial_hit_share(CUBE_PUSH, dyn, 0.5, episodes=8, num_envs=4, seed=seed, policy=greedy_push)
               for seed in (4, 5, 6, 7)]
    assert all(0 < r["partial_hit_share"] < 1 for r in planned)
    assert len({r["partial_hit_share"] for r in planned}) >= 3
    again = partial_hit_share(CUBE_PUSH, dyn, 0.5, episodes=8, num_envs=4, seed=6, policy=greedy_push)
    assert again == planned[2]
    # a random policy where only the actions move anything: the actions' stream follows the seed
    steered = [partial_hit_share(AT_ORIGIN, Steered(), 0.1, episodes=8, num_envs=4, seed=seed)
               for seed in (4, 5, 6)]
    assert len({(r["steps"], r["any_hit_steps"]) for r in steered}) == 3


def test_table_covers_the_grid_and_band_filters():
    rows = partial_hit_table(AT_ORIGIN, Offsets([0.0, 5, 5, 5, 5]), [0.1, 0.3], [0.05, 0.2], episodes=2)
    assert [(r["tolerance"], r["rate"]) for r in rows] == [(0.05, 0.1), (0.05, 0.3), (0.2, 0.1), (0.2, 0.3)]
    rows[0]["partial_hit_share"] = 0.2
    assert in_band(rows[:1]) == rows[:1] and in_band(rows[1:2], 0.1, 0.3) == []
    with pytest.raises(ValueError):
        in_band(rows, 0.5, 0.1)
    with pytest.raises(ValueError, match="rate"):
        partial_hit_table(AT_ORIGIN, Offsets([0.0]), [], [None], episodes=1)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="goal_margin"):
        with_tolerance(TOWER, 0.04)  # a displaced goal within its margin would be met at reset
    with pytest.raises(ValueError, match="positive"):
        with_tolerance(CUBE_PUSH, 0.0)
    with pytest.raises(ValueError, match="episodes"):
        partial_hit_share(AT_ORIGIN, Offsets([0.0]), 0.1, episodes=0)
    assert with_tolerance(CUBE_PUSH, None) is CUBE_PUSH


def test_random_actions_fill_the_bounds():
    a = random_actions(TOWER, 4096, torch.Generator().manual_seed(0))
    assert a.shape == (4096, 3) and a.abs().max() <= TOWER.max_force
    assert a.min() < -0.95 * TOWER.max_force and a.max() > 0.95 * TOWER.max_force
