r"""What the horizontally equivariant HRN reads of a scene, and how it writes a horizontal answer.

Gravity singles out the vertical axis; every horizontal direction is alike, and so is every
mirror image in a vertical plane. The group of those maps is O(2) acting on :math:`(x, y)`. The
network of :mod:`hrn_pyg.nn.equivariant` commutes with all of it by construction:

- its MLPs read only *invariants*: heights and vertical components, lengths of horizontal
  vectors and dot products of two of them (no turn or mirror changes these);
- its horizontal outputs are *weighted sums of horizontal vectors* of the scene (edge offsets,
  velocities, forces, and vector effects made so themselves), the weights being MLP outputs.

A map :math:`g` of the scene then maps every horizontal output by the same :math:`g`, exactly (up
to rounding): the network has no horizontal direction of its own, so no bias of its weights can
push a resting body sideways (E(n)-equivariant graph networks, Satorras et al. 2021, build
messages the same way for every rotation of space).

A horizontal vector is the pair :math:`(x, y)` of a 3-vector, ``[..., 2]``; a set of ``C``
vector channels of a node is ``[N, C, 2]``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hrn_pyg.nn.collision import NORM_EPSILON
from hrn_pyg.nn.mlp import sum_by_index


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
    :math:`E_c / (1 + \lVert E_c \rVert)`.

    Commutes with every turn and mirror, and keeps the vector effects bounded: a vector effect is
    copied through the phases with a weight, and its dot products with edge offsets are read by
    the next phase's MLP, so unbounded channels can feed on themselves (in a fresh network they
    grew by about seven times a phase, and a rollout flew apart within a few steps).

    **Shapes:** ``[M, C, 2]`` -> ``[M, C, 2]``.
    """
    return channels / (1.0 + channel_length(channels)).unsqueeze(-1)


def invariant_state(state: Tensor) -> Tensor:
    r"""A state vector (:data:`hrn_pyg.nn.hrn.STATE_LAYOUT`, velocity first) with its horizontal
    velocity replaced by that velocity's length: :math:`[\lVert v_h \rVert, v_z, \dots]`.

    Invariant only when the velocity's horizontal normalisation is (zero mean, one scale for x
    and y: :func:`hrn_pyg.nn.normalizer.isotropic_horizontal`).

    **Shapes:** ``[N, S]`` -> ``[N, S - 1]``.
    """
    return torch.cat([horizontal_length(state[:, :2]), state[:, 2:]], dim=-1)


def weighted_sum(weights: Tensor, basis: Tensor) -> Tensor:
    r"""Channel :math:`c` of a row: :math:`\sum_k w_{k c}\, b_k` over the row's ``K`` horizontal
    basis vectors. **Shapes:** weights ``[M, K, C]``, basis ``[M, K, 2]`` -> ``[M, C, 2]``.

    Eagerly one batched matrix product; under ``torch.compile`` the products and the sum over
    ``k`` written out (:func:`weighted_sum_elementwise`), which the compiler fuses with the
    operations around them (a batched product of ``M`` tiny matrices stays a call of its own)."""
    if torch.compiler.is_compiling():
        return weighted_sum_elementwise(weights, basis)
    return torch.einsum("mkc,mkd->mcd", weights, basis)


def weighted_sum_elementwise(weights: Tensor, basis: Tensor) -> Tensor:
    """:func:`weighted_sum` as broadcast products summed over ``k`` (the same numbers up to
    rounding). **Shapes:** as :func:`weighted_sum`."""
    return (weights.unsqueeze(-1) * basis.unsqueeze(2)).sum(1)


def mean_vectors_by_index(vectors: Tensor, index: Tensor, count: Tensor) -> Tensor:
    r"""Vector channels of edges averaged over their destinations: :math:`\sum_{e \to i} E_e /
    \max(n_i, 1)` with :math:`n_i` the node's in-degree ``count`` (a row no edge reaches is an
    exact zero). A mean, not a sum: a vector effect keeps the scale of the vectors it is made of
    however many edges a node has (a root hears every leaf of its object), and it is copied on
    through the next phases, where sums would compound.

    **Shapes:** vectors ``[E, C, 2]``, index ``[E]``, count ``[num_rows]`` -> ``[num_rows, C, 2]``.
    """
    e, c, _ = vectors.shape
    n = count.size(0)
    total = sum_by_index(vectors.reshape(e, 2 * c), index, n).view(n, c, 2)
    return total / count.to(total.dtype).clamp_min(1.0).view(n, 1, 1)


def check_edge_inputs(who: str, num_nodes: int, pos: Tensor, velocity: Tensor, edge_index: Tensor,
                      mask: Tensor | None, batch: Tensor | None) -> None:
    """Raise a one-line ValueError naming ``who`` unless ``pos`` is ``[N, 3]``, ``velocity``
    ``[N, 2]`` and ``edge_index`` ``[2, E]``, and a dropout mask comes with the batch vector
    (the checks an edge module of this package makes before it reads its inputs)."""
    if pos.shape != (num_nodes, 3) or velocity.shape != (num_nodes, 2):
        raise ValueError(f"{who}: pos must be [N, 3] and velocity [N, 2], got {tuple(pos.shape)} and "
                         f"{tuple(velocity.shape)}")
    if edge_index.dim() != 2 or edge_index.size(0) != 2:
        raise ValueError(f"{who}: edge_index must be [2, E], got {tuple(edge_index.shape)}")
    if mask is not None and batch is None:
        raise ValueError(f"{who}: a dropout mask needs the node batch vector")
