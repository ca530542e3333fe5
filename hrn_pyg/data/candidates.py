r"""Collision candidates with a skin: a pair set that stays valid while nothing moves far.

A *Verlet list* holds every pair closer than :math:`r + s` (the skin :math:`s`) at the search.
While no leaf has moved more than :math:`s / 2` since, no pair outside it can be closer than
:math:`r`:

.. math::
    \lVert x_i - x_j \rVert \ \ge\ \lVert x^0_i - x^0_j \rVert - \lVert x_i - x^0_i \rVert
        - \lVert x_j - x^0_j \rVert \ \ge\ (r + s) - 2 \cdot \tfrac{s}{2} = r,

so a step's collision edges are exactly the candidates with :math:`\lVert x_i - x_j \rVert^2 <
r^2` (the search's float expression and order), used as a fixed set with 0 / 1 weights
(:func:`active_collisions`); :func:`largest_move` measures staleness on the device.
``capacity`` pads the list to a rarely changing size with inactive pairs, for CUDA graphs.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import leaf_collision_edges

#: a list is stale once a leaf has moved this fraction of the skin: a little under the half the
#: bound allows, so that the rounding of the float comparisons cannot lose a pair
STALE_FRACTION = 0.49


class CollisionCandidates(NamedTuple):
    """A Verlet list of collision pairs (module docstring).

    Attributes:
        edge_index: ``[2, C]`` long, the pairs closer than ``radius + skin`` at ``reference``
            (source, destination; sorted by destination, then source), then padding ``0 -> 0``.
        valid: ``[C]`` bool, False on the padding.
        reference: ``[N, 3]`` positions at the search.
        radius: the collision radius ``r`` (metres).
        skin: the skin ``s`` (metres).
        pairs: how many pairs the search found.
    """

    edge_index: Tensor
    valid: Tensor
    reference: Tensor
    radius: float
    skin: float
    pairs: int


def padded_size(pairs: int, minimum: int = 64) -> int:
    """The next power of two ``>= pairs`` (at least ``minimum``): list sizes change rarely."""
    size = max(int(minimum), 1)
    while size < pairs:
        size *= 2
    return size


def build_candidates(graph: HeteroData, pos: Tensor, radius: float, skin: float,
                     capacity: int | None = None) -> CollisionCandidates:
    """Search the leaves of ``graph`` at ``pos`` ``[N, 3]`` at ``radius + skin``; ``capacity`` pads the
    list (:func:`pad_candidates`)."""
    if not radius > 0 or not skin > 0:
        raise ValueError(f"radius and skin must be > 0, got radius={radius}, skin={skin}")
    edges = leaf_collision_edges(graph, pos.detach(), radius + skin)
    valid = torch.ones(edges.size(1), dtype=torch.bool, device=edges.device)
    candidates = CollisionCandidates(edges, valid, pos.detach().clone(), float(radius), float(skin), edges.size(1))
    return candidates if capacity is None else pad_candidates(candidates, capacity)


def pad_candidates(candidates: CollisionCandidates, capacity: int) -> CollisionCandidates:
    """The list padded to ``capacity`` pairs (it must hold them all) with pairs ``0 -> 0`` that
    are never active."""
    pad = capacity - candidates.edge_index.size(1)
    if pad < 0:
        raise ValueError(f"capacity {capacity} is smaller than the {candidates.edge_index.size(1)} pairs found")
    edges = torch.cat([candidates.edge_index, candidates.edge_index.new_zeros(2, pad)], dim=1)
    valid = torch.cat([candidates.valid, candidates.valid.new_zeros(pad)])
    return candidates._replace(edge_index=edges, valid=valid)


def active_collisions(candidates: CollisionCandidates, pos: Tensor) -> Tensor:
    """``[C]`` float, 1 for the candidates closer than the radius at ``pos`` ``[N, 3]`` (the
    collision edges of ``pos``, when the list is not :func:`stale`), 0 for the others."""
    src, dst = candidates.edge_index
    x = pos.detach()
    diff = x[dst] - x[src]
    near = (diff * diff).sum(dim=-1) < candidates.radius * candidates.radius
    return (near & candidates.valid).to(pos.dtype)


def largest_move(candidates: CollisionCandidates, pos: Tensor) -> Tensor:
    """0-d tensor, on the device: the farthest any node of ``pos`` ``[N, 3]`` has moved since the
    search (metres; inf when a position is not finite). The list holds every collision pair
    while this is at most :func:`move_limit`."""
    moved = pos.detach() - candidates.reference
    largest = (moved * moved).sum(dim=-1).amax().sqrt()
    return torch.nan_to_num(largest, nan=float("inf"))


def move_limit(skin: float) -> float:
    """How far a node may move before a list with this skin is stale (:data:`STALE_FRACTION`)."""
    return STALE_FRACTION * skin


def collisions_of(candidates: CollisionCandidates, pos: Tensor) -> Tensor:
    """``[2, E_C]``: the candidates closer than the radius at ``pos`` ``[N, 3]``, in their order:
    the collision edges of ``pos``, as a search gives them, while the list is not stale
    (:func:`largest_move` at most :func:`move_limit`)."""
    near = active_collisions(candidates, pos).bool()
    return candidates.edge_index[:, near]


class VerletSearch:
    """A rollout's collision edges from a Verlet list, searched again only when stale.

    Each call gives :func:`~hrn_pyg.data.graph.leaf_collision_edges` at ``pos`` (the same edges in
    the same order) from the list while no node moved past :func:`move_limit` (one host read),
    else from a new search. The graphs must share the start graph's leaves, objects and batch;
    ``radius`` and ``skin`` are metres > 0.
    """

    def __init__(self, radius: float, skin: float) -> None:
        if not radius > 0 or not skin > 0:
            raise ValueError(f"radius and skin must be > 0, got radius={radius}, skin={skin}")
        self.radius, self.skin = float(radius), float(skin)
        self.candidates: CollisionCandidates | None = None
        self.searches = 0

    def __call__(self, graph: HeteroData, pos: Tensor) -> Tensor:
        """``[2, E_C]`` collision edges (node indices) of ``graph``'s leaves at ``pos`` ``[N, 3]``."""
        if self.candidates is None or float(largest_move(self.candidates, pos)) > move_limit(self.skin):
            self.candidates = build_candidates(graph, pos, self.radius, self.skin)
            self.searches += 1
        return collisions_of(self.candidates, pos)
