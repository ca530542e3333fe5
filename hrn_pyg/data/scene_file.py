r"""Scenes from files: a TOML file of objects (any mesh, any material) and scripted pushes.

.. code-block:: toml

    steps = 150                    # model steps per episode
    pitch = 0.02                   # optional: voxel size of the leaves (m), substeps, physics_hz, friction

    [[objects]]
    mesh = "duck.obj"              # a file trimesh reads (relative to this file, absolute, or
                                   # pybullet_data:<path> for pybullet's own) or a primitive:
                                   # box, sphere, cylinder, capsule, cone; cloth: "sheet" (a square
                                   # of side size on the lattice) or a surface mesh file
    material = "rigid"             # rigid, soft, cloth or static
    size = { min = 0.15, max = 0.25 }   # longest extent (m) after scaling; or scale = factor
    mass = 0.5                     # kg
    position = [0.0, 0.0, 0.3]     # m, the centre of the bounding box
    yaw = { min = 0, max = 360 }   # degrees; or orientation = [x, y, z, w]
    velocity = [0.5, 0.0, 0.0]     # m/s at the start
    spin = [0.0, 0.0, 2.0]         # rad/s at the start
    stiffness = 0.5                # soft and cloth: 0..1 over the package's fixed stiffness range
    friction = 0.6

    [[pushes]]
    object = 0                     # index into objects
    steps = [20, 25]               # first and last model step of the push
    force = [3.0, 0.0, 0.0]        # N, on the object's centre of mass

Any number or vector may be a range ``{ min = ..., max = ... }`` (vectors element-wise), drawn
per seed, so one file describes a whole dataset. The draws of a seed come in file order (the
objects' fields in the order above, then the pushes); when the drawn objects' bounding boxes
overlap at the start, the whole draw is repeated (up to :data:`OVERLAP_TRIES` times) from the
same seed's random stream; objects that overlap whatever is drawn are an error naming them.

:func:`read_scene_file` reads and validates a file into a :class:`SceneSpec` (every mistake is
one line naming the key); :meth:`SceneSpec.make_scene` gives the pybullet
:class:`~hrn_pyg.data.scenes.Scene` of a seed, which
:func:`hrn_pyg.data.scenes.simulate_episode` runs like a built-in scene.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.graph import CLOTH, MATERIALS, RIGID, SOFT, STATIC
from hrn_pyg.data.meshes import (
    PRIMITIVES,
    clean_mesh,
    convex_parts,
    load_mesh,
    primitive_mesh,
    sized_mesh,
    solid_points,
    too_many_leaves,
)
from hrn_pyg.data.scenes import (
    CLOTH_LOG10_K_RANGE,
    SOFT_LOG10_MU_RANGE,
    STATIC_DENSITY,
    Scene,
    SceneConfig,
    SceneObject,
)
from hrn_pyg.data.voxelise import (
    grid_sheet,
    lattice_tetrahedra,
)
from hrn_pyg.utils.files import import_pybullet

p = import_pybullet()

#: keys of the file's top level, of an object and of a push
SCENE_KEYS = ("steps", "pitch", "substeps", "physics_hz", "friction", "objects", "pushes")
OBJECT_KEYS = ("mesh", "material", "size", "scale", "mass", "position", "orientation", "yaw", "velocity",
               "spin", "stiffness", "friction")
PUSH_KEYS = ("object", "steps", "force")
#: a cloth is a square sheet of side ``size``
SHEET = "sheet"
#: a mesh named ``pybullet_data:<path>`` is one of the meshes that ship with pybullet
PYBULLET_DATA = "pybullet_data:"
#: draws of one seed tried before objects that overlap at the start are an error
OVERLAP_TRIES = 100
#: the most leaves one object may have (the model's cost grows with them)
MAX_LEAVES = 20_000
#: where convex decompositions are cached (``HRN_PYG_CACHE`` overrides it)
CACHE_DIR = Path(os.environ.get("HRN_PYG_CACHE", Path.home() / ".cache" / "hrn_pyg")) / "convex_parts"

#: ``{"min": ..., "max": ...}`` read into a pair of arrays, or a fixed value
Value = tuple[np.ndarray, np.ndarray]


def _value(raw: Any, where: str, length: int | None) -> Value:
    """A number or vector (``length``), or a ``{min, max}`` range of them, as ``(low, high)``."""
    if isinstance(raw, dict):
        unknown = sorted(set(raw) - {"min", "max"})
        if unknown or set(raw) != {"min", "max"}:
            raise ValueError(f"{where}: a range needs exactly the keys min and max, got {sorted(raw)}")
        low, high = _value(raw["min"], f"{where}.min", length)[0], _value(raw["max"], f"{where}.max", length)[0]
        if np.any(low > high):
            raise ValueError(f"{where}: min {low.tolist()} > max {high.tolist()}")
        return low, high
    numbers = raw if isinstance(raw, list) else [raw]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in numbers):
        raise ValueError(f"{where}: expected a number{' or a list of numbers' if length else ''}, got {raw!r}")
    array = np.asarray(raw, dtype=np.float64)
    if length is None and array.ndim != 0:
        raise ValueError(f"{where}: expected a number, got {raw!r}")
    if length is not None and array.shape != (length,):
        raise ValueError(f"{where}: expected a list of {length} numbers, got {raw!r}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{where}: must be finite, got {raw!r}")
    return array, array


def _check_keys(table: dict, allowed: tuple[str, ...], where: str) -> None:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; the keys are {', '.join(allowed)}")


def _draw(rng: np.random.Generator, value: Value) -> np.ndarray:
    low, high = value
    return low.copy() if np.array_equal(low, high) else np.asarray(rng.uniform(low, high))


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a scene file; every field a ``(low, high)`` pair (equal when fixed)."""

    mesh: str
    material: str
    size: Value | None
    scale: Value | None
    mass: Value
    position: Value
    orientation: Value | None
    yaw: Value | None
    velocity: Value
    spin: Value
    stiffness: Value
    friction: Value | None

    @cached_property
    def base_mesh(self) -> trimesh.Trimesh | None:
        """The object's mesh cleaned (seams merged), before sizing; None for a sheet."""
        if self.mesh == SHEET:
            return None
        return primitive_mesh(self.mesh) if self.mesh in PRIMITIVES else clean_mesh(load_mesh(self.mesh), self.mesh)


