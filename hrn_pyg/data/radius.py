"""Collision edges: leaf pairs of different objects closer than the collision radius.

A fixed-radius neighbour search of our own (PyG's ``radius`` needs pyg-lib or torch-cluster),
vectorised in torch on the positions' device. Up to :data:`DENSE_MAX_POINTS` points every pair
is tested (:func:`dense_collision_edges`); above, a uniform cell grid:

1. each leaf gets a cell ``c = floor((x - x_min) / h)``, ``h >= r`` (coordinates compressed per
   axis, :func:`_compress_cells`) and one int64 key of its batch copy and cell;
2. leaves are sorted by key; the occupied cells are the runs of equal keys;
3. each cell's occupied neighbours among the 27 around it come from one ``searchsorted``;
4. cell pairs holding only leaves of one and the same object are dropped;
5. the rest are expanded into leaf pairs, kept when the objects differ and
   ``|x_i - x_j|^2 < r^2``.

A per-leaf radius (scenes at different pitches in one batch) searches at the largest and keeps a
pair within its destination's radius (:func:`within_radius`).
"""

from __future__ import annotations

import torch
from torch import Tensor

#: The cell is this fraction wider than the radius, so rounding in ``(x - x_min) / h`` can
#: never put two points closer than ``r`` more than one cell apart.
CELL_MARGIN = 1e-6

#: Keys are int64; the grid (batch copies x cells per axis) must fit well below 2**63.
MAX_KEYS = 2**62

#: Up to this many points the search tests every pair (:func:`dense_collision_edges`); above,
#: the cell grid. Timed on one CPU thread (random scenes of 27-point objects, median of 5):
#: dense / grid 0.30 / 2.2 ms at 50 points, 1.9 / 4.3 ms at 200, 5.2 / 6.4 ms at 300, 7.1 / 5.4 ms
#: at 400; the dense test's memory at 256 points is under 1 MB.
DENSE_MAX_POINTS = 256

#: The 27 neighbour offsets (dx, dy, dz) in {-1, 0, 1}^3.
_OFFSETS = torch.cartesian_prod(*(torch.tensor([-1, 0, 1]),) * 3)


def _validate(leaf_pos: Tensor, leaf_object: Tensor, radius: float | Tensor, batch: Tensor | None) -> None:
    if leaf_pos.dim() != 2 or leaf_pos.shape[1] != 3:
        raise ValueError(f"leaf_pos must have shape [L, 3], got {list(leaf_pos.shape)}")
    n = leaf_pos.shape[0]
    if not leaf_pos.is_floating_point():
        raise ValueError(f"leaf_pos must be floating point, got {leaf_pos.dtype}")
    if leaf_object.shape != (n,) or leaf_object.is_floating_point():
        raise ValueError(f"leaf_object must be an integer tensor of shape [{n}], got {list(leaf_object.shape)}")
    if batch is not None and (batch.shape != (n,) or batch.is_floating_point()):
        raise ValueError(f"batch must be an integer tensor of shape [{n}], got {list(batch.shape)}")
    if isinstance(radius, Tensor):
        if radius.shape != (n,) or not radius.is_floating_point():
            raise ValueError(f"a per-leaf radius must be a float tensor of shape [{n}], got "
                             f"{radius.dtype} {list(radius.shape)}")
        if n > 0 and not bool((torch.isfinite(radius) & (radius >= 0)).all()):
            raise ValueError("a per-leaf radius must be finite and >= 0 everywhere")
    else:
        radius = float(radius)
        if not radius >= 0 or radius == float("inf"):
            raise ValueError(f"radius must be finite and >= 0, got {radius}")
    if n > 0 and not bool(torch.isfinite(leaf_pos).all()):
        raise ValueError("leaf_pos contains NaN or infinite values")


def _compress_cells(cell: Tensor) -> Tensor:
    """Renumber the occupied cell coordinates of each axis to ``0, 1, 2, ...``: a gap of one stays
    one, a larger gap becomes two, so adjacency is kept and the int64 keys cannot overflow however
    far apart the points are.

    **Shapes**: ``(L, 3)`` long -> ``(L, 3)`` long.
    """
    out = torch.empty_like(cell)
    for axis in range(3):  # three axes, not particles
        values, inverse = torch.unique(cell[:, axis], return_inverse=True)
        steps = torch.diff(values).clamp_(max=2)
        out[:, axis] = torch.cat([steps.new_zeros(1), torch.cumsum(steps, 0)])[inverse]
    return out


