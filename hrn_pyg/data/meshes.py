r"""Meshes as they come: read, clean, size, fill with leaves, and decompose for collision.

* :func:`load_mesh` reads any file trimesh reads into one mesh, or names the problem;
* :func:`clean_mesh` merges duplicate vertices (texture seams vanish), drops degenerate and
  repeated faces, keeps every piece;
* :func:`sized_mesh` scales a mesh to longest extent ``size`` and centres its bounding box;
* :func:`solid_points` is the leaf lattice: a closed mesh filled by
  :func:`hrn_pyg.data.voxelise.voxelise`, an open one by the generalised winding number
  (:func:`winding_numbers`), inside where :math:`|w(p)| \ge \tfrac12` with

  .. math:: w(p) = \frac{1}{4\pi} \sum_{f} \Omega_f(p), \qquad
      \tan\frac{\Omega_f}{2} = \frac{a \cdot (b \times c)}
      {|a||b||c| + (a \cdot b)|c| + (b \cdot c)|a| + (c \cdot a)|b|}

  (:math:`a, b, c` the triangle's corners relative to :math:`p`); a mesh that encloses nothing
  keeps the voxels its surface passes through, with a warning;
* :func:`convex_parts` writes the convex decomposition (V-HACD) pybullet collides a concave
  rigid body with, cached by the mesh's digest.
"""

from __future__ import annotations

import hashlib
import math
import os
import warnings
from pathlib import Path

import numpy as np
import trimesh

from hrn_pyg.data.voxelise import box_mesh, sphere_mesh, voxelise, wedge_mesh
from hrn_pyg.utils.files import import_pybullet, quiet_stdout

#: primitive shapes a scene may name instead of a mesh file
PRIMITIVES = ("box", "sphere", "cylinder", "capsule", "cone", "wedge")
#: each primitive's extents ``(x, y, z)`` when it is given by its longest extent (1 m here)
PRIMITIVE_PROPORTIONS: dict[str, tuple[float, float, float]] = {
    "box": (1.0, 1.0, 1.0), "sphere": (1.0, 1.0, 1.0), "cylinder": (1.0, 1.0, 1.0), "capsule": (0.5, 0.5, 1.0),
    "cone": (1.0, 1.0, 1.0), "wedge": (1.0, 1.0, 0.5)}
#: the fewest leaves a body may have (one leaf has no shape)
MIN_LEAVES = 2
#: lattice points tested against the faces at a time by :func:`winding_numbers` (memory bound)
WINDING_CHUNK = 2**22
#: a lattice point is inside an open mesh when the winding number's magnitude reaches this
INSIDE_WINDING = 0.5
#: how much finer V-HACD's voxel resolution is made when a concave mesh comes back as one part
FINER_RESOLUTION = 4
#: an open mesh encloses a volume when some lattice point has a winding number this large (a
#: surface that bounds nothing, a sheet or a cap, stays near 0.5 even right beside itself)
ENCLOSED_WINDING = 0.75
#: the largest mesh file read (bytes; pybullet_data's duck is 0.3 MB): trimesh parses 16 MB of
#: OBJ in about a second and 150 MB, and the file's size is known before it is opened
MAX_MESH_BYTES = 16 * 2**20
#: the most faces and vertices of one mesh (the duck, the largest mesh the package's scenes and
#: tests use, has 4,212 faces and 2,277 vertices); counted before the voxeliser, the inside test
#: or pybullet sees the mesh
MAX_FACES = 100_000
MAX_VERTICES = 100_000
#: the most point-face pairs of the inside test of an open mesh (:func:`winding_numbers`; its
#: lattice cells times its faces, estimated from the bounding box before a lattice is built):
#: a few million pairs a second on one core, so at most about half a minute
MAX_INSIDE_PAIRS = 5 * 10**7


