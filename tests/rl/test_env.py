import dataclasses

import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from hrn_pyg.rl.dynamics import PointMassDynamics, StochasticDynamics, dropout_spread
from hrn_pyg.rl.env import HRNEnv, choose_next, partial_hits
from hrn_pyg.rl.tasks import (
    CUBE_PUSH,
    TOWER,
    action_to_forces,
    get_task,
    goal_held,
    goal_reached,
    goal_streak,
)


class ScriptedDynamics:
    """k fixed futures: sample j moves object 0 to x = offsets[j]; records the rate it got."""

    num_objects = 2
    object_dim = 6
    state_dim = 12

    def __init__(self, offsets):
        self.offsets = torch.tensor(offsets, dtype=torch.float32)
        self.rates = []

    def reset_states(self, batch, generator):
        s = torch.zeros(batch, 2, 6)
        s[:, :, 0] = 5.0  # far from any goal drawn for cube_push (<= 0.45 m from the origin)
        return s.reshape(batch, 12)

    def roots(self, states):
        return states.reshape(*states.shape[:-1], 2, 6)

    def sample_next(self, states, forces, k, rate, generator):
        self.rates.append(rate)
        B = states.shape[0]
        out = states.reshape(B, 1, 2, 6).repeat(1, k, 1, 1)
        out[:, :, 0, 0] = self.offsets[:k]
        out[:, :, 0, 3] = torch.arange(k, dtype=torch.float32)  # a tag naming the sample
        return out.reshape(B, k, 12)


def test_check_env_specs_both_tasks():
    for task in ("cube_push", "tower"):
        env = HRNEnv(task, batch_size=3, seed=0)
        check_env_specs(env)
        assert env.observation_spec["observation"].shape == (3, env.task.num_objects * 6 + 2)
        assert env.action_spec.shape == (3, env.task.action_dim)
        assert set(env.full_done_spec.keys()) == {"done", "terminated", "truncated"}


def test_point_mass_satisfies_protocol():
    assert isinstance(PointMassDynamics.for_task("tower"), StochasticDynamics)


def test_relaxation_any_sample_in_goal_rewards_and_terminates():
    # only sample 3 of 5 lands on the goal (x = 0): reward 1, terminated, next state = sample 3
    dyn = ScriptedDynamics([5.0, 5.0, 5.0, 0.0, 5.0])
    env = HRNEnv(CUBE_PUSH, dyn, batch_size=4, seed=0)
    td = env.reset()
    td["goal"] = torch.zeros(4, 2)
    td["action"] = torch.zeros(4, CUBE_PUSH.action_dim)
    out = env.step(td)["next"]
    assert out["reward"].flatten().tolist() == [1.0] * 4
    assert out["terminated"].all() and out["done"].all() and not out["truncated"].any()
    assert torch.equal(dyn.roots(out["state"])[:, 0, 3], torch.full((4,), 3.0))


def test_relaxation_otherwise_next_state_is_one_sample_drawn_at_random():
    dyn = ScriptedDynamics([5.0, 6.0, 7.0, 8.0, 9.0])
    env = HRNEnv(CUBE_PUSH, dyn, batch_size=64, seed=1)
    td = env.reset()
    td["action"] = torch.zeros(64, CUBE_PUSH.action_dim)
    out = env.step(td)["next"]
    assert (out["reward"] == 0).all() and not out["done"].any()
    roots = dyn.roots(out["state"])
    tag = roots[:, 0, 3].long()
    assert torch.equal(roots[:, 0, 0], dyn.offsets[tag])  # exactly the tagged sample
    assert set(tag.tolist()) == {0, 1, 2, 3, 4}           # drawn, not always the same one


def test_relaxation_takes_the_first_hit_by_hand():
    task = CUBE_PUSH
    samples = torch.zeros(2, 3, 12)
    samples[..., 0] = torch.tensor([[1.0, 0.05, 0.0], [1.0, 1.0, 1.0]])   # cube 0 x per sample
    samples[..., 6] = 1.0                                                 # cube 1 away
    in_goal = goal_reached(task, samples.reshape(2, 3, 2, 6), torch.zeros(2, 1, 2))
    gen = torch.Generator().manual_seed(0)
    nxt, hit = choose_next(in_goal, samples, gen, relax=True)
    assert hit.tolist() == [True, False]
    assert nxt[0, 0] == 0.05                                               # the first in the goal


