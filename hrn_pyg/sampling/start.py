"""A scene to a start state in one call, and the deterministic rollout in the sampler's convention.

:func:`scene` simulates the first steps of a built-in scene or a scene file in pybullet and
returns the model's start state (a one-scene graph with its history and pitch, carrying the
ground truth of the steps simulated). :func:`rollout` is what a user calls for one deterministic
future: the leaves' positions ``[steps, L, 3]``, without gradients unless asked, as
:func:`~hrn_pyg.sampling.sample.sample` returns K of them. (The rollout loop that training and
evaluation use, every node with gradients, is :func:`hrn_pyg.sim.rollout.rollout`.)

.. code-block:: python

    import hrn_pyg
    model = hrn_pyg.load_model("shapes")
    state = hrn_pyg.scene("my_scene.toml", seed=0)
    path = hrn_pyg.rollout(model, state, steps=30)                       # [30, L, 3]
    futures = hrn_pyg.sample(model, state, k=8, steps=30, rate=0.2, seed=0)  # [8, 30, L, 3]
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import HISTORY, NODE
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.nn.hrn import HRN
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sampling.sample import copies_forces, sample
from hrn_pyg.sim.rollout import rollout as rollout_nodes
from hrn_pyg.sim.sleeping import DEFAULT_SLEEP, SleepConfig


def scene(source: str | os.PathLike, seed: int = 0, steps: int | None = None) -> HeteroData:
    """The model's start state of a scene: a built-in scene's name (``"wedge"``) or a scene
    file's path (``"my_scene.toml"``), episode ``seed`` simulated in pybullet for ``steps``
    model steps (default: the scene's own length), the state at step 2 (two steps of history).

    The graph carries the ground truth of the simulated steps (``pos_seq``, ``force_seq``) and
    the scene's pitch; pass it to :func:`rollout` or :func:`~hrn_pyg.sampling.sample.sample`.
    """
    text = os.fspath(source)
    spec = read_scene_file(text) if text.endswith(".toml") or Path(text).is_file() else text
    if steps is not None and steps < HISTORY + 1:
        raise ValueError(f"steps must be >= {HISTORY + 1} (two of history and one to predict), got {steps}")
    return episode_state(simulate_episode(spec, seed=seed, steps=steps), start=HISTORY)


def rollout(model: HRN, state: HeteroData, steps: int, forces: Tensor | None = None,
            sleep: SleepConfig | None = DEFAULT_SLEEP, effects: SceneEffects | None = None,
            grad: bool = False) -> Tensor:
    """The deterministic future of ``state``: leaf positions ``[steps, L, 3]`` at ``t+1 ..
    t+steps``, the convention of :func:`~hrn_pyg.sampling.sample.sample` (whose ``k=1, rate=0``
    future it equals). ``forces`` ``[steps, N or L, 3]`` (N) or None; ``sleep``: objects at rest
    held (None: every object at every step); ``grad=True`` records gradients through the
    rollout (the graph's device, every step kept for backward)."""
    if not grad:
        return sample(model, state, 1, steps, 0.0, forces=forces, sleep=sleep, effects=effects)[0]
    leaf = state[NODE].is_leaf
    full = copies_forces(forces, state, steps, 1)  # [steps, N, 3] on every node, or None
    with torch.enable_grad():
        return rollout_nodes(model, state, steps, full, sleep=sleep, effects=effects)[:, leaf]
