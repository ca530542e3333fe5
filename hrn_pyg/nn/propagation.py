"""Hierarchical effect propagation of the HRN (Fig. 2): one pairwise graph convolution."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig, check_edges, check_state, in_degree, sum_by_index


class PropagationModule(nn.Module):
    r"""One phase of hierarchical effect propagation, summed into the destination.

    .. math::
        \Delta e(i) = \sum_{j \in \mathcal{N}(i)}
            \eta\bigl(s_j,\ s_i,\ e_j,\ x_j - x_i\ [,\ \bar x_j - \bar x_i]\bigr)

    The HRN runs three with separate weights, each adding :math:`e \leftarrow e + \Delta e`:
    leaf-to-ancestor (L2A), within-siblings (WS), ancestor-to-descendant (A2D), over the edge sets
    of those names. :math:`s` is the state, :math:`e` the effect so far, :math:`x` the scaled
    position, :math:`\bar x` the rest shape (with ``rest_offsets``, as MeshGraphNets' mesh-space
    coordinates); a node without incoming edges gets an exact zero.

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect (input and output).
        mlp: shape of :math:`\eta`.
        name: the phase, shown in ``repr`` (``"l2a"``, ``"ws"``, ``"a2d"``).
        rest_offsets: take the rest-shape offset as a further edge input.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, effect :math:`(|\mathcal{V}|, D)`,
          pos :math:`(|\mathcal{V}|, 3)`, edge_index :math:`(2, |\mathcal{E}|)`,
          mask :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)` (with a mask),
          rest_pos :math:`(|\mathcal{V}|, 3)` (with ``rest_offsets``), optionally
          degree :math:`(|\mathcal{V}|,)` and rest_offset :math:`(|\mathcal{E}|, 3)`
        - **output:** effect increment :math:`(|\mathcal{V}|, D)`
    """

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig(), name: str = "",
                 rest_offsets: bool = False) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.name = name
        self.rest_offsets = bool(rest_offsets)
        self.offset_dim = 6 if self.rest_offsets else 3
        self.eta = MLP(2 * state_dim + effect_dim + self.offset_dim, effect_dim, mlp)

    def reset_parameters(self) -> None:
        self.eta.reset_parameters()

    def forward(
        self,
        state: Tensor,
        effect: Tensor,
        pos: Tensor,
        edge_index: Tensor,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
        rest_pos: Tensor | None = None,
        degree: Tensor | None = None,
        rest_offset: Tensor | None = None,
    ) -> Tensor:
        """The effect increment; ``degree`` ``(N,)`` (:func:`~hrn_pyg.nn.mlp.in_degree`) and
        ``rest_offset`` ``(E, 3)`` (:func:`edge_offsets` of ``rest_pos``) may be passed precomputed,
        with the same result."""
        n = check_state("PropagationModule", state, self.state_dim)
        if effect.shape != (n, self.effect_dim):
            raise ValueError(f"PropagationModule: effect must be [N, {self.effect_dim}], got {tuple(effect.shape)}")
        check_edges("PropagationModule", n, pos, edge_index, mask, batch)
        src, dst = edge_index
        offset = edge_offsets(pos, edge_index)  # x_j - x_i
        if self.rest_offsets:
            rest_offset = given_rest_offset("PropagationModule", rest_offset, rest_pos, edge_index, n)
            offset = torch.cat([offset, rest_offset], dim=-1)  # both offsets go through one weight block
        # an edge takes the trajectory copy of its destination (both ends share one copy)
        edge_batch = batch.index_select(0, dst) if mask is not None else None
        # eta([s_j, s_i, e_j, x_j - x_i (, rest offset)]) with its first layer split by input blocks,
        # each applied per node and gathered onto the edges
        w_src, w_dst, w_effect, w_offset = self.eta.split_first_weight(
            (self.state_dim, self.state_dim, self.effect_dim, self.offset_dim))
        from_src = state @ w_src.T + effect @ w_effect.T
        from_dst = torch.addmm(self.eta.first_bias, state, w_dst.T)
        # the gathered rows are made for this call alone: without autograd they take the sum in place
        pre = from_src.index_select(0, src)
        b_i = from_dst.index_select(0, dst)
        pre = (pre.add_(b_i) if not torch.is_grad_enabled() else pre + b_i).addmm_(offset, w_offset.T)
        hidden = self.eta.last_hidden_from_first(pre, mask, edge_batch, pre_is_scratch=True)
        # eta's last hidden layer is summed per destination; its output layer runs once per node
        hidden_sum = sum_by_index(hidden, dst, n)
        return self.eta.output_of_sum(hidden_sum, in_degree(edge_index, n) if degree is None else degree)

    def __repr__(self) -> str:
        tag = f"{self.name}, " if self.name else ""
        return (
            f"{self.__class__.__name__}({tag}state_dim={self.state_dim}, "
            f"effect_dim={self.effect_dim}, rest_offsets={self.rest_offsets}, eta={self.eta})"
        )


def edge_offsets(x: Tensor, edge_index: Tensor) -> Tensor:
    r"""Every edge's offset :math:`x_j - x_i` from its destination :math:`i` to its source :math:`j`.

    **Shapes:** x ``(N, F)``, edge_index ``(2, E)``; returns ``(E, F)``.
    """
    return x.index_select(0, edge_index[0]) - x.index_select(0, edge_index[1])


def given_rest_offset(who: str, rest_offset: Tensor | None, rest_pos: Tensor | None, edge_index: Tensor,
                      num_nodes: int) -> Tensor:
    """The edges' rest offsets: ``rest_offset`` when the caller has them, else the
    :func:`edge_offsets` of ``rest_pos`` (a one-line ValueError naming ``who`` unless it is
    ``[N, 3]``)."""
    if rest_offset is not None:
        return rest_offset
    if rest_pos is None or rest_pos.shape != (num_nodes, 3):
        got = None if rest_pos is None else tuple(rest_pos.shape)
        raise ValueError(f"{who}: rest_offsets needs rest_pos [N, 3], got {got}")
    return edge_offsets(rest_pos, edge_index)
