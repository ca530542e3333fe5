"""Force module of the HRN (Fig. 2): the effect of an external force on the particle it acts on."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig, check_force, check_state


class ForceModule(nn.Module):
    r"""Effect of an external force on a particle.

    .. math::
        e_F(i) = \begin{cases} \phi_F(s_i, f_i) & f_i \ne 0 \\ 0 & f_i = 0 \end{cases}

    :math:`s_i` is the state, :math:`f_i` the normalised force. Only pushed rows are fed to
    :math:`\phi_F`; the others are exactly zero. ``dense=True`` runs :math:`\phi_F` on every row and
    zeroes those without force (no data-dependent shape, for :mod:`hrn_pyg.sim.fixed_shape`).

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect.
        mlp: shape of :math:`\phi_F`.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, force :math:`(|\mathcal{V}|, 3)`,
          mask :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)` (needed with a mask)
        - **output:** effect :math:`(|\mathcal{V}|, D)`
    """

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.phi = MLP(state_dim + 3, effect_dim, mlp)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()

    def forward(
        self,
        state: Tensor,
        force: Tensor,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
        dense: bool = False,
    ) -> Tensor:
        check_force("ForceModule", force, check_state("ForceModule", state, self.state_dim))
        if dense:
            index = batch if (mask is not None and batch is not None) else None
            effect = self.phi(torch.cat([state, force], dim=-1), mask, index)
            pushed = (force != 0).any(dim=-1, keepdim=True)
            return torch.where(pushed, effect, torch.zeros_like(effect))
        active = (force != 0).any(dim=-1).nonzero().squeeze(1)
        x = torch.cat([state.index_select(0, active), force.index_select(0, active)], dim=-1)
        index = batch.index_select(0, active) if (mask is not None and batch is not None) else None
        effect = self.phi(x, mask, index)
        out = state.new_zeros(state.size(0), self.effect_dim)
        return out.index_copy(0, active, effect)

    def __repr__(self) -> str:
        return f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, phi={self.phi})"
