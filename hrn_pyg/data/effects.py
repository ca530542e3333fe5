"""What a scene needs simulated: :class:`SceneEffects`, and the per-rollout plan built from it.

A step sums history, force :math:`e_F` and collision :math:`e_C` effects; many scenes need
fewer (a lone soft cube has nothing to collide with). A scene declares it once
(:class:`SceneEffects`, a scene file's ``effects``) and :func:`plan_effects` turns that, the
graph and the forces into an :class:`EffectPlan` before the first step: ``force_active[t]`` (one
host transfer for the whole rollout) and ``collisions`` (False when declared or when no copy
holds two objects that can touch). Skipping a module gives the same result as running it on
empty input; a declaration the data contradict is an error.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import NODE, copy_object_ids, object_span
from hrn_pyg.data.kinds import SceneEffects

__all__ = ["EffectPlan", "SceneEffects", "can_collide", "plan_effects"]


class EffectPlan(NamedTuple):
    """What each step of one rollout runs (:func:`plan_effects`).

    Attributes:
        force_active: one flag per step: run the force module.
        collisions: search collision edges and run the collision module.
    """

    force_active: tuple[bool, ...]
    collisions: bool


def can_collide(graph: HeteroData) -> bool:
    """Whether any batch copy of ``graph`` holds leaves of two different objects, at least one of
    them movable (two static bodies never need a collision: neither moves)."""
    store = graph[NODE]
    leaf = store.is_leaf
    if "batch" in store:
        copy_id = store.batch[leaf]
    else:
        copy_id = torch.zeros_like(store.object[leaf])
    obj, static = store.object[leaf], store.is_static[leaf]
    if obj.numel() == 0:
        return False
    span = object_span(obj)
    key = copy_object_ids(copy_id, obj, span)
    pairs, first = torch.unique(key, return_inverse=True)
    movable = torch.zeros(pairs.numel(), dtype=torch.bool, device=key.device).index_fill(0, first[~static], True)
    copies = torch.div(pairs, span, rounding_mode="floor")
    counts = torch.zeros(int(copies.max()) + 1, dtype=torch.long, device=key.device).index_add(
        0, copies, torch.ones_like(copies))
    has_movable = torch.zeros_like(counts).index_add(0, copies, movable.long())
    return bool(((counts >= 2) & (has_movable >= 1)).any())


def plan_effects(graph: HeteroData, steps: int, forces: Tensor | None,
                 declared: SceneEffects | None = None) -> EffectPlan:
    """The :class:`EffectPlan` of ``steps`` steps under ``forces`` ``[S, N, 3]`` (None: none), as
    ``declared``; ValueError when the declaration and the data disagree."""
    declared = declared or SceneEffects()
    if forces is None:
        active = [False] * steps
    else:
        active = forces[:steps].ne(0).flatten(1).any(dim=1).tolist()  # one host read per rollout
    if declared.forces is False and any(active):
        first = active.index(True)
        raise ValueError(f"the scene declares no external forces (SceneEffects.forces=False), but step {first} "
                         "has a nonzero force")
    collisions = declared.collisions if declared.collisions is not None else can_collide(graph)
    return EffectPlan(force_active=tuple(bool(a) for a in active), collisions=bool(collisions))
