import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys

import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.rl import ppo
from hrn_pyg.rl.curves import curve_metrics, read_curve
from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import evaluate_policy
from hrn_pyg.rl.ppo import MODES, PPOConfig, build_actor_critic, mode_settings, train
from hrn_pyg.rl.tasks import CUBE_PUSH, TOWER
from hrn_pyg.utils.checkpoint import load_checkpoint


class FixedDynamics:
    """Every sample puts cube 0 at ``(x, x)`` (cube 1 stays at 5 m), whatever the action."""

    num_objects, object_dim, state_dim = 2, 6, 12

    def __init__(self, x: float):
        self.x = x

    def reset_states(self, batch, generator):
        return torch.full((batch, 12), 5.0)

    def roots(self, states):
        return states.reshape(*states.shape[:-1], 2, 6)

    def sample_next(self, states, forces, k, rate, generator):
        out = states[:, None].repeat(1, k, 1)
        out[..., :2] = self.x
        return out


class RecordingPointMass(PointMassDynamics):
    """Point-mass cube_push that records the dropout rate of every step it is asked for."""

    def __init__(self):
        super().__init__(PointMassDynamics.for_task("cube_push").config)
        self.rates: list[float] = []

    def sample_next(self, states, forces, k, rate, generator):
        self.rates.append(rate)
        return super().sample_next(states, forces, k, rate, generator)


TINY = PPOConfig(updates=2, num_envs=4, frames_per_batch=40, epochs=1, minibatch=20, hidden=16,
                 eval_episodes=4)


def test_annealing_schedule_values():
    cfg = PPOConfig()
    sched, noise = mode_settings("stochastic_annealed", TOWER, cfg)
    assert noise == 0.0
    assert [sched(u) for u in (0, 600, 1200, 5000)] == pytest.approx([0.1, 0.05, 0.0, 0.0])
    sched, _ = mode_settings("stochastic", CUBE_PUSH, cfg)
    assert sched(0) == sched(1200) == pytest.approx(0.1)
    sched, noise = mode_settings("action_noise", CUBE_PUSH, cfg)
    assert sched(0) == 0.0 and noise == cfg.action_noise_std
    sched, noise = mode_settings("deterministic", TOWER, cfg)
    assert sched(0) == 0.0 and noise == 0.0
    with pytest.raises(ValueError, match="mode"):
        mode_settings("greedy", TOWER, cfg)


def _episode_stats_by_hand(batch) -> dict:
    """Episodes that ended in a collected batch ``(B, T)``, one frame at a time."""
    done = batch["next", "done"].squeeze(-1).tolist()
    t = batch["next", "t"].squeeze(-1).tolist()
    won = batch["next", "terminated"].squeeze(-1).tolist()
    ended = [(t[b][i], won[b][i]) for b in range(len(done)) for i in range(len(done[b])) if done[b][i]]
    rewards = [r for row in batch["next", "reward"].squeeze(-1).tolist() for r in row]
    hits = [h for row in batch["next", "goal_hits"].squeeze(-1).tolist() for h in row]
    return {"episodes": len(ended), "mean_episode_length": sum(n for n, _ in ended) / len(ended),
            "success_rate": sum(w for _, w in ended) / len(ended),
            "reward_mean": sum(rewards) / len(rewards),
            "partial_hit_share": sum(0 < h < CUBE_PUSH.num_samples for h in hits) / len(hits)}


