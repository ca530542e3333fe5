"""The learned HRN as the environment's physics (small random HRN, small pool), and the
ground-truth check that replays a policy's episodes in pybullet."""

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE, set_state
from hrn_pyg.data.io import save_episode
from hrn_pyg.data.scene_file import make_scene
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.rl.dynamics import StochasticDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import (
    closed_loop_in_pybullet,
    deterministic_actions,
    ground_truth_success,
    record_episodes,
    replay_in_pybullet,
)
from hrn_pyg.rl.hrn_dynamics import POOL_SEEDS, HRNDynamics
from hrn_pyg.rl.ppo import build_actor_critic
from hrn_pyg.rl.tasks import get_task, goal_reached
from hrn_pyg.sim.step import step as model_step

POOL = POOL_SEEDS[:4]
#: windows of the tiny cube_push folder the normaliser is fitted on
FIT_WINDOWS = 12


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> HRN:
    """A small random-init HRN with dropout on its force module and a fitted normaliser."""
    folder = tmp_path_factory.mktemp("cube_push")
    for seed in (0, 1):  # both in the train split
        save_episode(folder / f"episode_{seed:06d}.npz", simulate_episode("cube_push", seed, steps=10))
    windows = EpisodeWindows(folder, "train", horizon=1)
    torch.manual_seed(0)
    net = HRN(HRNConfig(hidden=16, effect_dim=16, dropout_modules=("force",)))
    fit_normalizer((windows[i] for i in range(FIT_WINDOWS)), net.normalizer)
    return net.eval()


@pytest.fixture(scope="module")
def dynamics(model) -> HRNDynamics:
    return HRNDynamics(model, "cube_push", pool_seeds=POOL)