@dataclass(frozen=True)
class PushSpec:
    """A scripted push: ``force`` (N) on object ``object`` from model step ``first`` to ``last``."""

    object: int
    first: int
    last: int
    force: Value


@dataclass(frozen=True)
class SceneSpec:
    """A scene read from a file (:func:`read_scene_file`)."""

    name: str
    config: SceneConfig
    objects: tuple[ObjectSpec, ...]
    pushes: tuple[PushSpec, ...] = ()
    source: str = ""
    text: str = field(default="", repr=False)

    @property
    def effects(self) -> SceneEffects:
        """Pushed objects need the force module; a lone object no collision search."""
        return SceneEffects(forces=bool(self.pushes), collisions=len(self.objects) > 1 or None)

    def make_scene(self, seed: int) -> FileScene:
        """The pybullet scene of seed ``seed`` (call ``reset()`` to start it)."""
        return FileScene(self, seed)

    def draw(self, rng: np.random.Generator) -> dict:
        """One seed's values of every range, redrawn while objects overlap (JSON-able)."""
        for _ in range(OVERLAP_TRIES):
            params = {"objects": [self._draw_object(o, rng) for o in self.objects],
                      "pushes": [_draw(rng, push.force).tolist() for push in self.pushes]}
            if not overlapping(self, params["objects"]):
                return params
        first, second = overlapping(self, params["objects"])[0]
        raise ValueError(f"{self.name}: objects {first} and {second} overlap at the start in every one of "
                         f"{OVERLAP_TRIES} draws; move them apart")

    @staticmethod
    def _draw_object(obj: ObjectSpec, rng: np.random.Generator) -> dict:
        drawn = {}
        for name in ("size", "scale", "mass", "position", "orientation", "yaw", "velocity", "spin", "stiffness",
                     "friction"):
            value = getattr(obj, name)
            if value is not None:
                number = _draw(rng, value)
                drawn[name] = number.tolist()
        return drawn

    def check(self, seed: int = 0) -> None:
        """Raise the errors an episode of ``seed`` would raise before it simulates anything:
        objects that overlap in every draw, a mesh with too few or too many leaves at the pitch."""
        drawn = self.draw(np.random.default_rng(seed))["objects"]
        for index, (obj, values) in enumerate(zip(self.objects, drawn)):
            mesh = posed_mesh(obj, values)
            if mesh is None:
                continue
            where = f"{self.name}: objects[{index}]"
            if obj.material == "cloth":
                surface_leaves(mesh, where)
            else:
                leaves_of(mesh, self.config.pitch, where)


