"""Trained PPO policies: the shipped ``cube_push_policy`` or a run's ``policy.pt``, by name or path.

:func:`load_actor` reads a policy checkpoint (weights-only) into the actor of
:func:`hrn_pyg.rl.ppo.build_actor_critic`; :func:`load_policy` also builds the environment it
was trained in::

    actor, env = load_policy("cube_push_policy")
    rollout = env.rollout(env.task.max_steps, actor)
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule

from hrn_pyg.checkpoints import MAX_WIDTH, POLICY_NAMES, checkpoint_path
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.utils.checkpoint import CheckpointError, bounded_json, load_checkpoint


def policy_path(policy: str | os.PathLike) -> Path:
    """The policy file ``policy`` names: a path to a file, or a shipped policy's name
    (``cube_push_policy``). Raises FileNotFoundError naming the shipped policies."""
    path = Path(policy)
    if path.is_file():
        return path
    name = str(policy)[:-3] if str(policy).endswith(".pt") else str(policy)
    if name in POLICY_NAMES and checkpoint_path(name).is_file():
        return checkpoint_path(name)
    raise FileNotFoundError(f"policy not found: {policy} is neither a file nor a shipped policy "
                            f"({', '.join(POLICY_NAMES)})")


def load_actor(policy: str | os.PathLike, env: HRNEnv) -> TensorDictModule:
    """The trained actor of a policy checkpoint (a path or a shipped policy's name) for ``env``,
    in eval mode on the environment's device. Raises CheckpointError (a ValueError) for a file
    that is not a policy of ``hrn-pyg rl``."""
    from hrn_pyg.rl.ppo import build_actor_critic

    path = policy_path(policy)
    ckpt = load_checkpoint(path)
    try:
        hidden = bounded_json(ckpt["config"], f"{path}'s config")["ppo"]["hidden"]
        if not isinstance(hidden, int) or isinstance(hidden, bool) or not 1 <= hidden <= MAX_WIDTH:
            raise CheckpointError(f"{path}: the policy's hidden width must be a whole number in 1..{MAX_WIDTH}, "
                                  f"got {hidden!r}")
        actor, _ = build_actor_critic(env, hidden)
        actor.load_state_dict(ckpt["model"]["actor"])
    except (KeyError, TypeError, RuntimeError) as exc:
        raise CheckpointError(f"{path} is not a policy written by `hrn-pyg rl` ({type(exc).__name__}: "
                              f"{str(exc).strip().splitlines()[0] if str(exc).strip() else ''})") from None
    return actor.eval()


def load_policy(policy: str | os.PathLike = "cube_push_policy", env: HRNEnv | None = None, *,
                task: str = "cube_push", model: str | os.PathLike = "cube_push", batch_size: int = 1,
                seed: int | None = 0, device: str | torch.device | None = None) -> tuple[TensorDictModule, HRNEnv]:
    """A policy's actor and the environment it acts in: ``env``, or (None) an :class:`HRNEnv`
    of ``task`` stepped by ``model`` (a path or a shipped model's name; by default the shipped
    cube-push dynamics the shipped policy was trained in) at dropout rate 0, ``batch_size``
    environments seeded by ``seed``, on ``device`` (None: the CPU)."""
    if env is None:
        from hrn_pyg.rl.hrn_dynamics import HRNDynamics

        dynamics = HRNDynamics.from_checkpoint(model, task, device)
        env = HRNEnv(task, dynamics, batch_size=batch_size, seed=seed, dropout_rate=0.0)
    return load_actor(policy, env), env
