"""Point tracks in, episodes out: ``hrn-pyg import``.

Tracks are the positions of points over frames, each point with an object and each object a
material (motion capture, a tracker, another simulator). :func:`tracks_to_episode` turns them
into the episode format of ``docs/data.md``:

* **leaves** are the points (``leaves="points"``) or lattice cells of spacing ``pitch``
  (``leaves="lattice"``: an object's rest-frame points snapped to
  :func:`~hrn_pyg.data.voxelise.lattice_indices`' grid, or a rigid object's mesh's voxels,
  :func:`~hrn_pyg.data.meshes.solid_points`). A rigid object's leaves move with the
  least-squares rigid motion of its points (:func:`rigid_motion`), a soft or cloth leaf by the
  mean displacement of its cell's points; a **static** object's leaves never move;
* the **rest shape** is frame ``rest_frame`` (earlier frames dropped), where the hierarchy is
  clustered (:func:`~hrn_pyg.data.hierarchy.build_hierarchy`);
* every ``frame_stride``-th frame is kept, each step's force the mean of its frames'.

Two ``.npz`` layouts are read without pickle (:data:`FORMATS`; the keys of each are in
docs/data.md, "Your own trajectories"): ``npz`` (:func:`save_tracks` writes it) and
``learning_to_simulate`` (GNS's datasets, each particle type one object of a material from
``particle_materials``).

Positions are turned so that ``up`` becomes z (2-D ``(x, y)`` becomes ``(x, 0, y)``) and
shifted so that the height ``ground`` is ``z = 0``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.io import save_episode
from hrn_pyg.data.kinds import CLOTH, MATERIALS, RIGID, SOFT, STATIC
from hrn_pyg.data.meshes import load_mesh, solid_points
from hrn_pyg.data.voxelise import lattice_indices
from hrn_pyg.utils.files import atomic_path

#: the layouts a tracks file may have
FORMATS = ("npz", "learning_to_simulate")
#: how leaves are made from points
LEAVES = ("points", "lattice")
#: the stiffness of a soft or cloth object whose tracks give none (the middle of the range)
DEFAULT_STIFFNESS = 0.5
#: the most points and frames a tracks file may hold (a file from someone else gets bounded memory)
MAX_POINTS = 200_000
MAX_FRAMES = 100_000
#: a learning_to_simulate key, with an optional trajectory number
LTS_KEY = re.compile(r"^(position|particle_type)(?:_(\d+))?$")


@dataclass(frozen=True)
class Tracks:
    """Point tracks, already in the package's frame (z up, the ground ``z = 0``).

    **Shapes** (``T`` frames, ``P`` points, ``O`` objects): ``positions [T, P, 3]`` float64 (m),
    ``point_object [P]`` int64 in ``0..O-1``, ``point_mass [P]`` float64 (kg, > 0),
    ``object_material [O]`` int64 (0-3), ``object_stiffness [O]`` float64 in [0, 1],
    ``forces [T-1, P, 3]`` float64 (N) or None, ``dt`` (s per frame), ``pitch`` (m) or None.
    """

    positions: np.ndarray
    point_object: np.ndarray
    point_mass: np.ndarray
    object_material: np.ndarray
    object_stiffness: np.ndarray
    dt: float
    forces: np.ndarray | None = None
    pitch: float | None = None
    name: str = "tracks"

    def __post_init__(self) -> None:
        check_tracks(self)


@dataclass(frozen=True)
class ImportConfig:
    """How tracks become an episode (recorded in the episode's ``params``).

    Attributes:
        leaves: ``points`` (each point a leaf) or ``lattice`` (leaves on the lattice at ``pitch``).
        pitch: the lattice spacing (m); for ``points``, the spacing recorded for pitch-aware models.
        rest_frame: the frame whose positions are the rest shape; earlier frames are dropped.
        frame_stride: keep every n-th frame from the rest frame on.
        meshes: object index -> mesh file (posed as at the rest frame) whose voxels are a rigid or
            static object's leaves (``lattice`` only).
    """

    leaves: str = "points"
    pitch: float | None = None
    rest_frame: int = 0
    frame_stride: int = 1
    meshes: dict[int, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.leaves not in LEAVES:
            raise ValueError(f"--leaves: one of {', '.join(LEAVES)}, got {self.leaves!r}")
        if self.pitch is not None and not (math.isfinite(self.pitch) and self.pitch > 0):
            raise ValueError(f"--pitch: a finite number > 0 (m), got {self.pitch}")
        if self.leaves == "lattice" and self.pitch is None:
            raise ValueError("--leaves lattice needs --pitch (the lattice spacing, m)")
        if self.rest_frame < 0 or self.frame_stride < 1:
            raise ValueError(f"--rest-frame must be >= 0 and --frame-stride >= 1, got {self.rest_frame} "
                             f"and {self.frame_stride}")
        if self.meshes and self.leaves != "lattice":
            raise ValueError("--mesh: meshes give lattice leaves; add --leaves lattice")


def check_tracks(tracks: Tracks) -> None:
    """ValueError naming the first array of ``tracks`` with a wrong shape, dtype or value."""
    pos = tracks.positions
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] < 2 or pos.shape[1] < 1:
        raise ValueError(f"positions: expected [T >= 2, P >= 1, 3], got {list(pos.shape)}")
    if pos.shape[0] > MAX_FRAMES or pos.shape[1] > MAX_POINTS:
        raise ValueError(f"positions: at most {MAX_FRAMES} frames of {MAX_POINTS} points, got {list(pos.shape)}")
    if not np.all(np.isfinite(pos)):
        raise ValueError("positions: contain NaN or inf (a lost track?)")
    frames, points = pos.shape[:2]
    n_obj = len(tracks.object_material)
    if tracks.point_object.shape != (points,) or tracks.point_object.dtype.kind not in "iu":
        raise ValueError(f"object: expected [{points}] integers, got {tracks.point_object.dtype} "
                         f"{list(tracks.point_object.shape)}")
    if np.any(np.bincount(tracks.point_object, minlength=n_obj) == 0) or tracks.point_object.max() >= n_obj:
        raise ValueError(f"object: every object 0..{n_obj - 1} needs points")
    if np.any((tracks.object_material < 0) | (tracks.object_material >= len(MATERIALS))):
        raise ValueError(f"material: codes 0..{len(MATERIALS) - 1} ({', '.join(MATERIALS)})")
    if tracks.point_mass.shape != (points,) or not np.all(np.isfinite(tracks.point_mass) & (tracks.point_mass > 0)):
        raise ValueError(f"mass: expected [{points}] finite masses > 0 (kg)")
    stiff = tracks.object_stiffness
    if stiff.shape != (n_obj,) or not np.all((stiff >= 0) & (stiff <= 1)):
        raise ValueError(f"stiffness: expected [{n_obj}] values in [0, 1]")
    if tracks.forces is not None and (tracks.forces.shape != (frames - 1, points, 3)
                                      or not np.all(np.isfinite(tracks.forces))):
        raise ValueError(f"forces: expected finite [{frames - 1}, {points}, 3], got {list(tracks.forces.shape)}")
    if not (math.isfinite(tracks.dt) and tracks.dt > 0):
        raise ValueError(f"dt: a finite number > 0 (seconds per frame), got {tracks.dt}")


# -- reading ------------------------------------------------------------------------------------


def to_z_up(positions: np.ndarray, up: str = "z", ground: float = 0.0) -> np.ndarray:
    """Positions turned by a proper rotation so that axis ``up`` is z, then shifted so that the height
    ``ground`` is ``z = 0``. **Shapes** ``[T, P, dim]`` (``dim`` 2 or 3) -> ``[T, P, 3]`` float64."""
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 3 or x.shape[2] not in (2, 3):
        raise ValueError(f"positions: expected [T, P, 2 or 3], got {list(x.shape)}")
    if x.shape[2] == 2:
        if up != "y":
            raise ValueError(f"--up: 2-D tracks have y up, got {up!r}")
        x = np.stack([x[..., 0], np.zeros_like(x[..., 0]), x[..., 1]], axis=-1)
    elif up == "y":  # +90 degrees about x: y -> z, z -> -y
        x = np.stack([x[..., 0], -x[..., 2], x[..., 1]], axis=-1)
    elif up == "x":  # -90 degrees about y: x -> z, z -> -x
        x = np.stack([-x[..., 2], x[..., 1], x[..., 0]], axis=-1)
    elif up != "z":
        raise ValueError(f"--up: x, y or z, got {up!r}")
    x[..., 2] -= ground
    return x


def _material_codes(raw: np.ndarray) -> np.ndarray:
    if raw.dtype.kind in "iu":
        return raw.astype(np.int64)
    if raw.dtype.kind == "U":
        unknown = sorted(set(raw.tolist()) - set(MATERIALS))
        if unknown:
            raise ValueError(f"material: unknown {unknown[0]!r}; the materials are {', '.join(MATERIALS)}")
        return np.array([MATERIALS.index(m) for m in raw.tolist()], dtype=np.int64)
    raise ValueError(f"material: integer codes or names, got dtype {raw.dtype}")


def tracks_from_points(positions: np.ndarray, point_object: np.ndarray, point_material: np.ndarray, *, dt: float,
                       point_mass: np.ndarray | None = None, object_mass: float = 1.0,
                       stiffness: np.ndarray | None = None, forces: np.ndarray | None = None,
                       pitch: float | None = None, name: str = "tracks") -> Tracks:
    """:class:`Tracks` from per-point arrays with any object ids; an object's points share one
    material. Default masses: ``object_mass`` kg per object, shared by its points; default
    stiffness: 1 for rigid and static, :data:`DEFAULT_STIFFNESS` for soft and cloth.

    **Shapes** ``positions [T, P, 3]``, ``point_object [P]``, ``point_material [P]``,
    ``point_mass [P]``, ``stiffness [O]``, ``forces [T-1, P, 3]``.
    """
    ids = np.asarray(point_object)
    if ids.ndim != 1 or ids.dtype.kind not in "iu":
        raise ValueError(f"object: expected [P] integers, got {ids.dtype} {list(ids.shape)}")
    _, obj = np.unique(ids, return_inverse=True)
    material = _material_codes(np.asarray(point_material))
    if material.shape != obj.shape:
        raise ValueError(f"material: expected one per point [{len(obj)}], got {list(material.shape)}")
    n_obj = int(obj.max()) + 1 if len(obj) else 0
    object_material = np.full(n_obj, -1, dtype=np.int64)
    object_material[obj] = material
    if np.any(object_material[obj] != material):
        bad = int(np.unique(ids)[obj[object_material[obj] != material][0]])
        raise ValueError(f"material: the points of object {bad} have more than one material")
    counts = np.bincount(obj, minlength=n_obj)
    mass = (np.full(len(obj), float(object_mass)) / counts[obj] if point_mass is None
            else np.asarray(point_mass, dtype=np.float64))
    if stiffness is None:
        stiffness = np.where(np.isin(object_material, (RIGID, STATIC)), 1.0, DEFAULT_STIFFNESS)
    return Tracks(positions=np.asarray(positions, dtype=np.float64), point_object=obj.astype(np.int64),
                  point_mass=mass, object_material=object_material,
                  object_stiffness=np.asarray(stiffness, dtype=np.float64), dt=float(dt),
                  forces=None if forces is None else np.asarray(forces, dtype=np.float64),
                  pitch=None if pitch is None else float(pitch), name=name)


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"tracks file not found: {path}")
    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz of named arrays")
        with data:
            return {key: data[key] for key in data.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: not a readable .npz without pickled objects ({exc})") from None


def read_npz_tracks(path: str | Path, *, dt: float | None = None, up: str = "z", ground: float = 0.0,
                    object_mass: float = 1.0) -> list[Tracks]:
    """The one trajectory of a tracks file in the package's ``npz`` layout (module docstring)."""
    path = Path(path)
    data = _load_npz(path)
    for key in ("positions", "object", "material"):
        if key not in data:
            raise ValueError(f"{path}: missing key {key!r} (a tracks file has positions, object, material)")
    file_dt = float(data["dt"]) if "dt" in data else None
    if file_dt is None and dt is None:
        raise ValueError(f"{path}: no dt in the file; give --dt (seconds per frame)")
    try:
        return [tracks_from_points(
            to_z_up(data["positions"], up, ground), data["object"], data["material"],
            dt=dt if dt is not None else file_dt, point_mass=data.get("mass"), object_mass=object_mass,
            stiffness=data.get("stiffness"), forces=data.get("forces"),
            pitch=float(data["pitch"]) if "pitch" in data else None, name=path.stem)]
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def parse_particle_materials(text: str) -> dict[int, int]:
    """``"3=static,5=soft"`` -> ``{3: STATIC, 5: SOFT}`` (particle type -> material code)."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        type_text, sep, name = item.partition("=")
        if not sep or not type_text.strip().lstrip("-").isdigit() or name.strip() not in MATERIALS:
            raise ValueError(f"--particle-materials: TYPE=MATERIAL pairs such as 3=static,5=soft "
                             f"(materials: {', '.join(MATERIALS)}), got {item!r}")
        out[int(type_text)] = MATERIALS.index(name.strip())
    return out


def read_learning_to_simulate(path: str | Path, particle_materials: dict[int, int], *, dt: float | None,
                              up: str = "y", ground: float = 0.0, object_mass: float = 1.0) -> list[Tracks]:
    """The trajectories of a file in the learning_to_simulate layout (module docstring): each
    particle type one object of material ``particle_materials[type]``."""
    path = Path(path)
    if dt is None:
        raise ValueError(f"{path}: the learning_to_simulate layout keeps dt in its metadata; give --dt")
    data = _load_npz(path)
    found: dict[str, dict[str, np.ndarray]] = {}
    for key, value in data.items():
        if (m := LTS_KEY.match(key)):
            found.setdefault(m.group(2) or "", {})[m.group(1)] = value
    if not found:
        raise ValueError(f"{path}: no position / particle_type arrays (the learning_to_simulate layout)")
    out = []
    for number in sorted(found, key=lambda n: int(n) if n else -1):
        pair = found[number]
        where = f"{path}: trajectory {number or 0}"
        if set(pair) != {"position", "particle_type"}:
            raise ValueError(f"{where}: needs both position and particle_type")
        types = np.asarray(pair["particle_type"]).astype(np.int64)
        unmapped = sorted(set(types.tolist()) - set(particle_materials))
        if unmapped:
            raise ValueError(f"{where}: particle type {unmapped[0]} has no material; add it to --particle-materials "
                             "(e.g. 3=static for the kinematic particles)")
        material = np.array([particle_materials[t] for t in types.tolist()], dtype=np.int64)
        try:
            out.append(tracks_from_points(to_z_up(pair["position"], up, ground), types, material, dt=dt,
                                          object_mass=object_mass, name=f"{path.stem}_{number or 0}"))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    return out


# -- writing ------------------------------------------------------------------------------------


def tracks_of_episode(episode: dict[str, np.ndarray]) -> Tracks:
    """An episode's leaves as tracks (every leaf a point): what the round trip through
    :func:`tracks_to_episode` starts from."""
    pitch = None
    try:
        pitch = json.loads(str(episode["params"]))["config"]["pitch"]
    except (KeyError, TypeError, ValueError):
        pass
    leaf_object = np.asarray(episode["leaf_object"])
    return Tracks(positions=np.asarray(episode["positions"], dtype=np.float64), point_object=leaf_object,
                  point_mass=np.asarray(episode["leaf_mass"], dtype=np.float64),
                  object_material=np.asarray(episode["object_material"], dtype=np.int64),
                  object_stiffness=np.asarray(episode["object_stiffness"], dtype=np.float64),
                  dt=float(episode["dt"]), forces=np.asarray(episode["forces"], dtype=np.float64),
                  pitch=pitch, name=str(episode["scene"]))


def save_tracks(path: str | Path, tracks: Tracks) -> None:
    """Write ``tracks`` as a file of the ``npz`` layout (atomically, no pickle)."""
    arrays = {"positions": tracks.positions, "object": tracks.point_object,
              "material": tracks.object_material[tracks.point_object], "mass": tracks.point_mass,
              "stiffness": tracks.object_stiffness, "dt": np.array(tracks.dt)}
    if tracks.forces is not None:
        arrays["forces"] = tracks.forces
    if tracks.pitch is not None:
        arrays["pitch"] = np.array(tracks.pitch)
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


# -- tracks -> episode --------------------------------------------------------------------------


def rigid_motion(rest: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""Per frame, the rotation and translation that best carry the rest points onto it,
    :math:`\min_{R_t, c_t} \sum_i \| R_t (\bar x_i - \bar\mu) + c_t - x_{t,i} \|^2` (Kabsch, no
    reflection); :math:`c_t` is the frame's centroid.

    **Shapes** ``rest [P, 3]``, ``frames [T, P, 3]`` -> ``R [T, 3, 3]``, ``c [T, 3]``.
    """
    centre = frames.mean(axis=1)  # [T, 3]
    a = rest - rest.mean(axis=0)  # [P, 3]
    b = frames - centre[:, None]  # [T, P, 3]
    u, _, vt = np.linalg.svd(np.einsum("pi,tpj->tij", a, b))  # H = A^T B, [T, 3, 3]
    d = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", u, vt)))
    flip = np.ones((len(d), 3))
    flip[:, 2] = d
    rotation = np.einsum("tji,tj,tkj->tik", vt, flip, u)  # V diag(1, 1, d) U^T
    return rotation, centre


def _object_leaves(rest: np.ndarray, frames: np.ndarray, forces: np.ndarray, material: int, pitch: float,
                   mesh: str | None, where: str) -> tuple[np.ndarray, np.ndarray]:
    """One object's lattice leaves over the frames ``[T, M, 3]`` and their forces ``[T-1, M, 3]``."""
    if mesh is not None:
        if material not in (RIGID, STATIC):
            raise ValueError(f"{where}: --mesh is for rigid and static objects")
        leaves0, _ = solid_points(load_mesh(mesh), pitch, where)
        cell = None
    else:
        origin = rest.min(axis=0)
        snapped = np.rint((rest - origin) / pitch).astype(np.int64)
        cells, cell = np.unique(snapped, axis=0, return_inverse=True)
        cell = cell.reshape(-1)
        leaves0 = origin + cells * pitch
    n = len(leaves0)
    if material == STATIC:
        return np.broadcast_to(leaves0, (len(frames), n, 3)).copy(), np.zeros((len(forces), n, 3))
    if material == RIGID:
        rotation, centre = rigid_motion(rest, frames)
        moved = np.einsum("tij,mj->tmi", rotation, leaves0 - rest.mean(axis=0)) + centre[:, None]
        return moved, np.broadcast_to(forces.sum(axis=1, keepdims=True) / n, (len(forces), n, 3)).copy()
    counts = np.bincount(cell, minlength=n)[:, None]
    shift = np.zeros((len(frames), n, 3))
    np.add.at(shift, (slice(None), cell), frames - rest)
    pushed = np.zeros((len(forces), n, 3))
    np.add.at(pushed, (slice(None), cell), forces)
    return leaves0 + shift / counts, pushed


def tracks_to_episode(tracks: Tracks, config: ImportConfig = ImportConfig(), seed: int = 0) -> dict[str, np.ndarray]:
    """The episode (``docs/data.md``'s format) of ``tracks`` under ``config`` (module docstring).

    **Shapes** ``S = (T - 1 - rest_frame) // frame_stride`` steps; ``positions [S+1, L, 3]``,
    ``forces [S, L, 3]``; ``L = P`` for ``points``, the occupied lattice cells (or mesh voxels)
    of every object for ``lattice``.
    """
    stride, first = config.frame_stride, config.rest_frame
    steps = (len(tracks.positions) - 1 - first) // stride
    if steps < 1:
        raise ValueError(f"tracks: {len(tracks.positions)} frames leave no step after rest frame {first} "
                         f"at stride {stride}")
    frames = tracks.positions[first: first + steps * stride + 1: stride]  # [S+1, P, 3]
    raw = np.zeros_like(tracks.positions[1:]) if tracks.forces is None else tracks.forces
    forces = raw[first: first + steps * stride].reshape(steps, stride, *raw.shape[1:]).mean(axis=1)
    order = np.argsort(tracks.point_object, kind="stable")  # leaves grouped by object
    obj, material = tracks.point_object, tracks.object_material
    pitch = config.pitch if config.pitch is not None else tracks.pitch
    unknown = sorted(set(config.meshes) - set(range(len(material))))
    if unknown:
        raise ValueError(f"--mesh: no object {unknown[0]} (the objects are 0..{len(material) - 1})")
    if config.leaves == "points":
        positions, leaf_forces = frames[:, order], forces[:, order]
        leaf_object, leaf_mass = obj[order], tracks.point_mass[order]
        static = material[leaf_object] == STATIC
        positions[:, static] = positions[0, static]
    else:
        parts = [_object_leaves(frames[0, obj == o], frames[:, obj == o], forces[:, obj == o], int(material[o]),
                                float(pitch), config.meshes.get(o), f"object {o}") for o in range(len(material))]
        positions = np.concatenate([p for p, _ in parts], axis=1)
        leaf_forces = np.concatenate([f for _, f in parts], axis=1)
        counts = np.array([p.shape[1] for p, _ in parts])
        leaf_object = np.repeat(np.arange(len(material)), counts)
        object_mass = np.bincount(obj, weights=tracks.point_mass, minlength=len(material))
        leaf_mass = (object_mass / counts)[leaf_object]
    positions = positions.astype(np.float32)
    leaf_mass = leaf_mass.astype(np.float32)
    record = {"config": {"pitch": pitch},
              "import": {"leaves": config.leaves, "rest_frame": first, "frame_stride": stride,
                         "meshes": {str(k): v for k, v in config.meshes.items()}}}
    return {
        "positions": positions,
        "forces": leaf_forces.astype(np.float32),
        "leaf_mass": leaf_mass,
        "leaf_object": leaf_object.astype(np.int64),
        "object_material": material.astype(np.int64),
        "object_stiffness": tracks.object_stiffness.astype(np.float32),
        "hierarchy_parent": np.asarray(build_hierarchy(positions[0].astype(np.float64),
                                                       leaf_mass.astype(np.float64), leaf_object), dtype=np.int64),
        "seed": np.array(seed, dtype=np.int64),
        "scene": np.array(tracks.name),
        "params": np.array(json.dumps(record, sort_keys=True)),
        "dt": np.array(tracks.dt * stride, dtype=np.float64),
    }


# -- the command --------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tracks", action="append", required=True, metavar="FILE",
                        help="a tracks file (repeatable; episodes in the order given)")
    parser.add_argument("--format", choices=FORMATS, default="npz", help="the layout of the tracks files")
    parser.add_argument("--out", required=True, help="the episode folder to write")
    parser.add_argument("--leaves", choices=LEAVES, default="points",
                        help="each point a leaf, or leaves on the package's lattice at --pitch")
    parser.add_argument("--pitch", type=float, default=None,
                        help="the lattice spacing of the leaves in m (recorded for pitch-aware models)")
    parser.add_argument("--rest-frame", type=int, default=0,
                        help="the frame whose positions are the rest shape (earlier frames are dropped)")
    parser.add_argument("--frame-stride", type=int, default=1, help="keep every n-th frame (one model step)")
    parser.add_argument("--first-seed", type=int, default=0, help="the seed of the first episode (then +1 each)")
    parser.add_argument("--dt", type=float, default=None, help="seconds per frame (default: the file's)")
    parser.add_argument("--up", choices=("x", "y", "z"), default=None,
                        help="the file's up axis (default: z for npz, y for learning_to_simulate)")
    parser.add_argument("--ground", type=float, default=0.0, help="the height of the ground along --up, in m")
    parser.add_argument("--mass", type=float, default=1.0,
                        help="kg per object where the file gives no masses (shared equally by its points)")
    parser.add_argument("--mesh", action="append", default=[], metavar="OBJECT=FILE",
                        help="a rigid or static object's mesh, posed as at the rest frame (repeatable)")
    parser.add_argument("--particle-materials", default="",
                        help="learning_to_simulate: TYPE=MATERIAL pairs, e.g. 3=static,0=rigid")


