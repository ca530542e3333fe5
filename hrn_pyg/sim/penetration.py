r"""Cloth leaves inside other objects: does a cloth pass through what it falls on?

**Definition.** Every object that is not cloth (rigid, soft or static) is a set of leaves on a
cubic lattice of pitch :math:`p` in its own frame. Its *solid* is the union of the lattice cells
whose eight corners are all its leaves, each cell cut into the six Kuhn tetrahedra
(:data:`hrn_pyg.data.kinds.KUHN_TETS`, the cut pybullet's soft bodies are made of) whose
corners are leaves. At rest this is the object's voxel occupancy (a cube of side :math:`p`
around every leaf) shrunk by half a pitch; as the leaves move the solid moves with them, rigidly
with a rigid object and deformed with a soft body. A cloth leaf is *inside* at a step when it
lies in a tetrahedron of another object's solid, closed: all four barycentric coordinates
:math:`\ge -10^{-6}`. The count of a step is the number of cloth leaves inside any solid, its
share that count over the cloth leaves.

**Why this solid.** It needs only the leaves, so the model's rollout and pybullet's episode are
judged by one rule; it needs no mesh and no fit of a rigid frame (the cells are found once, from
the rest positions, and soft bodies come for free); a step costs a test of each cloth leaf
against the tetrahedra whose bounding box holds it. Shrinking by half a pitch is what keeps it
honest: a cloth resting on an object lies between the object's surface and its outermost leaf
centres (pybullet's contact keeps it on the surface, which sits up to a pitch beyond those
centres), and there it must not count.

**What it misses.** A cloth leaf less than about half a pitch into an object (2.5 cm at 5 cm) is
not counted; parts thinner than two leaves (a slab one leaf thick, a thin handle or rim) have no
cells and nothing counts there; only leaves are tested, so a sheet whose edges between leaves
cut a corner of an object counts nothing; a cloth that passes right through counts only at the
steps its leaves are inside. A soft body's cells are cut along one diagonal chosen here, which
may differ from pybullet's cut of the same cells: the solids agree at rest and differ a little
where the body is strongly deformed.

**Shapes.** ``rest [L, 3]``, ``leaf_object [L]``, ``object_material [O]`` (codes of
:data:`hrn_pyg.data.kinds.MATERIALS`) give :class:`ObjectSolids` (:func:`object_solids`);
:func:`cloth_inside` takes positions ``[T, L, 3]`` or one frame ``[L, 3]`` and gives ``[T, C]``
(or ``[C]``) bool for the ``C`` cloth leaves; :func:`cloth_inside_counts` ``[T]`` (or a 0-d)
count; :func:`inside_summary` the mean, largest and share of steps with any.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from hrn_pyg.data.io import episode_pitch
from hrn_pyg.data.kinds import CLOTH, KUHN_TETS, MATERIALS

#: the corners of each tetrahedron of a lattice cell (:data:`~hrn_pyg.data.kinds.KUHN_TETS`)
CELL_TETS = np.array(KUHN_TETS, dtype=np.int64)
#: a leaf lies in a tetrahedron when its barycentric coordinates are all at least minus this
INSIDE_TOLERANCE = 1e-6
#: how far (in pitches) a rest position may lie from its lattice point, and two leaves' distance
#: from one pitch for them to be lattice neighbours
LATTICE_TOLERANCE = 1e-2


@dataclass(frozen=True)
class ObjectSolids:
    """The solids of a scene's objects that are not cloth, and its cloth leaves.

    ``tets [K, 4]`` leaf indices of the tetrahedra (corners of full lattice cells), ``tet_object
    [K]`` the object of each; ``cloth [C]`` the indices of the cloth leaves, ``cloth_object [C]``
    their objects; ``leaves`` the scene's leaf count ``L``.
    """

    tets: Tensor
    tet_object: Tensor
    cloth: Tensor
    cloth_object: Tensor
    leaves: int

    @property
    def cloth_leaves(self) -> int:
        return int(self.cloth.numel())


def lattice_cells(points: np.ndarray, pitch: float, where: str = "object") -> np.ndarray:
    """The full lattice cells of one object's leaves at rest, as ``[C, 8]`` indices into
    ``points [P, 3]`` (corner ``i + 2 j + 4 k`` at offset ``(i, j, k)`` along the lattice axes).

    The axes are found from the leaves themselves (two neighbours one pitch apart give the first,
    a neighbour at a right angle to it the second), so any rotation of the lattice will do.
    No cells (``[0, 8]``) when no two leaves are neighbours. Raises ValueError naming ``where``
    when the leaves are not on a lattice of ``pitch``.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 8:
        return np.zeros((0, 8), dtype=np.int64)
    pairs = cKDTree(points).query_pairs((1.0 + LATTICE_TOLERANCE) * pitch, output_type="ndarray")
    offsets = (points[pairs[:, 1]] - points[pairs[:, 0]]) / pitch
    steps = offsets[np.abs(np.linalg.norm(offsets, axis=1) - 1.0) < LATTICE_TOLERANCE]
    if len(steps) == 0:
        return np.zeros((0, 8), dtype=np.int64)
    first = steps[0] / np.linalg.norm(steps[0])
    across = steps[np.abs(steps @ first) < LATTICE_TOLERANCE]
    if len(across) == 0:  # one row of leaves: no cells
        return np.zeros((0, 8), dtype=np.int64)
    second = across[0] - (across[0] @ first) * first
    second /= np.linalg.norm(second)
    axes = np.stack([first, second, np.cross(first, second)])  # rows: a right-handed frame
    coords = (points - points[0]) @ axes.T / pitch
    index = np.rint(coords)
    if np.max(np.abs(coords - index)) > LATTICE_TOLERANCE:
        raise ValueError(f"{where}: its rest leaves are not on a lattice of pitch {pitch} m")
    index = (index - index.min(axis=0)).astype(np.int64)
    dims = index.max(axis=0) + 2  # room for the corner one past the last leaf
    lookup = np.full(int(np.prod(dims)), -1, dtype=np.int64)
    lookup[np.ravel_multi_index(index.T, dims)] = np.arange(len(points))
    corner = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])
    corners = lookup[np.ravel_multi_index((index[:, None, :] + corner[None]).transpose(2, 0, 1), dims)]
    return corners[np.all(corners >= 0, axis=1)]


