"""Scores only the experiments report: each object's position and shape error
(:func:`per_object_errors`, ``experiments/generalist/unseen_shapes.py``) and a model's hold from
a resting episode's end (:func:`rest_check`, that script and ``experiments/many_objects.py``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor
from torch_geometric.data import Batch
from torch_geometric.utils import scatter

from hrn_pyg.data.graph import NODE, object_span
from hrn_pyg.evaluate.rest import objects_at_rest
from hrn_pyg.losses import full_shape_loss, shape_groups
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.stability import StabilityLimits, stability_report


def per_object_errors(pred: Tensor, truth: Tensor, graph: Batch) -> dict[str, Tensor]:
    r"""Position and shape error of each object of each trajectory copy at one time.

    Position: the mean over the object's moving leaves of :math:`\frac{1}{3}\lVert \hat x_l - x_l
    \rVert^2`; shape: the pairwise-distance error over its leaves. Row ``c * O + o`` is object
    ``o`` of copy ``c``; a static object is NaN.

    **Shapes:** ``pred``, ``truth`` ``[N, 3]``; returns ``{"position": [B*O], "shape": [B*O]}``.
    """
    store = graph[NODE]
    leaf_index, groups = shape_groups(graph)  # moving leaves, one group per (copy, object)
    span = object_span(store.object)
    copies = int(store.batch.max()) + 1 if "batch" in store else 1
    rows = copies * span
    pos_err = (pred - truth)[leaf_index].pow(2).mean(-1)
    position = scatter(pos_err, groups, dim=0, dim_size=rows, reduce="mean")
    shape = torch.full((rows,), float("nan"), dtype=pred.dtype, device=pred.device)
    present = torch.unique(groups)
    for g in present.tolist():  # a few objects per copy
        member = groups == g
        shape[g] = full_shape_loss(pred[leaf_index[member]], truth[leaf_index[member]], groups[member])
    empty = torch.ones(rows, dtype=torch.bool, device=pred.device)
    empty[present] = False
    position[empty] = float("nan")
    return {"position": position, "shape": shape}


def rest_check(model, episode: Mapping[str, Any], steps: int,
               limits: StabilityLimits = StabilityLimits()) -> dict[str, float | bool] | None:
    """:func:`hrn_pyg.sim.stability.stability_report` of ``steps`` force-free steps of ``model`` from
    the last state of ``episode``; None when pybullet's objects are not all at rest there
    (:func:`hrn_pyg.evaluate.rest.objects_at_rest`)."""
    truth = torch.as_tensor(episode["positions"], dtype=torch.float32)
    obj = torch.as_tensor(episode["leaf_object"], dtype=torch.long)
    count = int(obj.max()) + 1
    if not bool(objects_at_rest(truth, obj, torch.ones_like(obj, dtype=torch.bool), count).all()):
        return None
    graph = episode_state(episode, start=truth.shape[0] - 2, steps=1)
    del graph[NODE].pos_seq, graph[NODE].force_seq
    with torch.no_grad():
        try:
            return stability_report(rollout(model, graph, steps, sleep=None), graph, settle=0, limits=limits)
        except ValueError as exc:  # left the finite numbers
            return {"finite": False, "passes_check": False, "holds": False, "error": str(exc)}
