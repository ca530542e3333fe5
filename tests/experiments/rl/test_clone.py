"""The planner cloned into the PPO actor (experiments.rl.clone) and PPO started from it; the
near-miss share. On the point-mass stand-in of cube_push_stop, so each test takes seconds."""

import csv
import dataclasses
import hashlib
import json

import pytest
import torch

from experiments.rl.clone import main as clone_main
from experiments.rl.clone import (
    ActorPolicy,
    CloneConfig,
    action_distribution,
    clone_planner,
    collect_demonstrations,
    load_policy_actor,
    mean_action,
    policy_network,
    save_clone,
)
from experiments.rl.partial_hits import partial_hit_share
from experiments.rl.planners import stop_push
from hrn_pyg.cli import main
from hrn_pyg.rl import ppo
from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.env import HRNEnv, near_miss_share
from hrn_pyg.rl.ppo import (
    PPOConfig,
    RunMismatch,
    build_actor_critic,
    load_init_policy,
    train,
)
from hrn_pyg.rl.tasks import CUBE_PUSH_STOP, TOWER_ASIDE
from hrn_pyg.utils.checkpoint import load_checkpoint

SMALL = CloneConfig(episodes=8, num_envs=8, steps=1000, hidden=32, seed=3)
TINY = PPOConfig(updates=2, num_envs=4, frames_per_batch=40, epochs=1, minibatch=20, hidden=32,
                 eval_episodes=4, ground_truth_episodes=0)


def _dynamics() -> PointMassDynamics:
    return PointMassDynamics.for_task("cube_push")


@pytest.fixture(scope="module")
def cloned():
    torch.set_num_threads(1)
    actor, report = clone_planner(CUBE_PUSH_STOP, _dynamics(), SMALL)
    return actor, report


@pytest.fixture
def clone_file(cloned, tmp_path):
    actor, report = cloned
    path = tmp_path / "clone.pt"
    sha = save_clone(path, actor, CUBE_PUSH_STOP, SMALL, report, "point mass")
    return path, sha


def test_the_clone_matches_the_planner_on_the_states_it_was_fitted_on(cloned):
    actor, report = cloned
    obs, actions = collect_demonstrations(CUBE_PUSH_STOP, _dynamics(), stop_push, SMALL.episodes,
                                          num_envs=SMALL.num_envs, collect_noise=SMALL.collect_noise,
                                          seed=SMALL.seed)
    assert obs.shape == (report["states"], 14) and actions.shape == (report["states"], 4)
    with torch.no_grad():
        error = (mean_action(actor, obs) - actions) / CUBE_PUSH_STOP.max_force
    rms = float(error.pow(2).mean().sqrt())
    assert rms == pytest.approx(report["loss_final"] ** 0.5, rel=1e-4)
    assert rms < 0.1                                    # within a tenth of the force bound
    assert report["loss_final"] < 0.1 * report["loss_initial"]
    # the mean action is F tanh(loc), inside the bounds
    with torch.no_grad():
        loc = action_distribution(actor, obs).loc
    torch.testing.assert_close(mean_action(actor, obs).detach(), CUBE_PUSH_STOP.max_force * torch.tanh(loc))


def test_the_exploration_is_the_given_fraction_of_the_force_bound_to_first_order(cloned):
    actor, report = cloned
    obs, _ = collect_demonstrations(CUBE_PUSH_STOP, _dynamics(), stop_push, SMALL.episodes,
                                    num_envs=SMALL.num_envs, seed=SMALL.seed)
    with torch.no_grad():
        dist = action_distribution(actor, obs)
    # one scale per action entry, the same in every state
    assert torch.equal(dist.scale, dist.scale[:1].expand_as(dist.scale))
    assert dist.scale[0].tolist() == pytest.approx(report["exploration_scale"], rel=1e-6)
    first_order = ((1 - torch.tanh(dist.loc) ** 2) * dist.scale).mean(0)  # action std / F
    assert first_order.tolist() == pytest.approx([SMALL.noise] * 4, rel=1e-3)
    last = policy_network(actor)[-2]
    assert torch.count_nonzero(last.weight[4:]) == 0


def test_cloning_is_deterministic_with_a_seed_and_leaves_the_random_state(cloned):
    actor, report = cloned
    before = torch.get_rng_state().clone()
    again, report2 = clone_planner(CUBE_PUSH_STOP, _dynamics(), SMALL)
    assert torch.equal(torch.get_rng_state(), before)
    for key, value in actor.state_dict().items():
        assert torch.equal(value, again.state_dict()[key]), key
    assert {k: v for k, v in report.items() if k != "seconds"} == \
        {k: v for k, v in report2.items() if k != "seconds"}
    other, _ = clone_planner(CUBE_PUSH_STOP, _dynamics(), dataclasses.replace(SMALL, seed=4, steps=5))
    assert not torch.equal(other.state_dict()["module.0.module.0.weight"],
                           actor.state_dict()["module.0.module.0.weight"])


