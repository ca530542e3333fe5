r"""The scenes' symmetry about the vertical axis, used to augment training windows.

Turning a scene about z or mirroring it in a vertical plane gives another scene of the same
physics; every position, force and rest shape is mapped by

.. math::
    Q = \begin{pmatrix} \pm\cos\theta & -\sin\theta & 0 \\ \pm\sin\theta & \cos\theta & 0 \\
        0 & 0 & 1 \end{pmatrix}, \qquad \theta \sim U[0, 2\pi),

drawn per copy, so the model learns no preferred horizontal direction.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import NODE

#: per-node attributes of a window that are vectors in world space (rows ``[N, 3]`` or ``[N, T, 3]``)
WORLD_VECTORS = ("pos", "prev_pos", "prev_prev_pos", "force", "pos_seq", "force_seq", "rest_pos")


def random_vertical_symmetries(
    num: int,
    generator: torch.Generator | None = None,
    reflect: bool = True,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """``[num, 3, 3]`` matrices: a rotation about z by a uniform angle, composed with the mirror
    ``x -> -x`` with probability 1/2 when ``reflect``. Drawn on the CPU (``generator`` is a CPU
    generator), then moved to ``device``."""
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    theta = torch.rand(num, generator=generator, dtype=torch.float64) * (2.0 * math.pi)
    sign = torch.ones(num, dtype=torch.float64)
    if reflect:
        flip = torch.rand(num, generator=generator, dtype=torch.float64) < 0.5
        sign = torch.where(flip, -sign, sign)
    c, s = torch.cos(theta), torch.sin(theta)
    q = torch.zeros(num, 3, 3, dtype=torch.float64)
    q[:, 0, 0], q[:, 0, 1] = sign * c, -s
    q[:, 1, 0], q[:, 1, 1] = sign * s, c
    q[:, 2, 2] = 1.0
    return q.to(dtype=dtype, device=device)


def apply_vertical_symmetry(window: HeteroData, symmetries: Tensor) -> HeteroData:
    """A copy of ``window`` with every world-space vector (:data:`WORLD_VECTORS`) of copy ``b`` mapped
    by ``symmetries[b]`` about the origin; edges and other attributes shared.

    **Shapes:** ``symmetries`` ``[B, 3, 3]`` with ``B`` the window's copies (1 without ``batch``).
    """
    store = window[NODE]
    batch = store.batch if "batch" in store else None
    copies = int(batch.max()) + 1 if batch is not None and batch.numel() else 1
    if symmetries.shape != (copies, 3, 3):
        raise ValueError(f"symmetries must be [{copies}, 3, 3] (one per copy), got {tuple(symmetries.shape)}")
    out = window.clone()
    per_node = symmetries[batch] if batch is not None else symmetries.expand(store.num_nodes, 3, 3)
    for name in WORLD_VECTORS:
        if name not in store:
            continue
        value = store[name]
        q = per_node.to(value.dtype)
        if value.dim() == 2:
            out[NODE][name] = torch.einsum("nij,nj->ni", q, value)
        else:
            out[NODE][name] = torch.einsum("nij,ntj->nti", q, value)
    return out
