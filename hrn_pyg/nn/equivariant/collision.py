"""Collision module of the horizontally equivariant HRN: effects of nearby particles of other objects."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.collision import safe_norm
from hrn_pyg.nn.equivariant.features import (check_edge_inputs, dot, horizontal, horizontal_length,
                                             mean_vectors_by_index, squash, weighted_sum)
from hrn_pyg.nn.mlp import MLP, MLPConfig, check_force, check_state, in_degree, sum_by_index

#: invariants of a collision edge: |o_h|, o_z, |o|, v_i . o_h, v_j . o_h, v^_i . v^_j (squashed velocities)
EDGE_INVARIANTS = 6
#: with ``reads_force``: per end |f_h| and f_z, per edge f_i . o_h and f_j . o_h
FORCE_NODE_INVARIANTS, FORCE_EDGE_INVARIANTS = 2, 2


class CollisionModule(nn.Module):
    r"""Sum of pairwise collision effects over the collision edges ``j -> i``, a scalar part and
    ``C`` horizontal vectors.

    .. math::
        h_{ij} &= \phi_C\bigl(\tilde s_i,\ \tilde s_j,\ \lVert o_h \rVert,\ o_z,\ \lVert o \rVert,\
            v_i \cdot o_h,\ v_j \cdot o_h,\ \hat v_i \cdot \hat v_j\bigr), \qquad o = x_i - x_j \\
        e_C(i) &= \sum_j (W h_{ij} + b), \qquad
        E_C(i)_c = \frac{1}{n_i} \sum_j a_c(h_{ij})\, o_h + a'_c(h_{ij})\, (v_j - v_i)

    :math:`\tilde s` is the invariant state, :math:`v` the normalised horizontal velocity,
    :math:`\hat v = v / (1 + \lVert v \rVert)`, :math:`x` the scaled position; vectors are averaged
    over the :math:`n_i` edges into :math:`i`, scalars summed; an edge of weight 0 adds an exact
    zero. With ``reads_force`` the messages also read :math:`\lVert f_{i,h} \rVert,\ f_{i,z},\
    \lVert f_{j,h} \rVert,\ f_{j,z},\ f_i \cdot o_h,\ f_j \cdot o_h` and the vectors are also
    weighted sums of :math:`f_{i,h}, f_{j,h}`.

    Args:
        state_dim: size :math:`S'` of an invariant state vector.
        effect_dim: size :math:`D` of the scalar effect.
        channels: number :math:`C` of vector channels.
        mlp: shape of :math:`\phi_C`.
        reads_force: the messages read the force on both ends (``force`` is then required).

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S')`, velocity :math:`(|\mathcal{V}|, 2)`,
          pos :math:`(|\mathcal{V}|, 3)`, edge_index :math:`(2, |\mathcal{E}_C|)`, mask
          :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)`, edge_weight
          :math:`(|\mathcal{E}_C|,)` or None, force :math:`(|\mathcal{V}|, 3)` (with ``reads_force``)
        - **output:** effect :math:`(|\mathcal{V}|, D)`, vectors :math:`(|\mathcal{V}|, C, 2)`
    """

    def __init__(self, state_dim: int, effect_dim: int, channels: int, mlp: MLPConfig = MLPConfig(),
                 reads_force: bool = False) -> None:
        super().__init__()
        self.state_dim, self.effect_dim, self.channels = state_dim, effect_dim, channels
        self.reads_force = bool(reads_force)
        self.node_dim = state_dim + (FORCE_NODE_INVARIANTS if self.reads_force else 0)
        self.edge_dim = EDGE_INVARIANTS + (FORCE_EDGE_INVARIANTS if self.reads_force else 0)
        self.basis = 4 if self.reads_force else 2  # o_h, v_j - v_i (, f_i, f_j)
        self.phi = MLP(2 * self.node_dim + self.edge_dim, effect_dim, mlp)
        self.vector = nn.Linear(mlp.hidden, self.basis * channels)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()
        self.vector.reset_parameters()

    def forward(self, state: Tensor, velocity: Tensor, pos: Tensor, edge_index: Tensor,
                mask: Tensor | None = None, batch: Tensor | None = None,
                edge_weight: Tensor | None = None, force: Tensor | None = None) -> tuple[Tensor, Tensor]:
        n = check_state("equivariant CollisionModule", state, self.state_dim)
        check_edge_inputs("equivariant CollisionModule", n, pos, velocity, edge_index, mask, batch, edge_weight)
        if self.reads_force:
            check_force("equivariant CollisionModule: reads_force", force, n)
        src, dst = edge_index
        edge_batch = batch.index_select(0, dst) if mask is not None else None
        offset = pos.index_select(0, dst) - pos.index_select(0, src)  # x_i - x_j
        o_h = horizontal(offset)
        v_i, v_j = velocity.index_select(0, dst), velocity.index_select(0, src)
        unit = squash(velocity)  # once per node, then gathered: the same rows as squashing per edge
        parts = [horizontal_length(o_h), offset[:, 2:], safe_norm(offset),
                 dot(v_i, o_h), dot(v_j, o_h), dot(unit.index_select(0, dst), unit.index_select(0, src))]
        basis = [o_h, v_j - v_i]
        node = state
        if self.reads_force:
            f_h = horizontal(force)
            f_i, f_j = f_h.index_select(0, dst), f_h.index_select(0, src)
            node = torch.cat([state, horizontal_length(f_h), force[:, 2:]], dim=-1)
            parts += [dot(f_i, o_h), dot(f_j, o_h)]
            basis += [f_i, f_j]
        w_dst, w_src, w_edge = self.phi.split_first_weight((self.node_dim, self.node_dim, self.edge_dim))
        from_dst = torch.addmm(self.phi.first_bias, node, w_dst.T)
        pre = from_dst.index_select(0, dst) + (node @ w_src.T).index_select(0, src)
        pre = pre.addmm_(torch.cat(parts, dim=-1), w_edge.T)
        hidden = self.phi.last_hidden_from_first(pre, mask, edge_batch, pre_is_scratch=True)
        weights = self.vector(hidden).view(-1, self.basis, self.channels)
        vectors = weighted_sum(weights, torch.stack(basis, dim=1))
        if edge_weight is not None:
            weight = edge_weight.to(hidden.dtype)
            hidden = hidden * weight.unsqueeze(-1)
            vectors = vectors * weight.view(-1, 1, 1)
        degree = in_degree(edge_index, n, edge_weight)
        effect = self.phi.output_of_sum(sum_by_index(hidden, dst, n), degree)
        return effect, mean_vectors_by_index(vectors, dst, degree)

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"channels={self.channels}, {'reads_force=True, ' if self.reads_force else ''}phi={self.phi})")