def read_scene_file(path: str | os.PathLike) -> SceneSpec:
    """The :class:`SceneSpec` of a scene file; ValueError naming the key for every mistake,
    FileNotFoundError for a missing scene or mesh file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    text = path.read_text()
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not TOML ({exc})") from None
    return parse_scene(table, name=path.stem, base=path.parent, source=str(path), text=text)


def parse_scene(table: dict, name: str = "scene", base: Path = Path("."), source: str = "", text: str = "") -> SceneSpec:
    """A :class:`SceneSpec` from the file's TOML table (mesh paths relative to ``base``)."""
    _check_keys(table, SCENE_KEYS, name)
    if "steps" not in table:
        raise ValueError(f"{name}: steps (model steps per episode) is required")
    settings = {key: table[key] for key in ("steps", "pitch", "substeps", "physics_hz", "friction") if key in table}
    for key, value in settings.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: {key} must be a number, got {value!r}")
    try:
        config = SceneConfig(**settings)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: {exc}") from None
    objects = table.get("objects")
    if not isinstance(objects, list) or not objects:
        raise ValueError(f"{name}: needs at least one [[objects]] table")
    specs = tuple(_object(o, f"{name}: objects[{i}]", base) for i, o in enumerate(objects))
    pushes = table.get("pushes", [])
    if not isinstance(pushes, list):
        raise ValueError(f"{name}: pushes must be a list of [[pushes]] tables")
    push_specs = tuple(_push(q, f"{name}: pushes[{i}]", specs, config.steps) for i, q in enumerate(pushes))
    return SceneSpec(name=name, config=config, objects=specs, pushes=push_specs, source=source, text=text)


def _object(raw: Any, where: str, base: Path) -> ObjectSpec:
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a table")
    _check_keys(raw, OBJECT_KEYS, where)
    material = raw.get("material")
    if material not in MATERIALS:
        raise ValueError(f"{where}: unknown material {material!r}; choose from {', '.join(MATERIALS)}")
    mesh = raw.get("mesh")
    if not isinstance(mesh, str) or not mesh:
        raise ValueError(f"{where}: mesh (a file or one of {', '.join(PRIMITIVES)}) is required")
    if material == "cloth" and mesh in PRIMITIVES:
        raise ValueError(f"{where}: a cloth is a surface: mesh = {SHEET!r} or a surface mesh file")
    if mesh == SHEET and material != "cloth":
        raise ValueError(f"{where}: mesh = {SHEET!r} is for cloth only")
    if mesh not in PRIMITIVES and mesh != SHEET:
        path = mesh_path(mesh, base)
        if not path.is_file():
            looks_like_file = any(sep in mesh for sep in "/\\.")
            if looks_like_file:
                raise FileNotFoundError(f"{where}: mesh file not found: {path}")
            raise ValueError(f"{where}: unknown primitive {mesh!r}; choose from {', '.join(PRIMITIVES)} "
                             "or give a mesh file")
        mesh = str(path.resolve())
    if ("size" in raw) == ("scale" in raw):
        raise ValueError(f"{where}: give one of size (longest extent, m) and scale")
    if mesh == SHEET and "scale" in raw:
        raise ValueError(f"{where}: a sheet takes size (its side, m), not scale")
    if "orientation" in raw and "yaw" in raw:
        raise ValueError(f"{where}: give orientation or yaw, not both")
    if "position" not in raw:
        raise ValueError(f"{where}: position (m, the centre of the bounding box) is required")
    spec = ObjectSpec(
        mesh=mesh, material=material,
        size=_value(raw["size"], f"{where}.size", None) if "size" in raw else None,
        scale=_value(raw["scale"], f"{where}.scale", None) if "scale" in raw else None,
        mass=_value(raw.get("mass", 1.0), f"{where}.mass", None),
        position=_value(raw["position"], f"{where}.position", 3),
        orientation=_value(raw["orientation"], f"{where}.orientation", 4) if "orientation" in raw else None,
        yaw=_value(raw["yaw"], f"{where}.yaw", None) if "yaw" in raw else None,
        velocity=_value(raw.get("velocity", [0.0, 0.0, 0.0]), f"{where}.velocity", 3),
        spin=_value(raw.get("spin", [0.0, 0.0, 0.0]), f"{where}.spin", 3),
        stiffness=_value(raw.get("stiffness", 0.5), f"{where}.stiffness", None),
        friction=_value(raw["friction"], f"{where}.friction", None) if "friction" in raw else None,
    )
    if material == "static" and (np.any(spec.velocity[1] != 0) or np.any(spec.velocity[0] != 0)
                                 or np.any(spec.spin[0] != 0) or np.any(spec.spin[1] != 0)):
        raise ValueError(f"{where}: a static object cannot have a velocity or a spin")
    for key in ("size", "scale", "mass"):
        value = getattr(spec, key)
        if value is not None and value[0] <= 0:
            raise ValueError(f"{where}.{key}: must be > 0, got {value[0].tolist()}")
    if not (0.0 <= spec.stiffness[0] and spec.stiffness[1] <= 1.0):
        raise ValueError(f"{where}.stiffness: must lie in [0, 1], got {spec.stiffness[0]}..{spec.stiffness[1]}")
    if spec.friction is not None and spec.friction[0] < 0:
        raise ValueError(f"{where}.friction: must be >= 0")
    if spec.orientation is not None and np.any(np.linalg.norm(spec.orientation[0]) == 0):
        raise ValueError(f"{where}.orientation: a quaternion [x, y, z, w] of nonzero length")
    mesh_of = spec.base_mesh
    if mesh_of is not None and material != "cloth" and not (mesh_of.volume > 0 if mesh_of.is_watertight else mesh_of.extents.min() > 0):
        raise ValueError(f"{where}: the mesh has no volume (it is flat)")
    return spec


