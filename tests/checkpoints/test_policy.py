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
