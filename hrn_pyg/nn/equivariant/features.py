"""What the horizontally equivariant HRN reads of a scene, and how it writes a horizontal answer.

The group is O(2) acting on :math:`(x, y)` (gravity singles out z). The network of
:mod:`hrn_pyg.nn.equivariant` commutes with it by construction (as E(n)-equivariant graph
networks do, Satorras et al. 2021): its MLPs read only invariants (heights, vertical
components, horizontal lengths and dot products), and its horizontal outputs are weighted sums
of the scene's horizontal vectors with MLP weights. So it has no horizontal direction of its own.

A horizontal vector is ``[..., 2]``; ``C`` vector channels of a node are ``[N, C, 2]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hrn_pyg.nn.collision import NORM_EPSILON
from hrn_pyg.nn.mlp import check_edges, sum_by_index


def horizontal(v: Tensor) -> Tensor:
    """The horizontal part :math:`(v_x, v_y)` of 3-vectors. **Shapes:** ``[..., 3]`` -> ``[..., 2]``."""
    return v[..., :2]


def horizontal_length(v: Tensor) -> Tensor:
    r""":math:`\lVert (v_x, v_y) \rVert`, with a finite gradient at 0. **Shapes:** ``[..., 3]``
    or ``[..., 2]`` -> ``[..., 1]``."""
    x, y = v[..., 0:1], v[..., 1:2]
    return torch.sqrt(torch.addcmul(x * x, y, y) + NORM_EPSILON)


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise dot product of two horizontal vectors. **Shapes:** ``[M, 2]`` twice -> ``[M, 1]``.

    Written out, :math:`a_x b_x + a_y b_y`: on the CPU a reduction over a dimension of two
    costs several times the two products (so do the channel functions below)."""
    return torch.addcmul(a[:, 0:1] * b[:, 0:1], a[:, 1:2], b[:, 1:2])


def channel_dot(channels: Tensor, direction: Tensor) -> Tensor:
    r""":math:`E_c \cdot d` for every channel :math:`c` of a row. **Shapes:** channels
    ``[M, C, 2]``, direction ``[M, 2]`` -> ``[M, C]``."""
    return torch.addcmul(channels[..., 0] * direction[:, 0:1], channels[..., 1], direction[:, 1:2])


def channel_length(channels: Tensor) -> Tensor:
    r""":math:`\lVert E_c \rVert` for every channel of a row, finite gradient at 0.
    **Shapes:** ``[M, C, 2]`` -> ``[M, C]``."""
    x, y = channels[..., 0], channels[..., 1]
    return torch.sqrt(torch.addcmul(x * x, y, y) + NORM_EPSILON)


def squash(channels: Tensor) -> Tensor:
    r"""Each vector channel shrunk to a length under 1, its direction kept:
    :math:`E_c / (1 + \lVert E_c \rVert)`, so vector effects stay bounded through the phases.

    **Shapes:** ``[M, C, 2]`` -> ``[M, C, 2]``.
    """
    return channels / (1.0 + channel_length(channels)).unsqueeze(-1)


def invariant_state(state: Tensor) -> Tensor:
    r"""A state vector (:data:`hrn_pyg.nn.hrn.STATE_LAYOUT`) with its horizontal velocity replaced by
    its length, :math:`[\lVert v_h \rVert, v_z, \dots]` (invariant when the normaliser is,
    :func:`hrn_pyg.nn.normalizer.isotropic_horizontal`).

    **Shapes:** ``[N, S]`` -> ``[N, S - 1]``.
    """
    return torch.cat([horizontal_length(state[:, :2]), state[:, 2:]], dim=-1)


def weighted_sum(weights: Tensor, basis: Tensor) -> Tensor:
    r"""Channel :math:`c` of a row: :math:`\sum_k w_{k c}\, b_k` over its ``K`` horizontal basis vectors
    (a batched matrix product; written out under ``torch.compile``, :func:`weighted_sum_elementwise`).

    **Shapes:** weights ``[M, K, C]``, basis ``[M, K, 2]`` -> ``[M, C, 2]``.
    """
    if torch.compiler.is_compiling():
        return weighted_sum_elementwise(weights, basis)
    return torch.einsum("mkc,mkd->mcd", weights, basis)


def weighted_sum_elementwise(weights: Tensor, basis: Tensor) -> Tensor:
    """:func:`weighted_sum` as broadcast products summed over ``k`` (the same numbers up to
    rounding). **Shapes:** as :func:`weighted_sum`."""
    return (weights.unsqueeze(-1) * basis.unsqueeze(2)).sum(1)


def mean_vectors_by_index(vectors: Tensor, index: Tensor, count: Tensor) -> Tensor:
    r"""Vector channels of edges averaged over their destinations, :math:`\sum_{e \to i} E_e /
    \max(n_i, 1)` with :math:`n_i` = ``count`` (a mean keeps the scale however many edges).

    **Shapes:** vectors ``[E, C, 2]``, index ``[E]``, count ``[num_rows]`` -> ``[num_rows, C, 2]``.
    """
    e, c, _ = vectors.shape
    n = count.size(0)
    total = sum_by_index(vectors.reshape(e, 2 * c), index, n).view(n, c, 2)
    return total / count.to(total.dtype).clamp_min(1.0).view(n, 1, 1)


def check_edge_inputs(who: str, num_nodes: int, pos: Tensor, velocity: Tensor, edge_index: Tensor,
                      mask: Tensor | None, batch: Tensor | None, edge_weight: Tensor | None = None) -> None:
    """:func:`~hrn_pyg.nn.mlp.check_edges`, and ``velocity`` must be ``[N, 2]``."""
    check_edges(who, num_nodes, pos, edge_index, mask, batch, edge_weight)
    if velocity.shape != (num_nodes, 2):
        raise ValueError(f"{who}: velocity must be [N, 2], got {tuple(velocity.shape)}")
