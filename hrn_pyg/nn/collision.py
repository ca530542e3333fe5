"""Collision module of the HRN (Fig. 2): effects of nearby particles of other objects."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig, check_edges, check_force, check_state, in_degree, sum_by_index

#: added under the square root of a squared distance so that its gradient stays finite when two
#: particles coincide (d|x|/dx is undefined at 0)
NORM_EPSILON = 1e-12


def safe_norm(x: Tensor, dim: int = -1, keepdim: bool = True) -> Tensor:
    r""":math:`\sqrt{\lVert x \rVert^2 + \epsilon}` with :data:`NORM_EPSILON`; finite gradient at 0."""
    return torch.sqrt((x * x).sum(dim=dim, keepdim=keepdim) + NORM_EPSILON)


class CollisionModule(nn.Module):
    r"""Sum of pairwise collision effects over the collision edges.

    .. math::
        e_C(i) = \sum_{j \in \mathcal{N}_C(i)}
            \phi_C\bigl(s_i,\ s_j,\ x_i - x_j,\ \lVert x_i - x_j \rVert\bigr)

    :math:`\mathcal{N}_C(i)`: the sources of collision edges ``j -> i`` (leaves of other objects
    within the radius); translation invariant; a node without messages gets an exact zero.
    ``edge_weight`` (0 or 1 per edge, the fixed-shape step's candidates) switches edges off exactly.
    With ``reads_force`` the messages also read the normalised force on both ends,
    :math:`\phi_C(s_i, s_j, f_i, f_j, x_i - x_j, \lVert x_i - x_j \rVert)`, so a push reaches the
    contact in its own step.

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect.
        mlp: shape of :math:`\phi_C`.
        reads_force: the messages read the force on both ends (``force`` is then required).

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, pos :math:`(|\mathcal{V}|, 3)`,
          edge_index :math:`(2, |\mathcal{E}_C|)`, mask :math:`(B, H)` or None,
          batch :math:`(|\mathcal{V}|,)` (with a mask; an edge uses its destination's id),
          edge_weight :math:`(|\mathcal{E}_C|,)` or None, force :math:`(|\mathcal{V}|, 3)`
        - **output:** effect :math:`(|\mathcal{V}|, D)`
    """

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig(), reads_force: bool = False) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.reads_force = bool(reads_force)
        self.node_dim = state_dim + (3 if self.reads_force else 0)
        self.phi = MLP(2 * self.node_dim + 4, effect_dim, mlp)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()

    def forward(
        self,
        state: Tensor,
        pos: Tensor,
        edge_index: Tensor,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
        edge_weight: Tensor | None = None,
        force: Tensor | None = None,
    ) -> Tensor:
        n = check_state("CollisionModule", state, self.state_dim)
        check_edges("CollisionModule", n, pos, edge_index, mask, batch, edge_weight)
        if self.reads_force:
            check_force("CollisionModule: reads_force", force, n)
        # an edge takes the trajectory copy of its destination (both ends share one copy)
        src, dst = edge_index
        edge_batch = batch.index_select(0, dst) if mask is not None else None
        # phi_C([s_i, s_j, x_i - x_j, |x_i - x_j|]) with its first layer split by input blocks,
        # each applied per node and gathered onto the edges
        node = torch.cat([state, force], dim=-1) if self.reads_force else state
        w_dst, w_src, w_offset, w_dist = self.phi.split_first_weight((self.node_dim, self.node_dim, 3, 1))
        from_dst = torch.addmm(self.phi.first_bias, node, w_dst.T)
        from_src = node @ w_src.T
        offset = pos.index_select(0, dst) - pos.index_select(0, src)  # x_i - x_j
        # the gathered rows are made for this call alone: without autograd they take the sum in place
        pre = from_dst.index_select(0, dst)
        b_j = from_src.index_select(0, src)
        pre = pre.add_(b_j) if not torch.is_grad_enabled() else pre + b_j
        pre = pre.addmm_(offset, w_offset.T).addmm_(safe_norm(offset), w_dist.T)
        hidden = self.phi.last_hidden_from_first(pre, mask, edge_batch, pre_is_scratch=True)
        if edge_weight is not None:
            weight = edge_weight.to(hidden.dtype).unsqueeze(-1)
            hidden = hidden.mul_(weight) if not torch.is_grad_enabled() else hidden * weight
        # phi_C's last hidden layer is summed per destination; its output layer runs once per node
        hidden_sum = sum_by_index(hidden, dst, n)
        return self.phi.output_of_sum(hidden_sum, in_degree(edge_index, n, edge_weight))

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"{'reads_force=True, ' if self.reads_force else ''}phi={self.phi})")
