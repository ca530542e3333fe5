"""Scenes from files: a TOML file of objects (any mesh, any material) and scripted pushes.

The format, with every key, is in docs/own_objects.md ("The file"): ``steps`` and the scene's
settings, ``[[objects]]`` (``mesh``, ``material``, ``size``, ``mass``, ``position``, ``yaw``,
...), ``[[pushes]]`` (a force, a velocity change or a random schedule), ``[settings]`` and
``[draw]``. Any number or vector may be a range ``{ min = ..., max = ... }`` drawn per seed, or
an expression (:mod:`hrn_pyg.data.expressions`). A seed's draws come in file order; objects that
overlap at the start (oriented bounding boxes, deeper than :data:`TOUCHING`) are drawn again,
up to :data:`OVERLAP_TRIES` times, unless ``pass_through`` or ``overlap = "allow"`` says so.

:func:`read_scene_file` reads and validates a file into a :class:`SceneSpec` (every mistake one
line naming the key); :meth:`SceneSpec.make_scene` gives the pybullet scene of a seed. The
package's own scenes are such files (:data:`SCENES`, :func:`builtin_scene`). A file is bounded
(:data:`MAX_FILE_CHARS`, counts of objects, pushes, draws, settings and mesh choices, steps,
sheet leaves, expressions); past a limit a :class:`~hrn_pyg.data.expressions.LimitError` names it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from hrn_pyg.data.expressions import (
    CONSTANTS,
    DRAWS,
    LimitError,
    check_elements,
    checked,
    count_text,
    evaluate,
    names_in,
)
from hrn_pyg.data.kinds import CLOTH, MATERIALS, RIGID, SCENES, SOFT, STATIC, SceneEffects  # noqa: F401  SCENES, here too
from hrn_pyg.data.meshes import (
    PRIMITIVE_PROPORTIONS,
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
    SOFT_COLLISION_MARGIN,
    SOFT_LOG10_MU_RANGE,
    STATIC_DENSITY,
    Scene,
    SceneConfig,
    SceneObject,
)
from hrn_pyg.data.voxelise import grid_sheet, lattice_tetrahedra
from hrn_pyg.utils.files import import_pybullet

p = import_pybullet()

#: the settings of a scene's top level (:class:`~hrn_pyg.data.scenes.SceneConfig`'s fields)
TOP_SETTINGS = tuple(f.name for f in dataclasses.fields(SceneConfig))
#: keys of the file's top level, of an object, of a push and of a random push schedule
SCENE_KEYS = (*TOP_SETTINGS, "engine", "effects", "pass_through", "overlap", "settings", "draw", "objects", "pushes")
OBJECT_KEYS = ("mesh", "material", "up", "size", "scale", "extents", "mass", "position", "orientation", "yaw", "velocity",
               "spin", "stiffness", "log10_mu", "log10_spring_k", "friction")
PUSH_KEYS = ("object", "steps", "every", "force", "velocity", "towards", "spin", "random")
RANDOM_KEYS = ("force", "hold", "pause", "aim", "aim_noise")
#: object fields drawn per seed, in the order they are drawn, with their length (None: a number)
OBJECT_FIELDS: dict[str, int | None] = {
    "size": None, "scale": None, "extents": 3, "mass": None, "position": 3, "orientation": 4, "yaw": None,
    "velocity": 3, "spin": 3, "stiffness": None, "log10_mu": None, "log10_spring_k": None, "friction": None}
#: a cloth is a square sheet of side ``size``
SHEET = "sheet"
#: a mesh's ``up`` axis -> the rotation that turns it to +z (the package's up): y up turns
#: +90 degrees about x, x up -90 degrees about y; z is the default and changes nothing
UP_ROTATIONS = {"z": np.eye(3), "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
                "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])}
#: a mesh named ``pybullet_data:<path>`` is one of the meshes that ship with pybullet
PYBULLET_DATA = "pybullet_data:"
#: draws of one seed tried before objects that overlap at the start are an error
OVERLAP_TRIES = 100
#: boxes that meet by no more than this (m) touch; they do not overlap
TOUCHING = 1e-9
#: the most leaves one object may have (the model's cost grows with them)
MAX_LEAVES = 20_000
#: the longest scene file (characters; the package's longest has under 3,000): reading and
#: parsing it take milliseconds
MAX_FILE_CHARS = 256 * 1024
#: the most objects of a scene (the package's largest has 4): each one's meshes are loaded and
#: voxelised (up to :data:`MAX_LEAVES` leaves each) and the model's cost grows with them
MAX_OBJECTS = 64
#: the most pushes of a scene (each is drawn per seed and applied every step)
MAX_PUSHES = 64
#: the most values of ``[draw]`` (evaluated per seed and redrawn up to :data:`OVERLAP_TRIES`
#: times) and of ``[settings]``; with the expressions' own limits they bound a seed's draw
MAX_DRAWS = 256
MAX_SETTINGS = 256
#: the most meshes one object draws from (every one is loaded and checked when the file is
#: read; ``data/shapes/meshes`` holds 49)
MAX_MESH_CHOICES = 256
#: the most model steps of an episode and physics steps of a model step: an episode's arrays
#: are allocated for all its steps at once and its time grows with both (the package's scenes
#: have 150 and 8)
MAX_STEPS = 10_000
MAX_SUBSTEPS = 1_000
#: the deepest a scene file's tables, lists and dotted keys may nest (the package's scenes: 3),
#: counted on the raw text before it is parsed (:func:`toml_nesting`)
MAX_NESTING = 32
#: what :func:`toml_nesting` stops at: a string's opening quotes, a comment, a bracket, a dot and
#: what ends a key
_TOML_SIGN = re.compile(r'"""|\'\'\'|["\'#\[\]{}.=,\n]')
#: where convex decompositions are cached (``HRN_PYG_CACHE`` overrides it)
CACHE_DIR = Path(os.environ.get("HRN_PYG_CACHE", Path.home() / ".cache" / "hrn_pyg")) / "convex_parts"
#: the engines a scene file may name (``engine = ...``); the first is the default
ENGINES = ("pybullet", "mujoco")
#: engine -> its scene class (called as ``cls(spec, seed)``); an engine's module adds itself
#: (:mod:`hrn_pyg.data.mujoco_scene`), the pybullet one is :class:`FileScene` below
ENGINE_SCENES: dict[str, Any] = {}
#: the package's own scenes (their names: :data:`~hrn_pyg.data.kinds.SCENES`), one file each
BUILTIN_DIR = Path(__file__).with_name("builtin_scenes")

#: a fixed value or a ``{min, max}`` range as ``(low, high)`` arrays, or an expression
Value = tuple[np.ndarray, np.ndarray] | str


def _value(raw: Any, where: str, length: int | None) -> Value:
    """A number or vector (``length``), a ``{min, max}`` range of them as ``(low, high)``, or an
    expression (a string; its names are checked by :func:`_check_names`)."""
    if isinstance(raw, str):
        return raw
    if isinstance(raw, dict):
        if set(raw) != {"min", "max"}:
            raise ValueError(f"{where}: a range needs exactly the keys min and max, got {sorted(raw)}")
        low, high = _value(raw["min"], f"{where}.min", length), _value(raw["max"], f"{where}.max", length)
        if isinstance(low, str) or isinstance(high, str):
            raise ValueError(f"{where}: a range's min and max are numbers; draw with uniform() in an expression")
        low, high = low[0], high[0]
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


