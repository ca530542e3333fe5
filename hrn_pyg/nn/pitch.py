r"""The voxel pitch as an input of a pitch-aware model (``HRNConfig.pitch_aware``).

A model reads a scene of pitch :math:`p` relative to :math:`s = p / p_{ref}`
(``HRNConfig.reference_pitch``):

* collision radius :math:`r_c\, s` (:func:`collision_radius_of`), also in the ground-contact
  column :math:`\mathrm{clip}(z / (r_c s), -1, 1)`;
* positions and rest positions divided by :math:`s` (:func:`pitch_scale`), so a neighbour one
  lattice step away looks the same at every pitch;
* a state column :math:`\log_2 s` (:func:`pitch_column`), velocities and heights in metres.

A graph's pitch is its graph-level ``pitch`` (:func:`hrn_pyg.data.graph.node_pitch`); a batch
may mix pitches.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from hrn_pyg.data.graph import graph_pitch, node_pitch

#: the state column of a pitch-aware model: :math:`\log_2(p / p_{ref})`
PITCH_DIM = 1


def is_pitch_aware(config: Any) -> bool:
    """Whether a network config reads the pitch (``pitch_aware``; False for configs without it)."""
    return bool(getattr(config, "pitch_aware", False))


def collision_radius_of(config: Any, graph: HeteroData) -> float | Tensor:
    r"""The collision radius of a model with ``config`` on ``graph``, found here only: plain models
    ``config.collision_radius`` :math:`r_c`; pitch-aware :math:`r_b = r_c\, p_b / p_{ref}` per
    graph, one number when all pitches agree, else a float64 tensor ``(B,)`` (one host read).

    **Shapes**: ``graph.pitch (B,)`` -> a number or ``(B,)`` float64.
    """
    radius = float(config.collision_radius)
    if not is_pitch_aware(config):
        return radius
    pitch = graph_pitch(graph)
    if pitch is None:
        raise ValueError("a pitch-aware model needs the graph's voxel pitch (graph.pitch; "
                         "hrn_pyg.data.graph.set_pitch)")
    radii = radius * pitch.detach().to(torch.float64).reshape(-1) / float(config.reference_pitch)
    if radii.numel() == 1 or bool((radii == radii[0]).all()):
        return float(radii[0])
    return radii


def pitch_scale(graph: HeteroData, reference_pitch: float) -> Tensor:
    """Every node's scale :math:`s_i = p_{b(i)} / p_{ref}`. **Shapes**: ``graph.pitch (B,)`` ->
    ``(N,)`` float64."""
    return node_pitch(graph).to(torch.float64) / float(reference_pitch)


def pitch_column(scale: Tensor, dtype: torch.dtype) -> Tensor:
    r"""The state column :math:`\log_2 s_i`, ``(N, 1)`` in ``dtype``. **Shapes**: ``(N,)`` -> ``(N, 1)``."""
    return torch.log2(scale).to(dtype).unsqueeze(-1)


def node_radius(config: Any, scale: Tensor, dtype: torch.dtype) -> Tensor:
    """Every node's collision radius :math:`r_c s_i`, ``(N, 1)`` in ``dtype``. **Shapes**: ``(N,)``
    -> ``(N, 1)``."""
    return (float(config.collision_radius) * scale).to(dtype).unsqueeze(-1)
