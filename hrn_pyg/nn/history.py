"""History module of the HRN (Fig. 2): the effect of a particle's own recent past."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig, check_state


class HistoryModule(nn.Module):
    r"""Effect of the previous state on a particle (the HRN sees two consecutive graphs), every row.

    .. math::
        e_H(i) = \phi_H\bigl(s_i(t),\ s_i(t-1)\bigr)

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect.
        mlp: shape of :math:`\phi_H`.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, prev_state :math:`(|\mathcal{V}|, S)`,
          mask :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)` (needed with a mask)
        - **output:** effect :math:`(|\mathcal{V}|, D)`
    """

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.phi = MLP(2 * state_dim, effect_dim, mlp)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()

    def forward(
        self,
        state: Tensor,
        prev_state: Tensor,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
    ) -> Tensor:
        check_state("HistoryModule", state, self.state_dim)
        if prev_state.shape != state.shape:
            raise ValueError(
                f"HistoryModule: prev_state must match state {tuple(state.shape)}, got {tuple(prev_state.shape)}"
            )
        return self.phi(torch.cat([state, prev_state], dim=-1), mask, batch)

    def __repr__(self) -> str:
        return f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, phi={self.phi})"
