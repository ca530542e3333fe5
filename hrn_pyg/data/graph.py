"""The hierarchical particle graph as PyG ``HeteroData`` (see docs/architecture.md).

One node type, ``particle``, holds leaves and ancestors. The static part (node attributes and
the hierarchy's edges) is built once per scene by :func:`build_structure`; the dynamic part
(``pos``, ``prev_pos``, ``prev_prev_pos``, ``force``, ``collision`` edges) by :func:`set_state`.
Ancestor states are derived from the leaves (:func:`leaf_to_ancestor_mean`). :func:`replicate`
batches K copies; everything here works on batched graphs. A graph carries its voxel pitch (m)
as the graph-level ``pitch`` ``(B,)`` float64 (:func:`node_pitch`).
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Batch, HeteroData

from hrn_pyg.data.io import episode_pitch
from hrn_pyg.data.kinds import CLOTH, HISTORY, MATERIALS, RIGID, SOFT, STATIC  # noqa: F401  the material codes, here too
from hrn_pyg.data.radius import collision_edges

#: The only node type: leaves and their ancestors.
NODE = "particle"
#: Edge types, ``(source type, name, destination type)``; row 0 of edge_index is the source.
CHILD_TO_PARENT = (NODE, "child_to_parent", NODE)
COLLISION = (NODE, "collision", NODE)
LEAF_TO_ANCESTOR = (NODE, "leaf_to_ancestor", NODE)
WITHIN_SIBLINGS = (NODE, "within_siblings", NODE)
ANCESTOR_TO_DESCENDANT = (NODE, "ancestor_to_descendant", NODE)
#: The graph-level attribute holding the voxel pitch (m) the scene was made at, ``(B,)`` float64.
PITCH = "pitch"


def _sort_edges(src: Tensor, dst: Tensor, num_nodes: int) -> Tensor:
    """Stack ``(src, dst)`` into an edge_index sorted by destination, then source."""
    perm = torch.argsort(dst * num_nodes + src)
    return torch.stack([src[perm], dst[perm]])


def _ancestor_pairs(parent: Tensor) -> tuple[Tensor, Tensor]:
    """All (descendant, ancestor) pairs, one parent lookup per tree level; ValueError on a cycle."""
    num_nodes = parent.shape[0]
    node = torch.nonzero(parent >= 0).flatten()
    anc = parent[node]
    nodes, ancestors = [], []
    for _ in range(num_nodes + 1):  # loop over depth, not over nodes
        if node.numel() == 0:
            break
        nodes.append(node)
        ancestors.append(anc)
        up = parent[anc]
        keep = up >= 0
        node, anc = node[keep], up[keep]
    else:
        raise ValueError("parent contains a cycle")
    if not nodes:
        empty = parent.new_empty(0)
        return empty, empty
    return torch.cat(nodes), torch.cat(ancestors)


def _sibling_pairs(parent: Tensor) -> tuple[Tensor, Tensor]:
    """All ordered pairs ``(j, i)``, ``j != i``, of children of one parent."""
    num_nodes = parent.shape[0]
    child = torch.nonzero(parent >= 0).flatten()
    p, perm = torch.sort(parent[child], stable=True)
    child = child[perm]
    count = torch.bincount(p, minlength=num_nodes)
    group_start = torch.cumsum(count, 0) - count
    size = count[p]  # size of each child's sibling group (itself included)
    total = int(size.sum())
    dst = child.repeat_interleave(size, output_size=total)
    within = torch.arange(total, device=parent.device) - (torch.cumsum(size, 0) - size).repeat_interleave(
        size, output_size=total
    )
    src = child[group_start[p].repeat_interleave(size, output_size=total) + within]
    keep = src != dst
    return src[keep], dst[keep]


def _validate_structure(
    parent: Tensor,
    leaf_mass: Tensor,
    leaf_object: Tensor,
    object_material: Tensor,
    object_stiffness: Tensor,
) -> None:
    if parent.dim() != 1 or parent.is_floating_point():
        raise ValueError(f"parent must be a 1-D integer tensor, got {list(parent.shape)} {parent.dtype}")
    if leaf_mass.dim() != 1 or leaf_mass.shape[0] < 1:
        raise ValueError(f"leaf_mass must have shape [L>=1], got {list(leaf_mass.shape)}")
    n_leaves, num_nodes = leaf_mass.shape[0], parent.shape[0]
    if num_nodes <= n_leaves:
        raise ValueError(f"parent has {num_nodes} nodes, needs more than the {n_leaves} leaves (one root at least)")
    if not bool(torch.isfinite(leaf_mass).all()) or bool((leaf_mass <= 0).any()):
        raise ValueError("leaf_mass must be finite and strictly positive")
    if leaf_object.shape != (n_leaves,) or leaf_object.is_floating_point():
        raise ValueError(f"leaf_object must be an integer tensor of shape [{n_leaves}], got {list(leaf_object.shape)}")
    if object_material.dim() != 1 or object_material.is_floating_point():
        raise ValueError(f"object_material must be a 1-D integer tensor, got {list(object_material.shape)}")
    n_objects = object_material.shape[0]
    if object_stiffness.shape != (n_objects,):
        raise ValueError(f"object_stiffness must have shape [{n_objects}], got {list(object_stiffness.shape)}")
    if bool((leaf_object < 0).any()) or bool((leaf_object >= n_objects).any()):
        raise ValueError(f"leaf_object must lie in 0..{n_objects - 1}")
    if bool((object_material < 0).any()) or bool((object_material >= len(MATERIALS)).any()):
        raise ValueError(f"object_material must lie in 0..{len(MATERIALS) - 1} {MATERIALS}")
    if not bool(torch.isfinite(object_stiffness).all()):
        raise ValueError("object_stiffness contains NaN or infinite values")
    if bool((parent < -1).any()) or bool((parent >= num_nodes).any()):
        raise ValueError(f"parent must lie in -1..{num_nodes - 1}")
    if bool((parent[:n_leaves] < n_leaves).any()):
        raise ValueError("every leaf needs a parent, and it must be an ancestor node (index >= L)")
    if bool(((parent[n_leaves:] >= 0) & (parent[n_leaves:] < n_leaves)).any()):
        raise ValueError("an ancestor's parent must be an ancestor node (index >= L) or -1")


def build_structure(
    parent: Tensor,
    leaf_mass: Tensor,
    leaf_object: Tensor,
    object_material: Tensor,
    object_stiffness: Tensor,
    rest_pos: Tensor | None = None,
    pitch: float | None = None,
) -> HeteroData:
    r"""Static part of the scene graph: node attributes and the hierarchy's edge sets.

    With :math:`\mathcal{A}(i)` the ancestors of node ``i`` and :math:`\mathcal{L}(a)` the leaf
    descendants of ancestor ``a``:

    .. math::
        m_a = \sum_{l \in \mathcal{L}(a)} m_l, \qquad
        \mathrm{depth}_i = |\mathcal{A}(i)|, \qquad
        \mathrm{object}_a = \mathrm{object}_l \ (l \in \mathcal{L}(a))

    Edges: ``child_to_parent`` ``i -> parent(i)``; ``leaf_to_ancestor`` ``i -> a`` for every
    ``a in A(i)`` (sorted by (dst, src)); ``ancestor_to_descendant`` its exact reverse;
    ``within_siblings`` ``j -> i`` for distinct children of one parent; ``collision`` empty.

    Args:
        parent: parent of each node (leaves ``0..L-1`` first, roots ``-1``;
            :func:`hrn_pyg.data.hierarchy.build_hierarchy`).
        leaf_mass: leaf masses, > 0.
        leaf_object: object of each leaf, ``0..O-1``.
        object_material: material column of each object (:data:`MATERIALS`).
        object_stiffness: stiffness of each object.
        rest_pos: leaf positions of the rest shape, stored as ``rest_pos (N, 3)`` with ancestors.
        pitch: the voxel pitch (m), stored as the graph-level ``pitch (1,)`` float64.

    Returns:
        HeteroData with ``graph['particle']``: ``mass (N,1)``, ``material (N,4)`` one-hot,
        ``stiffness (N,1)``, ``object (N,)``, ``depth (N,)``, ``is_leaf``, ``is_root``,
        ``is_static`` ``(N,)`` bool, and the five edge types.

    **Shapes**: parent ``(N,)``, leaf_mass ``(L,)``, leaf_object ``(L,)``,
    object_material ``(O,)``, object_stiffness ``(O,)``.
    """
    _validate_structure(parent, leaf_mass, leaf_object, object_material, object_stiffness)
    device = parent.device
    parent = parent.long()
    leaf_object = leaf_object.long().to(device)
    n_leaves, num_nodes = leaf_mass.shape[0], parent.shape[0]
    dtype = leaf_mass.dtype if leaf_mass.is_floating_point() else torch.get_default_dtype()
    leaf_mass = leaf_mass.to(device=device, dtype=dtype)

    desc, anc = _ancestor_pairs(parent)
    depth = torch.bincount(desc, minlength=num_nodes)

    # leaf -> ancestor pairs give each ancestor its mass and object
    from_leaf = desc < n_leaves
    leaf, leaf_anc = desc[from_leaf], anc[from_leaf]
    n_leaf_desc = torch.bincount(leaf_anc, minlength=num_nodes)
    if bool((n_leaf_desc[n_leaves:] == 0).any()):
        raise ValueError("every ancestor needs at least one leaf below it")
    mass = torch.zeros(num_nodes, dtype=dtype, device=device).index_add(0, leaf_anc, leaf_mass[leaf])
    mass[:n_leaves] = leaf_mass
    obj_min = torch.full((num_nodes,), n_leaves + 1, dtype=torch.long, device=device)
    obj_max = torch.full((num_nodes,), -1, dtype=torch.long, device=device)
    obj_min = obj_min.scatter_reduce(0, leaf_anc, leaf_object[leaf], reduce="amin")
    obj_max = obj_max.scatter_reduce(0, leaf_anc, leaf_object[leaf], reduce="amax")
    if bool((obj_min[n_leaves:] != obj_max[n_leaves:]).any()):
        raise ValueError("an ancestor has leaves of more than one object")
    obj = torch.cat([leaf_object, obj_min[n_leaves:]])

    material_index = object_material.long().to(device)[obj]
    graph = HeteroData()
    store = graph[NODE]
    store.num_nodes = num_nodes
    store.mass = mass[:, None]
    store.material = torch.nn.functional.one_hot(material_index, len(MATERIALS)).to(dtype)
    store.stiffness = object_stiffness.to(device=device, dtype=dtype)[obj][:, None]
    store.object = obj
    store.depth = depth
    store.is_leaf = torch.arange(num_nodes, device=device) < n_leaves
    store.is_root = parent < 0
    store.is_static = material_index == STATIC

    child = torch.nonzero(parent >= 0).flatten()
    graph[CHILD_TO_PARENT].edge_index = _sort_edges(child, parent[child], num_nodes)
    l2a = _sort_edges(desc, anc, num_nodes)
    graph[LEAF_TO_ANCESTOR].edge_index = l2a
    graph[ANCESTOR_TO_DESCENDANT].edge_index = l2a.flip(0)
    graph[WITHIN_SIBLINGS].edge_index = _sort_edges(*_sibling_pairs(parent), num_nodes)
    graph[COLLISION].edge_index = torch.empty(2, 0, dtype=torch.long, device=device)
    if rest_pos is not None:
        if rest_pos.shape != (n_leaves, 3) or not bool(torch.isfinite(rest_pos).all()):
            raise ValueError(f"rest_pos must be finite with shape [{n_leaves}, 3], got {list(rest_pos.shape)}")
        store.rest_pos = leaf_to_ancestor_mean(_to_nodes("rest_pos", rest_pos.to(device=device, dtype=dtype), graph), graph)
    if pitch is not None:
        set_pitch(graph, pitch)
    return graph


def episode_structure(episode: Mapping[str, Any], pitch: float | None = None) -> HeteroData:
    """The static graph of an episode's scene: :func:`build_structure` of its hierarchy, masses,
    objects and materials, with ``positions[0]`` as the rest shape and its pitch
    (:func:`~hrn_pyg.data.io.episode_pitch`). The one builder of a start graph (dataset windows,
    sampling, the RL pool). Arrays may be numpy or torch.

    **Shapes:** ``positions (S+1, L, 3)``, ``hierarchy_parent (N,)`` -> a graph of ``N`` nodes.
    """

    def tensor(key: str, dtype: torch.dtype) -> Tensor:
        value = episode[key]
        return (value if isinstance(value, Tensor) else torch.as_tensor(np.asarray(value))).to(dtype)

    return build_structure(
        tensor("hierarchy_parent", torch.long),
        tensor("leaf_mass", torch.float32),
        tensor("leaf_object", torch.long),
        tensor("object_material", torch.long),
        tensor("object_stiffness", torch.float32),
        rest_pos=tensor("positions", torch.float32)[0],
        pitch=episode_pitch(episode) if pitch is None else pitch,
    )


def set_pitch(graph: HeteroData, pitch: float) -> HeteroData:
    """Record the voxel pitch (m, finite and > 0) of a one-scene graph as ``graph.pitch``
    ``(1,)`` float64, in place; returns ``graph``."""
    value = float(pitch)
    if not 0.0 < value < float("inf"):
        raise ValueError(f"pitch must be a finite number > 0 (metres), got {pitch}")
    device = graph[NODE].is_leaf.device if "is_leaf" in graph[NODE] else None
    setattr(graph, PITCH, torch.tensor([value], dtype=torch.float64, device=device))
    return graph


def graph_pitch(graph: HeteroData) -> Tensor | None:
    """The voxel pitch of each graph of a (batched) graph, ``(B,)`` float64 (metres), or None
    when the graph carries none."""
    return getattr(graph, PITCH) if PITCH in graph else None


def node_pitch(graph: HeteroData) -> Tensor:
    """The voxel pitch (m) of every node's graph, :math:`p_{b(i)}` with :math:`b(i)` its batch copy;
    ValueError when the graph has none (:func:`set_pitch`).

    **Shapes**: ``pitch (B,)``, ``batch (N,)`` -> ``(N,)`` float64.
    """
    pitch = graph_pitch(graph)
    if pitch is None:
        raise ValueError("the graph carries no voxel pitch (graph.pitch): build it with "
                         "build_structure(..., pitch=...) or set_pitch")
    store = graph[NODE]
    n = store.num_nodes
    if pitch.numel() == 1:
        return pitch.reshape(1).expand(n)
    if "batch" not in store:
        raise ValueError(f"graph.pitch holds {pitch.numel()} values but the nodes have no batch vector")
    return pitch.index_select(0, store.batch)


def object_span(leaf_object: Tensor) -> int:
    """The number of object ids in use, ``max + 1`` (1 when there are none; one host read)."""
    return int(leaf_object.max()) + 1 if leaf_object.numel() else 1


def copy_object_ids(copy: Tensor, obj: Tensor, span: int) -> Tensor:
    """One id per (batch copy, object) pair: ``copy * span + obj``, ``span`` from :func:`object_span`
    (objects are numbered per copy, so the copies of one object need ids of their own)."""
    return copy * span + obj


def object_centres(positions: Tensor, leaf_object: Tensor, num_objects: int,
                   leaf_mass: Tensor | None = None) -> Tensor:
    r"""Mass-weighted centre of each object's leaves, the position of its hierarchy root.

    .. math:: r_o = \sum_{l \in o} m_l x_l \Big/ \sum_{l \in o} m_l

    ``leaf_mass`` ``(L,)`` or ``(*, L)``; None: equal masses. An object without leaves gets zeros.

    **Shapes:** positions ``(*, L, 3)``, leaf_object ``(L,)`` long; returns ``(*, num_objects, 3)``.
    """
    weight = torch.ones_like(positions[..., 0]) if leaf_mass is None else leaf_mass.to(positions.dtype)
    weight = weight.expand(positions.shape[:-1])
    total = positions.new_zeros(*weight.shape[:-1], num_objects).index_add(-1, leaf_object, weight)
    summed = positions.new_zeros(*positions.shape[:-2], num_objects, 3).index_add(
        -2, leaf_object, positions * weight[..., None])
    return summed / total.clamp_min(torch.finfo(positions.dtype).tiny)[..., None]


def leaf_to_ancestor_mean(values: Tensor, graph: HeteroData) -> Tensor:
    r"""Keep leaf rows, replace every ancestor row by the mass-weighted mean of its leaves.

    .. math::
        v_a = \frac{1}{m_a} \sum_{l \in \mathcal{L}(a)} m_l\, v_l

    One scatter over the ``leaf_to_ancestor`` edges (weight 0 from ancestors; no host sync).

    **Shapes**: values ``(..., N, D)``; returns ``(..., N, D)``.
    """
    store = graph[NODE]
    num_nodes = store.num_nodes
    if values.dim() < 2 or values.shape[-2] != num_nodes:
        raise ValueError(f"values must have shape [..., {num_nodes}, D], got {list(values.shape)}")
    src, dst = graph[LEAF_TO_ANCESTOR].edge_index
    mass = store.mass[:, 0].to(values.dtype)
    weight = mass[src] * store.is_leaf[src].to(values.dtype) / mass[dst]  # [E]
    contrib = values.index_select(-2, src) * weight[:, None]
    agg = torch.zeros_like(values).index_add(-2, dst, contrib)
    return torch.where(store.is_leaf[:, None], values, agg)


def _to_nodes(name: str, value: Tensor, graph: HeteroData) -> Tensor:
    """``(N, 3)`` node tensor from an ``(N, 3)`` node or ``(L, 3)`` leaf tensor (ancestors 0)."""
    store = graph[NODE]
    num_nodes = store.num_nodes
    if value.dim() != 2 or value.shape[1] != 3:
        raise ValueError(f"{name} must have shape [N, 3] or [L, 3], got {list(value.shape)}")
    if value.shape[0] == num_nodes:
        return value
    leaf_index = torch.nonzero(store.is_leaf).flatten()
    if value.shape[0] != leaf_index.shape[0]:
        raise ValueError(
            f"{name} has {value.shape[0]} rows; expected {num_nodes} nodes or {leaf_index.shape[0]} leaves"
        )
    return value.new_zeros(num_nodes, 3).index_copy(0, leaf_index, value)


def set_state(
    graph: HeteroData,
    prev_prev_pos: Tensor,
    prev_pos: Tensor,
    pos: Tensor,
    *,
    radius: float | Tensor | None,
    force: Tensor | None = None,
) -> HeteroData:
    """A shallow copy of ``graph`` carrying the state ``x_{t-2}, x_{t-1}, x_t`` and its collisions.

    Positions for all nodes ``(N, 3)`` (ancestor rows ignored) or the leaves only ``(L, 3)``;
    ancestors derived; ``force`` zero on ancestors; ``collision`` edges of the leaves at ``x_t``
    (:func:`leaf_collision_edges`; ``radius=None``: none). Static tensors are shared.

    **Shapes**: positions and force ``(N, 3)`` or ``(L, 3)``; sets ``pos``, ``prev_pos``,
    ``prev_prev_pos``, ``force`` ``(N, 3)`` and ``collision`` ``(2, |E_C|)``.
    """
    for name, value in (("prev_prev_pos", prev_prev_pos), ("prev_pos", prev_pos), ("pos", pos), ("force", force)):
        if value is not None and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"set_state: {name} contains NaN or infinite values")
    out = copy.copy(graph)
    store = out[NODE]
    is_leaf = store.is_leaf[:, None]
    for name, value in (("prev_prev_pos", prev_prev_pos), ("prev_pos", prev_pos), ("pos", pos)):
        store[name] = leaf_to_ancestor_mean(_to_nodes(name, value, out), out)
    if force is None:
        store.force = torch.zeros_like(store.pos)
    else:
        store.force = torch.where(is_leaf, _to_nodes("force", force, out), 0.0)

    out[COLLISION].edge_index = leaf_collision_edges(out, store.pos, radius)
    return out


def leaf_collision_edges(graph: HeteroData, pos: Tensor, radius: float | Tensor | None) -> Tensor:
    """Collision edges (node indices) of the leaves at ``pos`` (:func:`hrn_pyg.data.radius.collision_edges`),
    per batch copy; none when ``radius`` is None or 0. ``radius``: a number, or one per graph
    (:func:`hrn_pyg.nn.pitch.collision_radius_of`).

    **Shapes**: pos ``(N, 3)``, radius ``(B,)`` or a number; returns ``(2, |E_C|)``.
    """
    store = graph[NODE]
    if radius is None or (not isinstance(radius, Tensor) and radius <= 0):
        return torch.empty(2, 0, dtype=torch.long, device=pos.device)
    leaf_index = torch.nonzero(store.is_leaf).flatten()
    batch = store.batch[leaf_index] if "batch" in store else None
    if isinstance(radius, Tensor):
        radius = per_node_radius(graph, radius).index_select(0, leaf_index)
    return leaf_index[collision_edges(pos[leaf_index], store.object[leaf_index], radius, batch)]


def per_node_radius(graph: HeteroData, radius: Tensor) -> Tensor:
    """Every node's radius ``(N,)`` from one radius per graph ``(B,)`` (a single value is every
    node's), looked up by ``graph['particle'].batch``."""
    store = graph[NODE]
    radius = radius.reshape(-1)
    if radius.numel() == 1:
        return radius.expand(store.num_nodes)
    if "batch" not in store:
        raise ValueError(f"{radius.numel()} radii given for a graph without a batch vector")
    return radius.index_select(0, store.batch)


def replicate(graph: HeteroData, k: int) -> HeteroData:
    """``k`` copies of one scene graph as one batched graph (``graph['particle'].batch`` = copy).

    **Shapes**: ``N`` nodes -> ``k N`` nodes; every edge set ``E`` -> ``k E``.
    """
    if int(k) < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    return Batch.from_data_list([graph] * int(k))