def _read_values(raw: dict, lengths: dict[str, int | None], known: set[str], where: str) -> dict[str, Value]:
    """The fields of ``raw`` named in ``lengths`` (key -> vector length, None: a number), read by
    :func:`_value`; an expression's names must be ``known``."""
    values = {}
    for key, length in lengths.items():
        if key in raw:
            values[key] = _value(raw[key], f"{where}.{key}", length)
            if isinstance(values[key], str):
                _check_names(values[key], known, f"{where}.{key}")
    return values


def _at(exc: ValueError, where: str) -> ValueError:
    """``exc`` with ``where`` (the key) before its message, a LimitError kept one."""
    return (LimitError if isinstance(exc, LimitError) else ValueError)(f"{where}: {exc}")


def _check_count(count: int, limit: int, what: str, where: str) -> None:
    """LimitError when a file has more than ``limit`` of ``what``."""
    if count > limit:
        raise LimitError(f"{where}: {count} {what}, more than {limit}")


def _check_steps(config: SceneConfig, where: str) -> None:
    """LimitError for more than :data:`MAX_STEPS` steps or :data:`MAX_SUBSTEPS` substeps."""
    for key, limit in (("steps", MAX_STEPS), ("substeps", MAX_SUBSTEPS)):
        if getattr(config, key) > limit:
            raise LimitError(f"{where}: {key} = {getattr(config, key)}, more than {limit}")


def _check_name(key: str, where: str) -> None:
    """A ``[settings]`` or ``[draw]`` key must be a name an expression can read."""
    if not key.isidentifier():
        raise ValueError(f"{where}: {key[:40]!r} is not a name (letters, digits and _, not starting with a digit)")


def _check_names(text: str, known: set[str], where: str) -> None:
    try:
        unknown = sorted(names_in(text) - known - set(CONSTANTS))
    except ValueError as exc:
        raise _at(exc, where) from None
    if unknown:
        raise ValueError(f"{where}: unknown name {unknown[0]!r} in {text!r}; the names known here are "
                         f"{', '.join(sorted(known)) or 'none'}")


def _draw(rng: np.random.Generator, value: Value, names: dict, where: str, length: int | None) -> Any:
    """One seed's value of a field (JSON-able: a float, an int or a list)."""
    if isinstance(value, str):
        try:
            drawn = evaluate(value, names, rng)
            array = np.asarray(drawn, dtype=np.float64)
        except ValueError as exc:
            raise _at(exc, where) from None
        except (TypeError, OverflowError) as exc:
            raise ValueError(f"{where}: {value!r} is not a number or a list of numbers ({exc})") from None
        if (length is None and array.ndim != 0) or (length is not None and array.shape != (length,)):
            expected = "a number" if length is None else f"{length} numbers"
            raise ValueError(f"{where}: {value!r} gives {array.tolist()}, expected {expected}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"{where}: {value!r} is not finite ({array.tolist()})")
        return array.tolist()
    low, high = value
    return (low.copy() if np.array_equal(low, high) else np.asarray(rng.uniform(low, high))).tolist()


def _json(value: Any) -> Any:
    """A drawn value as JSON (arrays as lists)."""
    return value.tolist() if isinstance(value, np.ndarray) else value


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a scene file: its mesh (or the meshes one is drawn from per seed, each as
    likely), its material, and every other field a ``(low, high)`` pair (equal when fixed), an
    expression, or None when not given."""

    meshes: tuple[str, ...]
    material: str
    up: str = "z"
    size: Value | None = None
    scale: Value | None = None
    extents: Value | None = None
    mass: Value = (np.array(1.0), np.array(1.0))
    position: Value = (np.zeros(3), np.zeros(3))
    orientation: Value | None = None
    yaw: Value | None = None
    velocity: Value = (np.zeros(3), np.zeros(3))
    spin: Value = (np.zeros(3), np.zeros(3))
    stiffness: Value | None = None
    log10_mu: Value | None = None
    log10_spring_k: Value | None = None
    friction: Value | None = None

    @property
    def mesh(self) -> str:
        """The object's mesh when it has one (the first of its choices otherwise)."""
        return self.meshes[0]


def base_mesh(mesh: str) -> trimesh.Trimesh | None:
    """A mesh file cleaned (seams merged), or a primitive at its unit size, before sizing; None
    for a sheet. Kept in memory by path, size and time of change: a dataset draws the same few
    meshes again and again, and a file changed since is read again."""
    if mesh == SHEET:
        return None
    stat = os.stat(mesh) if mesh not in PRIMITIVES and os.path.isfile(mesh) else None
    return _base_mesh(mesh, None if stat is None else (stat.st_size, stat.st_mtime_ns))


@lru_cache(maxsize=256)
def _base_mesh(mesh: str, version: tuple[int, int] | None) -> trimesh.Trimesh:
    return primitive_mesh(mesh) if mesh in PRIMITIVES else clean_mesh(load_mesh(mesh), mesh)


def drawn_mesh(obj: ObjectSpec, drawn: dict) -> str:
    """The mesh a seed drew for ``obj`` (``drawn["mesh"]`` is an index into its choices)."""
    return obj.meshes[int(drawn.get("mesh", 0))]


@dataclass(frozen=True)
class PushSpec:
    """A scripted push (see the module's docstring): its fields as read, expressions or values."""

    objects: tuple[int, ...]
    steps: Value
    every: Value | None = None
    force: Value | None = None
    velocity: Value | None = None
    towards: int | None = None
    spin: Value | None = None
    random: dict[str, Value] | None = None


@dataclass(frozen=True)
class SceneSpec:
    """A scene read from a file (:func:`read_scene_file`)."""

    name: str
    config: SceneConfig
    objects: tuple[ObjectSpec, ...]
    pushes: tuple[PushSpec, ...] = ()
    settings: dict[str, Any] = field(default_factory=dict)
    draws: tuple[tuple[str, str], ...] = ()
    pass_through: tuple[tuple[int, int], ...] = ()
    allow_overlap: bool = False
    declared_effects: dict[str, bool] = field(default_factory=dict)
    source: str = ""
    text: str = field(default="", repr=False)
    engine: str = ENGINES[0]

    @property
    def effects(self) -> SceneEffects:
        """What the file declares; else pushed objects need the force module and a lone object
        no collision search."""
        derived = {"forces": bool(self.pushes), "collisions": len(self.objects) > 1 or None}
        return SceneEffects(**(derived | self.declared_effects))

    @property
    def draws_anything(self) -> bool:
        """Whether a seed changes anything: a ``[draw]`` table, an expression that calls
        ``uniform`` or ``integer``, a range whose ends differ, a choice of meshes, or a random push.
        A scene that draws nothing makes the same episode for every seed."""
        def random(value: Any) -> bool:
            if isinstance(value, str):
                return any(f"{name}(" in value for name in DRAWS)
            if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, np.ndarray) for v in value):
                return not np.array_equal(value[0], value[1])
            if isinstance(value, dict):
                return any(random(v) for v in value.values())
            return False

        if self.draws or any(len(o.meshes) > 1 for o in self.objects):
            return True
        parts = [*self.objects, *self.pushes]
        return any(random(getattr(part, f.name)) for part in parts for f in dataclasses.fields(part)) or any(
            p.random for p in self.pushes)

    @property
    def uses_deformables(self) -> bool:
        return any(o.material in ("soft", "cloth") for o in self.objects)

    def settings_dict(self) -> dict[str, Any]:
        """Every setting a user may change (the top level's and ``[settings]``), JSON-able."""
        top = {f.name: getattr(self.config, f.name) for f in dataclasses.fields(self.config)}
        return top | {k: _json(v) for k, v in self.settings.items()}

    def with_settings(self, **overrides: Any) -> SceneSpec:
        """A copy with settings replaced (``None`` values ignored); unknown names are an error
        naming the settings there are."""
        overrides = {k: v for k, v in overrides.items() if v is not None}
        known = set(TOP_SETTINGS) | set(self.settings)
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"{self.name}: unknown setting {unknown[0]!r}; the settings are {', '.join(sorted(known))}")
        top = {k: v for k, v in overrides.items() if k in TOP_SETTINGS}
        try:
            config = dataclasses.replace(self.config, **top)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.name}: {exc}") from None
        _check_steps(config, self.name)
        settings = dict(self.settings)
        for key, value in overrides.items():
            if key not in TOP_SETTINGS:
                settings[key] = _setting(value, f"{self.name}: settings.{key}")
        return dataclasses.replace(self, config=config, settings=settings)

    def make_scene(self, seed: int) -> FileScene:
        """The scene of seed ``seed`` in the spec's engine (call ``reset()`` to start it)."""
        if self.engine not in ENGINE_SCENES:
            raise ValueError(f"{self.name}: the {self.engine} engine is not loaded (import "
                             f"hrn_pyg.data.{self.engine}_scene, or use hrn_pyg.data.episodes)")
        return ENGINE_SCENES[self.engine](self, seed)

    def with_engine(self, engine: str | None) -> SceneSpec:
        """A copy simulated by ``engine`` (one of :data:`ENGINES`; None: unchanged)."""
        return self if engine is None else dataclasses.replace(self, engine=_engine(engine, self.name))

    def names(self) -> dict[str, Any]:
        """What an expression may read before the draws: the settings and the scene's constants."""
        cfg = self.config
        return {"steps": cfg.steps, "substeps": cfg.substeps, "physics_hz": cfg.physics_hz, "pitch": cfg.pitch,
                "friction": cfg.friction, "rolling_friction": cfg.rolling_friction, "dt": cfg.dt,
                "soft_margin": SOFT_COLLISION_MARGIN, **self.settings}

    def draw(self, rng: np.random.Generator) -> dict:
        """One seed's values: the ``[draw]`` table, then every object's and push's fields,
        redrawn while objects overlap (JSON-able)."""
        for _ in range(OVERLAP_TRIES):
            params = self._draw_once(rng)
            if self.allow_overlap or not overlapping(self, params["objects"]):
                return params
        first, second = overlapping(self, params["objects"])[0]
        raise ValueError(f"{self.name}: objects {first} and {second} overlap at the start in every one of "
                         f"{OVERLAP_TRIES} draws; move them apart")

    def _draw_once(self, rng: np.random.Generator) -> dict:
        names = self.names()
        drawn_names: dict[str, Any] = {}
        for name, text in self.draws:
            try:
                names[name] = evaluate(text, names, rng)
            except ValueError as exc:
                raise _at(exc, f"{self.name}: draw.{name}") from None
            drawn_names[name] = _json(names[name])
        objects = [self._draw_object(i, o, rng, names) for i, o in enumerate(self.objects)]
        pushes = [self._draw_push(i, q, rng, names) for i, q in enumerate(self.pushes)]
        return {**drawn_names, "objects": objects, "pushes": pushes}

    def _draw_object(self, index: int, obj: ObjectSpec, rng: np.random.Generator, names: dict) -> dict:
        where = f"{self.name}: objects[{index}]"
        drawn = {"mesh": int(rng.integers(len(obj.meshes)))} if len(obj.meshes) > 1 else {}
        for name, length in OBJECT_FIELDS.items():
            value = getattr(obj, name)
            if value is not None:
                drawn[name] = _draw(rng, value, names, f"{where}.{name}", length)
        _check_object_values(drawn, obj, where)
        return drawn

    def _draw_push(self, index: int, push: PushSpec, rng: np.random.Generator, names: dict) -> dict:
        where = f"{self.name}: pushes[{index}]"
        drawn: dict[str, Any] = {"steps": _draw(rng, push.steps, names, f"{where}.steps", 2)}
        for key, length in (("every", None), ("force", 3), ("velocity", None if push.towards is not None else 3),
                            ("spin", 3)):
            value = getattr(push, key)
            if value is not None:
                drawn[key] = _draw(rng, value, names, f"{where}.{key}", length)
        if push.random is not None:
            drawn["random"] = {key: _draw(rng, value, names, f"{where}.random.{key}", None if key == "aim" else 2)
                               for key, value in push.random.items()}
        _check_push_values(drawn, len(self.objects), where)
        return drawn

    def check(self, seed: int = 0) -> None:
        """Raise the errors an episode of ``seed`` would raise before it simulates anything:
        objects that overlap in every draw, a mesh with too few or too many leaves at the pitch."""
        drawn = self.draw(np.random.default_rng(seed))["objects"]
        for index, (obj, values) in enumerate(zip(self.objects, drawn)):
            mesh = posed_mesh(obj, values)
            where = f"{self.name}: objects[{index}]"
            if mesh is None:
                check_sheet(float(values["size"]), self.config.pitch, where)
                continue
            if obj.material == "cloth":
                surface_leaves(mesh, where)
            elif obj.material == "soft":
                soft_lattice(mesh, self.config.pitch, where)
            else:
                leaves_of(mesh, self.config.pitch, where)


