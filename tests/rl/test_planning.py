"""The model-predictive planner: one batched graph of candidates x futures, the CEM search, the
three scores, gradient refinement, determinism, bad input, and ``hrn-pyg plan`` end to end."""

import json
import math

import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.planning import (
    APPROACH_DISTANCE,
    CONTACT_DISTANCE,
    MPCPlanner,
    PlannerConfig,
    cem,
    detour_length,
    episode_goal,
    plan_episode,
    planning_rewards,
    project_actions,
    refine,
    rollout_futures,
    route_length,
    route_object,
    route_push,
    score_returns,
)
from hrn_pyg.rl.tasks import CUBE_PUSH_STOP, TOWER_ASIDE, action_to_forces
from hrn_pyg.sim.copy_groups import MAX_NODES_PER_GROUP

SEED = 10_000


@pytest.fixture(scope="module")
def dynamics():
    torch.set_num_threads(1)
    return HRNDynamics.from_checkpoint("cube_push", CUBE_PUSH_STOP, pool_seeds=(SEED,))


def _start(dyn):
    return dyn.state_of(dyn.pool[0], torch.tensor(0))


def _actions(n, h, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, h, CUBE_PUSH_STOP.action_dim, generator=gen) * 2 - 1) * CUBE_PUSH_STOP.max_force


def _copies_seen(dyn):
    seen = []
    handle = dyn.model.register_forward_pre_hook(lambda _m, args: seen.append(int(args[0].batch.max()) + 1))
    return seen, handle


def test_one_graph_holds_candidates_times_futures_and_equals_single_rollouts(dynamics):
    N, K, H, rate = 3, 2, 2, 0.3
    state, actions = _start(dynamics), _actions(N, H)
    seen, handle = _copies_seen(dynamics)
    try:
        roots = rollout_futures(dynamics, state, actions, K, rate, torch.Generator().manual_seed(1))
    finally:
        handle.remove()
    assert roots.shape == (N, K, H, 2, 6)
    assert seen == [N * K] * H                       # one pass of N K copies per model step
    assert not torch.allclose(roots[:, 0], roots[:, 1])   # the futures differ
    for i in range(N):  # the slow path: one candidate at a time, the same masks
        alone = rollout_futures(dynamics, state, actions[i:i + 1], K, rate, torch.Generator().manual_seed(1))
        torch.testing.assert_close(alone[0], roots[i], atol=1e-5, rtol=0)


def test_grouped_pass_over_many_copies_equals_one_candidate_at_a_time(dynamics):
    N, K = 8, 8  # 64 copies of 72 nodes: more than one copy group
    per_copy = dynamics.structure_graph()["particle"].num_nodes
    assert N * K * per_copy > MAX_NODES_PER_GROUP
    state, actions = _start(dynamics), _actions(N, 1, seed=2)
    roots = rollout_futures(dynamics, state, actions, K, 0.3, torch.Generator().manual_seed(4))
    for i in (0, N - 1):
        alone = rollout_futures(dynamics, state, actions[i:i + 1], K, 0.3, torch.Generator().manual_seed(4))
        torch.testing.assert_close(alone[0], roots[i], atol=1e-5, rtol=0)


def test_deterministic_rollout_equals_the_environment_step(dynamics):
    state, actions = _start(dynamics), _actions(1, 1, seed=3)
    roots = rollout_futures(dynamics, state, actions, 1, 0.0, torch.Generator())
    forces = action_to_forces(CUBE_PUSH_STOP, actions[:, 0])
    nxt = dynamics.sample_next(state[None], forces, 1, 0.0, torch.Generator())
    torch.testing.assert_close(roots[0, 0, 0], dynamics.roots(nxt[0, 0]), atol=1e-6, rtol=0)


def test_cem_improves_a_known_toy_objective():
    target = torch.tensor([[3.0, -2.0], [1.0, 4.0], [-5.0, 0.5]])

    def score_fn(actions):
        return -((actions - target) ** 2).sum((-1, -2))

    config = PlannerConfig(candidates=64, elites=8, iterations=6, horizon=3)
    mean = torch.zeros(3, 2)
    best, score, _, std = cem(score_fn, mean, torch.full_like(mean, 5.0), 10.0, config,
                              torch.Generator().manual_seed(0))
    assert float(score) > float(score_fn(mean[None])[0]) * 0.01   # from -56 to about 0
    assert (best - target).abs().max() < 0.5
    assert (std < 5.0).all()
    # the bounds hold: a target outside them is approached from inside
    best, _, _, _ = cem(score_fn, mean, torch.full_like(mean, 5.0), 2.0, config, torch.Generator().manual_seed(0))
    assert best.abs().max() <= 2.0