def object_solids(rest: Tensor, leaf_object: Tensor, object_material: Tensor, pitch: float) -> ObjectSolids:
    """The solids of every object that is not cloth (module docstring) from the leaves' rest
    positions ``rest [L, 3]`` (each object's lattice), ``leaf_object [L]`` and ``object_material
    [O]``; ``pitch`` the lattice's (m)."""
    rest = torch.as_tensor(rest)
    leaf_object = torch.as_tensor(leaf_object, dtype=torch.long)
    object_material = torch.as_tensor(object_material, dtype=torch.long)
    if rest.dim() != 2 or rest.shape[1] != 3 or rest.shape[0] == 0:
        raise ValueError(f"rest must be [L, 3] with L >= 1, got {tuple(rest.shape)}")
    if leaf_object.shape != (rest.shape[0],):
        raise ValueError(f"leaf_object must be [{rest.shape[0]}], got {tuple(leaf_object.shape)}")
    if object_material.dim() != 1 or int(leaf_object.min()) < 0 or int(leaf_object.max()) >= len(object_material):
        raise ValueError(f"leaf_object must index object_material [{len(object_material)}]")
    if object_material.numel() and not 0 <= int(object_material.min()) <= int(object_material.max()) < len(MATERIALS):
        raise ValueError(f"object_material must be codes 0..{len(MATERIALS) - 1} ({', '.join(MATERIALS)})")
    if not (math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"pitch must be a finite number > 0, got {pitch}")
    if not bool(torch.isfinite(rest).all()):
        raise ValueError("rest must be finite")
    points = rest.detach().double().cpu().numpy()
    objects = leaf_object.cpu().numpy()
    tets, owners = [], []
    for obj, material in enumerate(object_material.tolist()):
        if material == CLOTH:
            continue
        members = np.flatnonzero(objects == obj)
        cells = lattice_cells(points[members], pitch, f"object {obj} ({MATERIALS[material]})")
        if len(cells):
            tets.append(members[cells[:, CELL_TETS].reshape(-1, 4)])
            owners.append(np.full(len(cells) * len(CELL_TETS), obj))
    cloth_of_leaf = object_material[leaf_object] == CLOTH
    return ObjectSolids(
        tets=torch.from_numpy(np.concatenate(tets) if tets else np.zeros((0, 4), dtype=np.int64)),
        tet_object=torch.from_numpy(np.concatenate(owners) if owners else np.zeros(0, dtype=np.int64)),
        cloth=torch.nonzero(cloth_of_leaf).flatten(),
        cloth_object=leaf_object[cloth_of_leaf],
        leaves=int(rest.shape[0]),
    )


def episode_solids(episode: Mapping[str, Any]) -> ObjectSolids:
    """:func:`object_solids` of an episode (``hrn-pyg generate``'s arrays; rest: its first frame,
    pitch: the one its ``params`` record)."""
    pitch = episode_pitch(episode)
    if pitch is None:
        raise ValueError("the episode records no pitch (params' config.pitch)")
    return object_solids(torch.as_tensor(np.asarray(episode["positions"][0], dtype=np.float64)),
                         torch.as_tensor(np.asarray(episode["leaf_object"]), dtype=torch.long),
                         torch.as_tensor(np.asarray(episode["object_material"]), dtype=torch.long), pitch)


