r"""A deformable mesh skinned to its leaves: weights fixed at rest, vertices as sums of leaves.

Each rest vertex :math:`v` takes its :data:`SKIN_NEIGHBOURS` nearest rest leaves
:math:`x_1 .. x_k` and the weights that reproduce it affinely,

.. math::
    \sum_j w_j = 1, \qquad \sum_j w_j x_j = v,

of least :math:`\sum_j w_j^2 / \phi_j`, :math:`\phi_j = 1 / (d_j^2 + h^2)` (:math:`h` =
:data:`SOFTENING` pitches): with :math:`B = [\mathbf 1^\top; (x_j - v)^\top]` and
:math:`\Phi = \mathrm{diag}(\phi)`,

.. math:: w = \Phi B^\top (B \Phi B^\top)^{-1} e_1 .

A frame's vertex is :math:`v(t) = \sum_j w_j x_j(t)`, so any affine motion of the leaves moves
the mesh by the same map. Flat neighbourhoods get a ridge of :data:`RIDGE` times the trace.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["SKIN_NEIGHBOURS", "SkinWeights", "skin_weights"]

#: leaves each vertex is tied to (8: the corners of the lattice cell around it, for a soft body)
SKIN_NEIGHBOURS = 8
#: softening length of the inverse-square preference, as a fraction of the pitch: a vertex on a
#: leaf follows it (to about 1e-6 of the others' weight), without a division by zero
SOFTENING = 1e-3
#: ridge added to the spatial 3x3 block of the normal matrix, relative to that block's trace:
#: below float64's rounding where the neighbours span space, it keeps a flat one solvable
RIDGE = 1e-12


@dataclass(frozen=True)
class SkinWeights:
    """Fixed weights of every vertex over its leaves.

    **Shapes:** ``index (V, k)`` leaf rows, ``weight (V, k)`` (each row sums to 1).
    """

    index: np.ndarray
    weight: np.ndarray

    def apply(self, leaves: np.ndarray) -> np.ndarray:
        r""":math:`v(t) = \sum_j w_j x_j(t)` for leaves ``(..., n, 3)``; returns ``(..., V, 3)``."""
        leaves = np.asarray(leaves, np.float64)
        return np.einsum("vk,...vkc->...vc", self.weight, leaves[..., self.index, :])


def skin_weights(vertices: np.ndarray, leaves: np.ndarray, pitch: float,
                 neighbours: int = SKIN_NEIGHBOURS) -> SkinWeights:
    """Skinning weights of rest ``vertices (V, 3)`` over rest ``leaves (n, 3)`` (see the module)."""
    vertices, leaves = np.asarray(vertices, np.float64), np.asarray(leaves, np.float64)
    if len(leaves) == 0:
        raise ValueError("skin_weights: an object without leaves")
    k = min(int(neighbours), len(leaves))
    distance, index = cKDTree(leaves).query(vertices, k=k)
    distance, index = distance.reshape(len(vertices), k), index.reshape(len(vertices), k)
    preference = 1.0 / ((distance / pitch) ** 2 + SOFTENING ** 2)  # [V, k], in pitches
    preference = preference / preference.max(axis=1, keepdims=True)
    arm = (leaves[index] - vertices[:, None, :]) / pitch  # [V, k, 3], in pitches
    basis = np.concatenate([np.ones((len(vertices), 1, k)), arm.transpose(0, 2, 1)], axis=1)  # [V, 4, k]
    weighted = basis * preference[:, None, :]
    normal = weighted @ basis.transpose(0, 2, 1)  # [V, 4, 4]
    spatial = np.trace(normal[:, 1:, 1:], axis1=1, axis2=2)[:, None, None]
    normal = normal + RIDGE * spatial * np.diag([0.0, 1.0, 1.0, 1.0])
    e1 = np.zeros((len(vertices), 4, 1))
    e1[:, 0] = 1.0
    weight = (weighted.transpose(0, 2, 1) @ np.linalg.solve(normal, e1))[..., 0]  # [V, k]
    return SkinWeights(index.astype(np.int64), weight)