def dense_collision_edges(leaf_pos: Tensor, leaf_object: Tensor, radius: float,
                          batch: Tensor | None = None) -> Tensor:
    """:func:`collision_edges` by testing every pair (cheaper for a few hundred leaves): the same edges
    in the same order. **Shapes**: as :func:`collision_edges`; memory ``O(L^2)``."""
    pos = leaf_pos.detach()
    diff = pos[:, None, :] - pos[None, :, :]  # [dst, src, 3]
    near = (diff * diff).sum(dim=-1) < radius * radius
    near &= leaf_object[:, None] != leaf_object[None, :]
    if batch is not None:
        near &= batch[:, None] == batch[None, :]
    dst, src = torch.nonzero(near, as_tuple=True)  # row-major: by destination, then source
    return torch.stack([src, dst])


def squared_limit(radius: Tensor, dtype: torch.dtype) -> Tensor:
    """The per-leaf squared radius :math:`r_i^2` squared in float64 and rounded once to the positions'
    ``dtype``, as comparing with the number ``r * r`` does, so equal radii keep the same pairs bit
    for bit. **Shapes**: ``(L,)`` -> ``(L,)``."""
    r = radius.detach().to(torch.float64)
    return (r * r).to(dtype)


def within_radius(edge_index: Tensor, leaf_pos: Tensor, radius: Tensor) -> Tensor:
    r"""The edges ``j -> i`` of ``edge_index`` with :math:`\lVert x_i - x_j \rVert^2 < r_i^2` (the
    destination's radius, :func:`squared_limit`), in their order.

    **Shapes**: edge_index ``(2, E)``, leaf_pos ``(L, 3)``, radius ``(L,)``; returns ``(2, E')``.
    """
    src, dst = edge_index
    pos = leaf_pos.detach()
    diff = pos[dst] - pos[src]
    keep = (diff * diff).sum(dim=-1) < squared_limit(radius, pos.dtype)[dst]
    return edge_index[:, keep]


def _empty(device: torch.device) -> Tensor:
    return torch.empty(2, 0, dtype=torch.long, device=device)