def _whole(value: Any, where: str, low: int = 0) -> int:
    number = float(value)
    if number != round(number) or number < low:
        raise ValueError(f"{where}: a whole number >= {low}, got {value}")
    return int(number)


def _check_object_values(drawn: dict, obj: ObjectSpec, where: str) -> None:
    """A drawn object's values in their domains (ranges and fixed values were checked when read)."""
    for key in ("size", "scale", "mass"):
        if key in drawn and not drawn[key] > 0:
            raise ValueError(f"{where}.{key}: must be > 0, got {drawn[key]}")
    if "extents" in drawn and not min(drawn["extents"]) > 0:
        raise ValueError(f"{where}.extents: must be > 0, got {drawn['extents']}")
    if "stiffness" in drawn and not 0.0 <= drawn["stiffness"] <= 1.0:
        raise ValueError(f"{where}.stiffness: must lie in [0, 1], got {drawn['stiffness']}")
    if "friction" in drawn and drawn["friction"] < 0:
        raise ValueError(f"{where}.friction: must be >= 0, got {drawn['friction']}")
    if "orientation" in drawn and not np.linalg.norm(drawn["orientation"]) > 0:
        raise ValueError(f"{where}.orientation: a quaternion [x, y, z, w] of nonzero length")
    if obj.material == "static" and (np.any(drawn["velocity"]) or np.any(drawn["spin"])):
        raise ValueError(f"{where}: a static object cannot have a velocity or a spin")