def test_scores_are_ordered_as_defined_on_a_hand_made_return_matrix():
    returns = torch.tensor([[1.0, 1.0, 1.0],     # sure, modest
                            [0.0, 2.0, 4.0],     # best on average, spread out
                            [3.0, -1.0, 1.0]])   # the deterministic column's favourite
    det = score_returns(returns, "deterministic")
    mean = score_returns(returns, "mean")
    risk = score_returns(returns, "risk", risk_std=1.0)
    assert det.tolist() == [1.0, 0.0, 3.0] and mean.tolist() == [1.0, 2.0, 1.0]
    spread = returns.std(1, correction=0)
    torch.testing.assert_close(risk, mean - spread)
    assert (det.argmax(), mean.argmax(), risk.argmax()) == (2, 1, 0)
    assert (risk <= mean).all() and risk[0] == mean[0]        # agreeing futures: no penalty
    assert torch.equal(score_returns(returns, "risk", risk_std=0.0), mean)


def test_refinement_lowers_the_planning_loss(dynamics):
    target = torch.tensor([[1.0, 2.0]])
    best, losses = refine(lambda u: ((u - target) ** 2).sum(), torch.zeros(1, 2), 5.0, 20, 0.3)
    assert len(losses) == 21
    assert losses[-1] < 0.1 * losses[0] and ((best - target) ** 2).sum() == min(losses)
    # through the learned rollout: the deterministic score of a plan from rest
    planner = MPCPlanner(dynamics, PlannerConfig(horizon=3), seed=0)
    goal = episode_goal(CUBE_PUSH_STOP, dynamics, 0, SEED)
    score_fn = planner.objective(_start(dynamics), goal, mask_seed=0)
    start = _actions(1, 3, seed=5)[0] * 0.3        # pushed: a resting, unpushed cube sleeps (no gradient)
    best, losses = refine(lambda u: -score_fn(u.unsqueeze(0))[0], start, CUBE_PUSH_STOP.max_force, 4, 1.5)
    assert min(losses) < losses[0]
    assert float(-score_fn(best[None])[0]) == pytest.approx(min(losses), abs=1e-5)
    assert best.abs().max() <= CUBE_PUSH_STOP.max_force


def test_planner_is_deterministic_given_its_seed(dynamics):
    config = PlannerConfig(score="mean", candidates=4, elites=2, iterations=1, horizon=2, futures=2,
                           refine_steps=1)
    state, goal = _start(dynamics), episode_goal(CUBE_PUSH_STOP, dynamics, 0, SEED)
    a = MPCPlanner(dynamics, config, seed=7).plan(state, goal)
    b = MPCPlanner(dynamics, config, seed=7).plan(state, goal)
    c = MPCPlanner(dynamics, config, seed=8).plan(state, goal)
    assert torch.equal(a["actions"], b["actions"]) and a["score"] == b["score"]
    assert not torch.equal(a["actions"], c["actions"])
    assert MPCPlanner(dynamics, config).rate == CUBE_PUSH_STOP.dropout_rate  # no calibrated rate


@pytest.mark.parametrize("change, match", [
    ({"score": "median"}, "score"),
    ({"candidates": 0}, "candidates"),
    ({"elites": 20}, "elites"),
    ({"rate": 1.5}, "rate"),
    ({"discount": 0.0}, "discount"),
    ({"action_repeat": 0}, "action_repeat"),
])
def test_bad_planner_settings_raise(change, match):
    with pytest.raises(ValueError, match=match):
        PlannerConfig(**change)


def test_bad_rollouts_and_returns_raise(dynamics):
    state = _start(dynamics)
    with pytest.raises(ValueError, match="futures"):
        rollout_futures(dynamics, state, _actions(2, 2), 2, 0.0, torch.Generator())
    with pytest.raises(ValueError, match="actions"):
        rollout_futures(dynamics, state, torch.zeros(2, 2, 3), 1, 0.0, torch.Generator())
    with pytest.raises(ValueError, match="returns"):
        score_returns(torch.zeros(3), "mean")
    with pytest.raises(ValueError, match="rate"):
        MPCPlanner(dynamics, PlannerConfig(score="risk", rate=0.0))
    with pytest.raises(ValueError, match="pool entry"):
        plan_episode(MPCPlanner(dynamics, PlannerConfig()), SEED + 1, torch.zeros(2))