def test_without_relaxation_only_the_drawn_sample_counts():
    """Sample 3 of 5 lands on the goal. Relaxed: every environment is rewarded and continues
    from sample 3. Unrelaxed, same seed: the next state is the sample drawn at random (the same
    draw the relaxed env made and ignored), rewarded exactly when that draw is sample 3; both
    report 1 of 5 samples in the goal."""
    dyn = ScriptedDynamics([5.0, 5.0, 5.0, 0.0, 5.0])
    outs = {}
    for relax in (True, False):
        env = HRNEnv(CUBE_PUSH, dyn, batch_size=256, relax=relax, seed=3)
        td = env.reset()
        td["goal"] = torch.zeros(256, 2)
        td["action"] = torch.zeros(256, CUBE_PUSH.action_dim)
        outs[relax] = env.step(td)["next"]
    relaxed, plain = outs[True], outs[False]
    assert (relaxed["reward"] == 1).all() and (relaxed["goal_hits"] == 1).all()
    assert (plain["goal_hits"] == 1).all()
    tag = dyn.roots(plain["state"])[:, 0, 3].long()
    assert set(tag.tolist()) == {0, 1, 2, 3, 4}
    assert torch.equal(plain["reward"].squeeze(-1) == 1, tag == 3)
    assert torch.equal(plain["terminated"].squeeze(-1), tag == 3)
    assert 0.1 < float((tag == 3).float().mean()) < 0.3  # about one in five


def test_choose_next_by_hand():
    samples = torch.arange(2 * 3, dtype=torch.float32).reshape(2, 3, 1)
    in_goal = torch.tensor([[False, True, True], [False, False, False]])
    gen = torch.Generator().manual_seed(0)
    drawn = torch.randint(3, (2,), generator=torch.Generator().manual_seed(0))
    nxt, hit = choose_next(in_goal, samples, gen, relax=True)
    assert hit.tolist() == [True, False]
    assert nxt[:, 0].tolist() == [1.0, float(3 + drawn[1])]          # first hit; else the draw
    nxt, hit = choose_next(in_goal, samples, torch.Generator().manual_seed(0), relax=False)
    assert nxt[:, 0].tolist() == [float(drawn[0]), float(3 + drawn[1])]
    assert hit.tolist() == [bool(in_goal[0, drawn[0]]), False]
    with pytest.raises(ValueError, match="in_goal"):
        choose_next(in_goal[:, :2], samples, gen)


def test_partial_hits_by_hand():
    hits = torch.tensor([[0], [1], [4], [5]])
    assert partial_hits(hits, 5).squeeze(-1).tolist() == [False, True, True, False]
    assert not partial_hits(torch.tensor([0, 1]), 1).any()  # one sample: never partial
    with pytest.raises(ValueError, match="k"):
        partial_hits(hits, 0)


def test_goal_hits_counts_the_samples_in_the_goal():
    """Two of five samples on the goal; reset reports 0."""
    dyn = ScriptedDynamics([0.0, 5.0, 0.02, 5.0, 5.0])
    env = HRNEnv(CUBE_PUSH, dyn, batch_size=3, seed=0)
    td = env.reset()
    assert (td["goal_hits"] == 0).all()
    td["goal"] = torch.zeros(3, 2)
    td["action"] = torch.zeros(3, CUBE_PUSH.action_dim)
    assert (env.step(td)["next", "goal_hits"] == 2).all()


class ScheduledDynamics(ScriptedDynamics):
    """Every sample of call n moves object 0 to x = xs[n]: a goal test scheduled step by step."""

    def __init__(self, xs):
        super().__init__([5.0])
        self.xs, self.calls = list(xs), 0

    def sample_next(self, states, forces, k, rate, generator):
        out = super().sample_next(states, forces, 1, rate, generator).repeat_interleave(k, 1)
        out = out.reshape(out.shape[0], k, 2, 6)
        out[:, :, 0, 0] = self.xs[self.calls]
        self.calls += 1
        return out.reshape(out.shape[0], k, 12)