def _check_push_values(drawn: dict, n_objects: int, where: str) -> None:
    first, last = drawn["steps"]  # steps past the episode's end are never reached (a shortened episode)
    if not (first == round(first) and last == round(last) and 0 <= first <= last):
        raise ValueError(f"{where}.steps: [first, last] whole model steps with 0 <= first <= last, got {drawn['steps']}")
    drawn["steps"] = [int(first), int(last)]
    if "every" in drawn:
        drawn["every"] = _whole(drawn["every"], f"{where}.every", 1)
    if "random" in drawn:
        schedule = drawn["random"]
        for key in ("hold", "pause"):
            lo, hi = (_whole(v, f"{where}.random.{key}") for v in schedule[key])
            if lo > hi or (key == "hold" and lo < 1):
                raise ValueError(f"{where}.random.{key}: [low, high] steps with {'1' if key == 'hold' else '0'} "
                                 f"<= low <= high, got {schedule[key]}")
            schedule[key] = [lo, hi]
        if schedule["force"][0] > schedule["force"][1] or schedule["force"][0] < 0:
            raise ValueError(f"{where}.random.force: [low, high] N with 0 <= low <= high, got {schedule['force']}")
        if "aim" in schedule:
            schedule["aim"] = _whole(schedule["aim"], f"{where}.random.aim")
            if schedule["aim"] >= n_objects:
                raise ValueError(f"{where}.random.aim: an index into objects (0..{n_objects - 1})")


def _setting(raw: Any, where: str) -> Any:
    """A ``[settings]`` value: a number or a (nested) list of numbers (lists as arrays)."""
    if isinstance(raw, (list, tuple)):
        try:
            array = np.asarray(raw, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: a number or a list of numbers, got {raw!r}") from None
        check_elements(array.size, f"{where}: a list")
        if array.dtype == object or not np.all(np.isfinite(array)) or any(isinstance(x, bool) for x in np.ravel(raw)):
            raise ValueError(f"{where}: finite numbers, got {raw!r}")
        return array
    if isinstance(raw, int) and not isinstance(raw, bool):
        try:
            checked(raw)
        except LimitError as exc:
            raise _at(exc, where) from None
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw):
        raise ValueError(f"{where}: a finite number or a list of numbers, got {raw!r}")
    return raw


