r"""The voxel pitch as an input of a pitch-aware model (``HRNConfig.pitch_aware``).

A scene voxelised at pitch :math:`p` has its leaves about :math:`p` apart. A model trained at one
pitch sees a finer or coarser lattice as a different world: neighbours closer or farther than
it ever saw, and collision edges of a fixed radius that reach more or fewer lattice steps. A
pitch-aware model instead reads every scene relative to its pitch, with the scale

.. math::
    s = p / p_{ref}

(``p_ref``: ``HRNConfig.reference_pitch``, the pitch at which a pitch-aware model reads a scene
as a plain model does):

* the collision radius is :math:`r_c\, s` (:func:`collision_radius_of`), so a leaf meets the
  same lattice neighbourhood of another object at every pitch; the ground-contact column
  :math:`\mathrm{clip}(z / (r_c s), -1, 1)` uses that radius too;
* the geometric inputs, the positions and rest positions whose differences the modules read as
  edge offsets, are divided by :math:`s` (:func:`pitch_scale`), so a neighbour one lattice step
  away looks the same at every pitch;
* the state gains the column :math:`\log_2 s` (:func:`pitch_column`; 0 at the reference pitch),
  so the network can still tell pitches apart where physics does (velocities and heights stay
  in metres: gravity sets a length scale of its own).

The pitch of a graph is its graph-level ``pitch`` (:func:`hrn_pyg.data.graph.node_pitch`); a
batch may mix graphs of different pitches, each read at its own.
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
    r"""The collision radius a model with ``config`` uses on ``graph``: the one place it is found.

    Plain models: ``config.collision_radius`` :math:`r_c`, whatever the graph. Pitch-aware models:

    .. math::
        r_b = r_c\, p_b / p_{ref}

    for each graph ``b`` of the batch, returned as one Python number when every graph has the
    same pitch (the usual rollout of one scene), else as a float64 tensor ``(B,)`` of one radius
    per graph (:func:`hrn_pyg.data.graph.leaf_collision_edges` searches at the largest and keeps
    each edge within its own graph's radius). Both forms give each graph the same edges. One
    host read for a pitch-aware model.

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
    r"""Every node's scale :math:`s_i = p_{b(i)} / p_{ref}`, ``(N,)`` float64: its graph's pitch
    over the reference pitch (1 at the reference).

    **Shapes**: ``graph.pitch (B,)`` -> ``(N,)``.
    """
    return node_pitch(graph).to(torch.float64) / float(reference_pitch)


def pitch_column(scale: Tensor, dtype: torch.dtype) -> Tensor:
    r"""The state column :math:`\log_2 s_i` of a pitch-aware model, ``(N, 1)`` in ``dtype``
    (0 at the reference pitch, +1 at twice it, -1 at half).

    **Shapes**: ``(N,)`` -> ``(N, 1)``.
    """
    return torch.log2(scale).to(dtype).unsqueeze(-1)


def node_radius(config: Any, scale: Tensor, dtype: torch.dtype) -> Tensor:
    r"""Every node's collision radius :math:`r_c s_i`, ``(N, 1)`` in ``dtype`` (the divisor of a
    pitch-aware model's ground-contact column).

    **Shapes**: ``(N,)`` -> ``(N, 1)``.
    """
    return (float(config.collision_radius) * scale).to(dtype).unsqueeze(-1)
