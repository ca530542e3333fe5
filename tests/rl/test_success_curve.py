import dataclasses
import math

import pytest
import torch

from hrn_pyg.rl import ppo, success_curve
from hrn_pyg.rl.dynamics import PointMassDynamics
from hrn_pyg.rl.ppo import PPOConfig, build_actor_critic, train
from hrn_pyg.rl.success_curve import (
    EvalConfig,
    curve_summary,
    evaluate_point,
    evaluation_env,
    frames_to_level,
    read_eval,
    success_auc,
)
from hrn_pyg.rl.tasks import CUBE_PUSH
from hrn_pyg.utils.checkpoint import load_checkpoint

TINY = PPOConfig(updates=3, num_envs=4, frames_per_batch=40, epochs=1, minibatch=20, hidden=16,
                 eval_episodes=4)


class Interrupt(Exception):
    pass


def test_frames_to_level_and_auc_by_hand():
    frames, success = [0, 100, 200, 400], [0.0, 0.5, 0.25, 1.0]
    assert frames_to_level(frames, success, 0.5) == 100
    assert frames_to_level(frames, success, 0.8) == 400
    assert frames_to_level(frames, [0.0, 0.1, 0.2, 0.3], 0.5) == math.inf
    # trapezoids: 100 * 0.25 + 100 * 0.375 + 200 * 0.625 = 187.5, over 400 frames
    assert success_auc(frames, success) == pytest.approx(187.5 / 400)
    assert success_auc([50], [0.7]) == 0.7
    assert success_auc([0, 10], [1.0, 1.0]) == 1.0


def test_curve_functions_reject_bad_input():
    with pytest.raises(ValueError, match="increase"):
        success_auc([0, 0], [0.1, 0.2])
    with pytest.raises(ValueError, match="as many"):
        frames_to_level([0, 1], [0.1], 0.5)
    with pytest.raises(ValueError, match="NaN"):
        success_auc([0, 1], [0.1, math.nan])
    with pytest.raises(ValueError, match="every"):
        EvalConfig(every=-1)
    with pytest.raises(ValueError, match="every"):
        PPOConfig(eval_every=2, eval_scenes=0)


def test_due_every_n_and_at_the_end():
    cfg = EvalConfig(every=4)
    assert [u for u in range(11) if cfg.due(u, 10)] == [0, 4, 8, 10]
    assert not any(EvalConfig(every=0).due(u, 10) for u in range(11))


def test_curve_summary_per_judge():
    curve = {"frames": [0.0, 10.0, 20.0], "model_success_rate": [0.0, 0.6, 0.9],
             "pybullet_success_rate": [0.0, 0.2, 0.5]}
    got = curve_summary(curve)
    assert got["model_frames_to_50"] == 10 and got["model_frames_to_80"] == 20
    assert got["pybullet_frames_to_50"] == 20 and got["pybullet_frames_to_80"] == math.inf
    assert got["pybullet_success_auc"] == pytest.approx((10 * 0.1 + 10 * 0.35) / 20)
    assert got["model_final_success"] == 0.9 and got["eval_points"] == 3
    nan = {"frames": [0.0], "model_success_rate": [0.5], "pybullet_success_rate": [math.nan]}
    assert "pybullet_success_auc" not in curve_summary(nan)


class WithScenes(PointMassDynamics):
    """Point masses that claim pybullet scenes: evaluate_point takes the replay path."""

    def __init__(self):
        super().__init__(PointMassDynamics.for_task("cube_push").config)

    def scene_seeds(self, states):
        return torch.zeros(states.shape[:-1], dtype=torch.long)


def test_every_evaluation_sees_the_same_scenes_and_replays_them(monkeypatch):
    seen = []

    def fake_ground_truth(policy, env, episodes, closed_loop=False):
        assert closed_loop  # the default evaluation also runs the policy closed loop
        seen.append(env.reset()["state"].clone())
        assert env.dropout_rate == 0.0 and env.action_noise_std == 0.0
        return {"ground_truth_episodes": episodes, "model_success_rate": 0.5, "model_mean_length": 3.0,
                "pybullet_success_rate": 0.25, "pybullet_mean_length": 4.0, "agreement": 0.75}

    monkeypatch.setattr(success_curve, "ground_truth_success", fake_ground_truth)
    cfg = EvalConfig(every=1, episodes=6)
    env = evaluation_env(CUBE_PUSH, WithScenes(), cfg)
    actor, _ = build_actor_critic(env, 8)
    first = evaluate_point(actor, env, cfg)
    env.reset()  # moves the generator on
    second = evaluate_point(actor, env, cfg)
    assert first == second and "ground_truth_episodes" not in first
    assert first["pybullet_success_rate"] == 0.25
    assert torch.equal(seen[0], seen[1])
    other = evaluate_point(actor, env, dataclasses.replace(cfg, pybullet=False))
    assert set(other) == {"model_success_rate", "model_mean_length"}


def test_evaluation_leaves_training_unchanged_and_writes_the_curve(tmp_path):
    plain = train(CUBE_PUSH, "stochastic", 0, TINY, tmp_path / "plain", progress=False)
    cfg = dataclasses.replace(TINY, eval_every=2, eval_scenes=5)
    judged = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "judged", progress=False)
    logs = [(tmp_path / run / "log.csv").read_text().splitlines() for run in ("plain", "judged")]
    seconds = logs[0][0].split(",").index("seconds")

    def without_seconds(lines):
        return [[c for i, c in enumerate(line.split(",")) if i != seconds] for line in lines]

    assert without_seconds(logs[0]) == without_seconds(logs[1])
    assert plain["success_rate"] == judged["success_rate"]
    curve = read_eval(tmp_path / "judged" / "eval.csv")
    assert curve["step"] == [0, 2, 3] and curve["frames"] == [0, 80, 120]
    assert all(0 <= s <= 1 for s in curve["model_success_rate"])
    assert judged["eval_points"] == 3 and "model_success_auc" in judged
    assert not (tmp_path / "plain" / "eval.csv").exists()


def test_a_resumed_run_keeps_one_evaluation_history(tmp_path, monkeypatch):
    """Killed during update 3 with checkpoints every 2 updates and an evaluation after every
    update: the rerun drops the evaluation after the checkpoint, and the evaluations up to it
    are those of an uninterrupted run, value for value."""
    cfg = dataclasses.replace(TINY, updates=4, checkpoint_every=2, eval_every=1, eval_scenes=4)
    whole = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "whole", progress=False)
    update, done = ppo._ppo_update, []

    def killed_in_fourth(batch, *args):
        if len(done) == 3:
            raise Interrupt
        done.append(1)
        return update(batch, *args)

    monkeypatch.setattr(ppo, "_ppo_update", killed_in_fourth)
    with pytest.raises(Interrupt):
        train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "run", progress=False)
    assert load_checkpoint(tmp_path / "run" / "policy.pt")["update"] == 2
    assert read_eval(tmp_path / "run" / "eval.csv")["step"] == [0, 1, 2, 3]
    monkeypatch.setattr(ppo, "_ppo_update", update)
    resumed = train(CUBE_PUSH, "stochastic", 0, cfg, tmp_path / "run", progress=False)
    assert resumed["resumed_at"] == 2 and whole["eval_points"] == resumed["eval_points"] == 5
    got, want = read_eval(tmp_path / "run" / "eval.csv"), read_eval(tmp_path / "whole" / "eval.csv")
    assert got["step"] == [0, 1, 2, 3, 4]
    for name in ("model_success_rate", "model_mean_length"):
        assert got[name][:3] == want[name][:3]
