"""Hierarchical effect propagation of the horizontally equivariant HRN: one pairwise graph convolution."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.equivariant.features import (check_edge_inputs, channel_dot, dot, horizontal, horizontal_length,
                                             mean_vectors_by_index, weighted_sum)
from hrn_pyg.nn.mlp import MLP, MLPConfig, check_state, in_degree, sum_by_index
from hrn_pyg.nn.propagation import edge_offsets, given_rest_offset


def edge_invariant_count(channels: int, rest_offsets: bool) -> int:
    """Invariants of a propagation edge: |o_h|, o_z, (|r_h|, r_z, o_h . r_h), v_i . o_h,
    v_j . o_h, then E_j . o_h per channel."""
    return 4 + (3 if rest_offsets else 0) + channels


class PropagationModule(nn.Module):
    r"""One phase of hierarchical effect propagation (L2A, WS or A2D), scalar and vector effects
    summed into the destination.

    .. math::
        h_{ij} &= \eta\bigl(\tilde s_j,\ \tilde s_i,\ e_j,\ \lVert o_h \rVert,\ o_z\
            [,\ \lVert r_h \rVert,\ r_z,\ o_h \cdot r_h],\ v_i \cdot o_h,\ v_j \cdot o_h,\
            (E_{j,c} \cdot o_h)_c\bigr) \\
        \Delta e(i) &= \sum_j (W h_{ij} + b), \qquad
        \Delta E(i)_c = \frac{1}{n_i} \sum_j a_c\, o_h\ [+\ b_c\, r_h]\ +\ d_c\, v_j\ +\ g_c\, E_{j,c}

    with :math:`o = x_j - x_i`, :math:`r = \bar x_j - \bar x_i` (with ``rest_offsets``), :math:`v`
    the normalised horizontal velocity, :math:`(e, E)` the effect so far, :math:`a, b, d, g` linear
    in :math:`h_{ij}` and :math:`n_i` the in-degree.

    Args:
        state_dim: size :math:`S'` of an invariant state vector.
        effect_dim: size :math:`D` of the scalar effect (input and output).
        channels: number :math:`C` of vector channels (input and output).
        mlp: shape of :math:`\eta`.
        name: the phase, shown in ``repr``.
        rest_offsets: take the rest-shape offset as a further edge input.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S')`, velocity :math:`(|\mathcal{V}|, 2)`,
          effect :math:`(|\mathcal{V}|, D)`, vectors :math:`(|\mathcal{V}|, C, 2)`, pos
          :math:`(|\mathcal{V}|, 3)`, edge_index :math:`(2, |\mathcal{E}|)`, mask, batch,
          rest_pos, degree and rest_offset as in :class:`hrn_pyg.nn.propagation.PropagationModule`
        - **output:** effect increment :math:`(|\mathcal{V}|, D)`, vector increment
          :math:`(|\mathcal{V}|, C, 2)`
    """

    def __init__(self, state_dim: int, effect_dim: int, channels: int, mlp: MLPConfig = MLPConfig(),
                 name: str = "", rest_offsets: bool = False) -> None:
        super().__init__()
        self.state_dim, self.effect_dim, self.channels = state_dim, effect_dim, channels
        self.name = name
        self.rest_offsets = bool(rest_offsets)
        self.edge_dim = edge_invariant_count(channels, self.rest_offsets)
        self.basis = 3 if self.rest_offsets else 2  # o_h, (r_h,) v_j
        self.eta = MLP(2 * state_dim + effect_dim + self.edge_dim, effect_dim, mlp)
        self.vector = nn.Linear(mlp.hidden, (self.basis + 1) * channels)

    def reset_parameters(self) -> None:
        self.eta.reset_parameters()
        self.vector.reset_parameters()

    def forward(self, state: Tensor, velocity: Tensor, effect: Tensor, vectors: Tensor, pos: Tensor,
                edge_index: Tensor, mask: Tensor | None = None, batch: Tensor | None = None,
                rest_pos: Tensor | None = None, degree: Tensor | None = None,
                rest_offset: Tensor | None = None) -> tuple[Tensor, Tensor]:
        n, c = check_state("equivariant PropagationModule", state, self.state_dim), self.channels
        if effect.shape != (n, self.effect_dim) or vectors.shape != (n, c, 2):
            raise ValueError(f"equivariant PropagationModule: effect must be [N, {self.effect_dim}] and "
                             f"vectors [N, {c}, 2], got {tuple(effect.shape)} and {tuple(vectors.shape)}")
        check_edge_inputs("equivariant PropagationModule", n, pos, velocity, edge_index, mask, batch)
        src, dst = edge_index
        offset = edge_offsets(pos, edge_index)  # x_j - x_i
        o_h = horizontal(offset)
        parts = [horizontal_length(o_h), offset[:, 2:]]
        basis = [o_h]
        if self.rest_offsets:
            rest_offset = given_rest_offset("equivariant PropagationModule", rest_offset, rest_pos, edge_index, n)
            r_h = horizontal(rest_offset)
            parts += [horizontal_length(r_h), rest_offset[:, 2:], dot(o_h, r_h)]
            basis.append(r_h)
        v_i, v_j = velocity.index_select(0, dst), velocity.index_select(0, src)
        vectors_j = vectors.index_select(0, src)
        parts += [dot(v_i, o_h), dot(v_j, o_h), channel_dot(vectors_j, o_h)]
        basis.append(v_j)
        edge_batch = batch.index_select(0, dst) if mask is not None else None
        w_src, w_dst, w_effect, w_edge = self.eta.split_first_weight(
            (self.state_dim, self.state_dim, self.effect_dim, self.edge_dim))
        from_src = state @ w_src.T + effect @ w_effect.T
        from_dst = torch.addmm(self.eta.first_bias, state, w_dst.T)
        pre = from_src.index_select(0, src) + from_dst.index_select(0, dst)
        pre = pre.addmm_(torch.cat(parts, dim=-1), w_edge.T)
        hidden = self.eta.last_hidden_from_first(pre, mask, edge_batch, pre_is_scratch=True)
        weights = self.vector(hidden).view(-1, self.basis + 1, c)
        message = weighted_sum(weights[:, :self.basis], torch.stack(basis, dim=1))
        message = message + weights[:, self.basis].unsqueeze(-1) * vectors_j
        degree = in_degree(edge_index, n) if degree is None else degree
        increment = self.eta.output_of_sum(sum_by_index(hidden, dst, n), degree)
        return increment, mean_vectors_by_index(message, dst, degree)

    def __repr__(self) -> str:
        tag = f"{self.name}, " if self.name else ""
        return (f"{self.__class__.__name__}({tag}state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"channels={self.channels}, rest_offsets={self.rest_offsets}, eta={self.eta})")
