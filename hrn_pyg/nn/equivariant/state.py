"""Next-state module of the horizontally equivariant HRN: each particle's velocity change."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.equivariant.features import channel_length, squash, weighted_sum
from hrn_pyg.nn.mlp import MLP, MLPConfig, check_state


class NextStateModule(nn.Module):
    r"""The normalised change of each particle's local velocity, vertical part from an MLP of
    invariants, horizontal part a weighted sum of the particle's vectors.

    .. math::
        h_i &= \psi\bigl(\tilde s_i,\ e_i,\ (\lVert E_{i,c} \rVert)_c\bigr), \qquad
        \hat u_{i,z} = w^\top h_i + b \\
        \hat u_{i,h} &= \sum_c a_c(h_i)\, E_{i,c} + a_v(h_i)\, \frac{v_i}{1 + \lVert v_i \rVert}

    decoded as :class:`hrn_pyg.nn.state.NextStateModule`'s output (with horizontally isotropic
    statistics); static particles get an exact zero. Every vector summed is shorter than one, so the
    output grows linearly in the inputs, as a plain MLP's does.

    Args:
        state_dim: size :math:`S'` of an invariant state vector.
        effect_dim: size :math:`D` of the scalar effect.
        channels: number :math:`C` of vector channels.
        mlp: shape of :math:`\psi`.

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S')`, velocity :math:`(|\mathcal{V}|, 2)`,
          effect :math:`(|\mathcal{V}|, D)`, vectors :math:`(|\mathcal{V}|, C, 2)`, is_static
          :math:`(|\mathcal{V}|,)` bool or None, mask :math:`(B, H)` or None, batch
        - **output:** normalised local velocity change :math:`(|\mathcal{V}|, 3)`
    """

    def __init__(self, state_dim: int, effect_dim: int, channels: int, mlp: MLPConfig = MLPConfig()) -> None:
        super().__init__()
        self.state_dim, self.effect_dim, self.channels = state_dim, effect_dim, channels
        self.psi = MLP(state_dim + effect_dim + channels, 1, mlp)
        self.vector = nn.Linear(mlp.hidden, channels + 1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """``psi`` as every MLP; the horizontal readout at zero, so a fresh model predicts no horizontal
        change."""
        self.psi.reset_parameters()
        nn.init.zeros_(self.vector.weight)
        nn.init.zeros_(self.vector.bias)

    def forward(self, state: Tensor, velocity: Tensor, effect: Tensor, vectors: Tensor,
                is_static: Tensor | None = None, mask: Tensor | None = None,
                batch: Tensor | None = None) -> Tensor:
        n, c = check_state("equivariant NextStateModule", state, self.state_dim), self.channels
        if effect.shape != (n, self.effect_dim) or vectors.shape != (n, c, 2) or velocity.shape != (n, 2):
            raise ValueError(f"equivariant NextStateModule: effect must be [N, {self.effect_dim}], vectors "
                             f"[N, {c}, 2] and velocity [N, 2]")
        x = torch.cat([state, effect, channel_length(vectors)], dim=-1)
        hidden = self.psi.last_hidden_from_first(self.psi.hidden_layers[0](x), mask, batch, pre_is_scratch=True)
        weights = self.vector(hidden).view(n, c + 1, 1)
        basis = torch.cat([vectors, squash(velocity.unsqueeze(1))], dim=1)  # [N, C + 1, 2]
        out = torch.cat([weighted_sum(weights, basis).squeeze(1), self.psi.output_layer(hidden)], dim=-1)
        if is_static is not None:
            out = torch.where(is_static.unsqueeze(-1), torch.zeros_like(out), out)
        return out

    def __repr__(self) -> str:
        return (f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, "
                f"channels={self.channels}, psi={self.psi})")
