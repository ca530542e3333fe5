"""Mesh voxelisation: the one path from a trimesh mesh to leaf particles.

A rigid body's leaves are the filled voxel centres of its mesh; a soft body's are the same
centres as the nodes of a tetrahedral mesh (:func:`lattice_tetrahedra`,
:func:`write_tetrahedral_vtk`); a cloth is a one-layer lattice (:func:`grid_sheet`). The grid
runs through the mesh's lower corner, so a box of side ``n * pitch`` has ``n + 1`` centres per
axis, the outer ones on its faces.
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from hrn_pyg.data import kinds
from hrn_pyg.utils.files import atomic_write_text

#: Relative tolerance when snapping voxel centres to integer lattice indices (float round-off
#: from trimesh's transform is ~1e-16 of the pitch; anything above 1e-3 means "not on a lattice").
LATTICE_SNAP_TOL = 1e-3

#: :data:`hrn_pyg.data.kinds.KUHN_TETS` as an array.
KUHN_TETS = np.array(kinds.KUHN_TETS, dtype=np.int64)


def _check_mesh(mesh: trimesh.Trimesh) -> None:
    """Raise ``ValueError`` naming the first problem that makes ``mesh`` unusable as a solid."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"mesh: expected trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise ValueError("mesh: empty (no vertices or no faces)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError("mesh: vertices contain NaN or inf")
    if not mesh.is_watertight:
        raise ValueError("mesh: not watertight (cannot fill its interior)")


def voxelise(mesh: trimesh.Trimesh, pitch: float) -> np.ndarray:
    """Filled voxel centres of a closed mesh: :math:`c` is a leaf iff the voxel of side ``pitch``
    centred at :math:`c` meets the surface or lies inside it (``mesh.voxelized(pitch).fill()``).

    **Shapes** ``mesh`` watertight and finite; returns ``[L, 3]`` float64 in the mesh's frame.
    """
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(f"pitch: must be a finite number > 0, got {pitch}")
    _check_mesh(mesh)
    points = np.asarray(mesh.voxelized(pitch).fill().points, dtype=np.float64)
    if len(points) == 0:
        raise ValueError(f"mesh: no voxel at pitch {pitch} (mesh smaller than one voxel?)")
    return points


def box_mesh(extents: tuple[float, float, float] | float) -> trimesh.Trimesh:
    """Axis-aligned box centred at the origin. ``extents``: full side lengths (m)."""
    ext = np.broadcast_to(np.asarray(extents, dtype=np.float64), (3,))
    if not np.all(np.isfinite(ext)) or np.any(ext <= 0):
        raise ValueError(f"extents: must be finite and > 0, got {ext.tolist()}")
    return trimesh.creation.box(extents=ext)


def sphere_mesh(radius: float, subdivisions: int = 3) -> trimesh.Trimesh:
    """Icosphere of ``radius`` (m) centred at the origin."""
    if not np.isfinite(radius) or radius <= 0:
        raise ValueError(f"radius: must be finite and > 0, got {radius}")
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def wedge_mesh(width: float, height: float, length: float) -> trimesh.Trimesh:
    """Triangular prism, ridge along y: base from ``(-width/2, 0)`` to ``(width/2, 0)`` on ``z = 0``,
    apex ``(0, height)``, over ``y`` in ``[-length/2, length/2]``."""
    for name, value in (("width", width), ("height", height), ("length", length)):
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"{name}: must be finite and > 0, got {value}")
    h = length / 2
    tri = np.array([[-width / 2, 0.0], [width / 2, 0.0], [0.0, height]])
    vertices = np.concatenate(
        [np.column_stack([tri[:, 0], np.full(3, -h), tri[:, 1]]),
         np.column_stack([tri[:, 0], np.full(3, h), tri[:, 1]])]
    )
    faces = np.array(
        [[0, 2, 1], [3, 4, 5],  # end caps
         [0, 1, 4], [0, 4, 3],  # base
         [1, 2, 5], [1, 5, 4],  # right slope
         [2, 0, 3], [2, 3, 5]],  # left slope
        dtype=np.int64,
    )
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=True)
    mesh.fix_normals()
    return mesh


def lattice_indices(points: np.ndarray, pitch: float) -> np.ndarray:
    """Integer lattice coordinates of points on a grid of spacing ``pitch``.

    **Shapes** ``points [L, 3]`` -> ``[L, 3]`` int64, relative to the lowest point per axis.
    """
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(f"pitch: must be a finite number > 0, got {pitch}")
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points: expected a non-empty [L, 3] array, got {points.shape}")
    scaled = (points - points.min(axis=0)) / pitch
    idx = np.rint(scaled)
    if np.max(np.abs(scaled - idx)) > LATTICE_SNAP_TOL:
        raise ValueError("points: not on a lattice of the given pitch")
    return idx.astype(np.int64)


class LatticeWarning(UserWarning):
    """A lattice was changed to be simulated (cells apart from its largest piece dropped)."""