def tet_coordinates(corners: Tensor, point: Tensor) -> tuple[Tensor, Tensor]:
    r"""The barycentric coordinates ``[P, 4]`` of each ``point`` ``[P, 3]`` in the tetrahedron of
    its ``corners`` ``[P, 4, 3]``, and ``[P]`` bool whether it is not flattened (a flattened one
    holds nothing; its coordinates are not meaningful):

    .. math::
        q - x_0 = \sum_{k=1}^{3} b_k (x_k - x_0), \qquad b_0 = 1 - b_1 - b_2 - b_3,

    flattened when :math:`|\det E| \le 10^{-12} \prod_k \lVert x_k - x_0 \rVert`, :math:`E` the
    edges' matrix."""
    edges = corners[:, 1:] - corners[:, :1]  # [P, 3, 3], rows x_k - x_0
    usable = torch.linalg.det(edges).abs() > 1e-12 * edges.norm(dim=2).prod(dim=1)
    safe = torch.where(usable.view(-1, 1, 1), edges, torch.eye(3, dtype=edges.dtype, device=edges.device))
    b = torch.linalg.solve(safe.transpose(1, 2), (point - corners[:, 0]).unsqueeze(-1)).squeeze(-1)
    return torch.cat([1.0 - b.sum(dim=1, keepdim=True), b], dim=1), usable


def _inside_frame(x: Tensor, solids: ObjectSolids) -> Tensor:
    """``[L, 3]`` -> ``[C]`` bool: the cloth leaves inside a tetrahedron of another object."""
    inside = torch.zeros(solids.cloth_leaves, dtype=torch.bool)
    if solids.tets.numel() == 0 or solids.cloth_leaves == 0:
        return inside
    corners = x[solids.tets]  # [K, 4, 3]
    q = x[solids.cloth]  # [C, 3]
    low, high = corners.min(dim=1).values, corners.max(dim=1).values
    slack = INSIDE_TOLERANCE * (high - low).amax(dim=1, keepdim=True)
    near = ((q[:, None] >= low[None] - slack[None]) & (q[:, None] <= high[None] + slack[None])).all(dim=2)
    near &= solids.cloth_object[:, None] != solids.tet_object[None]  # never the cloth's own object
    leaf, tet = torch.nonzero(near, as_tuple=True)
    if leaf.numel() == 0:
        return inside
    bary, usable = tet_coordinates(corners[tet], q[leaf])
    hit = usable & (bary >= -INSIDE_TOLERANCE).all(dim=1)
    inside[leaf[hit]] = True
    return inside


def cloth_inside(positions: Tensor, solids: ObjectSolids) -> Tensor:
    """Which cloth leaves lie inside another object's solid: positions ``[T, L, 3]`` ->
    ``[T, C]`` bool (one frame ``[L, 3]`` -> ``[C]``), in the order of ``solids.cloth``."""
    if positions.dim() not in (2, 3) or positions.shape[-2:] != (solids.leaves, 3):
        raise ValueError(f"positions must be [T, {solids.leaves}, 3] or [{solids.leaves}, 3], "
                         f"got {tuple(positions.shape)}")
    if not bool(torch.isfinite(positions).all()):
        raise ValueError("positions must be finite")
    frames = positions.detach().double().cpu()
    if frames.dim() == 2:
        return _inside_frame(frames, solids)
    if frames.shape[0] == 0:
        return torch.zeros(0, solids.cloth_leaves, dtype=torch.bool)
    return torch.stack([_inside_frame(x, solids) for x in frames])


def cloth_inside_counts(positions: Tensor, solids: ObjectSolids) -> Tensor:
    """The number of cloth leaves inside another object's solid at each step: ``[T, L, 3]`` ->
    ``[T]`` long (one frame: a 0-d tensor)."""
    return cloth_inside(positions, solids).sum(dim=-1)


def inside_summary(counts: Tensor, cloth_leaves: int) -> dict[str, float]:
    """Of per-step counts ``[T]`` (T >= 1): ``mean`` and ``max`` leaves inside, ``mean_share``
    (the mean over the ``cloth_leaves``) and ``steps_with_any`` (the share of steps with at least
    one leaf inside)."""
    if counts.dim() != 1 or counts.numel() == 0:
        raise ValueError(f"counts must be [T] with T >= 1, got {tuple(counts.shape)}")
    if cloth_leaves < 1:
        raise ValueError(f"cloth_leaves must be >= 1, got {cloth_leaves}")
    c = counts.double()
    return {"mean": float(c.mean()), "max": int(counts.max()), "mean_share": float(c.mean() / cloth_leaves),
            "steps_with_any": float((counts > 0).double().mean())}
