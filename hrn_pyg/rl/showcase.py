"""A trained policy shown end to end: one episode in the learned environment, the same actions
replayed in pybullet, and a picture of both (used by ``hrn-pyg demo``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from hrn_pyg.data.graph import HISTORY
from hrn_pyg.rl.env import HRNEnv
from hrn_pyg.rl.evaluate import record_episodes, replay_in_pybullet
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.policy import load_actor
from hrn_pyg.utils.files import atomic_write_json

#: environment seed of the shown episode (fixes its start scene and goal)
SHOWCASE_SEED = 7


def showcase_policy(model: str | os.PathLike, policy: str | os.PathLike, out: str | os.PathLike,
                    task: str = "cube_push", episodes: int = 4, device: str | torch.device | None = None) -> str:
    """Run ``episodes`` deterministic episodes of ``policy`` in the learned model (dropout 0) on
    ``device`` (None: the CPU), replay each in pybullet, draw the first one, and return a
    one-line summary."""
    from hrn_pyg.viz import object_colors, rollout_grid

    out = Path(out)
    dynamics = HRNDynamics.from_checkpoint(model, task, device)
    env = HRNEnv(task, dynamics, batch_size=episodes, seed=SHOWCASE_SEED, dropout_rate=0.0)
    actor = load_actor(policy, env)
    records = record_episodes(actor, env, episodes)  # CPU tensors
    replays = [replay_in_pybullet(r["actions"], task, r["seed"], r["goal"], history_steps=HISTORY)
               for r in records]  # one pybullet scene per episode
    rec, real = records[0], replays[0]
    learned = dynamics.leaf_history(rec["states"])[0][:, 2].numpy()  # x_t after each action
    pyb = real["leaves"].numpy()
    length = max(len(learned), len(pyb))
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], length - len(a), 0)]) if len(a) < length else a
    times = sorted({int(t) for t in np.linspace(0, length - 1, 4).round()})
    rollout_grid({"learned model": pad(learned), "pybullet replay": pad(pyb)}, times,
                 object_colors(dynamics.leaf_object.cpu().numpy()), out / f"{task}_policy.png",
                 title=f"{task}: the same actions in the learned model and in pybullet")
    summary = {
        "episodes": episodes,
        "learned_model_success": sum(r["success"] for r in records) / episodes,
        "pybullet_success": sum(r["success"] for r in replays) / episodes,
        "first_episode": {"scene_seed": rec["seed"], "steps": rec["length"], "model_success": rec["success"],
                          "pybullet_success": real["success"]},
    }
    atomic_write_json(out / f"{task}_policy.json", summary)
    return (f"{summary['learned_model_success']:.0%} of {episodes} episodes reach the goal in the learned model, "
            f"{summary['pybullet_success']:.0%} when replayed in pybullet; picture {out / f'{task}_policy.png'}")
