"""The shipped policy loads by name into an environment and acts."""

from __future__ import annotations

import pytest

from hrn_pyg.checkpoints import checkpoint_path, load_model
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.policy import load_actor, load_policy, policy_path
from hrn_pyg.utils.checkpoint import CheckpointError


@pytest.fixture(scope="module")
def env():
    dynamics = HRNDynamics(load_model("cube_push"), "cube_push", pool_seeds=(10_000, 10_001))
    return HRNEnv("cube_push", dynamics, batch_size=2, seed=0, dropout_rate=0.0)


def test_the_shipped_policy_acts_in_its_environment(env):
    actor, same = load_policy("cube_push_policy", env)
    assert same is env
    steps = env.rollout(3, actor, break_when_any_done=False)
    assert tuple(steps["action"].shape[:2]) == (2, 3)


def test_bad_policies_are_one_line_errors(env):
    with pytest.raises(FileNotFoundError, match="neither a file nor a shipped policy.*cube_push_policy"):
        policy_path("no_such_policy")
    with pytest.raises(CheckpointError, match="not a policy"):
        load_actor(checkpoint_path("wedge"), env)


@pytest.mark.parametrize("hidden", [10**7, -3, "64", [64]])
def test_a_policy_asking_for_an_absurd_width_is_refused_before_it_is_built(env, tmp_path, hidden):
    """A small file whose config asks for 10^7 hidden units would build a network of gigabytes."""
    import json

    import torch

    ckpt = torch.load(checkpoint_path("cube_push_policy"), weights_only=True)
    config = json.loads(ckpt["config"])
    config["ppo"]["hidden"] = hidden
    ckpt["config"] = json.dumps(config)
    path = tmp_path / "wide.pt"
    torch.save(ckpt, path)
    with pytest.raises(CheckpointError, match="hidden width must be a whole number"):
        load_actor(path, env)