def mesh_path(mesh: str, base: Path) -> Path:
    """Where a scene file's ``mesh`` is: an absolute path, ``pybullet_data:<path>`` (a mesh that
    ships with pybullet, wherever it is installed) or a path relative to the file's folder."""
    if mesh.startswith(PYBULLET_DATA):
        import pybullet_data

        return Path(pybullet_data.getDataPath()) / mesh[len(PYBULLET_DATA):]
    return Path(mesh) if Path(mesh).is_absolute() else base / mesh


def _push(raw: Any, where: str, objects: tuple[ObjectSpec, ...], steps: int) -> PushSpec:
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a table")
    _check_keys(raw, PUSH_KEYS, where)
    index = raw.get("object")
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(objects):
        raise ValueError(f"{where}.object: an index into objects (0..{len(objects) - 1}), got {index!r}")
    if objects[index].material == "static":
        raise ValueError(f"{where}.object: object {index} is static and cannot be pushed")
    span = raw.get("steps")
    if (not isinstance(span, list) or len(span) != 2 or not all(isinstance(s, int) and not isinstance(s, bool)
                                                                   for s in span)
            or not 0 <= span[0] <= span[1] < steps):
        raise ValueError(f"{where}.steps: [first, last] model steps within 0..{steps - 1}, got {span!r}")
    if "force" not in raw:
        raise ValueError(f"{where}: force (N, a list of 3 numbers) is required")
    return PushSpec(object=index, first=span[0], last=span[1], force=_value(raw["force"], f"{where}.force", 3))


def posed_mesh(obj: ObjectSpec, drawn: dict) -> trimesh.Trimesh | None:
    """The object's mesh sized by its drawn ``size`` or ``scale``, centred (None: a sheet)."""
    if obj.base_mesh is None:
        return None
    if "size" in drawn:
        return sized_mesh(obj.base_mesh, size=float(drawn["size"]))
    return sized_mesh(obj.base_mesh, scale=float(drawn["scale"]))


def quaternion(drawn: dict) -> list[float]:
    """The drawn orientation as a unit quaternion ``[x, y, z, w]`` (yaw in degrees)."""
    if "orientation" in drawn:
        q = np.asarray(drawn["orientation"], dtype=np.float64)
        return (q / np.linalg.norm(q)).tolist()
    yaw = math.radians(drawn.get("yaw", 0.0))
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]


