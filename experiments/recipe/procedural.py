r"""Procedural shapes for training: random convex hulls and concave unions of boxes, as mesh files.

Every shape is drawn from a :class:`numpy.random.Generator`, centred on its bounding box with
longest extent 1 m (a scene file scales it by ``size``). The kinds (:data:`KINDS`), in the
frame before that scaling:

* ``random_hull``: the hull of :math:`n \in [8, 30]` points uniform in an ellipsoid of
  semi-axes :math:`a_i \sim U[1, 3]`, :math:`p = r^{1/3}\, (a \odot u)` with :math:`u` uniform
  on the unit sphere and :math:`r \sim U[0, 1]`;
* ``l_shape``: a bar of length 1 (height :math:`t_1`) with an upright bar (thickness
  :math:`t_2`, height :math:`h`) on one end; :math:`t_1, t_2 \in [0.15, 0.35]`,
  :math:`h \in [0.45, 1]`, depth :math:`[0.2, 0.6]`;
* ``t_shape``: a top bar of length 1 on a stem of width :math:`[0.15, 0.3]` and height
  :math:`[0.35, 0.9]`, off the middle by up to a quarter of the bar;
* ``cross``: two bars crossing in the ground plane, lengths 1 and :math:`[0.5, 1]`, widths
  :math:`[0.15, 0.3]`, heights :math:`[0.12, 0.4]`;
* ``cup``: a floor and four walls, width 1, depth :math:`[0.6, 1]`, height :math:`[0.4, 1]`,
  walls :math:`[0.12, 0.18]` thick;
* ``ring``: :math:`n \in \{4, 5, 6\}` straight segments between the apothems
  :math:`0.5 \mp b/2`, :math:`b \in [0.2, 0.36]`, height :math:`[0.12, 0.3]`; segment :math:`k`
  is the prism :math:`|x| \le y \tan(\pi/n) + \delta`, :math:`|y - 0.5| \le b/2`, turned by
  :math:`2\pi k/n` about :math:`z` (:math:`\delta` = :data:`OVERLAP`).

A concave shape is the concatenation of closed convex pieces overlapping by :data:`OVERLAP`
(never sharing an edge), so trimesh reads the union as closed with no boolean engine;
:func:`union_volume` measures it.

``python -m experiments.recipe.procedural --out DIR --per-kind N --seed S`` writes
``DIR/<kind>_<i:03d>.obj`` (:func:`make_shape` ``(kind, S + i)``) and ``DIR/index.json``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull
from trimesh.exchange.obj import export_obj

from hrn_pyg.data.meshes import clean_mesh, load_mesh, sized_mesh
from hrn_pyg.data.voxelise import box_mesh
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

#: how far (unit frame) the pieces of a union reach into each other, so no two share an edge
OVERLAP = 0.02
#: grid cells along the longest extent when :func:`union_volume` measures a union
VOLUME_CELLS = 100
#: digits of the vertex coordinates in the written OBJ files
OBJ_DIGITS = 8


def _box(lower: Sequence[float], upper: Sequence[float]) -> trimesh.Trimesh:
    """The closed axis-aligned box between two corners."""
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    mesh = box_mesh(tuple(hi - lo))
    mesh.apply_translation((lo + hi) / 2)
    return mesh


def _unit(pieces: Sequence[trimesh.Trimesh]) -> trimesh.Trimesh:
    """The pieces as one mesh, centred on its bounding box with longest extent 1."""
    return sized_mesh(trimesh.util.concatenate(list(pieces)), size=1.0)


def random_hull(rng: np.random.Generator) -> trimesh.Trimesh:
    """The convex hull of 8-30 points uniform in an ellipsoid of semi-axes in [1, 3]."""
    count = int(rng.integers(8, 31))
    axes = rng.uniform(1.0, 3.0, size=3)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(0.0, 1.0, size=(count, 1)) ** (1.0 / 3.0)
    hull = trimesh.Trimesh(vertices=radii * directions * axes, process=False).convex_hull
    return _unit([hull])


def l_shape(rng: np.random.Generator) -> trimesh.Trimesh:
    """A bar along x with an upright bar standing on one end (it stands at least 0.1 above the bar)."""
    t1, t2 = rng.uniform(0.15, 0.35, size=2)
    height = rng.uniform(0.45, 1.0)
    depth = rng.uniform(0.2, 0.6)
    y = depth / 2
    base = _box((-0.5, -y, 0.0), (0.5, y, t1))
    upright = _box((-0.5, -y, t1 - OVERLAP), (-0.5 + t2, y, height))
    return _unit([base, upright])


def t_shape(rng: np.random.Generator) -> trimesh.Trimesh:
    """A bar along x on top of a stem, the stem up to a quarter of the bar off its middle."""
    thickness = rng.uniform(0.15, 0.3)
    width = rng.uniform(0.15, 0.3)
    height = rng.uniform(0.35, 0.9)
    depth = rng.uniform(0.15, 0.4)
    offset = rng.uniform(-0.25, 0.25) * (1.0 - width)
    y = depth / 2
    stem = _box((offset - width / 2, -y, 0.0), (offset + width / 2, y, height + OVERLAP))
    top = _box((-0.5, -y, height), (0.5, y, height + thickness))
    return _unit([stem, top])


def cross(rng: np.random.Generator) -> trimesh.Trimesh:
    """Two bars crossing at right angles in the ground plane, each of its own width and height."""
    length = rng.uniform(0.5, 1.0)
    w1, w2 = rng.uniform(0.15, 0.3, size=2)
    h1, h2 = rng.uniform(0.12, 0.4, size=2)
    at = rng.uniform(-0.25, 0.25) * (1.0 - w2)  # where the second bar crosses the first (x)
    shift = rng.uniform(-0.25, 0.25) * (length - w1)  # where the first crosses the second (y)
    first = _box((-0.5, shift - w1 / 2, 0.0), (0.5, shift + w1 / 2, h1))
    second = _box((at - w2 / 2, -length / 2, 0.0), (at + w2 / 2, length / 2, h2))
    return _unit([first, second])


def cup(rng: np.random.Generator) -> trimesh.Trimesh:
    """A floor and four walls (an open box), walls at least 0.12 of the longest extent thick."""
    width = 1.0
    depth = rng.uniform(0.6, 1.0)
    height = rng.uniform(0.4, 1.0)
    wall, floor = rng.uniform(0.12, 0.18, size=2)
    x, y = width / 2, depth / 2
    pieces = [
        _box((-x, -y, 0.0), (x, y, floor)),
        _box((-x, -y, floor - OVERLAP), (x, -y + wall, height)),
        _box((-x, y - wall, floor - OVERLAP), (x, y, height)),
        _box((-x, -y + wall - OVERLAP, floor - OVERLAP), (-x + wall, y - wall + OVERLAP, height)),
        _box((x - wall, -y + wall - OVERLAP, floor - OVERLAP), (x, y - wall + OVERLAP, height)),
    ]
    return _unit(pieces)


def _ring_segment(sides: int, k: int, inner: float, outer: float) -> trimesh.Trimesh:
    """Segment ``k`` of a ring of ``sides`` sides, height 1: the prism between the apothems
    ``inner`` and ``outer`` cut at the two mitre planes, each end carried :data:`OVERLAP` further
    along the segment so that neighbours overlap without sharing an edge."""
    slope = math.tan(math.pi / sides)
    corners = [(sign * (r * slope + OVERLAP), r, z) for sign in (-1.0, 1.0) for r in (inner, outer) for z in (0.0, 1.0)]
    segment = trimesh.Trimesh(vertices=np.array(corners), process=False).convex_hull
    segment.apply_transform(trimesh.transformations.rotation_matrix(2 * math.pi * k / sides, (0.0, 0.0, 1.0)))
    return segment


def ring(rng: np.random.Generator) -> trimesh.Trimesh:
    """A regular polygon of 4, 5 or 6 mitred straight segments about a hole (module docstring)."""
    sides = int(rng.choice([4, 5, 6]))
    width = rng.uniform(0.2, 0.36)
    height = rng.uniform(0.12, 0.3)  # of the ring's extent across
    flat = trimesh.util.concatenate([_ring_segment(sides, k, 0.5 - width / 2, 0.5 + width / 2) for k in range(sides)])
    flat.apply_scale((1.0, 1.0, height * float(flat.extents[:2].max())))
    return _unit([flat])


#: the procedural kinds, name -> function of a random generator
KINDS: dict[str, Callable[[np.random.Generator], trimesh.Trimesh]] = {
    "random_hull": random_hull, "l_shape": l_shape, "t_shape": t_shape, "cross": cross, "cup": cup,
    "ring": ring}


def check_kind(kind: str) -> None:
    """Raise ValueError naming the kinds if ``kind`` is not one of :data:`KINDS`."""
    if kind not in KINDS:
        raise ValueError(f"unknown shape kind {kind!r}; choose from {', '.join(KINDS)}")


def check_seed(seed: int, name: str = "seed") -> None:
    """Raise ValueError unless ``seed`` is an integer >= 0."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {seed!r}")