def read_scene_file(path: str | os.PathLike) -> SceneSpec:
    """The :class:`SceneSpec` of a scene file; ValueError naming the key for every mistake (a
    LimitError for a file or an expression past a limit), FileNotFoundError for a missing scene
    or mesh file. No more than :data:`MAX_FILE_CHARS` characters are read."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        with path.open(encoding="utf-8") as f:
            text = f.read(MAX_FILE_CHARS + 1)  # never more than the limit in memory
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x}: {exc.reason})") from None
    if len(text) > MAX_FILE_CHARS:
        raise LimitError(f"{path}: a scene file of more than {MAX_FILE_CHARS} characters")
    nesting = toml_nesting(text)
    if nesting > MAX_NESTING:
        raise LimitError(f"{path}: tables, lists and dotted keys nested {nesting} deep, more than {MAX_NESTING}")
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not TOML ({exc})") from None
    except RecursionError:
        raise LimitError(f"{path}: lists or tables nested too deeply") from None
    return parse_scene(table, name=path.stem, base=path.parent, source=str(path), text=text)


def toml_nesting(text: str) -> int:
    """How deep one key, table header or value of TOML ``text`` nests at most, read off the raw
    characters so the parser never meets a file past :data:`MAX_NESTING`: outside strings and
    comments, the open ``[`` and ``{`` plus the dots of the key being read (resetting at ``=``,
    ``,``, a bracket and a line end)."""
    deepest = depth = dots = 0
    position = 0
    while (match := _TOML_SIGN.search(text, position)) is not None:
        sign, position = match.group(), match.end()
        if sign in ("\"", "'", '"""', "'''"):  # skip to the string's end (escapes in basic strings)
            end = position
            while (end := text.find(sign, end)) >= 0 and sign[0] == '"' and _escaped(text, end):
                end += 1
            if end < 0:
                break  # an unclosed string: the parser says so
            position = end + len(sign)
        elif sign == "#":
            end = text.find("\n", position)
            position = len(text) if end < 0 else end
        elif sign == ".":
            dots += 1
        else:
            depth = depth + 1 if sign in "[{" else max(depth - 1, 0) if sign in "]}" else depth
            dots = 0
        deepest = max(deepest, depth + dots)
    return deepest


def _escaped(text: str, index: int) -> bool:
    """Whether the character at ``index`` follows an odd run of backslashes."""
    run = index
    while run > 0 and text[run - 1] == "\\":
        run -= 1
    return (index - run) % 2 == 1


def parse_scene(table: dict, name: str = "scene", base: Path = Path("."), source: str = "", text: str = "") -> SceneSpec:
    """A :class:`SceneSpec` from the file's TOML table (mesh paths relative to ``base``)."""
    _check_keys(table, SCENE_KEYS, name)
    if "steps" not in table:
        raise ValueError(f"{name}: steps (model steps per episode) is required")
    top = {key: table[key] for key in TOP_SETTINGS if key in table}
    for key, value in top.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{name}: {key} must be a number, got {value!r}")
    try:
        config = SceneConfig(**top)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: {exc}") from None
    _check_steps(config, name)
    settings = _table(table, "settings", name)
    _check_count(len(settings), MAX_SETTINGS, "settings", name)
    for key in settings:
        _check_name(key, f"{name}: settings")
    settings = {key: _setting(value, f"{name}: settings.{key}") for key, value in settings.items()}
    clash = sorted(set(settings) & (set(TOP_SETTINGS) | set(CONSTANTS) | {"dt", "soft_margin"}))
    if clash:
        raise ValueError(f"{name}: settings.{clash[0]}: the name is taken (a scene setting or a constant)")
    known = set(settings) | set(TOP_SETTINGS) | {"dt", "soft_margin"}
    draws = []
    draw_table = _table(table, "draw", name)
    _check_count(len(draw_table), MAX_DRAWS, "draws", name)
    for key, expression in draw_table.items():
        _check_name(key, f"{name}: draw")
        if not isinstance(expression, str):
            raise ValueError(f"{name}: draw.{key}: an expression (a string) such as \"uniform(0, 1)\", got {expression!r}")
        if key in known or key in ("objects", "pushes"):
            raise ValueError(f"{name}: draw.{key}: the name is taken")
        _check_names(expression, known, f"{name}: draw.{key}")
        draws.append((key, expression))
        known.add(key)
    objects = table.get("objects")
    if not isinstance(objects, list) or not objects:
        raise ValueError(f"{name}: needs at least one [[objects]] table")
    _check_count(len(objects), MAX_OBJECTS, "objects", name)
    specs = tuple(_object(o, f"{name}: objects[{i}]", base, known) for i, o in enumerate(objects))
    pushes = table.get("pushes", [])
    if not isinstance(pushes, list):
        raise ValueError(f"{name}: pushes must be a list of [[pushes]] tables")
    _check_count(len(pushes), MAX_PUSHES, "pushes", name)
    push_specs = tuple(_push(q, f"{name}: pushes[{i}]", specs, config.steps, known) for i, q in enumerate(pushes))
    return SceneSpec(name=name, config=config, objects=specs, pushes=push_specs, settings=settings,
                     draws=tuple(draws), pass_through=_pairs(table.get("pass_through", []), len(specs), name),
                     allow_overlap=_overlap_rule(table.get("overlap", "redraw"), name),
                     declared_effects=_effects(table.get("effects", {}), name), source=source, text=text,
                     engine=_engine(table.get("engine", ENGINES[0]), name))


def _engine(raw: Any, name: str) -> str:
    if raw not in ENGINES:
        raise ValueError(f"{name}: engine: one of {', '.join(ENGINES)}, got {raw!r}")
    return raw


def _table(table: dict, key: str, name: str) -> dict:
    value = table.get(key, {})
    if not isinstance(value, dict):
        raise ValueError(f"{name}: {key} must be a table [{key}]")
    return value


def _pairs(raw: Any, n_objects: int, name: str) -> tuple[tuple[int, int], ...]:
    ok = isinstance(raw, list) and all(
        isinstance(pair, list) and len(pair) == 2 and all(isinstance(i, int) and not isinstance(i, bool)
                                                          and 0 <= i < n_objects for i in pair) and pair[0] != pair[1]
        for pair in raw)
    if not ok:
        raise ValueError(f"{name}: pass_through: a list of [i, j] pairs of object indices (0..{n_objects - 1}), "
                         f"got {raw!r}")
    return tuple((min(i, j), max(i, j)) for i, j in raw)


def _overlap_rule(raw: Any, name: str) -> bool:
    if raw not in ("redraw", "allow"):
        raise ValueError(f"{name}: overlap: \"redraw\" (the default) or \"allow\", got {raw!r}")
    return raw == "allow"


def _effects(raw: Any, name: str) -> dict[str, bool]:
    if not isinstance(raw, dict) or set(raw) - {"forces", "collisions"} or not all(
            isinstance(v, bool) for v in raw.values()):
        raise ValueError(f"{name}: effects: a table of forces = true/false and collisions = true/false, got {raw!r}")
    return dict(raw)


def _object(raw: Any, where: str, base: Path, known: set[str]) -> ObjectSpec:
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a table")
    _check_keys(raw, OBJECT_KEYS, where)
    material = raw.get("material")
    if material not in MATERIALS:
        raise ValueError(f"{where}: unknown material {material!r}; choose from {', '.join(MATERIALS)}")
    raw_meshes = raw.get("mesh")
    raw_meshes = raw_meshes if isinstance(raw_meshes, list) and raw_meshes else [raw_meshes]
    _check_count(len(raw_meshes), MAX_MESH_CHOICES, "meshes", f"{where}.mesh")
    meshes = tuple(path for mesh in raw_meshes for path in _matching(mesh, base, where))
    _check_count(len(meshes), MAX_MESH_CHOICES, "meshes", f"{where}.mesh")
    meshes = tuple(_mesh(mesh, material, base, where) for mesh in meshes)
    if len(meshes) > 1 and SHEET in meshes:
        raise ValueError(f"{where}: a sheet is not drawn among other meshes")
    mesh = meshes[0]
    if sum(key in raw for key in ("size", "scale", "extents")) != 1:
        raise ValueError(f"{where}: give one of size (longest extent, m), scale and extents")
    if "extents" in raw and any(m not in PRIMITIVES for m in meshes):
        raise ValueError(f"{where}: extents are for primitives; size or scale a mesh file")
    if mesh == SHEET and "scale" in raw:
        raise ValueError(f"{where}: a sheet takes size (its side, m), not scale")
    if "orientation" in raw and "yaw" in raw:
        raise ValueError(f"{where}: give orientation or yaw, not both")
    if "position" not in raw:
        raise ValueError(f"{where}: position (m, the centre of the bounding box) is required")
    own = {"soft": "log10_mu", "cloth": "log10_spring_k"}.get(material)
    for key in ("log10_mu", "log10_spring_k"):
        if key in raw and key != own:
            raise ValueError(f"{where}: {key} is for {'soft' if key == 'log10_mu' else 'cloth'} objects")
    if own in raw and "stiffness" in raw:
        raise ValueError(f"{where}: give stiffness or {own}, not both")
    values = _read_values(raw, OBJECT_FIELDS, known, where)
    if material in ("soft", "cloth") and own not in raw and "stiffness" not in raw:
        values["stiffness"] = (np.array(0.5), np.array(0.5))
    up = raw.get("up", "z")
    if not isinstance(up, str) or up not in UP_ROTATIONS:
        raise ValueError(f"{where}.up: the mesh's up axis is one of {', '.join(sorted(UP_ROTATIONS))}, got {up!r}")
    spec = ObjectSpec(meshes=meshes, material=material, up=up, **values)
    fixed = {k: v for k, v in values.items() if not isinstance(v, str)}
    for key in ("size", "scale", "mass"):
        if key in fixed and fixed[key][0] <= 0:
            raise ValueError(f"{where}.{key}: must be > 0, got {fixed[key][0].tolist()}")
    if "extents" in fixed and np.any(fixed["extents"][0] <= 0):
        raise ValueError(f"{where}.extents: must be > 0, got {fixed['extents'][0].tolist()}")
    if "stiffness" in fixed and not (0.0 <= fixed["stiffness"][0] and fixed["stiffness"][1] <= 1.0):
        raise ValueError(f"{where}.stiffness: must lie in [0, 1], got {fixed['stiffness'][0]}..{fixed['stiffness'][1]}")
    if "friction" in fixed and fixed["friction"][0] < 0:
        raise ValueError(f"{where}.friction: must be >= 0")
    if "orientation" in fixed and np.linalg.norm(fixed["orientation"][0]) == 0:
        raise ValueError(f"{where}.orientation: a quaternion [x, y, z, w] of nonzero length")
    if material == "static" and any(key in fixed and (np.any(fixed[key][0]) or np.any(fixed[key][1]))
                                    for key in ("velocity", "spin")):
        raise ValueError(f"{where}: a static object cannot have a velocity or a spin")
    for mesh in meshes:
        mesh_of = base_mesh(mesh) if mesh not in PRIMITIVES else None
        if mesh_of is not None and material != "cloth" and not (
                mesh_of.volume > 0 if mesh_of.is_watertight else mesh_of.extents.min() > 0):
            raise ValueError(f"{where}: the mesh has no volume (it is flat)")
    return spec


def _matching(mesh: Any, base: Path, where: str) -> list[Any]:
    """The files a ``mesh`` entry with ``*`` names (sorted; relative to the scene file's folder),
    or the entry itself."""
    if not isinstance(mesh, str) or "*" not in mesh:
        return [mesh]
    pattern = mesh_path(mesh, base)
    found = sorted(str(path.resolve()) for path in pattern.parent.glob(pattern.name) if path.is_file())
    if not found:
        raise FileNotFoundError(f"{where}: no mesh file matches {pattern}")
    return found


def _mesh(mesh: Any, material: str, base: Path, where: str) -> str:
    """A checked ``mesh`` entry: a primitive's name, ``sheet`` or a mesh file's absolute path."""
    if not isinstance(mesh, str) or not mesh:
        raise ValueError(f"{where}: mesh (a file or one of {', '.join(PRIMITIVES)}, or a list of them) is required")
    if material == "cloth" and mesh in PRIMITIVES:
        raise ValueError(f"{where}: a cloth is a surface: mesh = {SHEET!r} or a surface mesh file")
    if mesh == SHEET and material != "cloth":
        raise ValueError(f"{where}: mesh = {SHEET!r} is for cloth only")
    if mesh in PRIMITIVES or mesh == SHEET:
        return mesh
    path = mesh_path(mesh, base)
    if not path.is_file():
        if any(sep in mesh for sep in "/\\."):
            raise FileNotFoundError(f"{where}: mesh file not found: {path}")
        raise ValueError(f"{where}: unknown primitive {mesh!r}; choose from {', '.join(PRIMITIVES)} "
                         "or give a mesh file")
    return str(path.resolve())


def mesh_path(mesh: str, base: Path) -> Path:
    """Where a scene file's ``mesh`` is: an absolute path, ``pybullet_data:<path>`` (a mesh that
    ships with pybullet, wherever it is installed) or a path relative to the file's folder."""
    if mesh.startswith(PYBULLET_DATA):
        import pybullet_data

        return Path(pybullet_data.getDataPath()) / mesh[len(PYBULLET_DATA):]
    return Path(mesh) if Path(mesh).is_absolute() else base / mesh


def _push(raw: Any, where: str, objects: tuple[ObjectSpec, ...], steps: int, known: set[str]) -> PushSpec:
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a table")
    _check_keys(raw, PUSH_KEYS, where)
    targets = raw.get("object")
    targets = targets if isinstance(targets, list) and targets else [targets]
    for index in targets:
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(objects):
            raise ValueError(f"{where}.object: an index into objects (0..{len(objects) - 1}) or a list of them, "
                             f"got {raw.get('object')!r}")
        if objects[index].material == "static":
            raise ValueError(f"{where}.object: object {index} is static and cannot be pushed")
    kinds = [key for key in ("force", "velocity", "random") if key in raw]
    if len(kinds) != 1 and not (kinds == [] and "spin" in raw):
        raise ValueError(f"{where}: give one of force (N), velocity (m/s) and random (a schedule)")
    if "steps" not in raw:
        raise ValueError(f"{where}.steps: [first, last] model steps is required")
    span = raw["steps"]
    if not isinstance(span, str) and (
            not isinstance(span, list) or len(span) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) for s in span)
            or not 0 <= span[0] <= span[1] < steps):
        raise ValueError(f"{where}.steps: [first, last] model steps within 0..{steps - 1}, got {span!r}")
    towards = raw.get("towards")
    if towards is not None:
        if "velocity" not in raw:
            raise ValueError(f"{where}.towards: needs velocity, a speed (m/s) towards that object")
        if isinstance(towards, bool) or not isinstance(towards, int) or not 0 <= towards < len(objects):
            raise ValueError(f"{where}.towards: an index into objects (0..{len(objects) - 1}), got {towards!r}")
    if "spin" in raw and any(objects[i].material not in ("soft", "cloth") for i in targets):
        raise ValueError(f"{where}.spin: spins are for soft and cloth objects")
    if "random" in raw and "every" in raw:
        raise ValueError(f"{where}: a random schedule sets its own timing (no every)")
    lengths = {"steps": 2, "every": None, "force": 3, "velocity": None if towards is not None else 3, "spin": 3}
    values = _read_values(raw, lengths, known, where)
    random = None
    if "random" in raw:
        table = raw["random"]
        if not isinstance(table, dict):
            raise ValueError(f"{where}.random: a table of {', '.join(RANDOM_KEYS)}")
        _check_keys(table, RANDOM_KEYS, f"{where}.random")
        for key in ("force", "hold"):
            if key not in table:
                raise ValueError(f"{where}.random.{key} is required")
        random = {}
        for key in RANDOM_KEYS:
            if key in table or key == "pause":
                raw_value = table.get(key, [0, 0])
                random[key] = _value(raw_value, f"{where}.random.{key}", None if key == "aim" else 2)
                if isinstance(random[key], str):
                    _check_names(random[key], known, f"{where}.random.{key}")
    return PushSpec(objects=tuple(targets), towards=towards, random=random, **values)