def _forces(B: int, seed: int = 0) -> torch.Tensor:
    return (torch.rand(B, 2, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1) * 10.0


def test_protocol_and_shapes(dynamics):
    assert isinstance(dynamics, StochasticDynamics)
    L, R = dynamics.num_leaves, dynamics.num_roots
    assert dynamics.state_dim == 9 * L + 2 * R + 1 and dynamics.num_objects == 2 and R == 2
    states = dynamics.reset_states(6, torch.Generator().manual_seed(0))
    assert states.shape == (6, 9 * L + 2 * R + 1)
    assert dynamics.roots(states).shape == (6, 2, 6)
    # a reset state's sleep state is the one its history implies: still count -1
    assert torch.equal(states[:, 9 * L:-1], torch.tensor([-1.0, -1.0, 0.0, 0.0]).expand(6, 4))
    samples = dynamics.sample_next(states, _forces(6), 3, 0.1, torch.Generator().manual_seed(1))
    assert samples.shape == (6, 3, 9 * L + 2 * R + 1)
    assert dynamics.roots(samples).shape == (6, 3, 2, 6)
    # the history shifts by one step and the pool index rides along
    pos, index = dynamics.leaf_history(samples)
    before, start = dynamics.leaf_history(states)
    assert torch.equal(pos[:, :, :2], before[:, None, 1:].expand(6, 3, 2, L, 3))
    assert torch.equal(index, start[:, None].expand(6, 3))
    assert torch.equal(dynamics.state_of(before, start), states)
    # both cubes pushed: awake, no still step counted
    assert torch.equal(samples[..., 9 * L:-1], torch.zeros(6, 3, 4))
    assert torch.isfinite(samples).all()


def test_rate_zero_gives_k_copies_of_one_deterministic_step(dynamics, model):
    B, L = 3, dynamics.num_leaves
    states = dynamics.reset_states(B, torch.Generator().manual_seed(2))
    forces = _forces(B, 1)
    samples = dynamics.sample_next(states, forces, 4, 0.0, torch.Generator().manual_seed(3))
    assert torch.equal(samples, samples[:, :1].expand_as(samples))
    # the same step by hand: one unbatched graph per environment through hrn_pyg.sim.step.step
    per_object = torch.bincount(dynamics.leaf_object).float()
    for b in range(B):
        x, index = dynamics.leaf_history(states[b])
        leaf_force = forces[b, dynamics.leaf_object] / per_object[dynamics.leaf_object, None]
        graph = set_state(dynamics.structure_graph(int(index)), x[0], x[1], x[2],
                          radius=model.config.collision_radius, force=leaf_force)
        with torch.no_grad():
            nxt = model_step(model, graph).pos[graph[NODE].is_leaf]
        got = dynamics.leaf_history(samples[b, 0])[0][2]
        torch.testing.assert_close(got, nxt, rtol=1e-5, atol=1e-6)
        assert not torch.allclose(got, x[2])  # the step moved something


def test_the_next_history_holds_the_x_t_a_ground_lift_moved(model):
    """A model whose ground lift is not a motion (``ground_lift_velocity`` False), the objects
    sunk 5 cm into the ground and falling: the next state's three frames are those of the graph that
    ``hrn_pyg.sim.step.step`` advances to (x_t moved up by the lift), not x_t as it was."""
    from hrn_pyg.checkpoints import with_applied_options

    lifting = with_applied_options(model, ground_projection=True, ground_lift_velocity=False)
    dynamics = HRNDynamics(lifting, "cube_push", pool_seeds=POOL[:1])
    states = dynamics.reset_states(1, torch.Generator().manual_seed(2))
    x, index = dynamics.leaf_history(states[0])
    x = x.clone()
    x[..., 2] -= 0.05 + x[2, :, 2].min()  # the lowest leaf 5 cm under the ground, falling 1 cm a step
    x[0, :, 2] += 0.02
    x[1, :, 2] += 0.01
    states = dynamics.state_of(x[None], index[None])
    forces = torch.zeros(1, 2, 3)
    got = dynamics.leaf_history(dynamics.sample_next(states, forces, 1, 0.0, torch.Generator().manual_seed(3)))[0][0, 0]
    structure = dynamics.structure_graph(int(index))
    graph = set_state(structure, x[0], x[1], x[2], radius=lifting.config.collision_radius,
                      force=torch.zeros(structure[NODE].num_nodes, 3))
    with torch.no_grad():
        nxt = model_step(lifting, graph).graph[NODE]
    leaf = nxt.is_leaf
    torch.testing.assert_close(got[2], nxt.pos[leaf], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[1], nxt.prev_pos[leaf], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[0], x[1])
    assert got[2][:, 2].min() >= -1e-6 and (got[1][:, 2] > x[2][:, 2] + 0.01).any()  # lifted, and x_t with it


def test_dropout_samples_differ_and_seeded_generator_repeats(dynamics):
    states = dynamics.reset_states(2, torch.Generator().manual_seed(4))
    forces = _forces(2, 2)
    a = dynamics.sample_next(states, forces, 5, 0.3, torch.Generator().manual_seed(5))
    b = dynamics.sample_next(states, forces, 5, 0.3, torch.Generator().manual_seed(5))
    c = dynamics.sample_next(states, forces, 5, 0.3, torch.Generator().manual_seed(6))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    for env in range(2):  # the k futures of one environment are not all the same
        spread = (a[env] - a[env, :1]).abs().amax(-1)
        assert (spread[1:] > 0).all()


def test_roots_are_mass_weighted_leaf_means_by_hand(dynamics):
    states = dynamics.reset_states(4, torch.Generator().manual_seed(7))
    roots = dynamics.roots(states)
    for b in range(4):
        pos, index = dynamics.leaf_history(states[b])
        mass = dynamics.leaf_mass[int(index)].double().numpy()
        x = pos.double().numpy()
        for obj in range(2):  # two objects, each a weighted sum over its own leaves
            sel = dynamics.leaf_object.numpy() == obj
            w = mass[sel] / mass[sel].sum()
            now = (w[:, None] * x[2, sel]).sum(0)
            prev = (w[:, None] * x[1, sel]).sum(0)
            np.testing.assert_allclose(roots[b, obj, :3].numpy(), now, atol=1e-6)
            np.testing.assert_allclose(roots[b, obj, 3:].numpy(), now - prev, atol=1e-6)


def test_scene_seeds_round_trip_to_the_pybullet_scene(dynamics):
    states = dynamics.reset_states(8, torch.Generator().manual_seed(8))
    seeds = dynamics.scene_seeds(states)
    assert seeds.shape == (8,) and set(seeds.tolist()) <= set(POOL)
    assert torch.equal(seeds, torch.tensor(POOL)[dynamics.leaf_history(states)[1]])
    nxt = dynamics.sample_next(states, _forces(8), 2, 0.1, torch.Generator().manual_seed(9))
    assert torch.equal(dynamics.scene_seeds(nxt), seeds[:, None].expand(8, 2))
    # the state is the named scene after HISTORY zero-force steps
    seed = int(seeds[0])
    scene = make_scene("cube_push", seed)
    try:
        frames = [scene.reset()]
        for _ in range(HISTORY):
            frames.append(scene.step(scene.zero_action()))
    finally:
        scene.close()
    expected = torch.tensor(np.stack(frames), dtype=torch.float32)
    assert torch.equal(dynamics.leaf_history(states[0])[0], expected)


def test_bad_input_raises(dynamics, model):
    states = dynamics.reset_states(2, torch.Generator().manual_seed(0))
    gen = torch.Generator()
    with pytest.raises(ValueError, match="states"):
        dynamics.sample_next(states[:, :-1], _forces(2), 2, 0.1, gen)
    with pytest.raises(ValueError, match="forces"):
        dynamics.sample_next(states, _forces(3), 2, 0.1, gen)
    with pytest.raises(ValueError, match="k"):
        dynamics.sample_next(states, _forces(2), 0, 0.1, gen)
    with pytest.raises(ValueError, match="rate"):
        dynamics.sample_next(states, _forces(2), 2, 1.0, gen)
    with pytest.raises(ValueError, match="pool_seeds"):
        HRNDynamics(model, "cube_push", pool_seeds=())
    no_force = HRN(HRNConfig(hidden=8, effect_dim=8, dropout_modules=("collision",)))
    with pytest.raises(ValueError, match="dropout"):
        HRNDynamics(no_force, "cube_push", pool_seeds=POOL)


def test_dropout_only_on_the_task_modules(model):
    # cube_push samples dropout on the force module only: a model that also takes collision
    # masks gives the very same futures, even with the cubes overlapping (collision edges)
    both = HRN(HRNConfig(hidden=16, effect_dim=16, dropout_modules=("force", "collision")))
    both.load_state_dict(model.state_dict())
    force_only = HRNDynamics(model, "cube_push", pool_seeds=POOL[:1])
    with_collision = HRNDynamics(both.eval(), "cube_push", pool_seeds=POOL[:1])
    states = force_only.reset_states(2, torch.Generator().manual_seed(0))
    pos, index = force_only.leaf_history(states)
    pos = pos.clone()
    cube0, cube1 = force_only.leaf_object == 0, force_only.leaf_object == 1
    pos[:, :, cube1] = pos[:, :, cube0][:, :, : int(cube1.sum())] + 0.01  # cube 1 inside cube 0
    states = force_only.state_of(pos, index)
    graph = set_state(force_only.structure_graph(0), *pos[0], radius=model.config.collision_radius)
    assert graph["particle", "collision", "particle"].edge_index.shape[1] > 0
    a = force_only.sample_next(states, _forces(2), 3, 0.3, torch.Generator().manual_seed(1))
    b = with_collision.sample_next(states, _forces(2), 3, 0.3, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)


def test_env_specs_and_random_rollout_stay_finite(dynamics):
    env = HRNEnv("cube_push", dynamics, batch_size=3, seed=0)
    check_env_specs(env)
    td = env.rollout(12, break_when_any_done=False)  # random actions; auto-reset after episodes
    assert td.batch_size == (3, 12)
    for key in ("observation", "state", "reward"):
        assert torch.isfinite(td["next", key]).all()
    assert ((td["next", "t"] >= 1) & (td["next", "t"] <= env.task.max_steps)).all()


class SeekNorthGoals(torch.nn.Module):
    """Pushes both cubes at full force straight at the goal when the goal lies north of the
    origin (y > 0) and does nothing otherwise: in pybullet it solves about half the episodes
    (a zero action never does: no goal is met at reset)."""

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        xy = obs[..., :12].reshape(*obs.shape[:-1], 2, 6)[..., :2]          # (..., 2 cubes, 2)
        to_goal = obs[..., None, 12:14] - xy
        push = 15.0 * to_goal / to_goal.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        return (push * (obs[..., None, 13:14] > 0)).flatten(-2)             # (..., 4)


def test_record_episodes_and_ground_truth_check(dynamics):
    task = get_task("cube_push")
    env = HRNEnv(task, dynamics, batch_size=3, seed=1, dropout_rate=0.1)
    torch.manual_seed(0)
    actor, _ = build_actor_critic(env, 8)
    records = record_episodes(actor, env, 4)
    assert len(records) == 4
    for rec in records:
        n = rec["length"]
        assert 1 <= n <= env.task.max_steps and rec["seed"] in POOL
        assert rec["actions"].shape == (n, env.task.action_dim) and rec["states"].shape == (n + 1, dynamics.state_dim)
        assert rec["actions"].abs().max() <= env.task.max_force
        assert int(dynamics.scene_seeds(rec["states"][0])) == rec["seed"]
        # success is the goal met by the last state and by no earlier one; a failure runs out
        met = goal_reached(task, dynamics.roots(rec["states"]), rec["goal"])
        assert rec["success"] == bool(met[-1]) and not met[:-1].any()
        assert rec["success"] or n == task.max_steps

    # the check, then the same episodes by hand: a fresh environment with the same seed at the
    # settings the check uses (dropout 0, no action noise), replayed in pybullet one by one
    policy = TensorDictModule(SeekNorthGoals(), in_keys=["observation"], out_keys=["action"])
    env = HRNEnv(task, dynamics, batch_size=3, seed=1, dropout_rate=0.1, action_noise_std=0.2)
    episodes = 6
    result = ground_truth_success(policy, env, episodes)
    assert (env.dropout_rate, env.action_noise_std) == (0.1, 0.2)  # restored after the check
    records = record_episodes(policy, HRNEnv(task, dynamics, batch_size=3, seed=1, dropout_rate=0.0),
                              episodes)
    model_ok, model_len, real_ok, real_len = [], [], [], []
    for rec in records:
        replay = replay_in_pybullet(rec["actions"], task, rec["seed"], rec["goal"],
                                    history_steps=HISTORY)
        met = goal_reached(task, replay["roots"], rec["goal"])            # (steps + 1,)
        assert replay["success"] == bool(met[-1]) and not met[:-1].any()
        assert replay["steps"] == (int(met.nonzero()[0]) if met.any() else rec["length"])
        model_ok.append(rec["success"])
        model_len.append(rec["length"] if rec["success"] else task.max_steps)
        real_ok.append(replay["success"])
        real_len.append(replay["steps"] if replay["success"] else task.max_steps)
    expected = {
        "ground_truth_episodes": episodes,
        "model_success_rate": sum(model_ok) / episodes,
        "model_mean_length": sum(model_len) / episodes,
        "pybullet_success_rate": sum(real_ok) / episodes,
        "pybullet_mean_length": sum(real_len) / episodes,
        "agreement": sum(a == b for a, b in zip(model_ok, real_ok)) / episodes,
    }
    assert result == pytest.approx(expected)
    # the numbers are not trivially 0 or 1: the random model solves none of the episodes,
    # pybullet the northern ones (3 of these 6), so the two agree on the other half
    assert 0.0 < expected["pybullet_success_rate"] < 1.0 and 0.0 < expected["agreement"] < 1.0
    assert sum(real_ok) == sum(bool(rec["goal"][1] > 0) for rec in records)


def test_closed_loop_sees_pybullet_states_from_the_learned_start(dynamics):
    task = get_task("cube_push")
    env = HRNEnv(task, dynamics, batch_size=4, seed=2, dropout_rate=0.0)
    td = env.reset()
    seeds = dynamics.scene_seeds(td["state"])
    seen = []

    def still(obs):  # records what it sees, pushes nothing
        seen.append(obs.clone())
        return torch.zeros(obs.shape[0], task.action_dim)

    out = closed_loop_in_pybullet(still, task, int(seeds[0]), td["goal"][0])
    # its first observation is the learned environment's start (same roots, same goal)
    torch.testing.assert_close(seen[0][0], td["observation"][0], rtol=0, atol=1e-5)
    assert out == {"success": False, "steps": task.max_steps} and len(seen) == task.max_steps
    with pytest.raises(ValueError, match="history_steps"):
        closed_loop_in_pybullet(still, task, int(seeds[0]), td["goal"][0], history_steps=-1)

    # a policy that pushes toward northern goals succeeds there, in every one of them
    policy = TensorDictModule(SeekNorthGoals(), in_keys=["observation"], out_keys=["action"])
    result = ground_truth_success(policy, HRNEnv(task, dynamics, batch_size=3, seed=1), 6, closed_loop=True)
    records = record_episodes(policy, HRNEnv(task, dynamics, batch_size=3, seed=1, dropout_rate=0.0), 6)
    act = deterministic_actions(policy)
    runs = [closed_loop_in_pybullet(act, task, r["seed"], r["goal"]) for r in records]
    assert result["closed_loop_success_rate"] == sum(r["success"] for r in runs) / 6
    assert result["closed_loop_mean_length"] == sum(r["steps"] for r in runs) / 6
    assert [r["success"] for r in runs] == [bool(r["goal"][1] > 0) for r in records]
    assert all(r["steps"] < task.max_steps for r in runs if r["success"])


def test_replay_starts_where_the_learned_episode_starts(dynamics):
    # zero actions: the replay's first root state is the learned state's, velocity included
    states = dynamics.reset_states(1, torch.Generator().manual_seed(3))
    seed = int(dynamics.scene_seeds(states)[0])
    replay = replay_in_pybullet(torch.zeros(2, 4), "cube_push", seed, goal=torch.tensor([9.0, 9.0]),
                                history_steps=HISTORY)
    torch.testing.assert_close(replay["roots"][0], dynamics.roots(states)[0], rtol=0, atol=1e-5)
    assert replay["leaves"].shape == (3, dynamics.num_leaves, 3) and not replay["success"]
    with pytest.raises(ValueError, match="history_steps"):
        replay_in_pybullet(torch.zeros(1, 4), "cube_push", seed, goal=torch.zeros(2), history_steps=-1)


def test_from_checkpoint_on_an_explicit_device(model, dynamics, tmp_path):
    from hrn_pyg.train import TrainConfig, model_payload
    from hrn_pyg.utils.checkpoint import save_checkpoint

    path = tmp_path / "cube_push.pt"
    save_checkpoint(path, model_payload(model, TrainConfig(), 0))
    loaded = HRNDynamics.from_checkpoint(path, "cube_push", device=torch.device("cpu"), pool_seeds=POOL)
    assert loaded.device == torch.device("cpu")
    assert loaded.pool.device == loaded.leaf_object.device == torch.device("cpu")
    env = HRNEnv("cube_push", loaded, batch_size=2, seed=0)
    assert env.device == loaded.device  # the environment follows its dynamics by default
    states = loaded.reset_states(2, torch.Generator().manual_seed(0))
    a = loaded.sample_next(states, _forces(2), 2, 0.2, torch.Generator().manual_seed(1))
    b = dynamics.sample_next(states, _forces(2), 2, 0.2, torch.Generator().manual_seed(1))
    assert torch.equal(a, b)


def test_an_object_the_state_shows_at_rest_sleeps_unless_pushed(dynamics, model):
    """Reset states are pybullet scenes at rest; with a push on cube 0 only, cube 1 (untouched)
    is held exactly where it is, while the same model with sleeping off lets it creep, and the
    pushed cube moves as it does with sleeping off."""
    from hrn_pyg.sim.sleeping import SleepConfig

    awake = HRNDynamics(model, "cube_push", pool_seeds=POOL, sleep=None)
    B = 3
    states = dynamics.reset_states(B, torch.Generator().manual_seed(5))
    forces = torch.zeros(B, 2, 3)
    forces[:, 0, 0] = 10.0
    held = dynamics.sample_next(states, forces, 2, 0.0, torch.Generator())
    free = awake.sample_next(states, forces, 2, 0.0, torch.Generator())
    cube1 = dynamics.leaf_object == 1
    now = dynamics.leaf_history(states)[0][:, 2]
    nxt_held = dynamics.leaf_history(held[:, 0])[0][:, 2]
    nxt_free = awake.leaf_history(free[:, 0])[0][:, 2]
    assert torch.equal(nxt_held[:, cube1], now[:, cube1])
    assert not torch.equal(nxt_free[:, cube1], now[:, cube1])
    torch.testing.assert_close(nxt_held[:, ~cube1], nxt_free[:, ~cube1], rtol=1e-5, atol=1e-6)
    assert "sleep=SleepConfig" in repr(dynamics) and "sleep=None" in repr(awake)
    assert HRNDynamics(model, "cube_push", pool_seeds=POOL, sleep=SleepConfig(enabled=False)).sleep is None


def test_the_sleep_state_is_carried_from_step_to_step(model):
    """Each object's still count and asleep flag ride in the state: an object awake with no still
    step yet (every step still under a 1 m threshold) falls asleep after ``patience`` steps, as in
    a sleeping rollout, while a reset state's history puts it to sleep at once."""
    from hrn_pyg.sim.sleeping import SleepConfig

    dyn = HRNDynamics(model, "cube_push", pool_seeds=POOL[:1], sleep=SleepConfig(threshold=1.0, patience=3))
    block = slice(9 * dyn.num_leaves, -1)
    zero, gen = torch.zeros(1, 2, 3), torch.Generator()
    reset = dyn.reset_states(1, torch.Generator().manual_seed(0))
    assert dyn.sample_next(reset, zero, 1, 0.0, gen)[0, 0, block].tolist() == [0.0, 0.0, 1.0, 1.0]
    states = reset.clone()
    states[0, block] = 0.0  # both cubes awake, no still step counted
    seen = []
    for _ in range(4):
        states = dyn.sample_next(states, zero, 1, 0.0, gen)[:, 0]
        seen.append(states[0, block].tolist())
    assert seen == [[1.0, 1.0, 0.0, 0.0], [2.0, 2.0, 0.0, 0.0], [3.0, 3.0, 1.0, 1.0], [0.0, 0.0, 1.0, 1.0]]


def test_a_run_record_names_only_the_sleep_settings_a_step_uses(model):
    """The environment starts every episode from the state's own history, so a rollout's
    ``start_from_history`` does not change the dynamics, nor the record a resumed run checks;
    the threshold, the patience and sleeping off do."""
    from hrn_pyg.rl.hrn_dynamics import sleep_repr
    from hrn_pyg.sim.sleeping import SleepConfig

    on = HRNDynamics(model, "cube_push", POOL, SleepConfig(start_from_history=True))
    off = HRNDynamics(model, "cube_push", POOL, SleepConfig(start_from_history=False))
    assert repr(on) == repr(off)
    assert "start_from_history" not in repr(on)
    assert sleep_repr(SleepConfig(threshold=1e-3)) != sleep_repr(SleepConfig())
    assert sleep_repr(SleepConfig(patience=3)) != sleep_repr(SleepConfig())
    assert "sleep=None" in repr(HRNDynamics(model, "cube_push", POOL, None))