def start_box(obj: ObjectSpec, drawn: dict) -> tuple[np.ndarray, np.ndarray]:
    """The object's axis-aligned bounding box at the start, ``(low [3], high [3])``."""
    centre = np.asarray(drawn["position"])
    mesh = posed_mesh(obj, drawn)
    if mesh is None:
        half = np.array([drawn["size"] / 2, drawn["size"] / 2, 0.0])
        return centre - half, centre + half
    x, y, z, w = quaternion(drawn)
    rotation = trimesh.transformations.quaternion_matrix([w, x, y, z])[:3, :3]
    corners = np.asarray(trimesh.bounds.corners(mesh.bounds)) @ rotation.T
    return centre + corners.min(axis=0), centre + corners.max(axis=0)


def overlapping(spec: SceneSpec, drawn: list[dict]) -> list[tuple[int, int]]:
    """Pairs of objects whose start boxes overlap (touching is allowed)."""
    boxes = [start_box(o, d) for o, d in zip(spec.objects, drawn)]
    return [(i, j) for i in range(len(boxes)) for j in range(i + 1, len(boxes))
            if np.all(boxes[i][0] < boxes[j][1]) and np.all(boxes[j][0] < boxes[i][1])]


class FileScene(Scene):
    """The pybullet scene of a :class:`SceneSpec` and a seed (see :class:`~hrn_pyg.data.scenes.Scene`)."""

    uses_deformables = True

    def __init__(self, spec: SceneSpec, seed: int) -> None:
        self.spec = spec
        self.name = spec.name
        self.config_cls = SceneConfig
        self.effects = spec.effects
        self.actuated = tuple(sorted({q.object for q in spec.pushes}))
        super().__init__(seed, spec.config)

    def draw_params(self, rng: np.random.Generator) -> dict:
        return self.spec.draw(rng)

    def build(self) -> None:
        for index, (obj, drawn) in enumerate(zip(self.spec.objects, self.params["objects"])):
            material = MATERIALS.index(obj.material)
            if material in (RIGID, STATIC):
                self._add_mesh_body(obj, drawn, material == STATIC, f"objects[{index}]")
            elif material == SOFT:
                self._add_soft_mesh(obj, drawn, f"objects[{index}]")
            else:
                self._add_cloth(obj, drawn, f"objects[{index}]")
            self._start_moving(self._objects[-1], drawn)

    def scripted_action(self, t: int) -> tuple[np.ndarray, np.ndarray | None]:
        forces = self.zero_action()
        for push, force in zip(self.spec.pushes, self.params["pushes"]):
            if push.first <= t <= push.last:
                forces[push.object] += force
        return forces, None

    # -- bodies -------------------------------------------------------------------------------
    def _leaves(self, mesh: trimesh.Trimesh, where: str) -> np.ndarray:
        return leaves_of(mesh, self.config.pitch, f"{self.spec.name}: {where}")

    def _add_mesh_body(self, obj: ObjectSpec, drawn: dict, static: bool, where: str) -> None:
        c = self._client
        mesh = posed_mesh(obj, drawn)
        leaves = self._leaves(mesh, where)
        shape = self._collision_shape(obj, mesh, static)
        mass = STATIC_DENSITY * float(mesh.volume) if static else float(drawn["mass"])
        body = p.createMultiBody(0.0 if static else mass, shape, basePosition=list(drawn["position"]),
                                 baseOrientation=quaternion(drawn), physicsClientId=c)
        p.changeDynamics(body, -1, lateralFriction=drawn.get("friction", self.config.friction), physicsClientId=c)
        self._objects.append(SceneObject(STATIC if static else RIGID, body, mass, 1.0, leaves))

    def _collision_shape(self, obj: ObjectSpec, mesh: trimesh.Trimesh, static: bool) -> int:
        """A primitive's own pybullet shape; a convex mesh as its hull; a concave one as its
        convex parts (moving) or as its triangles (static)."""
        c, extents = self._client, np.asarray(mesh.extents)
        if obj.mesh == "box":
            return p.createCollisionShape(p.GEOM_BOX, halfExtents=(extents / 2).tolist(), physicsClientId=c)
        if obj.mesh == "sphere":
            return p.createCollisionShape(p.GEOM_SPHERE, radius=float(extents.max() / 2), physicsClientId=c)
        if obj.mesh == "cylinder":
            return p.createCollisionShape(p.GEOM_CYLINDER, radius=float(extents[0] / 2), height=float(extents[2]),
                                          physicsClientId=c)
        if obj.mesh == "capsule":
            radius = float(extents[0] / 2)
            return p.createCollisionShape(p.GEOM_CAPSULE, radius=radius, height=float(extents[2] - 2 * radius),
                                          physicsClientId=c)
        hull = mesh.convex_hull
        if obj.mesh == "cone" or (mesh.is_watertight and hull.volume - mesh.volume <= 0.02 * hull.volume):
            return p.createCollisionShape(p.GEOM_MESH, vertices=hull.vertices.tolist(), physicsClientId=c)
        if static:
            return p.createCollisionShape(p.GEOM_MESH, vertices=mesh.vertices.tolist(),
                                          indices=mesh.faces.flatten().tolist(),
                                          flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=c)
        return p.createCollisionShape(p.GEOM_MESH, fileName=str(convex_parts(mesh, CACHE_DIR)), physicsClientId=c)

    def _add_soft_mesh(self, obj: ObjectSpec, drawn: dict, where: str) -> None:
        """A soft body: the tetrahedra of the mesh's voxel lattice."""
        nodes, tets = lattice_tetrahedra(self._leaves(posed_mesh(obj, drawn), where), self.config.pitch)
        self._add_soft_lattice(nodes, tets, float(drawn["mass"]), stiffness_exponent(drawn, SOFT_LOG10_MU_RANGE),
                               drawn["position"], quaternion(drawn), drawn.get("friction", self.config.friction))

    def _add_cloth(self, obj: ObjectSpec, drawn: dict, where: str) -> None:
        """A mass-spring cloth: a square sheet on the lattice, or a surface mesh whose (merged)
        vertices are the leaves."""
        mesh = posed_mesh(obj, drawn)
        if mesh is None:
            vertices, faces = grid_sheet(float(drawn["size"]), self.config.pitch)
        else:
            vertices, faces = surface_leaves(mesh, f"{self.spec.name}: {where}"), np.asarray(mesh.faces)
        self._add_cloth_mesh(vertices, faces, float(drawn["mass"]), stiffness_exponent(drawn, CLOTH_LOG10_K_RANGE),
                             drawn["position"], quaternion(drawn), drawn.get("friction", self.config.friction))

    def _start_moving(self, obj: SceneObject, drawn: dict) -> None:
        """The drawn start velocity and spin (a soft body's nodes move as one rigid body)."""
        velocity, spin = np.asarray(drawn["velocity"]), np.asarray(drawn["spin"])
        if obj.material == STATIC or not (np.any(velocity) or np.any(spin)):
            return
        p.resetBaseVelocity(obj.body, velocity.tolist(), spin.tolist(), physicsClientId=self._client)
        if obj.material in (SOFT, CLOTH):
            x = self._object_positions(obj)
            obj.velocity = velocity + np.cross(spin, x - x.mean(axis=0))