def test_plan_command_runs_one_short_closed_loop_episode(tmp_path, capsys):
    out = tmp_path / "plan"
    rc = main(["plan", "--task", "cube_push_stop", "--model", "cube_push", "--score", "risk", "--refine",
               "--refine-steps", "1", "--candidates", "4", "--elites", "2", "--iterations", "1",
               "--horizon", "2", "--k", "2", "--control-steps", "2", "--device", "cpu", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and (out / "episode.png").stat().st_size > 0
    record = json.loads((out / "episode.json").read_text())
    assert record["steps"] == 2 and record["device"] == "cpu" and len(record["plan_seconds"]) == 2
    assert "after 2 steps" in text and "planning per control step" in text and "pybullet step" in text


def test_plan_command_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    rc = main(["plan", "--task", "cube_push_stop", "--model", "cube_push", "--candidates", "0",
               "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "candidates" in err


def test_action_repeat_holds_each_planned_action_and_replans_once_per_hold(dynamics):
    state, goal = _start(dynamics), episode_goal(CUBE_PUSH_STOP, dynamics, 0, SEED)
    actions = _actions(3, 2, seed=6)
    held = MPCPlanner(dynamics, PlannerConfig(horizon=2, action_repeat=3)).objective(state, goal, mask_seed=0)
    flat = MPCPlanner(dynamics, PlannerConfig(horizon=6)).objective(state, goal, mask_seed=0)
    # a plan of 2 actions held 3 model steps scores as the 6-step plan that repeats them
    torch.testing.assert_close(held(actions), flat(actions.repeat_interleave(3, dim=1)), atol=1e-5, rtol=0)
    planner = MPCPlanner(dynamics, PlannerConfig(candidates=2, elites=1, iterations=1, horizon=2, action_repeat=3))
    plans = []
    original = planner.plan
    planner.plan = lambda s, g: plans.append(1) or original(s, g)
    got = [planner.act(state, goal) for _ in range(7)]
    assert len(plans) == 3                                   # calls 0, 3 and 6 plan
    assert torch.equal(got[0], got[1]) and torch.equal(got[0], got[2])
    planner.reset()
    planner.act(state, goal)
    assert len(plans) == 4                                   # a reset plans afresh


def test_horizontal_projection_keeps_forces_in_the_ground_plane_and_the_disc():
    bound = TOWER_ASIDE.max_force
    actions = torch.tensor([[3.0, 4.0, 5.0], [8.0, 8.0, -2.0], [-20.0, 0.0, 1.0]])
    out = project_actions(TOWER_ASIDE, actions, horizontal=True)
    assert (out[:, 2] == 0).all()
    torch.testing.assert_close(out[0], torch.tensor([3.0, 4.0, 0.0]))             # inside: kept
    torch.testing.assert_close(out[1, :2].norm(), torch.tensor(bound))             # scaled to the rim
    torch.testing.assert_close(out[1, 0], out[1, 1])                               # direction kept
    torch.testing.assert_close(out[2], torch.tensor([-bound, 0.0, 0.0]))
    boxed = project_actions(TOWER_ASIDE, actions, horizontal=False)
    assert torch.equal(boxed, actions.clamp(-bound, bound))
    # the two controlled cubes of cube_push_stop are projected one by one
    two = project_actions(CUBE_PUSH_STOP, torch.tensor([30.0, 40.0, 1.0, 2.0]), horizontal=True)
    torch.testing.assert_close(two, torch.tensor([9.0, 12.0, 1.0, 2.0]))


def test_detour_length_goes_around_the_disc_only_when_the_segment_crosses_it():
    c = torch.zeros(2)
    a, b = torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 0.0])
    tangent, arc = math.sqrt(1 - 0.25), 0.5 * (math.pi - 2 * math.acos(0.5))
    assert float(detour_length(a, b, c, 0.5)) == pytest.approx(2 * tangent + arc, abs=1e-5)
    assert float(detour_length(a, torch.tensor([1.0, 2.0]), c, 0.5)) == pytest.approx(math.sqrt(8), abs=1e-6)
    assert float(detour_length(a, b, torch.tensor([0.0, 0.6]), 0.5)) == pytest.approx(2.0, abs=1e-6)


def _tower_roots(ball, obj=(0.0, 0.0)):
    roots = torch.zeros(4, 6)
    roots[:3, :2] = torch.tensor(obj)
    roots[3, :2] = torch.tensor(ball)
    return roots


def test_route_leads_around_the_tower_to_the_approach_point_then_through_it():
    goal, u = torch.tensor([0.0, 0.13]), torch.tensor([0.0, 1.0])   # push along +y
    end = goal[1] - CONTACT_DISTANCE
    # behind the tower, on the push line: straight to where the ball stands at the end
    behind = route_length(TOWER_ASIDE, _tower_roots((0.0, -0.2)), goal, u)
    assert float(behind) == pytest.approx(end + 0.2, abs=1e-6)
    # at the approach point the two legs meet
    at_a = route_length(TOWER_ASIDE, _tower_roots((0.0, -APPROACH_DISTANCE)), goal, u)
    assert float(at_a) == pytest.approx(end + APPROACH_DISTANCE, abs=1e-6)
    # beside the tower (the side the goal lies off): back to the approach point first, more than
    # the straight line to the end
    side = route_length(TOWER_ASIDE, _tower_roots((-0.3, 0.0)), goal, u)
    assert float(side) > math.hypot(0.3, end) + 0.1
    # on the goal's side: the route wraps the tower, longer than from beside it
    front = route_length(TOWER_ASIDE, _tower_roots((0.0, 0.3)), goal, u)
    assert float(front) > float(side)
    # going around lowers it step by step
    path = [(-0.3, 0.0), (-0.25, -0.15), (-0.1, -0.24), (0.0, -0.2), (0.0, -0.15)]
    lengths = [float(route_length(TOWER_ASIDE, _tower_roots(p), goal, u)) for p in path]
    assert lengths == sorted(lengths, reverse=True)
    # the planning reward carries it with its weight; a directly pushed goal object has none
    r = planning_rewards(TOWER_ASIDE, _tower_roots((0.0, -0.2)), goal, 0.5, u)
    assert float(r) == pytest.approx(-(0.13 - TOWER_ASIDE.goal_radius) - 0.5 * float(behind), abs=1e-6)
    cube = torch.zeros(2, 6)
    assert float(planning_rewards(CUBE_PUSH_STOP, cube, torch.tensor([0.2, 0.0]), 0.5)) == \
        pytest.approx(-(0.2 - CUBE_PUSH_STOP.goal_radius), abs=1e-6)


def test_route_runs_around_the_lowest_free_object_and_its_push_follows_it():
    roots = _tower_roots((0.0, -0.2))
    roots[:3, 2] = torch.tensor([0.05, 0.15, 0.25])
    assert route_object(TOWER_ASIDE, roots) == 0
    roots[2, 2] = 0.05 - 0.01                                      # the top cube fell below the base
    assert route_object(TOWER_ASIDE, roots) == 2
    goal, u = torch.tensor([0.0, 0.13]), torch.tensor([0.0, 1.0])
    behind = route_push(TOWER_ASIDE, _tower_roots((0.0, -0.2)), goal, u, pushed=0)
    torch.testing.assert_close(behind, torch.tensor([0.0, TOWER_ASIDE.max_force, 0.0]))
    side = route_push(TOWER_ASIDE, _tower_roots((-0.3, 0.0)), goal, u, pushed=0)
    assert side[2] == 0 and float(side[:2].norm()) == pytest.approx(TOWER_ASIDE.max_force, abs=1e-4)
    assert side[0] > 0 and side[1] < 0                             # toward the approach point, behind


def test_cem_tries_the_proposals_in_its_first_draw():
    target = torch.tensor([[4.0, -4.0], [4.0, -4.0]])

    def score_fn(actions):
        return -((actions - target) ** 2).sum((-1, -2))

    config = PlannerConfig(candidates=4, elites=1, iterations=1, horizon=2)
    mean, std = torch.zeros(2, 2), torch.full((2, 2), 0.1)
    best, score, _, _ = cem(score_fn, mean, std, 10.0, config, torch.Generator().manual_seed(0),
                            proposals=target.unsqueeze(0))
    assert torch.equal(best, target) and float(score) == 0.0
    without, _, _, _ = cem(score_fn, mean, std, 10.0, config, torch.Generator().manual_seed(0))
    assert (without - target).abs().max() > 3.0
    with pytest.raises(ValueError, match="proposals"):
        cem(score_fn, mean, std, 10.0, config, torch.Generator(), proposals=target.expand(4, 2, 2))