def largest_piece(cell_index: np.ndarray) -> np.ndarray:
    """Which cells belong to the largest face-connected piece of a lattice.

    **Shapes:** ``cell_index`` ``[C, 3]`` distinct integer indices; returns ``[C]`` bool.
    """
    count = len(cell_index)
    shifted = cell_index - cell_index.min(axis=0) + 1  # room for a neighbour at -1
    dims = shifted.max(axis=0) + 2
    lookup = np.full(int(np.prod(dims)), -1, dtype=np.int64)
    lookup[np.ravel_multi_index(shifted.T, dims)] = np.arange(count)
    rows, cols = [], []
    for axis in range(3):  # the face neighbour one cell up each axis
        step = np.zeros(3, dtype=np.int64)
        step[axis] = 1
        neighbour = lookup[np.ravel_multi_index((shifted + step).T, dims)]
        has = neighbour >= 0
        rows.append(np.flatnonzero(has))
        cols.append(neighbour[has])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(count, count))
    _, label = connected_components(graph, directed=False)
    return label == np.bincount(label).argmax()


def lattice_tetrahedra(points: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Tetrahedral mesh whose nodes are voxel centres: every cell with all 8 corners filled is split
    into the 6 Kuhn tetrahedra (:data:`KUHN_TETS`), each with
    :math:`\det[x_1 - x_0, x_2 - x_0, x_3 - x_0] > 0`; centres in no complete cell are dropped.

    **Shapes** ``points [L, 3]`` on a lattice of spacing ``pitch``; returns ``nodes [M, 3]``
    float64 (a subset of ``points``, in order) and ``tets [T, 4]`` int64.
    """
    idx = lattice_indices(points, pitch)
    dims = idx.max(axis=0) + 1
    flat = np.ravel_multi_index(idx.T, dims)
    lookup = np.full(int(np.prod(dims)), -1, dtype=np.int64)
    lookup[flat] = np.arange(len(idx))
    offsets = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])  # corner i+2j+4k
    corner_idx = idx[:, None, :] + offsets[None, :, :]  # [L, 8, 3], each point as a cell's corner 0
    inside = np.all(corner_idx < dims, axis=2)
    corner_flat = np.where(inside, np.ravel_multi_index(
        np.minimum(corner_idx, dims - 1).transpose(2, 0, 1), dims), 0)
    corners = np.where(inside, lookup[corner_flat], -1)  # [L, 8]
    full = np.all(corners >= 0, axis=1)
    if not np.any(full):
        raise ValueError("points: no complete lattice cell (need at least 2x2x2 voxels)")
    cells = corners[full]  # [C, 8]
    keep = largest_piece(idx[full])
    if not keep.all():
        warnings.warn(f"lattice: {int((~keep).sum())} of {len(cells)} cells are joined to its largest piece "
                      f"by no chain of shared faces and were dropped (one body is one piece)",
                      LatticeWarning, stacklevel=2)
        cells = cells[keep]
    tets = cells[:, KUHN_TETS].reshape(-1, 4)  # [6C, 4]
    used = np.unique(tets)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    nodes = np.asarray(points, dtype=np.float64)[used]
    tets = remap[tets]
    x = nodes[tets]
    det = np.linalg.det(x[:, 1:] - x[:, :1])
    tets[det < 0] = tets[det < 0][:, [0, 2, 1, 3]]
    return nodes, tets


def write_tetrahedral_vtk(path: str | os.PathLike, nodes: np.ndarray, tets: np.ndarray) -> None:
    """Write a legacy ASCII ``.vtk`` grid of tetrahedra (cell type 10), atomically.
    **Shapes** ``nodes [M, 3]``, ``tets [T, 4]`` int."""
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or not np.all(np.isfinite(nodes)):
        raise ValueError(f"nodes: expected finite [M, 3], got {nodes.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.min() < 0 or tets.max() >= len(nodes):
        raise ValueError("tets: expected [T, 4] indices into nodes")
    lines = ["# vtk DataFile Version 2.0", "hrn_pyg voxel lattice", "ASCII",
             "DATASET UNSTRUCTURED_GRID", f"POINTS {len(nodes)} double"]
    lines += [f"{a:.9g} {b:.9g} {c:.9g}" for a, b, c in nodes]
    lines.append(f"CELLS {len(tets)} {5 * len(tets)}")
    lines += [f"4 {a} {b} {c} {d}" for a, b, c, d in tets]
    lines.append(f"CELL_TYPES {len(tets)}")
    lines += ["10"] * len(tets)
    atomic_write_text(path, "\n".join(lines) + "\n")


def grid_sheet(size: float, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """A square one-layer lattice in ``z = 0`` centred at the origin (a cloth), ``n = round(size /
    pitch) + 1`` nodes a side, each square two triangles.

    **Shapes** returns ``vertices [n*n, 3]`` float64 and ``faces [2 (n-1)^2, 3]`` int64.
    """
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(f"pitch: must be a finite number > 0, got {pitch}")
    if not np.isfinite(size) or size < pitch:
        raise ValueError(f"size: must be finite and >= pitch, got {size}")
    n = int(round(size / pitch)) + 1
    coords = (np.arange(n) - (n - 1) / 2) * pitch
    gx, gy = np.meshgrid(coords, coords, indexing="ij")
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(n * n)])
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    b, c, d = a + n, a + 1, a + n + 1
    faces = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    return vertices, faces


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a Wavefront ``.obj`` (1-based face indices), atomically."""
    lines = [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in np.asarray(vertices, dtype=np.float64)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces, dtype=np.int64)]
    atomic_write_text(path, "\n".join(lines) + "\n")
