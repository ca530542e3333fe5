"""History module of the horizontally equivariant HRN: a particle's effect of its own recent past."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.equivariant.features import dot, squash, weighted_sum
from hrn_pyg.nn.mlp import MLP, MLPConfig


class HistoryModule(nn.Module):
    r"""Effect of the previous state on a particle, a scalar part and ``C`` horizontal vectors.

    .. math::
        h_i &= \phi_H\bigl(\tilde s_i(t),\ \tilde s_i(t-1),\ \hat v_i(t) \cdot \hat v_i(t-1)\bigr) \\
        e_H(i) &= W h_i + b, \qquad
        E_H(i)_c = a_c(h_i)\, v_i(t) + a'_c(h_i)\, v_i(t-1)

    :math:`\tilde s` is the invariant state (:func:`~hrn_pyg.nn.equivariant.features.invariant_state`),
    :math:`v` the normalised horizontal velocity, :math:`\hat v = v / (1 + \lVert v \rVert)`.

    Args:
        state_dim: size :math:`S'` of an invariant state vector.
        effect_dim: size :math:`D` of the scalar effect.
        channels: number :math:`C` of vector channels.
        mlp: shape of :math:`\phi_H`.

    **Shapes:**
        - **input:** state, prev_state :math:`(|\mathcal{V}|, S')`, velocity, prev_velocity
          :math:`(|\mathcal{V}|, 2)`, mask :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)`
        - **output:** effect :math:`(|\mathcal{V}|, D)`, vectors :math:`(|\mathcal{V}|, C, 2)`
    """

    def __init__(self, state_dim: int, effect_dim: int, channels: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim, self.effect_dim, self.channels = state_dim, effect_dim, channels
        self.phi = MLP(2 * state_dim + 1, effect_dim, mlp)
        self.vector = nn.Linear(mlp.hidden, 2 * channels)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()
        self.vector.reset_parameters()

    def forward(self, state: Tensor, prev_state: Tensor, velocity: Tensor, prev_velocity: Tensor,
                mask: Tensor | None = None, batch: Tensor | None = None) -> tuple[Tensor, Tensor]:
        n = state.size(0)
        if state.dim() != 2 or state.size(1) != self.state_dim or prev_state.shape != state.shape:
            raise ValueError(f"equivariant HistoryModule: state and prev_state must be [N, {self.state_dim}], "
                             f"got {tuple(state.shape)} and {tuple(prev_state.shape)}")
        if velocity.shape != (n, 2) or prev_velocity.shape != (n, 2):
            raise ValueError("equivariant HistoryModule: velocity and prev_velocity must be [N, 2]")
        x = torch.cat([state, prev_state, dot(squash(velocity), squash(prev_velocity))], dim=-1)
        hidden = self.phi.last_hidden_from_first(self.phi.hidden_layers[0](x), mask, batch, pre_is_scratch=True)
        weights = self.vector(hidden).view(n, 2, self.channels)
        vectors = weighted_sum(weights, torch.stack([velocity, prev_velocity], dim=1))
        return self.phi.output_layer(hidden), vectors

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"channels={self.channels}, phi={self.phi})")
