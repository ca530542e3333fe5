"""The model-predictive planner: one batched graph of candidates x futures, the CEM search, the
three scores, gradient refinement, determinism, bad input, and ``hrn-pyg plan`` end to end."""

import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.planning import (
    MPCPlanner,
    PlannerConfig,
    cem,
    episode_goal,
    plan_episode,
    refine,
    rollout_futures,
    score_returns,
)
from hrn_pyg.rl.tasks import CUBE_PUSH_STOP, action_to_forces
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
    out = tmp_path / "episode.png"
    rc = main(["plan", "--task", "cube_push_stop", "--model", "cube_push", "--score", "risk", "--refine",
               "--refine-steps", "1", "--candidates", "4", "--elites", "2", "--iterations", "1",
               "--horizon", "2", "--k", "2", "--control-steps", "2", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and out.stat().st_size > 0
    assert "after 2 steps" in text and "planning per control step" in text and "pybullet step" in text


def test_plan_command_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    rc = main(["plan", "--task", "cube_push_stop", "--model", "cube_push", "--candidates", "0",
               "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "candidates" in err
