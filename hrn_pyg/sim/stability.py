r"""The package's stability check of a long rollout: finite, bounded, above the ground, shapes kept.

:func:`stability_report` scores a force-free rollout ``x_1 .. x_S`` from ``x_0`` against
:class:`StabilityLimits`:

* ``finite``; ``max_move``: the farthest a movable leaf gets from its start (``bound``, 50 m);
* ``min_z``: the lowest movable leaf (above ``-sink_depth``, 5 cm);
* ``rigid_shape``: the largest relative change of a rigid object's mean pairwise leaf distance
  :math:`\bar d = \frac{1}{P(P-1)}\sum_{i \ne j}\lVert x_i - x_j\rVert` (``rigid_change``, 1 %);
* ``rest_drift``: the largest move of an object's centre after step ``settle`` (``drift``, 5 cm);
* ``soft_extent``: soft and cloth height extent, end over start (reported).

``passes_check``: the first three; ``holds``: all five limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import MATERIALS, NODE

RIGID, SOFT, CLOTH = (MATERIALS.index(m) for m in ("rigid", "soft", "cloth"))


@dataclass(frozen=True)
class StabilityLimits:
    """The limits of :func:`stability_report` (metres, and a fraction for ``rigid_change``)."""

    bound: float = 50.0
    sink_depth: float = 0.05
    rigid_change: float = 0.01
    drift: float = 0.05


def mean_pairwise_distance(x: Tensor) -> Tensor:
    """``[..., P, 3]`` -> ``[...]``: the mean distance over ordered pairs of distinct points."""
    d = (x[..., :, None, :] - x[..., None, :, :]).norm(dim=-1)
    p = x.shape[-2]
    return d.sum(dim=(-1, -2)) / max(p * (p - 1), 1)


def stability_report(traj: Tensor, graph: HeteroData, settle: int,
                     limits: StabilityLimits = StabilityLimits()) -> dict[str, float | bool]:
    """Score one rollout ``traj`` ``[S, N, 3]`` (``x_1 .. x_S``) of ``graph`` (its ``pos`` is
    ``x_0``) by the module docstring; ``settle`` is the step from which objects should rest."""
    if traj.dim() != 3 or traj.shape[1:] != graph[NODE].pos.shape:
        raise ValueError(f"traj must be [S, {graph[NODE].num_nodes}, 3], got {tuple(traj.shape)}")
    if not 0 <= settle < traj.shape[0]:
        raise ValueError(f"settle must be in [0, {traj.shape[0]}), got {settle}")
    store = graph[NODE]
    leaves = torch.nonzero(store.is_leaf & ~store.is_static).flatten()
    start = store.pos
    finite = bool(torch.isfinite(traj).all())
    out: dict[str, float | bool] = {
        "finite": finite,
        "max_move": float((traj[:, leaves] - start[leaves]).abs().max()),
        "min_z": float(traj[:, leaves, 2].min()),
        "rigid_shape": 0.0,
        "rest_drift": 0.0,
        "soft_extent": float("nan"),
    }
    material = store.material.argmax(dim=1)
    mass = store.mass[:, 0]
    extents = []
    for obj in torch.unique(store.object[leaves]).tolist():  # a handful of objects per scene
        idx = leaves[store.object[leaves] == obj]
        kind = int(material[idx[0]])
        w = (mass[idx] / mass[idx].sum())[:, None]
        centre = (traj[:, idx] * w).sum(dim=1)  # [S, 3]
        out["rest_drift"] = max(out["rest_drift"], float((centre[settle:] - centre[settle]).norm(dim=-1).max()))
        if kind == RIGID:
            change = mean_pairwise_distance(traj[-1, idx]) / mean_pairwise_distance(start[idx]) - 1.0
            out["rigid_shape"] = max(out["rigid_shape"], abs(float(change)))
        elif kind in (SOFT, CLOTH):
            z0, z1 = start[idx, 2], traj[-1, idx, 2]
            extents.append(float((z1.max() - z1.min()) / (z0.max() - z0.min()).clamp_min(1e-3)))
    if extents:
        out["soft_extent"] = max(extents)
    out["passes_check"] = finite and out["max_move"] < limits.bound and out["min_z"] > -limits.sink_depth
    out["holds"] = (out["passes_check"] and out["rigid_shape"] <= limits.rigid_change
                    and out["rest_drift"] < limits.drift)
    return out