def posed_mesh(obj: ObjectSpec, drawn: dict) -> trimesh.Trimesh | None:
    """The object's mesh at its drawn ``size``, ``scale`` or ``extents``, in its body frame: the
    bounding box centred (a wedge: the middle of its base at the origin), its ``up`` axis turned
    to z. None: a sheet."""
    mesh = drawn_mesh(obj, drawn)
    if mesh == SHEET:
        return None
    if mesh in PRIMITIVES:
        posed = primitive_mesh(mesh, primitive_extents(mesh, drawn))
    elif "size" in drawn:
        posed = sized_mesh(base_mesh(mesh), size=float(drawn["size"]))
    else:
        posed = sized_mesh(base_mesh(mesh), scale=float(drawn["scale"]))
    if obj.up == "z":
        return posed
    turn = np.eye(4)
    turn[:3, :3] = UP_ROTATIONS[obj.up]  # a quarter turn: the centred box stays centred
    return posed.copy().apply_transform(turn)


def primitive_extents(mesh: str, drawn: dict) -> np.ndarray:
    """The drawn ``extents`` of a primitive (a round one: its diameter ``x``, and a sphere's
    height too; a capsule at least as long as it is wide), or its proportions times ``size``
    (its longest extent, m) or ``scale`` (the unit primitive's longest extent is 1 m)."""
    if "extents" not in drawn:
        factor = float(drawn["size"] if "size" in drawn else drawn["scale"])
        return np.asarray(PRIMITIVE_PROPORTIONS[mesh], dtype=np.float64) * factor
    x, y, z = (float(e) for e in drawn["extents"])
    if mesh == "sphere":
        return np.array([x, x, x])
    if mesh in ("cylinder", "cone"):
        return np.array([x, x, z])
    if mesh == "capsule":  # at least as long as it is wide
        return np.array([x, x, max(z, x)])
    return np.array([x, y, z])


def quaternion(drawn: dict) -> list[float] | None:
    """The drawn orientation as a unit quaternion ``[x, y, z, w]`` (yaw in degrees); None when
    neither is given. A quaternion of unit length (to 1e-12) is kept as given."""
    if "orientation" in drawn:
        q = np.asarray(drawn["orientation"], dtype=np.float64)
        norm = float(np.linalg.norm(q))
        return q.tolist() if abs(norm - 1.0) <= 1e-12 else (q / norm).tolist()
    if "yaw" not in drawn:
        return None
    yaw = math.radians(drawn["yaw"])
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]


def _rotation(drawn: dict) -> np.ndarray:
    q = quaternion(drawn)
    if q is None:
        return np.eye(3)
    x, y, z, w = q
    return trimesh.transformations.quaternion_matrix([w, x, y, z])[:3, :3]