def _meshes(items: list[str]) -> dict[int, str]:
    out = {}
    for item in items:
        index, sep, path = item.partition("=")
        if not sep or not index.isdigit() or not path:
            raise ValueError(f"--mesh: OBJECT=FILE with an object index, got {item!r}")
        if not Path(path).is_file():
            raise FileNotFoundError(f"--mesh: mesh file not found: {path}")
        out[int(index)] = path
    return out


def run(args: argparse.Namespace) -> int:
    config = ImportConfig(leaves=args.leaves, pitch=args.pitch, rest_frame=args.rest_frame,
                          frame_stride=args.frame_stride, meshes=_meshes(args.mesh))
    if args.first_seed < 0:
        raise ValueError(f"--first-seed: must be >= 0, got {args.first_seed}")
    if not (math.isfinite(args.mass) and args.mass > 0):
        raise ValueError(f"--mass: a number > 0 (kg), got {args.mass}")
    trajectories: list[Tracks] = []
    for path in args.tracks:
        if args.format == "npz":
            trajectories += read_npz_tracks(path, dt=args.dt, up=args.up or "z", ground=args.ground,
                                            object_mass=args.mass)
        else:
            trajectories += read_learning_to_simulate(path, parse_particle_materials(args.particle_materials),
                                                      dt=args.dt, up=args.up or "y", ground=args.ground,
                                                      object_mass=args.mass)
    episodes = [tracks_to_episode(t, config, seed=args.first_seed + i) for i, t in enumerate(trajectories)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for episode in episodes:
        save_episode(out / f"episode_{int(episode['seed']):06d}.npz", episode)
    leaves = sorted({e["positions"].shape[1] for e in episodes})
    print(f"{out}: {len(episodes)} episodes of {', '.join(map(str, leaves))} leaves written "
          f"(check them: hrn-pyg check-data {out})")
    return 0