def test_hold_steps_end_the_episode_only_after_that_many_goal_steps_in_a_row():
    # in the goal (x = 0) at steps 1, 2, 4, 5, 6: the miss at step 3 restarts the count
    task = dataclasses.replace(CUBE_PUSH, hold_steps=3)
    dyn = ScheduledDynamics([0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 5.0])
    env = HRNEnv(task, dyn, batch_size=2, seed=0)
    td = env.reset()
    td["goal"] = torch.zeros(2, 2)
    held, rewards, terminated = [], [], []
    for _ in range(6):
        td["action"] = torch.zeros(2, task.action_dim)
        td = env.step(td)
        held.append(int(td["next", "held"][0]))
        rewards.append(float(td["next", "reward"][0]))
        terminated.append(bool(td["next", "terminated"][0]))
        td = step_mdp(td)
    assert held == [1, 2, 0, 1, 2, 3]
    assert rewards == [0.0] * 5 + [1.0] and terminated == [False] * 5 + [True]
    check_env_specs(HRNEnv(task, batch_size=2, seed=0))


def test_goal_streak_counts_the_same_for_numbers_and_tensors():
    task = dataclasses.replace(CUBE_PUSH, hold_steps=2)
    counts, count = [], 0
    for reached in (True, False, True, True):
        count = goal_streak(count, reached)
        counts.append(count)
    assert counts == [1, 0, 1, 2] and goal_held(task, 2) and not goal_held(task, 1)
    held = goal_streak(torch.tensor([[0], [1], [4]]), torch.tensor([[True], [True], [False]]))
    assert held.flatten().tolist() == [1, 2, 0]
    assert goal_held(task, held).flatten().tolist() == [False, True, False]


def test_truncated_at_max_steps():
    dyn = ScriptedDynamics([5.0] * 5)
    env = HRNEnv(CUBE_PUSH, dyn, batch_size=2, seed=0)
    td = env.rollout(CUBE_PUSH.max_steps + 3, break_when_any_done=True)
    assert td.shape == (2, CUBE_PUSH.max_steps)
    assert td["next", "truncated"][:, -1].all() and not td["next", "terminated"].any()
    assert not td["next", "done"][:, :-1].any()


def test_seeding_reproduces_and_differs():
    def roll(seed):
        env = HRNEnv("cube_push", batch_size=3, seed=seed)
        torch.manual_seed(0)  # the random policy draws from the global generator
        return env.rollout(12, break_when_any_done=False)

    a, b, c = roll(3), roll(3), roll(4)
    assert torch.equal(a["next", "state"], b["next", "state"])
    assert torch.equal(a["next", "reward"], b["next", "reward"])
    assert not torch.equal(a["state"][:, 0], c["state"][:, 0])


def test_random_rollout_stays_finite():
    for task in ("cube_push", "tower"):
        env = HRNEnv(task, batch_size=4, seed=0, dropout_rate=0.3, action_noise_std=0.2)
        td = env.rollout(50, break_when_any_done=False)
        assert td.shape == (4, 50)
        for key in ("observation", "state"):
            assert torch.isfinite(td["next", key]).all()
        assert td["next", "done"].any()  # auto-reset happened inside 50 steps


def test_dropout_rate_changes_sample_spread():
    dyn = PointMassDynamics.for_task("cube_push")
    gen = torch.Generator().manual_seed(0)
    state = dyn.reset_states(8, gen)
    forces = action_to_forces(CUBE_PUSH, torch.full((8, 4), 30.0))

    def spread(rate):
        samples = dyn.sample_next(state, forces, 16, rate, torch.Generator().manual_seed(1))
        return dyn.roots(samples)[..., :3].std(1).mean().item()

    assert spread(0.0) == 0.0
    assert 0 < spread(0.05) < spread(0.1) < spread(0.3)
    # and through the env attribute
    env = HRNEnv(CUBE_PUSH, ScriptedDynamics([5.0] * 5), batch_size=2, seed=0)
    env.dropout_rate = 0.25
    td = env.reset()
    td["action"] = torch.zeros(2, 4)
    env.step(td)
    env.set_dropout_rate(0.0)
    env.step(td)
    assert env.dynamics.rates == [0.25, 0.0]