def start_box(obj: ObjectSpec, drawn: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The object's oriented bounding box at the start: ``(centre [3], axes [3, 3] (rows),
    half extents [3])``; a sheet is a square of no thickness."""
    mesh = posed_mesh(obj, drawn)
    rotation = _rotation(drawn)
    position = np.asarray(drawn["position"], dtype=np.float64)
    if mesh is None:
        return position, rotation.T, np.array([drawn["size"] / 2, drawn["size"] / 2, 0.0])
    low, high = mesh.bounds
    return position + rotation @ ((low + high) / 2), rotation.T, (high - low) / 2


def boxes_overlap(a: tuple, b: tuple, touching: float = TOUCHING) -> bool:
    """Whether two oriented boxes overlap by more than ``touching`` (m), by the separating-axis
    test over their 15 candidate axes (the 6 face normals and the 9 edge cross products)."""
    (ca, axes_a, ha), (cb, axes_b, hb) = a, b
    between = cb - ca
    candidates = [*axes_a, *axes_b] + [np.cross(u, v) for u in axes_a for v in axes_b]
    for axis in candidates:
        length = np.linalg.norm(axis)
        if length < 1e-9:
            continue
        axis = axis / length
        reach = np.sum(ha * np.abs(axes_a @ axis)) + np.sum(hb * np.abs(axes_b @ axis))
        if abs(between @ axis) >= reach - touching:
            return False
    return True


def overlapping(spec: SceneSpec, drawn: list[dict]) -> list[tuple[int, int]]:
    """Pairs of objects whose start boxes overlap (touching is allowed; pass-through pairs are
    left out)."""
    boxes = [start_box(o, d) for o, d in zip(spec.objects, drawn)]
    return [(i, j) for i in range(len(boxes)) for j in range(i + 1, len(boxes))
            if (i, j) not in spec.pass_through and boxes_overlap(boxes[i], boxes[j])]


class FileScene(Scene):
    """The pybullet scene of a :class:`SceneSpec` and a seed (see :class:`~hrn_pyg.data.scenes.Scene`)."""

    def __init__(self, spec: SceneSpec, seed: int) -> None:
        self.spec = spec
        self.name = spec.name
        self.config_cls = type(spec.config)
        self.effects = spec.effects
        self.uses_deformables = spec.uses_deformables
        self.actuated = tuple(sorted({i for q in spec.pushes for i in q.objects}))
        self._schedules: dict[int, dict] = {}
        super().__init__(seed, spec.config)

    def draw_params(self, rng: np.random.Generator) -> dict:
        return self.spec.draw(rng)

    def build(self) -> None:
        self._schedules = {}
        for index, (obj, drawn) in enumerate(zip(self.spec.objects, self.params["objects"])):
            material = MATERIALS.index(obj.material)
            if material in (RIGID, STATIC):
                self._add_mesh_body(obj, drawn, material == STATIC, f"objects[{index}]")
            elif material == SOFT:
                self._add_soft_mesh(obj, drawn, f"objects[{index}]")
            else:
                self._add_cloth(obj, drawn, f"objects[{index}]")
            self._start_moving(self._objects[-1], drawn)
        for i, j in self.spec.pass_through:
            p.setCollisionFilterPair(self._objects[i].body, self._objects[j].body, -1, -1, 0,
                                     physicsClientId=self._client)

    # -- pushes -------------------------------------------------------------------------------
    def scripted_action(self, t: int) -> tuple[np.ndarray, np.ndarray | None]:
        forces, spins = self.zero_action(), None
        for index, (push, drawn) in enumerate(zip(self.spec.pushes, self.params["pushes"])):
            first, last = drawn["steps"]
            if "random" in drawn:
                if first <= t <= last:
                    forces += self._random_push(index, drawn["random"], t - first)
                continue
            if not first <= t <= last or ("every" in drawn and (t - first) % drawn["every"] != 0):
                continue
            for target in push.objects:
                obj = self._objects[target]
                if "force" in drawn:
                    forces[target] += drawn["force"]
                elif "velocity" in drawn and push.towards is not None:
                    forces[target] += obj.mass * drawn["velocity"] * self._heading(target, push.towards) / self.dt
                elif "velocity" in drawn:
                    forces[target] += obj.mass * np.asarray(drawn["velocity"]) / self.dt
                if "spin" in drawn:
                    spins = np.zeros((self.num_objects, 3)) if spins is None else spins
                    spins[target] = drawn["spin"]
        return forces, spins

    def _heading(self, source: int, target: int) -> np.ndarray:
        """The horizontal unit vector from object ``source``'s leaves' centre to ``target``'s, ``[3]``."""
        towards = (self._object_positions(self._objects[target]).mean(axis=0)
                   - self._object_positions(self._objects[source]).mean(axis=0))[None]
        towards[:, 2] = 0.0
        towards /= np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-9)
        return towards[0]

    def _random_push(self, index: int, schedule: dict, t: int) -> np.ndarray:
        """A random schedule's forces ``[O, 3]`` at its step ``t``: a horizontal force on each of
        the push's objects (random heading, or towards ``aim`` give or take ``aim_noise``; random
        magnitude), held ``hold`` steps, then ``pause`` steps of none; drawn along the episode."""
        state = self._schedules.setdefault(index, {})
        if t == 0:
            state.update(current=self.zero_action(), push_end=0, next_change=0)
        if t >= state["next_change"]:
            push = self.zero_action()
            for target in self.spec.pushes[index].objects:
                if "aim" in schedule:
                    at = self._object_positions(self._objects[schedule["aim"]]).mean(axis=0)
                    source = self._object_positions(self._objects[target]).mean(axis=0)
                    to_aim = at - source
                    heading = math.atan2(to_aim[1], to_aim[0]) + float(self.rng.uniform(*schedule.get("aim_noise", (0, 0))))
                else:
                    heading = float(self.rng.uniform(0, 2 * np.pi))
                magnitude = float(self.rng.uniform(*schedule["force"]))
                push[target] = magnitude * np.array([math.cos(heading), math.sin(heading), 0.0])
            state["current"] = push
            state["push_end"] = t + int(self.rng.integers(schedule["hold"][0], schedule["hold"][1] + 1))
            state["next_change"] = state["push_end"] + int(self.rng.integers(schedule["pause"][0],
                                                                             schedule["pause"][1] + 1))
        if t >= state["push_end"]:
            return self.zero_action()
        return state["current"].copy()

    # -- bodies -------------------------------------------------------------------------------
    def _leaves(self, mesh: trimesh.Trimesh, where: str) -> np.ndarray:
        return leaves_of(mesh, self.config.pitch, f"{self.spec.name}: {where}")

    def _add_mesh_body(self, obj: ObjectSpec, drawn: dict, static: bool, where: str) -> None:
        c = self._client
        mesh = posed_mesh(obj, drawn)
        leaves = self._leaves(mesh, where)
        try:
            shape = self._collision_shape(obj, mesh, drawn, static)
        except p.error as exc:  # pybullet's own refusal of a mesh, one line
            raise ValueError(f"{self.spec.name}: {where}: pybullet could not make its collision shape ({exc})") from None
        mass = STATIC_DENSITY * float(mesh.volume) if static else float(drawn["mass"])
        pose = {"baseOrientation": q} if (q := quaternion(drawn)) is not None else {}
        body = p.createMultiBody(0.0 if static else mass, shape, basePosition=list(drawn["position"]),
                                 physicsClientId=c, **pose)
        p.changeDynamics(body, -1, lateralFriction=drawn.get("friction", self.config.friction), physicsClientId=c)
        self._objects.append(SceneObject(STATIC if static else RIGID, body, mass, 1.0, leaves))

    def _collision_shape(self, obj: ObjectSpec, mesh: trimesh.Trimesh, drawn: dict, static: bool) -> int:
        """A primitive's own pybullet shape at its nominal extents; a convex mesh as its hull; a
        concave one as its convex parts (moving) or as its triangles (static)."""
        c, name = self._client, drawn_mesh(obj, drawn)
        if name in PRIMITIVES:
            extents = primitive_extents(name, drawn)
            if name == "box":
                return p.createCollisionShape(p.GEOM_BOX, halfExtents=(np.asarray(mesh.extents) / 2).tolist(),
                                              physicsClientId=c)
            if name == "sphere":
                return p.createCollisionShape(p.GEOM_SPHERE, radius=float(extents[0] / 2), physicsClientId=c)
            if name == "cylinder":
                return p.createCollisionShape(p.GEOM_CYLINDER, radius=float(extents[0] / 2), height=float(extents[2]),
                                              physicsClientId=c)
            if name == "capsule":
                radius = float(extents[0] / 2)
                return p.createCollisionShape(p.GEOM_CAPSULE, radius=radius, height=max(float(extents[2]) - 2 * radius, 1e-4),
                                              physicsClientId=c)
            return p.createCollisionShape(p.GEOM_MESH, vertices=mesh.vertices.tolist(), physicsClientId=c)
        hull = mesh.convex_hull
        if mesh.is_watertight and hull.volume - mesh.volume <= 0.02 * hull.volume:
            return p.createCollisionShape(p.GEOM_MESH, vertices=hull.vertices.tolist(), physicsClientId=c)
        if static:
            return p.createCollisionShape(p.GEOM_MESH, vertices=mesh.vertices.tolist(),
                                          indices=mesh.faces.flatten().tolist(),
                                          flags=p.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=c)
        return p.createCollisionShape(p.GEOM_MESH, fileName=str(convex_parts(mesh, CACHE_DIR)), physicsClientId=c)

    def _add_soft_mesh(self, obj: ObjectSpec, drawn: dict, where: str) -> None:
        """A soft body: the tetrahedra of the mesh's voxel lattice."""
        nodes, tets = soft_lattice(posed_mesh(obj, drawn), self.config.pitch, f"{self.spec.name}: {where}")
        exponent = drawn["log10_mu"] if "log10_mu" in drawn else stiffness_exponent(drawn, SOFT_LOG10_MU_RANGE)
        self._add_soft_lattice(nodes, tets, float(drawn["mass"]), exponent, drawn["position"],
                               quaternion(drawn) or (0.0, 0.0, 0.0, 1.0), drawn.get("friction", self.config.friction))

    def _add_cloth(self, obj: ObjectSpec, drawn: dict, where: str) -> None:
        """A mass-spring cloth: a square sheet on the lattice, or a surface mesh whose (merged)
        vertices are the leaves."""
        mesh = posed_mesh(obj, drawn)
        if mesh is None:
            check_sheet(float(drawn["size"]), self.config.pitch, f"{self.spec.name}: {where}")
            vertices, faces = grid_sheet(float(drawn["size"]), self.config.pitch)
        else:
            vertices, faces = surface_leaves(mesh, f"{self.spec.name}: {where}"), np.asarray(mesh.faces)
        exponent = (drawn["log10_spring_k"] if "log10_spring_k" in drawn
                    else stiffness_exponent(drawn, CLOTH_LOG10_K_RANGE))
        self._add_cloth_mesh(vertices, faces, float(drawn["mass"]), exponent, drawn["position"], quaternion(drawn),
                             drawn.get("friction", self.config.friction))

    def _start_moving(self, obj: SceneObject, drawn: dict) -> None:
        """The drawn start velocity and spin (a soft body's nodes move as one rigid body)."""
        velocity, spin = np.asarray(drawn["velocity"]), np.asarray(drawn["spin"])
        if obj.material == STATIC or not (np.any(velocity) or np.any(spin)):
            return
        p.resetBaseVelocity(obj.body, velocity.tolist(), spin.tolist(), physicsClientId=self._client)
        if obj.material in (SOFT, CLOTH):
            x = self._object_positions(obj)
            obj.velocity = velocity + np.cross(spin, x - x.mean(axis=0))


