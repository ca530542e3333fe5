"""Next-state module of the HRN (Fig. 2): each particle's next velocity in its parent's frame."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from hrn_pyg.nn.mlp import MLP, MLPConfig


class NextStateModule(nn.Module):
    r"""Next velocity of each particle, local to its parent; a root's is global.

    .. math::
        \hat{u}_i = \psi(s_i, e_i), \qquad
        v^{loc}_i(t+1) = v^{loc}_i(t) + \mu_{r(i)} + \sigma_{r(i)} \odot \hat{u}_i

    :math:`\hat u_i` is the network's normalised output; the decoding on the right (done by
    :func:`hrn_pyg.sim.step.decode` with the model's :class:`~hrn_pyg.nn.normalizer.Normalizer`)
    turns it into the local velocity :math:`v_i(t+1) - v_{parent(i)}(t+1)`, with separate statistics
    :math:`(\mu, \sigma)` for roots (global frame) and for the other nodes (parent frame). Static
    particles (``is_static``) get an exact zero.

    With ``material_columns`` (the columns of the material's one-hot code in :math:`s_i`) there
    is one head per material, :math:`\hat u_i = \psi_{m(i)}(s_i, e_i)` for rigid, soft and cloth
    (a static particle's row is zero whichever head it meets): each material gets an output
    network of its own while the modules before it stay shared, and a scene of one material runs
    one head on every row, as the single head would.

    Args:
        state_dim: size :math:`S` of a particle's state vector.
        effect_dim: size :math:`D` of the effect.
        mlp: shape of :math:`\psi`.
        material_columns: ``(start, stop)`` of the material code in the state, or None (one head).

    **Shapes:**
        - **input:** state :math:`(|\mathcal{V}|, S)`, effect :math:`(|\mathcal{V}|, D)`,
          is_static :math:`(|\mathcal{V}|,)` bool or None, mask :math:`(B, H)` or None,
          batch :math:`(|\mathcal{V}|,)` (needed with a mask)
        - **output:** normalised local velocity :math:`(|\mathcal{V}|, 3)`
    """

    #: the materials with a head of their own, in the order of the state's one-hot code
    HEADS = 3

    def __init__(self, state_dim: int, effect_dim: int, mlp: MLPConfig = MLPConfig(),
                 material_columns: tuple[int, int] | None = None) -> None:
        super().__init__()
        self.state_dim = state_dim
        self.effect_dim = effect_dim
        self.material_columns = material_columns
        if material_columns is None:
            self.psi = MLP(state_dim + effect_dim, 3, mlp)
        else:
            self.heads = nn.ModuleList(MLP(state_dim + effect_dim, 3, mlp) for _ in range(self.HEADS))

    def reset_parameters(self) -> None:
        for head in self._heads():
            head.reset_parameters()

    def _heads(self) -> list[MLP]:
        return [self.psi] if self.material_columns is None else list(self.heads)

    def forward(
        self,
        state: Tensor,
        effect: Tensor,
        is_static: Tensor | None = None,
        mask: Tensor | None = None,
        batch: Tensor | None = None,
        dense: bool = False,
    ) -> Tensor:
        n = state.size(0)
        if state.dim() != 2 or state.size(1) != self.state_dim:
            raise ValueError(f"NextStateModule: state must be [N, {self.state_dim}], got {tuple(state.shape)}")
        if effect.shape != (n, self.effect_dim):
            raise ValueError(f"NextStateModule: effect must be [N, {self.effect_dim}], got {tuple(effect.shape)}")
        x = torch.cat([state, effect], dim=-1)
        if self.material_columns is None:
            out = self.psi(x, mask, batch)
        else:
            out = self._by_material(x, state, mask, batch, dense)
        if is_static is not None:
            out = torch.where(is_static.unsqueeze(-1), torch.zeros_like(out), out)
        return out

    def _by_material(self, x: Tensor, state: Tensor, mask: Tensor | None, batch: Tensor | None,
                     dense: bool) -> Tensor:
        """Each row through the head of its material (static rows: the last head's, zeroed by the
        caller). ``dense``: every head on every row, then the rows picked (no size depends on
        the data); else each head on its own rows (one host read), or on all of them when the
        rows are of one material."""
        start, stop = self.material_columns
        material = state[:, start:stop].argmax(dim=1).clamp_max(self.HEADS - 1)
        if dense:
            outs = torch.stack([head(x, mask, batch) for head in self.heads])  # [M, N, 3]
            return outs.gather(0, material.view(1, -1, 1).expand(1, -1, 3)).squeeze(0)
        low, high = (int(v) for v in torch.aminmax(material))
        if low == high:
            return self.heads[low](x, mask, batch)
        out = x.new_zeros(x.size(0), 3)
        for m in range(low, high + 1):
            rows = torch.nonzero(material == m).flatten()
            if rows.numel():
                out = out.index_copy(0, rows, self.heads[m](x[rows], mask, None if batch is None else batch[rows]))
        return out

    def __repr__(self) -> str:
        heads = "psi" if self.material_columns is None else f"{self.HEADS} heads by material, each"
        return f"{self.__class__.__name__}(state_dim={self.state_dim}, effect_dim={self.effect_dim}, {heads}={self._heads()[0]})"


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

    One scatter over the ``leaf_to_ancestor`` edges (row 0 the node, row 1 one of its ancestors).
    Inverse of :func:`to_local_velocity` on a tree whose ``leaf_to_ancestor`` edges hold every
    descendant/ancestor pair.

    **Shapes:** local :math:`(|\mathcal{V}|, \ldots, 3)`, leaf_to_ancestor :math:`(2, |\mathcal{E}_{L2A}|)`;
    returns the shape of ``local``.
    """
    node, ancestor = leaf_to_ancestor
    return local.index_add(0, node, local.index_select(0, ancestor))