def cell_keys(pos: Tensor, radius: float, batch: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Step 1 of the search: each point's int64 cell key (side ``h`` just above ``radius``, batch copy
    included) and the key offsets of the 27 neighbour cells.

    **Shapes**: pos ``(L, 3)`` (L >= 1), batch ``(L,)`` -> ``(L,)`` long, ``(27,)`` long.
    """
    # float64 for the cell assignment: robust for large scenes relative to the radius
    x = pos.detach().to(torch.float64)
    cell = _compress_cells(torch.floor((x - x.amin(dim=0)) / (radius * (1.0 + CELL_MARGIN))).long()) + 1
    dims = (cell.amax(dim=0) + 2).tolist()  # +1 shift and +1 margin: neighbours never wrap
    n_copies = 1 if batch is None else int(batch.max()) + 1
    if n_copies * dims[0] * dims[1] * dims[2] >= MAX_KEYS:
        raise ValueError(f"radius {radius} is too small for the extent of the scene (cell grid overflows)")
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    if batch is not None:
        key = key + batch.long() * (dims[0] * dims[1] * dims[2])
    offsets = _OFFSETS.to(pos.device)
    return key, (offsets[:, 0] * dims[1] + offsets[:, 1]) * dims[2] + offsets[:, 2]


def collision_edges(
    leaf_pos: Tensor,
    leaf_object: Tensor,
    radius: float | Tensor,
    batch: Tensor | None = None,
) -> Tensor:
    r"""All ordered leaf pairs of different objects of one batch copy closer than ``radius``.

    .. math::
        \mathcal{E}_C = \{(j, i) : o_j \ne o_i,\ b_j = b_i,\ \lVert x_i - x_j \rVert^2 < r_i^2\}

    Both directions, no self loops, sorted by destination then source; no gradient.

    Args:
        leaf_pos: leaf positions.
        leaf_object: object index of each leaf (within its batch copy).
        radius: ``r`` (strict ``<``; 0 gives no edges), or a float tensor ``(L,)`` of per-leaf
            radii, equal within a batch copy (:func:`within_radius`).
        batch: batch copy of each leaf; all zeros if None.

    Returns:
        ``edge_index``, row 0 the source ``j``, row 1 the destination ``i`` (leaf rows).

    **Shapes**: leaf_pos ``(L, 3)``, leaf_object ``(L,)``, batch ``(L,)``;
    returns ``(2, |E_C|)``.
    """
    _validate(leaf_pos, leaf_object, radius, batch)
    if isinstance(radius, Tensor):
        if leaf_pos.shape[0] < 2:
            return _empty(leaf_pos.device)
        widest = float(radius.max())
        if widest == 0.0:
            return _empty(leaf_pos.device)
        return within_radius(collision_edges(leaf_pos, leaf_object, widest, batch), leaf_pos, radius)
    device = leaf_pos.device
    n = leaf_pos.shape[0]
    radius = float(radius)
    if n < 2 or radius == 0.0:
        return _empty(device)
    if n <= DENSE_MAX_POINTS:
        return dense_collision_edges(leaf_pos, leaf_object, radius, batch)

    key, offset_key = cell_keys(leaf_pos, radius, batch)
    sorted_key, order = torch.sort(key, stable=True)

    # occupied cells: their keys, point runs in sorted order, and the objects they hold
    cell_key, cell_count = torch.unique_consecutive(sorted_key, return_counts=True)
    n_cells = cell_key.shape[0]
    cell_start = torch.cumsum(cell_count, 0) - cell_count
    point_cell = torch.arange(n_cells, device=device).repeat_interleave(cell_count, output_size=n)
    sorted_object = leaf_object.long()[order]
    obj_min = torch.full((n_cells,), torch.iinfo(torch.long).max, device=device)
    obj_min = obj_min.scatter_reduce(0, point_cell, sorted_object, reduce="amin")
    obj_max = torch.full((n_cells,), torch.iinfo(torch.long).min, device=device)
    obj_max = obj_max.scatter_reduce(0, point_cell, sorted_object, reduce="amax")

    # occupied neighbour cells of every occupied cell
    neighbour_key = (cell_key[:, None] + offset_key[None, :]).reshape(-1)  # [C * 27]
    found_at = torch.searchsorted(cell_key, neighbour_key).clamp_(max=n_cells - 1)
    found = cell_key[found_at] == neighbour_key
    cell_u = torch.arange(n_cells, device=device).repeat_interleave(_OFFSETS.shape[0])[found]
    cell_v = found_at[found]
    # skip cell pairs that hold one and the same object only (the inside of a body)
    single = obj_min == obj_max
    same = single[cell_u] & single[cell_v] & (obj_min[cell_u] == obj_min[cell_v])
    cell_u, cell_v = cell_u[~same], cell_v[~same]

    # expand each remaining cell pair (u, v) into its point pairs: dst in u, src in v
    count_u, count_v = cell_count[cell_u], cell_count[cell_v]
    n_pairs = count_u * count_v
    total = int(n_pairs.sum())
    if total == 0:
        return _empty(device)
    pair = torch.arange(cell_u.shape[0], device=device).repeat_interleave(n_pairs, output_size=total)
    local = torch.arange(total, device=device) - (torch.cumsum(n_pairs, 0) - n_pairs)[pair]
    width = count_v[pair]
    dst = order[cell_start[cell_u][pair] + torch.div(local, width, rounding_mode="floor")]
    src = order[cell_start[cell_v][pair] + local % width]

    diff = leaf_pos.detach()[dst] - leaf_pos.detach()[src]
    keep = (leaf_object[src] != leaf_object[dst]) & ((diff * diff).sum(dim=-1) < radius * radius)
    src, dst = src[keep], dst[keep]
    # canonical order: by destination, then source
    perm = torch.argsort(dst * n + src)
    return torch.stack([src[perm], dst[perm]])

