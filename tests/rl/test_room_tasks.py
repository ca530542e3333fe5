"""Tasks with room to learn (``cube_push_stop``, ``cube_push_hold``, ``tower_aside``): configs
and goals (their planners and thresholds: tests/experiments/rl/test_planners.py)."""

import dataclasses
import pytest
import torch

from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.tasks import (
    CUBE_PUSH,
    CUBE_PUSH_HOLD,
    CUBE_PUSH_STOP,
    TASKS,
    TOWER,
    TOWER_ASIDE,
    goal_clearance,
    goal_reached,
    sample_goal,
)

NEW_TASKS = (CUBE_PUSH_STOP, CUBE_PUSH_HOLD, TOWER_ASIDE)


def test_old_tasks_are_unchanged_and_new_ones_are_registered():
    # the run records of the old sweeps hold task.to_dict(): no new keys at the defaults
    for task in (CUBE_PUSH, TOWER, CUBE_PUSH_STOP, TOWER_ASIDE):
        assert "hold_steps" not in task.to_dict() and task.hold_steps == 1
    for task in (CUBE_PUSH, TOWER):
        assert "scene" not in task.to_dict() and "goal_speed" not in task.to_dict()
        assert task.scene_name == task.name
    assert CUBE_PUSH.to_dict()["goal_radius"] == 0.1 and TOWER.to_dict()["max_steps"] == 15
    for task in NEW_TASKS:
        assert TASKS[task.name] is task
    assert CUBE_PUSH_STOP.scene_name == "cube_push" and CUBE_PUSH_STOP.to_dict()["goal_speed"] == 0.005
    assert TOWER_ASIDE.scene_name == "tower" and TOWER_ASIDE.to_dict()["scene"] == "tower"
    # inside the forces the shipped models were trained on (scene force_range 15 N and 8 N)
    assert CUBE_PUSH_STOP.max_force == 15.0 and TOWER_ASIDE.max_force == 8.0


@pytest.mark.parametrize("change", [
    {"goal_kind": "sideways"},
    {"goal_speed": -0.1},
    {"goal_distance": (0.3, 0.1)},
    {"goal_distance": (0.05, 0.15)},   # an aside disc starting over the goal object
    {"hold_steps": 0},
    {"hold_steps": 41},                 # longer than the episode
])
def test_bad_task_configs_raise(change):
    with pytest.raises(ValueError):
        dataclasses.replace(TOWER_ASIDE, **change)


def test_goal_speed_only_for_disc_goals():
    with pytest.raises(ValueError, match="goal_speed"):
        dataclasses.replace(TOWER, goal_speed=0.01)


def test_aside_goal_by_hand_and_never_met_at_reset():
    # ball west of the tower: the line is along x, so the disc lies north or south of the
    # middle cube, goal_distance away
    roots = torch.zeros(2048, 4, 6)
    roots[:, 3, 0] = -0.3
    gen = torch.Generator().manual_seed(0)
    goal = sample_goal(TOWER_ASIDE, roots, gen)
    assert torch.equal(goal[:, 0], torch.zeros(2048))
    lo, hi = TOWER_ASIDE.goal_distance
    assert (goal[:, 1].abs() >= lo - 1e-6).all() and (goal[:, 1].abs() <= hi + 1e-6).all()
    assert 0.4 < (goal[:, 1] > 0).float().mean() < 0.6          # both sides drawn
    assert not goal_reached(TOWER_ASIDE, roots, goal).any()
    # ball south of the tower: the disc lies east or west
    roots[:, 3, :2] = torch.tensor([0.05, -0.3])
    goal = sample_goal(TOWER_ASIDE, roots, gen)
    assert torch.equal(goal[:, 1], torch.zeros(2048)) and (goal[:, 0].abs() >= lo - 1e-6).all()
    # other goal objects already in both possible discs: no goal that needs acting
    crowded = dataclasses.replace(TOWER_ASIDE, goal_objects=(1, 0, 2), goal_distance=(0.13, 0.13))
    roots = torch.zeros(8, 4, 6)
    roots[:, 3, 0] = -0.3
    roots[:, 0, 1], roots[:, 2, 1] = -0.13, 0.13
    with pytest.raises(ValueError, match="aside"):
        sample_goal(crowded, roots, gen)


def test_aside_goals_of_point_mass_resets_need_a_policy():
    dyn = PointMassDynamics.for_task(TOWER_ASIDE.scene_name)
    env = HRNEnv(TOWER_ASIDE, dyn, batch_size=512, seed=3)
    td = env.reset()
    roots = dyn.roots(td["state"])
    assert (goal_clearance(TOWER_ASIDE, roots, td["goal"]) > TOWER_ASIDE.goal_margin).all()
    # the disc is off the line from the ball to the tower by at least 45 degrees
    line = roots[:, 1, :2] - roots[:, 3, :2]
    side = td["goal"] - roots[:, 1, :2]
    cos = (line * side).sum(-1) / (line.norm(dim=-1) * side.norm(dim=-1))
    assert (cos.abs() <= 2 ** -0.5 + 1e-6).all()


def test_goal_speed_a_cube_must_stop_in_the_disc():
    roots = torch.zeros(3, 2, 6)
    roots[:, 1, :2] = 5.0                        # cube 1 far away
    roots[0, 0, 3] = 0.004                       # in the disc, slow: met
    roots[1, 0, 3] = 0.02                        # in the disc, too fast: not met
    roots[2, 0, 0], roots[2, 0, 3] = 0.05, 0.0   # still, outside the 3 cm disc: not met
    goal = torch.zeros(3, 2)
    assert goal_reached(CUBE_PUSH_STOP, roots, goal).tolist() == [True, False, False]
    clearance = goal_clearance(CUBE_PUSH_STOP, roots, goal)
    torch.testing.assert_close(clearance, torch.tensor([-0.001, 0.015, 0.02]))  # max(gap, speed - 0.005)
    # clearance <= 0 exactly when met, on random states
    gen = torch.Generator().manual_seed(1)
    many = torch.randn(4096, 2, 6, generator=gen) * 0.05
    g = torch.randn(4096, 2, generator=gen) * 0.05
    assert torch.equal(goal_clearance(CUBE_PUSH_STOP, many, g) <= 0, goal_reached(CUBE_PUSH_STOP, many, g))


def test_tower_top_aside_the_top_cube_must_rest_beside_the_tower():
    from hrn_pyg.rl.tasks import TOWER_TOP_ASIDE

    task = TOWER_TOP_ASIDE
    assert TASKS[task.name] is task and task.scene_name == "tower" and task.goal_objects == (2,)
    dyn = PointMassDynamics.for_task(task.scene_name)
    env = HRNEnv(task, dyn, batch_size=512, seed=5)
    td = env.reset()
    roots = dyn.roots(td["state"])
    assert (goal_clearance(task, roots, td["goal"]) > task.goal_margin).all()
    dist = (td["goal"] - roots[:, 2, :2]).norm(dim=-1)           # from the top cube's start
    lo, hi = task.goal_distance
    assert (dist >= lo - 1e-6).all() and (dist <= hi + 1e-6).all()
    # the top cube in the disc counts only at rest; the middle cube there does not count
    state = torch.zeros(3, 4, 6)
    state[:, :, :2] = 1.0                                         # everything far away
    state[0, 2, :2] = 0.0                                         # top cube in the disc, at rest
    state[1, 2, :2], state[1, 2, 5] = 0.0, -0.05                  # in the disc, still falling
    state[2, 1, :2] = 0.0                                         # the middle cube, not the top
    assert goal_reached(task, state, torch.zeros(3, 2)).tolist() == [True, False, False]