ENGINE_SCENES[ENGINES[0]] = FileScene


def stiffness_exponent(drawn: dict, log10_range: tuple[float, float]) -> float:
    """The drawn ``stiffness`` in [0, 1] as the exponent of pybullet's modulus over ``log10_range``."""
    low, high = log10_range
    return low + float(drawn["stiffness"]) * (high - low)


def check_sheet(size: float, pitch: float, name: str) -> None:
    """LimitError when a sheet of side ``size`` has more than :data:`MAX_LEAVES` leaves at
    ``pitch`` (``round(size / pitch) + 1`` a side, as :func:`~hrn_pyg.data.voxelise.grid_sheet`
    lays them), before any is made."""
    if not (math.isfinite(size) and math.isfinite(pitch) and pitch > 0):
        return  # grid_sheet names the bad value
    ratio = size / pitch
    side = round(ratio) + 1 if math.isfinite(ratio) else MAX_LEAVES
    if side * side > MAX_LEAVES:
        raise LimitError(f"{name}: a sheet of {count_text(side * side)} leaves at pitch {pitch} m, more than "
                         f"{MAX_LEAVES}; a pitch of {size / (math.isqrt(MAX_LEAVES) - 1):.3g} m fits")


def surface_leaves(mesh: trimesh.Trimesh, name: str) -> np.ndarray:
    """A cloth's leaves: the vertices of its surface mesh, at most :data:`MAX_LEAVES`."""
    if len(mesh.vertices) > MAX_LEAVES:
        raise ValueError(f"{name}: a cloth mesh of {len(mesh.vertices)} vertices, more than {MAX_LEAVES}; "
                         "simplify it")
    return np.asarray(mesh.vertices, dtype=np.float64)


def soft_lattice(mesh: trimesh.Trimesh, pitch: float, name: str) -> tuple[np.ndarray, np.ndarray]:
    """A soft body's nodes ``[M, 3]`` and tetrahedra ``[T, 4]``: the lattice cells its leaves fill
    (:func:`~hrn_pyg.data.voxelise.lattice_tetrahedra`); a body too thin for one whole cell at
    the pitch is an error naming it."""
    try:
        return lattice_tetrahedra(leaves_of(mesh, pitch, name), pitch)
    except ValueError as exc:
        if "lattice cell" not in str(exc):
            raise
        raise ValueError(f"{name}: too thin for a soft body at pitch {pitch} m (no 2 x 2 x 2 block of leaves); "
                         "make it larger or the pitch smaller") from None


def leaves_of(mesh: trimesh.Trimesh, pitch: float, name: str) -> np.ndarray:
    """:func:`~hrn_pyg.data.meshes.solid_points` of a posed mesh, at most :data:`MAX_LEAVES`
    (more is an error that names a pitch that fits)."""
    points, _ = solid_points(mesh, pitch, name, max_leaves=MAX_LEAVES)
    if len(points) > MAX_LEAVES:
        raise too_many_leaves(len(points), pitch, MAX_LEAVES, name)
    return points


# -- the package's own scenes ----------------------------------------------------------------


def builtin_scene(name: str, **settings: Any) -> SceneSpec:
    """The built-in scene ``name`` (one of :data:`SCENES`), its settings replaced by ``settings``
    (``None`` values ignored; an unknown name is an error naming the settings there are)."""
    check_scene_name(name)
    return _read_builtin(name).with_settings(**settings)


def check_scene_name(name: str | None) -> None:
    """Nothing for a built-in scene's name (or None: none given); else ValueError, one line
    listing the built-in scenes."""
    if name is not None and name not in SCENES:
        raise ValueError(f"scene: unknown {name!r}; the built-in scenes are {', '.join(SCENES)} "
                         "(your own scene: --scene-file)")


_BUILTIN_CACHE: dict[str, SceneSpec] = {}


def _read_builtin(name: str) -> SceneSpec:
    if name not in _BUILTIN_CACHE:
        _BUILTIN_CACHE[name] = read_scene_file(BUILTIN_DIR / f"{name}.toml")
    return _BUILTIN_CACHE[name]


def scene_spec(scene: str | SceneSpec) -> SceneSpec:
    """A scene given by its built-in name or as a spec, as a spec."""
    return builtin_scene(scene) if isinstance(scene, str) else scene


def make_scene(scene: str | SceneSpec, seed: int) -> FileScene:
    """The pybullet scene of a built-in scene's name or a spec, for ``seed``; ``reset()`` starts it."""
    return scene_spec(scene).make_scene(seed)


def scene_effects(scene: str | SceneSpec) -> SceneEffects:
    """The :class:`~hrn_pyg.data.effects.SceneEffects` a scene declares (what to simulate)."""
    return scene_spec(scene).effects

