"""Force module of the horizontally equivariant HRN: the effect of an external force on its particle."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.equivariant.features import dot, horizontal, horizontal_length, weighted_sum
from hrn_pyg.nn.mlp import MLP, MLPConfig


class ForceModule(nn.Module):
    r"""Effect of an external force :math:`f_i` on a particle, a scalar part and ``C`` horizontal vectors.

    .. math::
        h_i &= \phi_F\bigl(\tilde s_i,\ \lVert f_{i,h} \rVert,\ f_{i,z},\ f_{i,h} \cdot v_i\bigr) \\
        e_F(i) &= W h_i + b, \qquad E_F(i)_c = a_c(h_i)\, f_{i,h} + a'_c(h_i)\, v_i

    for a particle with :math:`f_i \ne 0`; every other row is an exact zero. :math:`\tilde s` is
    the invariant state, :math:`f_h` the (normalised) horizontal force, :math:`v` the normalised
    horizontal velocity. ``dense=True`` runs :math:`\phi_F` on every row and zeroes those without
    a force (no size depends on the data; the same numbers up to rounding).

    Args:
        state_dim: size :math:`S'` of an invariant state vector.
        effect_dim: size :math:`D` of the scalar effect.
        channels: number :math:`C` of vector channels.
        mlp: shape of :math:`\phi_F`.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S')`, velocity :math:`(|\mathcal{V}|, 2)`,
          force :math:`(|\mathcal{V}|, 3)`, mask :math:`(B, H)` or None, batch :math:`(|\mathcal{V}|,)`
        - **output:** effect :math:`(|\mathcal{V}|, D)`, vectors :math:`(|\mathcal{V}|, C, 2)`
    """

    def __init__(self, state_dim: int, effect_dim: int, channels: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim, self.effect_dim, self.channels = state_dim, effect_dim, channels
        self.phi = MLP(state_dim + 3, effect_dim, mlp)
        self.vector = nn.Linear(mlp.hidden, 2 * channels)

    def reset_parameters(self) -> None:
        self.phi.reset_parameters()
        self.vector.reset_parameters()

    def forward(self, state: Tensor, velocity: Tensor, force: Tensor, mask: Tensor | None = None,
                batch: Tensor | None = None, dense: bool = False) -> tuple[Tensor, Tensor]:
        n = state.size(0)
        if state.dim() != 2 or state.size(1) != self.state_dim:
            raise ValueError(f"equivariant ForceModule: state must be [N, {self.state_dim}], got {tuple(state.shape)}")
        if force.shape != (n, 3) or velocity.shape != (n, 2):
            raise ValueError("equivariant ForceModule: force must be [N, 3] and velocity [N, 2]")
        if dense:
            effect, vectors = self._effect(state, velocity, force, mask, batch if mask is not None else None)
            pushed = (force != 0).any(dim=-1)
            return (torch.where(pushed.unsqueeze(-1), effect, torch.zeros_like(effect)),
                    torch.where(pushed.view(n, 1, 1), vectors, torch.zeros_like(vectors)))
        active = (force != 0).any(dim=-1).nonzero().squeeze(1)
        index = batch.index_select(0, active) if (mask is not None and batch is not None) else None
        effect, vectors = self._effect(state.index_select(0, active), velocity.index_select(0, active),
                                       force.index_select(0, active), mask, index)
        return (state.new_zeros(n, self.effect_dim).index_copy(0, active, effect),
                state.new_zeros(n, self.channels, 2).index_copy(0, active, vectors))

    def _effect(self, state: Tensor, velocity: Tensor, force: Tensor, mask: Tensor | None,
                index: Tensor | None) -> tuple[Tensor, Tensor]:
        """Both parts of the effect on the rows given (all of them pushed, or zeroed after)."""
        f_h = horizontal(force)
        x = torch.cat([state, horizontal_length(f_h), force[:, 2:], dot(f_h, velocity)], dim=-1)
        hidden = self.phi.last_hidden_from_first(self.phi.hidden_layers[0](x), mask, index, pre_is_scratch=True)
        weights = self.vector(hidden).view(-1, 2, self.channels)
        return self.phi.output_layer(hidden), weighted_sum(weights, torch.stack([f_h, velocity], dim=1))

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"channels={self.channels}, phi={self.phi})")
