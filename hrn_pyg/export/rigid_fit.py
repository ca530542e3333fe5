r"""A rigid object's mesh moved by the best rigid transform of its leaves, frame by frame.

The package's shape matching (:func:`hrn_pyg.nn.rigid.rigid_motion`) from the rest leaves
:math:`x_i` to frame :math:`t`'s :math:`\hat x_i(t)`, equal weights, one batched fit:

.. math::
    c = \tfrac1n \textstyle\sum_i x_i, \quad \hat c(t) = \tfrac1n \sum_i \hat x_i(t), \quad
    R(t) = \mathrm{polar}\Bigl(\sum_i (\hat x_i(t) - \hat c(t))(x_i - c)^\top\Bigr), \quad
    v(t) = \hat c(t) + R(t)\,(v - c)

for every rest vertex :math:`v` of the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hrn_pyg.nn.rigid import rigid_motion

__all__ = ["RigidFrames", "fit_rigid_frames"]


@dataclass(frozen=True)
class RigidFrames:
    """A rigid object's pose in every frame: :math:`v(t) = \\hat c(t) + R(t) (v - c)`.

    **Shapes:** ``centre (3,)`` (:math:`c`, the leaves' mean at rest), ``translation (T, 3)``
    (:math:`\\hat c(t)`), ``rotation (T, 3, 3)`` (:math:`R(t)`).
    """

    centre: np.ndarray
    translation: np.ndarray
    rotation: np.ndarray

    def apply(self, vertices: np.ndarray) -> np.ndarray:
        """The rest ``vertices (V, 3)`` in every frame ``(T, V, 3)``."""
        arm = np.asarray(vertices, np.float64) - self.centre
        return self.translation[:, None, :] + np.einsum("tij,vj->tvi", self.rotation, arm)


def fit_rigid_frames(rest: np.ndarray, frames: np.ndarray) -> RigidFrames:
    """The best rigid motion from the leaves at rest to the leaves of each frame.

    **Shapes:** ``rest (n, 3)``, ``frames (T, n, 3)``; returns a :class:`RigidFrames` over ``T``.
    """
    rest, frames = np.asarray(rest, np.float64), np.asarray(frames, np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3 or frames.shape[1:] != rest.shape:
        raise ValueError(f"fit_rigid_frames: rest must be [n, 3] and frames [T, n, 3], got "
                         f"{rest.shape} and {frames.shape}")
    steps, n = frames.shape[:2]
    current = torch.from_numpy(np.broadcast_to(rest, frames.shape).reshape(-1, 3).copy())
    predicted = torch.from_numpy(frames.reshape(-1, 3))
    group = torch.arange(steps).repeat_interleave(n)
    centre, centre_hat, rotation = rigid_motion(current, predicted, torch.ones(steps * n, dtype=torch.float64),
                                                group, steps)
    return RigidFrames(centre[0].numpy(), centre_hat.numpy(), rotation.numpy())
