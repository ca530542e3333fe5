"""Ground-truth ensembles: M pybullet rollouts of one episode from slightly perturbed starts.

Member ``m`` replays the episode (same seed, parameters and actions) after a
:meth:`hrn_pyg.data.scenes.Scene.nudge` at ``reset``: every movable object shifted by a Gaussian
of ``position_std`` in x and y (not z) and optionally given a Gaussian velocity. The default,
2 mm, is far below the pitch yet sends a wedge ball to either side. :func:`episode_state` turns
an episode into a model's start state with its ground truth attached.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from torch_geometric.data import HeteroData

from hrn_pyg.data.episodes import simulate_episode_alone
from hrn_pyg.data.graph import (
    HISTORY,
    NODE,
    STATIC,
    episode_structure,
    leaf_to_ancestor_mean,
    set_state,
)
from hrn_pyg.data.scene_file import SceneSpec
from hrn_pyg.data.scenes import Scene


@dataclass(frozen=True)
class PerturbationConfig:
    """How the initial state of each ensemble member is perturbed.

    Attributes:
        position_std: standard deviation (m) of each movable object's x and y offset.
        velocity_std: standard deviation (m/s) of each movable object's added velocity, per axis.
        seed: seeds the offsets (member ``m`` of an ensemble uses draw ``m`` of this stream).
    """

    position_std: float = 0.002
    velocity_std: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("position_std", "velocity_std"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"PerturbationConfig.{name} must be finite and >= 0, got {value}")
        if int(self.seed) < 0:
            raise ValueError(f"PerturbationConfig.seed must be >= 0, got {self.seed}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def draw_offsets(
    rng: np.random.Generator, object_material: np.ndarray, perturbation: PerturbationConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Position ``[O, 3]`` (z zero) and velocity ``[O, 3]`` offsets; zero rows for static objects."""
    n_obj = len(object_material)
    offsets = rng.normal(0.0, 1.0, size=(n_obj, 3)) * perturbation.position_std
    offsets[:, 2] = 0.0
    velocities = rng.normal(0.0, 1.0, size=(n_obj, 3)) * perturbation.velocity_std
    static = np.asarray(object_material) == STATIC
    offsets[static] = 0.0
    velocities[static] = 0.0
    return offsets, velocities


@dataclass(frozen=True)
class MemberNudge:
    """The ``after_reset`` of ensemble member ``member``: its draw of the offset stream
    (:func:`draw_offsets` from one generator seeded ``perturbation.seed``, draw ``member``) applied
    by :meth:`Scene.nudge`. A value rather than a closure, so a member can be simulated in a process
    of its own (:func:`~hrn_pyg.data.episodes.simulate_episode_alone`) and still get its own draw."""

    perturbation: PerturbationConfig
    member: int

    def __call__(self, sim: Scene) -> None:
        rng = np.random.default_rng(int(self.perturbation.seed))
        for _ in range(self.member + 1):
            offsets, velocities = draw_offsets(rng, sim.object_material, self.perturbation)
        sim.nudge(offsets, velocities)


def ground_truth_ensemble(
    scene: str,
    seed: int,
    members: int,
    steps: int | None = None,
    perturbation: PerturbationConfig = PerturbationConfig(),
    config: SceneSpec | None = None,
) -> np.ndarray:
    """Leaf positions of ``members`` perturbed replays of episode ``(scene, seed)``
    (:func:`hrn_pyg.data.episodes.simulate_episode` nudged by :class:`MemberNudge`: member ``m``
    takes draw ``m`` of one stream seeded ``perturbation.seed``). ``config``: the scene with changed
    settings; None: ``scene``. A scene with soft bodies or cloth runs each member in a fresh
    process (:func:`~hrn_pyg.data.episodes.simulate_episode_alone`): pybullet's soft-body solver
    keeps state between episodes of one process, which would add a spread of its own.

    **Shapes:** returns ``(members, S + 1, L, 3)`` float32, ``S`` = ``steps`` or the config's.
    """
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ValueError(f"members must be an integer >= 1, got {members!r}")
    source = scene if config is None else config
    runs = [  # one pybullet simulation per member: the simulator is not batched
        simulate_episode_alone(source, seed, steps, after_reset=MemberNudge(perturbation, m))["positions"]
        for m in range(members)
    ]
    return np.stack(runs)


def episode_state(
    episode: dict[str, np.ndarray],
    start: int = HISTORY,
    steps: int | None = None,
    radius: float | None = None,
) -> HeteroData:
    """The model's start state at step ``start`` of an episode, carrying its ground truth as a dataset
    window does: the structure (:func:`~hrn_pyg.data.graph.episode_structure`), the state and force
    at ``start``, ``pos_seq (N, steps+3, 3)``, ``force_seq (N, steps, 3)`` and the ``pitch``.
    ``steps`` defaults to the rest of the episode."""
    positions = torch.from_numpy(np.asarray(episode["positions"], dtype=np.float32))  # [S+1, L, 3]
    forces = torch.from_numpy(np.asarray(episode["forces"], dtype=np.float32))  # [S, L, 3]
    total = positions.shape[0] - 1
    if not HISTORY <= start < total:
        raise ValueError(f"start must be in [{HISTORY}, {total - 1}] for an episode of {total} steps, got {start}")
    steps = total - start if steps is None else steps
    if not 1 <= steps <= total - start:
        raise ValueError(f"steps must be in [1, {total - start}] from start {start}, got {steps}")
    structure = episode_structure(episode)
    n, leaves = structure[NODE].num_nodes, positions.shape[1]
    seq = positions[start - HISTORY : start + steps + 1]  # [steps+3, L, 3]
    pad = seq.new_zeros(seq.shape[0], n - leaves, 3)
    pos_seq = leaf_to_ancestor_mean(torch.cat([seq, pad], dim=1), structure)  # [steps+3, N, 3]
    force_seq = torch.cat([forces[start : start + steps], forces.new_zeros(steps, n - leaves, 3)], dim=1)
    graph = set_state(structure, pos_seq[0], pos_seq[1], pos_seq[2], radius=radius, force=force_seq[0])
    graph[NODE].pos_seq = pos_seq.transpose(0, 1).contiguous()
    graph[NODE].force_seq = force_seq.transpose(0, 1).contiguous()
    return graph