def test_a_saved_clone_loads_weights_only_with_its_sha256(cloned, clone_file, tmp_path):
    actor, report = cloned
    path, sha = clone_file
    assert sha == hashlib.sha256(path.read_bytes()).hexdigest()
    # the same clone makes the same file (its fit time is not saved)
    assert save_clone(tmp_path / "again.pt", actor, CUBE_PUSH_STOP, SMALL, {**report, "seconds": 1.0},
                      "point mass") == sha
    ckpt = torch.load(path, weights_only=True)
    meta = json.loads(ckpt["config"])
    assert meta["ppo"]["hidden"] == SMALL.hidden and meta["task"]["name"] == "cube_push_stop"
    assert not list(tmp_path.glob(".*.tmp"))            # written through a temporary file
    assert "seconds" not in meta["fit"] and meta["fit"]["states"] == report["states"]
    env = HRNEnv(CUBE_PUSH_STOP, _dynamics(), batch_size=1, seed=0)
    fresh, _ = build_actor_critic(env, SMALL.hidden)
    assert load_init_policy(path, fresh, CUBE_PUSH_STOP) == sha
    for key, value in actor.state_dict().items():
        assert torch.equal(value, fresh.state_dict()[key])
    loaded = load_policy_actor(path, CUBE_PUSH_STOP, _dynamics())
    assert torch.equal(loaded.state_dict()["module.0.module.4.bias"], actor.state_dict()["module.0.module.4.bias"])


def test_load_init_policy_bad_input_raises_one_line(clone_file, tmp_path):
    path, _ = clone_file
    env = HRNEnv(CUBE_PUSH_STOP, _dynamics(), batch_size=1, seed=0)
    wide, _ = build_actor_critic(env, SMALL.hidden * 2)
    tower_actor, _ = build_actor_critic(HRNEnv(TOWER_ASIDE, batch_size=1, seed=0), SMALL.hidden)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    for call, error, match in (
        (lambda: load_init_policy(tmp_path / "missing.pt", wide, CUBE_PUSH_STOP), FileNotFoundError, "not found"),
        (lambda: load_init_policy(path, wide, CUBE_PUSH_STOP), ValueError, "does not fit"),
        (lambda: load_init_policy(path, tower_actor, TOWER_ASIDE), ValueError, "cube_push_stop"),
        (lambda: load_init_policy(garbage, wide, CUBE_PUSH_STOP), ValueError, "not a readable"),
    ):
        with pytest.raises(error, match=match) as exc:
            call()
        assert "\n" not in str(exc.value)


def test_bad_clone_settings_raise():
    for change in ({"episodes": 0}, {"steps": 0}, {"noise": 0.0}, {"noise": 1.5},
                   {"collect_noise": -0.1}, {"lr": 0.0}, {"seed": 900_001}):
        with pytest.raises(ValueError):
            CloneConfig(**change)

    class ValidationPool(PointMassDynamics):
        pool_seeds = torch.tensor([10_000, 20_000])

    dyn = ValidationPool(_dynamics().config)
    with pytest.raises(ValueError, match="validation"):
        collect_demonstrations(CUBE_PUSH_STOP, dyn, stop_push, 2)


def test_ppo_starts_from_the_init_policy_and_records_it(cloned, clone_file, tmp_path, monkeypatch):
    actor, _ = cloned
    path, sha = clone_file
    batches, update = [], ppo._ppo_update

    def keep_batch(batch, *args):
        batches.append(batch.clone())
        return update(batch, *args)

    monkeypatch.setattr(ppo, "_ppo_update", keep_batch)
    out = tmp_path / "run"
    res = train(CUBE_PUSH_STOP, "stochastic", 0, TINY, out, _dynamics(), progress=False, init_policy=path)
    assert res["init_policy_sha256"] == sha and res["resumed_at"] == 0
    first = batches[0]
    with torch.no_grad():
        dist = action_distribution(actor, first["observation"].reshape(-1, 14))
    # the first batch was collected by the clone: its action mean and scale at every observation
    torch.testing.assert_close(first["loc"].reshape(-1, 4), dist.loc)
    torch.testing.assert_close(first["scale"].reshape(-1, 4), dist.scale)
    config = json.loads(load_checkpoint(out / "policy.pt")["config"])
    assert config["init_policy_sha256"] == sha and config["init_policy"] == str(path)
    # the same command with more updates continues the run; another initial policy is another run
    more = dataclasses.replace(TINY, updates=3)
    assert train(CUBE_PUSH_STOP, "stochastic", 0, more, out, _dynamics(), progress=False,
                 init_policy=path)["resumed_at"] == 2
    other = tmp_path / "other.pt"
    save_clone(other, actor, CUBE_PUSH_STOP, dataclasses.replace(SMALL, noise=0.2), {}, "")
    with pytest.raises(RunMismatch, match="init_policy_sha256"):
        train(CUBE_PUSH_STOP, "stochastic", 0, more, out, _dynamics(), progress=False, init_policy=other)
    with pytest.raises(RunMismatch, match="init_policy_sha256"):
        train(CUBE_PUSH_STOP, "stochastic", 0, more, out, _dynamics(), progress=False)


