"""Next-state module of the HRN (Fig. 2): each particle's next velocity in its parent's frame."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig, check_state


class NextStateModule(nn.Module):
    r"""Next velocity of each particle, local to its parent; a root's is global.

    .. math::
        \hat{u}_i = \psi(s_i, e_i), \qquad
        v^{loc}_i(t+1) = v^{loc}_i(t) + \mu_{r(i)} + \sigma_{r(i)} \odot \hat{u}_i

    The module gives :math:`\hat u_i` (an exact zero on static particles); the decoding on the
    right is :func:`hrn_pyg.sim.step.decode`'s, with root or local statistics.

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect.
        mlp: shape of :math:`\psi`.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, effect :math:`(|\mathcal{V}|, D)`,
          is_static :math:`(|\mathcal{V}|,)` bool or None, mask :math:`(B, H)` or None,
          batch :math:`(|\mathcal{V}|,)` (with a mask)
        - **output:** normalised local velocity :math:`(|\mathcal{V}|, 3)`
    """

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.psi = MLP(state_dim + effect_dim, 3, mlp)

    def reset_parameters(self) -> None:
        self.psi.reset_parameters()

    def forward(
        self,
        state: Tensor,
        effect: Tensor,
        is_static: Tensor | None = None,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
    ) -> Tensor:
        n = check_state("NextStateModule", state, self.state_dim)
        if effect.shape != (n, self.effect_dim):
            raise ValueError(f"NextStateModule: effect must be [N, {self.effect_dim}], got {tuple(effect.shape)}")
        x = torch.cat([state, effect], dim=-1)
        out = self.psi(x, mask, batch)
        if is_static is not None:
            out = torch.where(is_static.unsqueeze(-1), torch.zeros_like(out), out)
        return out

    def __repr__(self) -> str:
        return f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, psi={self.psi})"


def to_local_velocity(velocity: Tensor, child_to_parent: Tensor) -> Tensor:
    r"""Velocities in the parent's frame; roots keep their global velocity.

    .. math::
        v^{loc}_i = v_i - v_{parent(i)} \ (i \text{ not a root}), \qquad v^{loc}_r = v_r

    **Shapes:** velocity :math:`(|\mathcal{V}|, \ldots, 3)`, child_to_parent :math:`(2, |\mathcal{V}| - R)`
    (row 0 child, row 1 parent); returns the shape of ``velocity``.
    """
    child, parent = child_to_parent
    return velocity.index_add(0, child, -velocity.index_select(0, parent))


def to_global_velocity(local: Tensor, leaf_to_ancestor: Tensor) -> Tensor:
    r"""Sum local velocities down the tree: a node's own plus all its ancestors'.

    .. math::
        v_i = v^{loc}_i + \sum_{a \in \mathrm{anc}(i)} v^{loc}_a

    One scatter over ``leaf_to_ancestor``; the inverse of :func:`to_local_velocity`.

    **Shapes:** local :math:`(|\mathcal{V}|, \ldots, 3)`, leaf_to_ancestor :math:`(2, |\mathcal{E}_{L2A}|)`;
    returns the shape of ``local``.
    """
    node, ancestor = leaf_to_ancestor
    return local.index_add(0, node, local.index_select(0, ancestor))