def stiffness_exponent(drawn: dict, log10_range: tuple[float, float]) -> float:
    """The drawn ``stiffness`` in [0, 1] as the exponent of pybullet's modulus over ``log10_range``."""
    low, high = log10_range
    return low + float(drawn["stiffness"]) * (high - low)


def surface_leaves(mesh: trimesh.Trimesh, name: str) -> np.ndarray:
    """A cloth's leaves: the vertices of its surface mesh, at most :data:`MAX_LEAVES`."""
    if len(mesh.vertices) > MAX_LEAVES:
        raise ValueError(f"{name}: a cloth mesh of {len(mesh.vertices)} vertices, more than {MAX_LEAVES}; "
                         "simplify it")
    return np.asarray(mesh.vertices, dtype=np.float64)


def leaves_of(mesh: trimesh.Trimesh, pitch: float, name: str) -> np.ndarray:
    """:func:`~hrn_pyg.data.meshes.solid_points` of a posed mesh, at most :data:`MAX_LEAVES`
    (more is an error that names a pitch that fits)."""
    points, _ = solid_points(mesh, pitch, name, max_leaves=MAX_LEAVES)
    if len(points) > MAX_LEAVES:
        raise too_many_leaves(len(points), pitch, MAX_LEAVES, name)
    return points