def test_near_miss_share_by_hand_and_in_the_ppo_log(cloned, clone_file, tmp_path):
    hits = torch.tensor([[0, 1, 5, 3], [5, 0, 0, 2]])
    # goal-reaching steps: 1, 5, 3, 5, 2; of these 1, 3, 2 are partial
    assert near_miss_share(hits, 5) == pytest.approx(3 / 5)
    mask = torch.tensor([[True, True, True, False], [True, True, True, False]])
    assert near_miss_share(hits, 5, mask) == pytest.approx(1 / 3)
    assert near_miss_share(torch.zeros(3, dtype=torch.long), 5) is None
    with pytest.raises(ValueError):
        near_miss_share(hits, 5, mask[:1])
    # the share measured for a sampled clone is deterministic and agrees with its counts
    actor, _ = cloned
    task = dataclasses.replace(CUBE_PUSH_STOP, goal_speed=0.0, goal_radius=0.1)
    row = partial_hit_share(task, _dynamics(), 0.3, 8, num_envs=8, policy=ActorPolicy(actor, sample=True))
    again = partial_hit_share(task, _dynamics(), 0.3, 8, num_envs=8, policy=ActorPolicy(actor, sample=True, seed=9))
    assert row == again                                   # the policy is reseeded from the seed
    assert row["any_hit_steps"] > 0 and row["partial_steps"] > 0  # the clone reaches the goal
    assert row["near_miss_share"] == row["partial_steps"] / row["any_hit_steps"]
    # PPO logs it: a column of log.csv, empty in a batch without a goal-reaching step, else in
    # (0, 1] and above the partial-hit share (the same partial steps over fewer steps)
    path, _ = clone_file
    train(task, "stochastic", 0, TINY, tmp_path / "run", _dynamics(), progress=False, init_policy=path)
    with open(tmp_path / "run" / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert "near_miss_share" in rows[0] and "partial_hit_share" in rows[0]
    shares = [(float(r["partial_hit_share"]), r["near_miss_share"]) for r in rows]
    assert any(share > 0 for share, _ in shares)          # the cloned start straddles the goal
    for share, near in shares:
        if share > 0:
            assert share < float(near) <= 1.0                # most steps reach nothing
        else:
            assert near == "" or float(near) == 0.0


@pytest.mark.parametrize("argv,match", [
    (["--episodes", "0"], "episodes"),
    (["--noise", "0"], "noise"),
    (["--noise", "2"], "noise"),
    (["--collect-noise", "-1"], "collect_noise"),
    (["--seed", "900001"], "EVAL_SEED"),
    (["--model", "does/not/exist.pt"], "does/not/exist.pt"),
    (["--threads", "0"], "threads"),
])
def test_clone_cli_bad_input_exits_2(argv, match, tmp_path, capsys):
    out = tmp_path / "clone.pt"
    assert clone_main(["--task", "cube_push_stop", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("python -m experiments.rl.clone: error:") and "\n" not in err and match in err
    assert not out.exists()


def test_clone_cli_refuses_a_folder_and_unknown_task(tmp_path, capsys):
    assert clone_main(["--task", "cube_push_stop", "--out", str(tmp_path)]) == 2
    assert "folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        clone_main(["--task", "cube_push", "--out", str(tmp_path / "x.pt")])
    assert exc.value.code == 2


def test_rl_cli_init_policy_errors_exit_2(clone_file, tmp_path, capsys):
    path, _ = clone_file
    base = ["rl", "--mode", "stochastic", "--updates", "1", "--num-envs", "2",
            "--frames-per-batch", "10", "--minibatch", "10", "--eval-episodes", "2",
            "--ground-truth-episodes", "0", "--no-progress", "--out", str(tmp_path / "runs")]
    assert main([*base, "--task", "cube_push_stop", "--init-policy", str(tmp_path / "missing.pt")]) == 2
    assert "--init-policy not found" in capsys.readouterr().err
    assert main([*base, "--task", "tower_aside", "--init-policy", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hrn-pyg rl: error:") and "cube_push_stop" in err and "\n" not in err