class MeshWarning(UserWarning):
    """A mesh was taken differently than it was given (e.g. replaced by its convex hull)."""


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """The mesh in ``path`` (any format trimesh reads; a scene's pieces concatenated).
    FileNotFoundError for a missing file; ValueError naming the file for one that is not a mesh, is
    empty or non-finite, or is past :data:`MAX_MESH_BYTES`, :data:`MAX_FACES` or :data:`MAX_VERTICES`
    (checked before it is processed)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    size = path.stat().st_size
    if size > MAX_MESH_BYTES:
        raise ValueError(f"{path}: a mesh file of {size} bytes, more than {MAX_MESH_BYTES}; "
                         f"simplify the mesh to at most {MAX_FACES} faces")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds for a file it cannot read
        raise ValueError(f"{path}: not a mesh trimesh can read ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: holds no triangle mesh (trimesh read a {type(mesh).__name__})")
    check_mesh(mesh, str(path))
    return mesh


def check_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> None:
    """Raise ValueError naming ``name`` if ``mesh`` has no faces, more than :data:`MAX_FACES`
    faces or :data:`MAX_VERTICES` vertices, or non-finite vertices."""
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise ValueError(f"{name}: empty mesh (no vertices or no faces)")
    for what, count, limit in (("faces", len(mesh.faces), MAX_FACES), ("vertices", len(mesh.vertices), MAX_VERTICES)):
        if count > limit:
            raise ValueError(f"{name}: a mesh of {count} {what}, more than {limit}; simplify it "
                             "(e.g. trimesh's simplify_quadric_decimation, or Blender's Decimate)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"{name}: vertices contain NaN or infinite values")


def primitive_mesh(name: str, extents: np.ndarray | None = None) -> trimesh.Trimesh:
    """The primitive ``name`` (:data:`PRIMITIVES`) at ``extents`` ``[x, y, z]`` (m; default
    :data:`PRIMITIVE_PROPORTIONS`), its bounding box centred (a wedge: its base, ridge along y).
    Round primitives take their diameter from ``x``."""
    if name not in PRIMITIVES:
        raise ValueError(f"unknown primitive {name!r}; choose from {', '.join(PRIMITIVES)}")
    x, y, z = (float(e) for e in (PRIMITIVE_PROPORTIONS[name] if extents is None else extents))
    if not all(math.isfinite(e) and e > 0 for e in (x, y, z)):
        raise ValueError(f"extents must be finite and > 0, got {[x, y, z]}")
    if name == "box":
        return box_mesh((x, y, z))
    if name == "sphere":
        return sphere_mesh(x / 2)
    if name == "wedge":
        return wedge_mesh(x, z, y)
    if name == "cylinder":
        mesh = trimesh.creation.cylinder(radius=x / 2, height=z, sections=32)
    elif name == "capsule":
        mesh = trimesh.creation.capsule(height=max(z - x, 0.0), radius=x / 2, count=(16, 16))
    else:
        mesh = trimesh.creation.cone(radius=x / 2, height=z, sections=32)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def clean_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """A copy of ``mesh`` with duplicate vertices merged by position, degenerate and repeated faces and
    unused vertices dropped; ValueError if nothing with an area is left."""
    check_mesh(mesh, name)
    out = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64),
                          faces=np.asarray(mesh.faces, dtype=np.int64), process=False)
    out.merge_vertices(merge_tex=True, merge_norm=True)
    out.update_faces(out.nondegenerate_faces())
    out.update_faces(out.unique_faces())
    out.remove_unreferenced_vertices()
    if len(out.faces) == 0 or not out.area > 0:
        raise ValueError(f"{name}: no face with an area (a degenerate mesh)")
    if out.is_watertight:
        out.fix_normals()
    return out


def sized_mesh(mesh: trimesh.Trimesh, size: float | None = None, scale: float | None = None) -> trimesh.Trimesh:
    """A copy of ``mesh`` scaled by ``scale``, or so that its longest extent is ``size`` (m), with
    its bounding box centred at the origin."""
    if (size is None) == (scale is None):
        raise ValueError("give one of size and scale")
    factor = scale if scale is not None else size
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"{'size' if scale is None else 'scale'} must be a finite number > 0, got {factor}")
    out = mesh.copy()
    out.apply_translation(-out.bounds.mean(axis=0))
    if scale is None:
        longest = float(out.extents.max())
        if not longest > 0:
            raise ValueError("mesh: zero extent, cannot be sized")
        factor = size / longest
    out.apply_scale(factor)
    return out


def winding_numbers(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """The generalised winding number of ``mesh`` at each point (module docstring).

    **Shapes:** points ``(P, 3)`` -> ``(P,)`` float64; ``F`` faces are summed in chunks of
    :data:`WINDING_CHUNK` point-face pairs.
    """
    points = np.asarray(points, dtype=np.float64)
    triangles = np.asarray(mesh.triangles, dtype=np.float64)  # [F, 3, 3]
    out = np.empty(len(points))
    step = max(1, WINDING_CHUNK // max(len(triangles), 1))
    for start in range(0, len(points), step):
        rel = triangles[None, :, :, :] - points[start:start + step, None, None, :]  # [p, F, 3, 3]
        a, b, c = rel[:, :, 0], rel[:, :, 1], rel[:, :, 2]
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        numerator = np.einsum("pfk,pfk->pf", a, np.cross(b, c))
        denominator = (la * lb * lc + np.einsum("pfk,pfk->pf", a, b) * lc
                       + np.einsum("pfk,pfk->pf", b, c) * la + np.einsum("pfk,pfk->pf", c, a) * lb)
        out[start:start + step] = np.arctan2(numerator, denominator).sum(axis=1) / (2.0 * math.pi)
    return out


def too_many_leaves(count: float, pitch: float, max_leaves: int, name: str) -> ValueError:
    """The error of a body with ``count`` leaves at ``pitch``, more than ``max_leaves``; it names
    a pitch that fits (leaf counts scale as the pitch's inverse cube)."""
    fits = pitch * (count / max_leaves) ** (1 / 3)
    return ValueError(f"{name} has about {int(count)} leaves at pitch {pitch} m, more than {max_leaves}; "
                      f"a pitch of {fits:.3g} m fits")


def leaf_estimate(mesh: trimesh.Trimesh, pitch: float) -> float:
    r"""About how many leaves ``mesh`` has at ``pitch`` before a lattice is built: its volume (closed)
    or bounding box's (open) over :math:`\text{pitch}^3`, or half its area over
    :math:`\text{pitch}^2` if more, at most its bounding box's cells."""
    extents = np.asarray(mesh.extents, dtype=np.float64)
    volume = float(mesh.volume) if mesh.is_watertight else float(np.prod(extents))
    box_cells = float(np.prod(np.floor(extents / pitch) + 1))
    return min(max(volume / pitch**3, 0.5 * float(mesh.area) / pitch**2), box_cells)


def inside_test_pairs(mesh: trimesh.Trimesh, pitch: float) -> float:
    """The point-face pairs of the inside test of an open mesh at ``pitch``: its bounding box's
    lattice cells times its faces (:func:`winding_numbers` runs over every pair)."""
    return float(np.prod(np.floor(np.asarray(mesh.extents) / pitch) + 1)) * len(mesh.faces)


def _surface_voxels(mesh: trimesh.Trimesh, pitch: float, name: str) -> trimesh.voxel.VoxelGrid:
    """``mesh.voxelized(pitch)``, its failures (trimesh's ``max_iter exceeded!`` when a face
    needs too many subdivisions) as a ValueError naming ``name``."""
    try:
        return mesh.voxelized(pitch)
    except ValueError as exc:
        raise ValueError(f"{name}: cannot be voxelised at pitch {pitch} m (trimesh: {exc}); "
                         "use a larger pitch") from None


def solid_points(mesh: trimesh.Trimesh, pitch: float, name: str = "mesh",
                 max_leaves: int | None = None) -> tuple[np.ndarray, str]:
    r"""The leaf lattice of a mesh: ``(points [L, 3], how)``, ``how`` one of ``"fill"`` (closed,
    :func:`hrn_pyg.data.voxelise.voxelise`), ``"winding"`` (open: surface voxels and points with
    :math:`|w| \ge` :data:`INSIDE_WINDING`) or ``"surface"`` (an open mesh that encloses nothing;
    a :class:`MeshWarning` says so).

    ValueError, naming a pitch that would do, when fewer than :data:`MIN_LEAVES` or more than
    ``max_leaves`` points (:func:`leaf_estimate`) are found, or when an open mesh's inside test
    exceeds :data:`MAX_INSIDE_PAIRS` pairs (:func:`inside_test_pairs`).
    """
    if not (math.isfinite(pitch) and pitch > 0):
        raise ValueError(f"pitch must be a finite number > 0, got {pitch}")
    check_mesh(mesh, name)
    if max_leaves is not None:
        estimate = leaf_estimate(mesh, pitch)
        if estimate > max_leaves:
            raise too_many_leaves(estimate, pitch, max_leaves, name)
    if mesh.is_watertight:
        how, points = "fill", _filled(mesh, pitch, name)
    else:
        pairs = inside_test_pairs(mesh, pitch)
        if pairs > MAX_INSIDE_PAIRS:
            fits = pitch * (pairs / MAX_INSIDE_PAIRS) ** (1 / 3)
            raise ValueError(f"{name} is open (it has holes), and its inside test at pitch {pitch} m would take "
                             f"{pairs:.3g} point-face pairs, more than {MAX_INSIDE_PAIRS:.3g}; close the mesh, "
                             f"simplify it, or use a pitch of about {fits:.3g} m")
        grid = _surface_voxels(mesh, pitch, name)  # the voxels the surface passes through (any mesh)
        shell = grid.matrix
        # the other cells of the box: their centres lie off the surface, where w is well defined
        cells = np.argwhere(~shell)
        winding = np.abs(winding_numbers(mesh, grid.indices_to_points(cells))) if len(cells) else np.zeros(0)
        if len(winding) and winding.max() >= ENCLOSED_WINDING:
            how = "winding"
            filled = shell.copy()
            filled[tuple(cells[winding >= INSIDE_WINDING].T)] = True
            points = grid.indices_to_points(np.argwhere(filled))
        else:
            warnings.warn(f"{name} encloses no volume at pitch {pitch} m (an open surface, or walls "
                          "thinner than a voxel): its leaves are the voxels its surface passes through",
                          MeshWarning, stacklevel=2)
            how, points = "surface", np.asarray(grid.points)
            if len(points) < MIN_LEAVES:
                raise ValueError(f"{name}: {len(points)} leaf at pitch {pitch} m, a body needs {MIN_LEAVES}")
    return np.asarray(points, dtype=np.float64), how


def _filled(mesh: trimesh.Trimesh, pitch: float, name: str) -> np.ndarray:
    try:
        points = voxelise(mesh, pitch)
    except ValueError as exc:
        if "max_iter" in str(exc):  # trimesh's answer to a face that needs too many subdivisions
            raise ValueError(f"{name}: cannot be voxelised at pitch {pitch} m (trimesh: {exc}); "
                             "use a larger pitch") from None
        points = np.zeros((0, 3))
    if len(points) < MIN_LEAVES:
        raise ValueError(f"{name}: {len(points)} leaf at pitch {pitch} m, a body needs {MIN_LEAVES}; its longest "
                         f"extent is {float(mesh.extents.max()):.4g} m: make it at least {2 * pitch:.4g} m "
                         f"long, or use a pitch of at most {float(mesh.extents.max()) / 2:.4g} m")
    return points


def mesh_digest(mesh: trimesh.Trimesh) -> str:
    """A SHA-256 of a mesh's vertices and faces (what decides its decomposition)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return digest.hexdigest()


def convex_parts(mesh: trimesh.Trimesh, cache_dir: str | os.PathLike, resolution: int = 100_000) -> Path:
    """An OBJ of the convex parts (V-HACD) pybullet collides a concave rigid ``mesh`` with, cached in
    ``cache_dir`` by digest and written atomically. A concave answer of one part is redone at
    :data:`FINER_RESOLUTION` times the resolution."""
    pybullet = import_pybullet()
    cache = Path(cache_dir)
    cache.mkdir(parents=True, exist_ok=True)
    key = f"{mesh_digest(mesh)[:24]}_r{resolution}"
    out = cache / f"{key}_parts.obj"
    if out.is_file():
        return out
    source = cache / f"{key}_{os.getpid()}_source.obj"
    partial = cache / f"{key}_{os.getpid()}_parts.obj"
    log = cache / f"{key}_{os.getpid()}.log"
    try:
        mesh.export(source)
        for attempt in (resolution, FINER_RESOLUTION * resolution):
            with quiet_stdout():
                pybullet.vhacd(str(source), str(partial), str(log), resolution=attempt)
            if not partial.is_file() or partial.stat().st_size == 0:
                raise ValueError(f"the convex decomposition of a mesh failed (see {log})")
            if part_count(partial) > 1:
                break
        os.replace(partial, out)
    finally:
        for leftover in (source, partial):
            leftover.unlink(missing_ok=True)
    log.unlink(missing_ok=True)
    return out


def part_count(path: str | os.PathLike) -> int:
    """The convex parts in a V-HACD OBJ file (one ``o`` line each)."""
    with open(path) as f:
        return sum(1 for line in f if line.startswith("o "))
