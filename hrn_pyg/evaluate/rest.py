r"""Ground and rest metrics of a long rollout: does a predicted object sink, float or creep?

On leaf positions ``pred`` and ``truth`` ``[S, L, 3]`` (``z`` up, the ground at ``z = 0``):

* **ground depth** of a trajectory :math:`g` over its movable leaves :math:`\mathcal{M}_g`:

  .. math:: d_g = \max_s \max_{l \in \mathcal{M}_g} \max(0, -z_{s,l})

* **objects at rest** in the truth: every leaf moved less than :data:`REST_SPEED` per step over
  the last :math:`K` = :data:`REST_STEPS` steps:

  .. math:: \mathrm{rest}_o = \Big[\max_{S-K < s \le S} \max_{l \in \mathcal{L}_o}
            \lVert x_{s,l} - x_{s-1,l} \rVert < v_{rest}\Big]

* for objects at rest, with the mass-weighted centroid :math:`c_{s,o}`, the **rest height
  error** :math:`|\hat c^z_{S,o} - c^z_{S,o}|` and the **rest drift**
  :math:`\lVert \hat c^{xy}_{S,o} - \hat c^{xy}_{S-K,o} \rVert`.

One scatter over leaves each; no Python loop.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hrn_pyg.data.graph import object_centres

__all__ = [
    "REST_SPEED",
    "REST_STEPS",
    "RestMetrics",
    "ground_depth",
    "object_centroids",
    "objects_at_rest",
    "rest_height_error",
    "rest_drift",
    "rest_metrics",
]

#: An object is at rest when each of its leaves moves less than this many metres per model step
#: (1 mm per step, 3 cm/s at 30 steps per second) ...
REST_SPEED: float = 1e-3
#: ... over each of the last this many steps of the ground-truth episode.
REST_STEPS: int = 5


def _check_positions(name: str, pos: Tensor, n_leaves: int | None = None) -> None:
    if pos.dim() != 3 or pos.shape[-1] != 3:
        raise ValueError(f"{name} must have shape [S, L, 3], got {list(pos.shape)}")
    if n_leaves is not None and pos.shape[1] != n_leaves:
        raise ValueError(f"{name} has {pos.shape[1]} leaves, expected {n_leaves}")


def ground_depth(pos: Tensor, movable: Tensor, group: Tensor, num_groups: int) -> Tensor:
    r"""How far the lowest movable leaf of each group gets below the ground, in metres.

    :math:`d_g = \max_s \max_{l \in g,\ \mathrm{movable}} \max(0, -z_{s,l})`; a group with no
    movable leaf, or none below ground, gets 0.

    **Shapes:** ``pos`` ``[S, L, 3]``, ``movable`` ``[L]`` bool, ``group`` ``[L]`` long in
    ``0..num_groups-1``; returns ``[num_groups]``.
    """
    _check_positions("pos", pos)
    depth = (-pos[..., 2]).clamp(min=0).amax(0)  # [L] deepest point of each leaf over time
    depth = torch.where(movable, depth, torch.zeros_like(depth))
    return depth.new_zeros(num_groups).scatter_reduce(0, group, depth, reduce="amax", include_self=True)


def object_centroids(pos: Tensor, obj: Tensor, num_objects: int, mass: Tensor | None = None) -> Tensor:
    r"""Mass-weighted centroid of each object at each state, :math:`c_{s,o}` (zeros if empty).

    **Shapes:** ``pos`` ``[S, L, 3]``, ``obj`` ``[L]`` long, ``mass`` ``[L]`` (None: equal
    masses); returns ``[S, num_objects, 3]``.
    """
    _check_positions("pos", pos)
    return object_centres(pos, obj, num_objects, mass)


def objects_at_rest(truth: Tensor, obj: Tensor, movable: Tensor, num_objects: int,
                    steps: int = REST_STEPS, speed: float = REST_SPEED) -> Tensor:
    """Which objects are at rest at the end of the ground truth (module docstring); an object with a
    static leaf, or none, never is.

    **Shapes:** ``truth`` ``[S, L, 3]`` (``S >= 2``), ``obj`` ``[L]``, ``movable`` ``[L]``
    bool; returns ``[num_objects]`` bool.
    """
    _check_positions("truth", truth)
    if truth.shape[0] < 2:
        raise ValueError(f"at least 2 states are needed to tell rest from motion, got {truth.shape[0]}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    k = min(int(steps), truth.shape[0] - 1)
    fastest = (truth[-k:] - truth[-k - 1:-1]).norm(dim=-1).amax(0)  # [L] largest step of each leaf
    fastest = torch.where(movable, fastest, torch.full_like(fastest, float("inf")))
    per_object = torch.full((num_objects,), float("inf"), dtype=fastest.dtype, device=fastest.device)
    per_object = per_object.scatter_reduce(0, obj, fastest, reduce="amax", include_self=False)
    return per_object < speed


def rest_height_error(pred: Tensor, truth: Tensor, obj: Tensor, num_objects: int,
                      mass: Tensor | None = None) -> Tensor:
    r""":math:`|\hat c^z_{S,o} - c^z_{S,o}|`: predicted vs true centroid height at the last state.

    **Shapes:** ``pred``, ``truth`` ``[S, L, 3]`` (only the last state is used), ``obj``
    ``[L]``, ``mass`` ``[L]`` or None; returns ``[num_objects]`` (metres; mask it with
    :func:`objects_at_rest`).
    """
    _check_positions("truth", truth)
    _check_positions("pred", pred, truth.shape[1])
    last_pred = object_centroids(pred[-1:], obj, num_objects, mass)[0, :, 2]
    last_true = object_centroids(truth[-1:], obj, num_objects, mass)[0, :, 2]
    return (last_pred - last_true).abs()


def rest_drift(pred: Tensor, obj: Tensor, num_objects: int, steps: int = REST_STEPS,
               mass: Tensor | None = None) -> Tensor:
    r""":math:`\lVert \hat c^{xy}_{S,o} - \hat c^{xy}_{S-K,o} \rVert`, ``K = min(steps, S - 1)``: the
    predicted centroid's net horizontal travel.

    **Shapes:** ``pred`` ``[S, L, 3]`` (``S >= 2``), ``obj`` ``[L]``, ``mass`` ``[L]`` or None;
    returns ``[num_objects]`` (metres).
    """
    _check_positions("pred", pred)
    if pred.shape[0] < 2:
        raise ValueError(f"at least 2 states are needed for a drift, got {pred.shape[0]}")
    k = min(int(steps), pred.shape[0] - 1)
    ends = object_centroids(pred[[-k - 1, -1]], obj, num_objects, mass)  # [2, O, 3]
    return (ends[1, :, :2] - ends[0, :, :2]).norm(dim=-1)


class RestMetrics(NamedTuple):
    """The rest metrics of a batch of rollouts (:func:`rest_metrics`).

    Attributes:
        depth: ``[G]`` predicted ground depth per trajectory (metres).
        truth_depth: ``[G]`` the same for the ground truth (pybullet's own contact slack).
        at_rest: ``[O]`` bool, objects at rest at the end of the ground truth.
        height_error: ``[O]`` rest height error (meaningful where ``at_rest``).
        drift: ``[O]`` rest drift (meaningful where ``at_rest``).
    """

    depth: Tensor
    truth_depth: Tensor
    at_rest: Tensor
    height_error: Tensor
    drift: Tensor


def rest_metrics(pred: Tensor, truth: Tensor, obj: Tensor, movable: Tensor, group: Tensor,
                 num_objects: int, num_groups: int, mass: Tensor | None = None,
                 steps: int = REST_STEPS, speed: float = REST_SPEED) -> RestMetrics:
    """All rest metrics of rollouts ``pred`` against ``truth`` (:class:`RestMetrics`); ``obj`` numbers
    objects uniquely across trajectories, ``group`` gives each leaf's trajectory.

    **Shapes:** ``pred``, ``truth`` ``[S, L, 3]``; ``obj``, ``group``, ``movable``, ``mass`` ``[L]``.
    """
    _check_positions("truth", truth)
    _check_positions("pred", pred, truth.shape[1])
    if pred.shape[0] != truth.shape[0]:
        raise ValueError(f"pred has {pred.shape[0]} states, truth {truth.shape[0]}")
    return RestMetrics(
        depth=ground_depth(pred, movable, group, num_groups),
        truth_depth=ground_depth(truth, movable, group, num_groups),
        at_rest=objects_at_rest(truth, obj, movable, num_objects, steps, speed),
        height_error=rest_height_error(pred, truth, obj, num_objects, mass),
        drift=rest_drift(pred, obj, num_objects, steps, mass),
    )
