"""One network pass over many copies of a scene, run as groups of copies that fit in the cache.

Once K copies' features and messages outgrow the CPU's cache, every gather and scatter streams
from memory (soft_bounce, one thread: 0.66 ms per copy and step at K = 16, 1.15 ms at K = 256).
Groups of at most :data:`MAX_NODES_PER_GROUP` nodes run the same pass each and give the same
answer, since no copy reads another's nodes. :func:`copy_groups` says where the groups are;
:func:`group_inputs` cuts the inputs and masks to one group.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import NamedTuple

import torch
from torch import Tensor

from hrn_pyg.nn.hrn import HRNInputs

#: nodes in one group of copies: soft_bounce's 198-node copies run fastest per copy in groups
#: of 8 to 16 (1.6k-3.2k nodes, about 2-4 MB of hidden features at width 128) on one CPU thread
MAX_NODES_PER_GROUP = 4096

#: the per-node fields of :class:`~hrn_pyg.nn.hrn.HRNInputs`, cut by node range
NODE_FIELDS = ("state", "prev_state", "pos", "force", "is_static", "is_root", "batch", "rest_pos")
#: the edge sets of :class:`~hrn_pyg.nn.hrn.HRNInputs`, cut by the copy of their source node
EDGE_FIELDS = ("collision", "leaf_to_ancestor", "within_siblings", "ancestor_to_descendant")


class CopyGroup(NamedTuple):
    """One group of whole copies: nodes ``[node_start, node_stop)`` and copies
    ``[copy_start, copy_stop)`` of the batched graph."""

    node_start: int
    node_stop: int
    copy_start: int
    copy_stop: int


def copy_groups(inputs: HRNInputs, max_nodes: int = MAX_NODES_PER_GROUP) -> list[CopyGroup] | None:
    """The groups of consecutive copies, each of at most ``max_nodes`` nodes (a larger copy alone);
    None where one pass is better: on an accelerator, in a fixed-shape step, with at most
    ``max_nodes`` nodes, or with ``batch`` not sorted."""
    batch = inputs.batch
    n = batch.numel()
    if batch.device.type != "cpu" or inputs.options.fixed_shape or n <= max_nodes:
        return None
    if n > 1 and bool((batch[1:] < batch[:-1]).any()):
        return None
    copies = int(batch[-1]) + 1
    ends = torch.cumsum(torch.bincount(batch, minlength=copies), 0).tolist()  # node stop of each copy
    groups: list[CopyGroup] = []
    node_start, copy_start = 0, 0
    for copy, stop in enumerate(ends):
        if stop - node_start > max_nodes and copy > copy_start:
            prev_stop = ends[copy - 1]
            groups.append(CopyGroup(node_start, prev_stop, copy_start, copy))
            node_start, copy_start = prev_stop, copy
    groups.append(CopyGroup(node_start, n, copy_start, copies))
    return groups if len(groups) > 1 else None


def edge_groups(edge_index: Tensor, groups: list[CopyGroup], by: Tensor | None = None) -> list[Tensor] | None:
    """``edge_index`` ``[2, E]`` cut into ``[2, E_g]`` per group, renumbered from the group's first
    node, in order; None when an edge joins two groups. With ``by``, the columns are per-edge values
    (``[C, E]``) cut as ``by`` is, not renumbered."""
    edges = edge_index if by is None else by
    if edges.size(1) == 0:
        return [edge_index] * len(groups)
    starts = torch.tensor([g.node_start for g in groups[1:]], dtype=torch.long, device=edges.device)
    src_group = torch.bucketize(edges[0], starts, right=True)
    if bool((src_group != torch.bucketize(edges[1], starts, right=True)).any()):
        return None
    counts = torch.bincount(src_group, minlength=len(groups)).tolist()
    if bool((src_group[1:] < src_group[:-1]).any()):  # a replicated graph's edges come in copy order
        edge_index = edge_index[:, torch.argsort(src_group, stable=True)]
    pieces = torch.split(edge_index, counts, dim=1)
    if by is not None:
        return list(pieces)
    return [piece - group.node_start for piece, group in zip(pieces, groups)]


def group_masks(masks: Mapping[str, Tensor], groups: list[CopyGroup], passes: int) -> list[dict[str, Tensor]] | None:
    """The dropout masks of each group. A mask has ``passes * copies`` rows (one block of
    ``copies`` rows per pass of a mirror average, :meth:`~hrn_pyg.nn.hrn.HRN.sample_masks`); a
    group keeps its copies' rows of every block. None when a mask has another number of rows."""
    copies = groups[-1].copy_stop
    out: list[dict[str, Tensor]] = [{} for _ in groups]
    for name, mask in masks.items():
        if mask.size(0) != passes * copies:
            return None
        blocks = mask.reshape(passes, copies, *mask.shape[1:])
        for rows, g in zip(out, groups):
            rows[name] = blocks[:, g.copy_start:g.copy_stop].reshape(-1, *mask.shape[1:])
    return out


def group_inputs(
    inputs: HRNInputs, masks: Mapping[str, Tensor], groups: list[CopyGroup], passes: int = 1
) -> list[tuple[HRNInputs, dict[str, Tensor]]] | None:
    """The network's inputs and dropout masks of each group (:func:`group_masks`); None when an
    edge joins two groups or the masks do not have a row per copy (then the pass must see the
    whole graph)."""
    per_group_masks = group_masks(masks, groups, passes)
    if per_group_masks is None:
        return None
    edges: dict[str, list[Tensor]] = {}
    for name in EDGE_FIELDS:
        cut = edge_groups(getattr(inputs, name), groups)
        if cut is None:
            return None
        edges[name] = cut
    weights: list[Tensor | None] = [None] * len(groups)
    weight = inputs.options.collision_weight
    if weight is not None:
        weights = edge_groups(weight.unsqueeze(0), groups, by=inputs.collision)
    out = []
    for i, g in enumerate(groups):
        fields: dict[str, object] = {name: edges[name][i] for name in EDGE_FIELDS}
        for name in NODE_FIELDS:
            value = getattr(inputs, name)
            fields[name] = None if value is None else value[g.node_start:g.node_stop]
        fields["batch"] = fields["batch"] - g.copy_start
        options = inputs.options
        if weight is not None:
            options = dataclasses.replace(options, collision_weight=weights[i][0])
        fields["options"] = options
        out.append((HRNInputs(**fields), per_group_masks[i]))
    return out