def test_rate_zero_is_deterministic_and_collision_noise_leaves_rest_quiet():
    dyn = PointMassDynamics.for_task("tower")
    gen = torch.Generator().manual_seed(0)
    state = dyn.reset_states(2, gen)
    assert torch.equal(dyn.roots(state)[..., 3:], torch.zeros(2, 4, 3))  # starts at rest
    out = dyn.sample_next(state, torch.zeros(2, 4, 3), 4, 0.0, gen)
    assert torch.equal(out[:, 0], out[:, 3])
    noisy = dyn.sample_next(state, torch.zeros(2, 4, 3), 4, 0.5, gen)
    assert torch.allclose(noisy, out, atol=1e-6)  # no force, no impact: no spread
    push = torch.zeros(2, 4, 3)
    push[:, 3, 0] = 10.0
    assert dyn.sample_next(state, push, 4, 0.5, gen)[:, :, -6:].std(1).max() > 0  # force noise


def test_action_noise_perturbs_the_step():
    def step(std):
        env = HRNEnv(CUBE_PUSH, batch_size=2, seed=0, dropout_rate=0.0, action_noise_std=std)
        td = env.reset()
        td["action"] = torch.full((2, 4), 10.0)
        return env.step(td)["next", "state"]

    assert torch.equal(step(0.0), step(0.0))
    assert not torch.equal(step(0.0), step(0.2))


def test_goal_tests_by_hand():
    roots = torch.zeros(1, 3, 2, 6)
    roots[0, :, 0, :2] = torch.tensor([[0.0, 0.0], [0.3, 0.0], [0.0, 0.09]])
    roots[0, :, 1, :2] = 1.0
    goal = torch.zeros(1, 1, 2)
    assert goal_reached(CUBE_PUSH, roots, goal).tolist() == [[True, False, True]]
    tower = torch.zeros(1, 2, 4, 6)
    tower[0, 1, 1, 0] = 0.11                                      # middle cube pushed out
    tower[0, 0, 3, 0] = 0.5                                       # only the ball moved
    assert goal_reached(TOWER, tower, goal).tolist() == [[False, True]]


def test_action_to_forces_scatter():
    f = action_to_forces(TOWER, torch.tensor([[1.0, 2.0, 3.0]]))
    assert f.shape == (1, 4, 3) and f[0, 3].tolist() == [1.0, 2.0, 3.0] and f[0, :3].abs().sum() == 0
    f = action_to_forces(CUBE_PUSH, torch.tensor([1.0, 2.0, 3.0, 4.0]))
    assert f.tolist() == [[1.0, 2.0, 0.0], [3.0, 4.0, 0.0]]


def test_bad_input_raises():
    with pytest.raises(ValueError, match="unknown task"):
        get_task("stack")
    with pytest.raises(ValueError, match="dropout rate"):
        HRNEnv("cube_push", batch_size=1, dropout_rate=1.0)
    with pytest.raises(ValueError, match="objects"):
        HRNEnv("tower", PointMassDynamics.for_task("cube_push"))
    with pytest.raises(ValueError, match="batch_size"):
        HRNEnv("tower", batch_size=0)
    with pytest.raises(ValueError, match="action"):
        action_to_forces(CUBE_PUSH, torch.zeros(3))
    with pytest.raises(ValueError):
        dropout_spread(-0.1)


def test_explicit_cpu_device_everywhere():
    """``device=torch.device("cpu")`` reaches the dynamics, the generator and every tensordict,
    and gives the run of the default device (None: the dynamics' own)."""
    cpu = torch.device("cpu")
    dyn = PointMassDynamics.for_task("tower", device=cpu)
    assert dyn.device == cpu
    env = HRNEnv("tower", dyn, batch_size=2, seed=5, dropout_rate=0.2, action_noise_std=0.1)
    assert env.device == cpu and env.rng.device == cpu
    explicit = HRNEnv("tower", batch_size=2, seed=5, dropout_rate=0.2, action_noise_std=0.1, device=cpu)
    torch.manual_seed(0)
    a = env.rollout(5, break_when_any_done=False)
    torch.manual_seed(0)
    b = explicit.rollout(5, break_when_any_done=False)
    assert a.device == cpu and a["next", "state"].device == cpu
    assert torch.equal(a["next", "state"], b["next", "state"])


def test_draws_follow_the_generator_and_results_the_samples():
    """choose_next draws on the generator's device and indexes on the samples' (the meta device
    stands in for CUDA)."""
    samples = torch.zeros(3, 2, 12, device="meta")
    in_goal = torch.zeros(3, 2, dtype=torch.bool, device="meta")
    state, hit = choose_next(in_goal, samples, torch.Generator(), relax=True)
    assert state.device.type == "meta" and state.shape == (3, 12) and hit.shape == (3,)