def make_shape(kind: str, seed: int) -> trimesh.Trimesh:
    """Shape ``kind`` drawn from seed ``seed``: the same mesh for the same pair, every time."""
    check_kind(kind)
    check_seed(seed)
    return KINDS[kind](np.random.default_rng(int(seed)))


def obj_text(mesh: trimesh.Trimesh) -> str:
    """The OBJ text of a mesh: vertices and faces only, at :data:`OBJ_DIGITS` digits."""
    return export_obj(mesh, include_normals=False, include_color=False, include_texture=False,
                      digits=OBJ_DIGITS)


def convex_pieces(mesh: trimesh.Trimesh, tolerance: float = 1e-6) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pieces of a mesh made of closed convex pieces, each ``(planes [H, 4], bounds [2, 3])``
    (inside: ``n . x + c <= 0`` for every row); ValueError if a piece is not closed and convex
    (volume short of its hull's by more than ``tolerance``)."""
    out = []
    for piece in mesh.split(only_watertight=False):
        hull = ConvexHull(np.asarray(piece.vertices))
        if not piece.is_watertight or abs(abs(piece.volume) - hull.volume) > tolerance * hull.volume:
            raise ValueError("mesh is not a union of closed convex pieces")
        out.append((np.unique(np.round(hull.equations, 12), axis=0), np.asarray(piece.bounds)))
    return out


def union_volume(mesh: trimesh.Trimesh, grow: float = 0.0, cells: int = VOLUME_CELLS) -> float:
    r"""The volume of the union of a mesh's convex pieces (:func:`convex_pieces`), each grown by
    ``grow`` (:math:`n \cdot x + c \le \text{grow}\, \|n\|_1`), counted at the midpoints of a grid of
    ``cells`` along the longest extent (error about 1 %)."""
    if not (math.isfinite(grow) and grow >= 0):
        raise ValueError(f"grow must be a finite number >= 0, got {grow}")
    lower, upper = mesh.bounds[0] - grow, mesh.bounds[1] + grow
    step = float((upper - lower).max()) / cells
    axes = [lower[k] + step * (np.arange(max(1, math.ceil((upper[k] - lower[k]) / step))) + 0.5) for k in range(3)]
    inside = np.zeros([len(a) for a in axes], dtype=bool)
    for planes, bounds in convex_pieces(mesh):
        window = tuple(slice(int(np.searchsorted(axes[k], bounds[0, k] - grow)),
                             int(np.searchsorted(axes[k], bounds[1, k] + grow, side="right"))) for k in range(3))
        slack = grow * np.abs(planes[:, :3]).sum(axis=1)
        ys, zs = axes[1][window[1]], axes[2][window[2]]
        for i in range(window[0].start, window[0].stop):  # one slab at a time (memory bound)
            slab = np.stack(np.meshgrid([axes[0][i]], ys, zs, indexing="ij"), axis=-1)[0]
            inside[i, window[1], window[2]] |= np.all(slab @ planes[:, :3].T + planes[:, 3] <= slack, axis=-1)
    return int(inside.sum()) * step**3


def gable_roof(width: float = 0.4, length: float = 0.3, eaves: float = 0.08, ridge: float = 0.2) -> trimesh.Trimesh:
    """A house roof for the two-outcome check (never a training kind): a convex ``width x length``
    box of height ``eaves`` under a gable whose ridge runs along ``y`` at ``x = 0``, ``ridge`` high."""
    if not (width > 0 and length > 0 and 0 < eaves < ridge):
        raise ValueError(f"gable_roof needs width, length > 0 and 0 < eaves < ridge, got "
                         f"{width}, {length}, {eaves}, {ridge}")
    half = width / 2
    profile = [(-half, 0.0), (half, 0.0), (half, eaves), (0.0, ridge), (-half, eaves)]  # x, z
    points = [(x, y, z) for x, z in profile for y in (-length / 2, length / 2)]
    roof = trimesh.Trimesh(vertices=np.array(points), process=False).convex_hull
    roof.apply_translation(-roof.bounds.mean(axis=0))
    return roof


def shape_record(path: Path, kind: str, seed: int) -> dict:
    """What ``index.json`` says of one written shape, read back from its file as a scene reads it."""
    mesh = clean_mesh(load_mesh(path), str(path))
    return {"file": path.name, "kind": kind, "seed": int(seed), "volume": round(union_volume(mesh), 6),
            "watertight": bool(mesh.is_watertight)}


def write_shapes(out: str | Path, per_kind: int, seed: int = 0, kinds: Sequence[str] | None = None) -> list[dict]:
    """Write ``per_kind`` shapes of each kind to ``out/<kind>_<i:03d>.obj`` (seed ``seed + i``) and
    ``out/index.json``, atomically; returns the records. An existing file with the same text is
    kept; one that differs raises ValueError."""
    if isinstance(per_kind, bool) or not isinstance(per_kind, (int, np.integer)) or per_kind < 0:
        raise ValueError(f"per_kind must be an integer >= 0, got {per_kind!r}")
    check_seed(seed)
    kinds = list(KINDS) if kinds is None else list(kinds)
    for kind in kinds:
        check_kind(kind)
    out = Path(out)
    records = []
    for kind in kinds:
        for i in range(per_kind):
            path = out / f"{kind}_{i:03d}.obj"
            text = obj_text(make_shape(kind, seed + i))
            if path.exists():
                if path.read_text() != text:
                    raise ValueError(f"{path} exists and is not shape {kind} of seed {seed + i}; "
                                     "write to another folder or remove it")
            else:
                atomic_write_text(path, text)
            records.append(shape_record(path, kind, seed + i))
    atomic_write_json(out / "index.json", {"seed": int(seed), "per_kind": int(per_kind), "shapes": records})
    return records


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m experiments.recipe.procedural --out DIR --per-kind N --seed S [--kinds ...]``; a bad
    argument is one line on stderr and exit code 2."""
    parser = argparse.ArgumentParser(prog="python -m experiments.recipe.procedural",
                                     description="Write procedural training shapes as OBJ files and an index.")
    parser.add_argument("--out", required=True, help="folder for the OBJ files and index.json")
    parser.add_argument("--per-kind", type=int, required=True, help="shapes of each kind")
    parser.add_argument("--seed", type=int, default=0, help="seed of shape 0 of each kind (shape i: seed + i)")
    parser.add_argument("--kinds", nargs="+", default=None, help=f"kinds to write (default all: {' '.join(KINDS)})")
    args = parser.parse_args(argv)
    try:
        records = write_shapes(args.out, args.per_kind, args.seed, args.kinds)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{len(records)} shapes in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