def test_tiny_ppo_run_writes_log_and_checkpoint(tmp_path, monkeypatch):
    batches, initial = [], {}
    update, build = ppo._ppo_update, ppo.build_actor_critic

    def keep_batch(batch, *args):  # the batch as collected, before GAE writes into it
        batches.append(batch.clone())
        return update(batch, *args)

    def keep_init(env, hidden):
        actor, critic = build(env, hidden)
        initial.update({f"actor.{k}": v.clone() for k, v in actor.state_dict().items()})
        initial.update({f"critic.{k}": v.clone() for k, v in critic.state_dict().items()})
        return actor, critic

    monkeypatch.setattr(ppo, "_ppo_update", keep_batch)
    monkeypatch.setattr(ppo, "build_actor_critic", keep_init)
    dyn = RecordingPointMass()
    res = train(CUBE_PUSH, "stochastic_annealed", 0, TINY, tmp_path, dyn, anneal_updates=2,
                progress=False)
    with open(tmp_path / "log.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["update"]) for r in rows] == [0, 1]
    assert [int(r["frames"]) for r in rows] == [40, 80]
    assert [float(r["dropout_rate"]) for r in rows] == pytest.approx([0.1, 0.05])
    # the dynamics got the logged rate on every step of its batch (10 steps of 4 environments),
    # then dropout 0 for the final evaluation
    steps = TINY.frames_per_batch // TINY.num_envs
    assert dyn.rates[:2 * steps] == pytest.approx([0.1] * steps + [0.05] * steps)
    assert len(dyn.rates) > 2 * steps and set(dyn.rates[2 * steps:]) == {0.0}
    # the logged episode statistics are those of the collected batches, recomputed by hand
    assert len(batches) == 2 and all(b.shape == (TINY.num_envs, steps) for b in batches)
    for row, batch in zip(rows, batches):
        expected = _episode_stats_by_hand(batch)
        assert int(row["episodes"]) == expected.pop("episodes") > 0
        assert {k: float(row[k]) for k in expected} == pytest.approx(expected)
        assert row["loss_objective"] != "" and row["loss_critic"] != ""
    # the checkpoint holds trained weights: every weight and bias of the actor and the critic
    # moved away from its initial value, in 2 updates x 1 epoch x 2 minibatches = 4 Adam steps
    ckpt = load_checkpoint(tmp_path / "policy.pt")
    assert ckpt["update"] == 2 and json.loads(ckpt["config"])["mode"] == "stochastic_annealed"
    saved = {f"{net}.{k}": v for net in ("actor", "critic") for k, v in ckpt["model"][net].items()}
    assert saved.keys() == initial.keys()
    assert sum(not torch.equal(saved[k], initial[k]) for k in saved) == len(saved)
    assert {int(s["step"]) for s in ckpt["optimizer"]["state"].values()} == {4}
    env = HRNEnv(CUBE_PUSH, batch_size=2, seed=0)
    actor, critic = build_actor_critic(env, TINY.hidden)
    actor.load_state_dict(ckpt["model"]["actor"])
    critic.load_state_dict(ckpt["model"]["critic"])
    # the result's curve metrics are those of the written log
    metrics = curve_metrics(read_curve(tmp_path / "log.csv"))
    assert {k: res[k] for k in metrics} == metrics
    assert metrics["final_length"] == float(rows[-1]["mean_episode_length"])
    assert 0.0 <= res["success_rate"] <= 1.0 and 1.0 <= res["mean_episode_length"] <= 10.0
    assert (tmp_path / "curve.png").stat().st_size > 0


def test_evaluate_policy_by_hand():
    near = dataclasses.replace(CUBE_PUSH, goal_distance=(0.0, 0.0))  # goal at the origin
    for x, expected in ((0.0, (1.0, 1.0)), (5.0, (0.0, 10.0))):
        env = HRNEnv(near, FixedDynamics(x), batch_size=3, seed=0)
        actor, _ = build_actor_critic(env, 8)
        assert evaluate_policy(actor, env, 5) == pytest.approx(expected)


def test_cli_trains_and_scores_one_run(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["rl", "--task", "tower", "--mode", "action_noise", "--seed", "3", "--updates", "1",
                 "--num-envs", "4", "--frames-per-batch", "20", "--minibatch", "20", "--eval-episodes", "2",
                 "--out", str(out), "--no-progress"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["curve.png", "log.csv", "policy.pt", "result.json"]
    result = json.loads((out / "result.json").read_text())
    assert (result["task"], result["mode"], result["seed"], result["updates"]) == ("tower", "action_noise", 3, 1)
    assert "tower action_noise seed 3: success" in capsys.readouterr().out


def test_cli_default_folder_names_the_task_mode_and_seed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(CLI_RUN) == 0
    assert (tmp_path / "runs/rl/cube_push/deterministic/seed0/result.json").is_file()


def test_cli_sweep_options_are_not_one_runs(tmp_path):
    """``hrn-pyg rl`` trains one run: modes and seeds in numbers are the sweep's
    (``python -m experiments.rl.sweep``)."""
    for argv in (["--num-seeds", "2"], ["--first-seed", "1"], ["--mode", "deterministic", "stochastic"]):
        with pytest.raises(SystemExit) as exc:
            main(["rl", "--out", str(tmp_path), "--no-progress", *argv])
        assert exc.value.code == 2
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("argv", [
    ["--updates", "0"],
    ["--frames-per-batch", "33"],
    ["--model", "does/not/exist.pt"],
    ["--anneal-updates", "-1"],
    ["--device", "nonsense"],
])
def test_cli_bad_input_exits_2(argv, tmp_path, capsys):
    assert main(["rl", "--out", str(tmp_path), "--no-progress", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hrn-pyg rl: error:") and "\n" not in err
    assert not any(tmp_path.iterdir())


def _spy_on_environments(monkeypatch) -> list[tuple[torch.device | None, torch.device]]:
    """Per environment PPO builds: the device it is asked for (None: the dynamics') and its
    dynamics' device."""
    made = []

    def spy(task, dynamics=None, **kwargs):
        asked = kwargs["device"]
        made.append((None if asked is None else torch.device(asked), dynamics.device))
        return HRNEnv(task, dynamics, **kwargs)

    monkeypatch.setattr(ppo, "HRNEnv", spy)
    return made


CLI_RUN = ["rl", "--task", "cube_push", "--mode", "deterministic", "--updates", "1",
           "--num-envs", "2", "--frames-per-batch", "10", "--minibatch", "10", "--eval-episodes", "2",
           "--no-progress"]


def test_cli_device_cpu(tmp_path, monkeypatch):
    """The default device is made ``meta`` here: a command that ignored ``--device cpu`` would
    build its dynamics and environment there (and fail); they must be on the CPU, and so the
    policy it saves."""
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("meta"))
    made = _spy_on_environments(monkeypatch)
    out = tmp_path / "rl"
    code = main([*CLI_RUN, "--out", str(out), "--device", "cpu"])
    assert code == 0
    assert made == [(torch.device("cpu"), torch.device("cpu"))]
    ckpt = load_checkpoint(out / "policy.pt")
    weights = [*ckpt["model"]["actor"].values(), *ckpt["model"]["critic"].values()]
    assert weights and all(w.device.type == "cpu" for w in weights)


def test_cli_device_meta_is_refused_before_anything_is_made(tmp_path, monkeypatch, capsys):
    """``--device meta`` is no device the package runs on: one line, exit 2, no environment made,
    nothing written."""
    made = _spy_on_environments(monkeypatch)
    out = tmp_path / "rl"
    assert main([*CLI_RUN, "--out", str(out), "--device", "meta"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "meta" in err[0]
    assert made == [] and not (out / "policy.pt").exists()


def test_train_on_an_explicit_device_repeats_the_default_run(tmp_path, monkeypatch):
    made = _spy_on_environments(monkeypatch)
    cfg = dataclasses.replace(TINY, updates=1)
    a = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "a", progress=False, device=torch.device("cpu"))
    b = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "b", progress=False)
    for key in ("success_rate", "mean_episode_length"):
        assert a[key] == b[key]
    rows = [(tmp_path / run / "log.csv").read_text().splitlines()[1].rsplit(",", 1)[0] for run in "ab"]
    assert rows[0] == rows[1]  # every logged value but the seconds
    # the device is used, not ignored: asked for meta, train builds its dynamics and environment there
    with pytest.raises((RuntimeError, NotImplementedError), match="(?i)meta"):
        train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "c", progress=False, device=torch.device("meta"))
    cpu, meta = torch.device("cpu"), torch.device("meta")
    assert made == [(cpu, cpu), (None, cpu), (meta, meta)]


def test_cli_unknown_task_or_mode_exits_2():
    for argv in (["rl", "--task", "stack"], ["rl", "--mode", "greedy"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    assert MODES == ("deterministic", "action_noise", "stochastic", "stochastic_annealed",
                     "stochastic_unrelaxed")


def test_replay_in_pybullet_judges_the_goal_on_ground_truth():
    from hrn_pyg.rl.evaluate import replay_in_pybullet

    still = torch.zeros(3, CUBE_PUSH.action_dim)
    first = replay_in_pybullet(still[:1], "cube_push", 5, goal=torch.tensor([9.0, 9.0]))
    start = first["roots"][0, 0, :2]                      # cube 0 where the scene put it
    hit = replay_in_pybullet(still, "cube_push", 5, goal=start)
    assert hit["success"] and hit["steps"] == 1 and hit["roots"].shape == (2, 2, 6)
    assert not first["success"] and first["steps"] == 1
    with pytest.raises(ValueError, match="goal"):
        replay_in_pybullet(still, "cube_push", 5)


def test_pybullet_judges_a_held_goal_only_after_hold_steps_in_a_row():
    from hrn_pyg.rl.evaluate import closed_loop_in_pybullet, replay_in_pybullet

    task = dataclasses.replace(CUBE_PUSH, hold_steps=3)
    still = torch.zeros(4, task.action_dim)
    start = replay_in_pybullet(still[:1], task, 5, goal=torch.tensor([9.0, 9.0]))["roots"][0, 0, :2]
    # the resting cube is in the disc at every step: success at the third, not before
    assert not replay_in_pybullet(still[:2], task, 5, goal=start)["success"]
    held = replay_in_pybullet(still, task, 5, goal=start)
    assert held["success"] and held["steps"] == 3
    closed = closed_loop_in_pybullet(lambda obs: torch.zeros(1, task.action_dim), task, 5, start,
                                     history_steps=0)
    assert closed == {"success": True, "steps": 3}


def test_curve_metrics_by_hand():
    from hrn_pyg.rl.curves import smooth, updates_to_reach

    assert smooth([4.0, float("nan"), 2.0], window=2) == [4.0, 4.0, 2.0]
    # 10 updates at 10, then 90 at 2: final 2, start 10, 90 % of the drop reached when the
    # 10-update average is <= 2.8, i.e. once at most one of the last ten values is 10
    curve = [10.0] * 10 + [2.0] * 90
    m = curve_metrics(curve)
    assert m["final_length"] == 2.0 and m["start_length"] == 10.0
    assert m["updates_to_final"] == 18
    assert updates_to_reach(curve, 6.0) == 14 and updates_to_reach(curve, 1.0) is None
    assert updates_to_reach([1.0] + [9.0] * 20, 5.0) is None  # one lucky first update is not enough
    assert curve_metrics([9.0, 7.0] * 5 + [2.0] * 10)["start_length"] == 8.0  # first ten
    flat = curve_metrics([9.0] * 50)
    assert flat["final_length"] == 9.0 and flat["updates_to_final"] is None   # no learning


class Interrupt(Exception):
    """Stands for a run killed between two updates."""


def _clone_state(state):
    """A deep copy of a (nested) state dict: tensors cloned, containers copied."""
    if isinstance(state, torch.Tensor):
        return state.detach().clone()
    if isinstance(state, dict):
        return {k: _clone_state(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_clone_state(v) for v in state)
    return state


def _assert_same_weights(got: dict, want: dict, what: str):
    assert got.keys() == want.keys(), what
    for k in want:
        assert torch.equal(got[k], want[k]), f"{what}: {k} differs"


def _assert_same_adam_state(got: dict, want: dict):
    """Every parameter's Adam moments and step count, and the parameter groups, bit for bit."""
    assert got["param_groups"] == want["param_groups"]
    params = [i for group in want["param_groups"] for i in group["params"]]
    assert sorted(want["state"]) == sorted(params) and len(params) > 0  # every parameter has state
    assert sorted(got["state"]) == sorted(want["state"])
    for i in params:
        assert set(want["state"][i]) == {"step", "exp_avg", "exp_avg_sq"}
        assert set(got["state"][i]) == set(want["state"][i]), f"parameter {i}"
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(got["state"][i][key], want["state"][i][key]), f"parameter {i}: {key} differs"


def test_a_killed_run_continues_from_its_last_checkpoint(tmp_path, monkeypatch):
    """Killed after update 3 with a checkpoint every 2 updates: the rerun starts at update 2 from
    the saved weights, Adam state and random state, and the log is one history 0..3.

    The state the rerun resumes with is compared with that of an uninterrupted run of the same
    settings as it enters update 2: actor and critic weights and the whole Adam state (both
    moments and the step count of every parameter) are the same, bit for bit. (After update 2
    the runs part: a resumed run starts fresh episodes, see ``ppo.resume_run``.)"""
    cfg = dataclasses.replace(TINY, updates=4, checkpoint_every=2)
    update, build = ppo._ppo_update, ppo.build_actor_critic

    # the uninterrupted run: its networks and optimiser as they enter update 2
    nets, entering = {}, {}

    def keep_nets(env, hidden):
        nets["actor"], nets["critic"] = build(env, hidden)
        nets["initial_critic"] = _clone_state(nets["critic"].state_dict())
        return nets["actor"], nets["critic"]

    def snapshot_at_two(batch, gae, loss_module, optim, config):
        entering.setdefault("calls", 0)
        if entering["calls"] == 2:
            entering.update(actor=_clone_state(nets["actor"].state_dict()),
                            critic=_clone_state(nets["critic"].state_dict()),
                            optim=_clone_state(optim.state_dict()))
        entering["calls"] += 1
        return update(batch, gae, loss_module, optim, config)

    monkeypatch.setattr(ppo, "build_actor_critic", keep_nets)
    monkeypatch.setattr(ppo, "_ppo_update", snapshot_at_two)
    whole = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "whole", RecordingPointMass(), progress=False)
    assert whole["resumed_at"] == 0 and entering["calls"] == 4
    # training moved every critic weight by update 2: a critic left at its initial weights differs
    assert all(not torch.equal(entering["critic"][k], v) for k, v in nets["initial_critic"].items())
    monkeypatch.setattr(ppo, "build_actor_critic", build)

    done = []

    def killed_after_three(batch, *args):
        if len(done) == 3:
            raise Interrupt
        done.append(1)
        return update(batch, *args)

    monkeypatch.setattr(ppo, "_ppo_update", killed_after_three)
    with pytest.raises(Interrupt):
        train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path, RecordingPointMass(), progress=False)
    saved = load_checkpoint(tmp_path / "policy.pt")
    assert saved["update"] == 2
    assert [int(r["update"]) for r in read_curve_rows(tmp_path)] == [0, 1, 2]  # update 2 was logged, not saved

    loaded = {}
    resume = ppo.resume_run

    def spy(path, identity, actor, critic, optim, env):
        start = resume(path, identity, actor, critic, optim, env)
        loaded.update(actor=_clone_state(actor.state_dict()), critic=_clone_state(critic.state_dict()),
                      optim=_clone_state(optim.state_dict()),
                      torch_rng=torch.get_rng_state().clone(), env_rng=env.rng.get_state().clone())
        return start

    monkeypatch.setattr(ppo, "_ppo_update", update)
    monkeypatch.setattr(ppo, "resume_run", spy)
    res = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path, RecordingPointMass(), progress=False)
    assert res["resumed_at"] == 2
    _assert_same_weights(loaded["actor"], entering["actor"], "actor")
    _assert_same_weights(loaded["critic"], entering["critic"], "critic")
    _assert_same_adam_state(loaded["optim"], entering["optim"])
    assert {int(s["step"]) for s in loaded["optim"]["state"].values()} == {2 * 2}  # 2 updates x 2 minibatches
    assert torch.equal(loaded["torch_rng"], saved["rng"]["torch"])
    assert torch.equal(loaded["env_rng"], saved["env_rng"])
    rows = read_curve_rows(tmp_path)
    assert [int(r["update"]) for r in rows] == [0, 1, 2, 3]
    assert [float(r["frames"]) for r in rows] == [40, 80, 120, 160]
    # the updates before the kill are the uninterrupted run's (every logged value but the seconds)
    unbroken = read_curve_rows(tmp_path / "whole")
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in rows[:2]] == \
        [{k: v for k, v in r.items() if k != "seconds"} for r in unbroken[:2]]
    final = load_checkpoint(tmp_path / "policy.pt")
    assert final["update"] == 4 and {int(s["step"]) for s in final["optimizer"]["state"].values()} == {8}


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_mid_update_saves_that_update_and_stops(tmp_path, monkeypatch, signum):
    """kill (SIGTERM) or Ctrl-C (SIGINT) during update 1, with checkpoints only every 50
    updates: the update under way finishes, policy.pt holds 2 updates, the run stops with
    KeyboardInterrupt and the handlers are restored; the rerun continues at update 2."""
    cfg = dataclasses.replace(TINY, updates=4, checkpoint_every=50)
    update = ppo._ppo_update
    done = []

    def signalled_in_second(batch, *args):
        done.append(1)
        if len(done) == 2:
            os.kill(os.getpid(), signum)  # arrives inside the update, as from outside
        return update(batch, *args)

    monkeypatch.setattr(ppo, "_ppo_update", signalled_in_second)
    before = signal.getsignal(signum)
    with pytest.raises(KeyboardInterrupt, match="after update 2"):
        train(CUBE_PUSH, "deterministic", 0, cfg, tmp_path, RecordingPointMass(), progress=False)
    assert signal.getsignal(signum) is before
    assert load_checkpoint(tmp_path / "policy.pt")["update"] == 2 and len(done) == 2
    monkeypatch.setattr(ppo, "_ppo_update", update)
    res = train(CUBE_PUSH, "deterministic", 0, cfg, tmp_path, RecordingPointMass(), progress=False)
    assert res["resumed_at"] == 2
    assert [int(r["update"]) for r in read_curve_rows(tmp_path)] == [0, 1, 2, 3]


def test_a_finished_run_is_extended_not_repeated_and_restart_starts_afresh(tmp_path, monkeypatch):
    train(CUBE_PUSH, "deterministic", 0, TINY, tmp_path, RecordingPointMass(), progress=False)
    calls = []
    update = ppo._ppo_update
    monkeypatch.setattr(ppo, "_ppo_update", lambda batch, *a: calls.append(1) or update(batch, *a))
    again = train(CUBE_PUSH, "deterministic", 0, TINY, tmp_path, RecordingPointMass(), progress=False)
    assert again["resumed_at"] == 2 and calls == []  # nothing left to train: only the evaluation
    more = train(CUBE_PUSH, "deterministic", 0, dataclasses.replace(TINY, updates=3), tmp_path,
                 RecordingPointMass(), progress=False)
    assert more["resumed_at"] == 2 and len(calls) == 1
    assert [int(r["update"]) for r in read_curve_rows(tmp_path)] == [0, 1, 2]
    rows_before = read_curve_rows(tmp_path)
    with pytest.raises(ppo.RunMismatch, match=r"another run \(ppo_training differ.*'lr': 0.0001.*--restart"):
        train(CUBE_PUSH, "deterministic", 0, dataclasses.replace(TINY, lr=1e-4), tmp_path,
              RecordingPointMass(), progress=False)  # another run's checkpoint: refused, kept
    assert read_curve_rows(tmp_path) == rows_before and load_checkpoint(tmp_path / "policy.pt")["update"] == 3
    fresh = train(CUBE_PUSH, "deterministic", 0, TINY, tmp_path, RecordingPointMass(), progress=False,
                  restart=True)
    assert fresh["resumed_at"] == 0 and [int(r["update"]) for r in read_curve_rows(tmp_path)] == [0, 1]


def read_curve_rows(folder):
    with open(folder / "log.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def test_a_sweep_option_says_in_one_line_where_it_went():
    proc = subprocess.run([sys.executable, "-m", "hrn_pyg.cli", "rl", "--task", "cube_push", "--num-seeds", "3"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "experiments.rl.sweep" in proc.stderr
