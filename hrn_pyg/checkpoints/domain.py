"""What a model was trained on, and what of a scene lies outside it.

A :class:`Domain` summarises episodes: voxel pitches (m) and, pitch-aware, their span;
materials; object sizes (m, the largest leaf distance at the start plus a pitch); moving
objects per scene; the fastest leaf speed (m/s). ``hrn-pyg train`` records it in each
checkpoint; shipped models carry theirs in ``manifest.json``.

:func:`outside` lists what of a scene's domain lies outside a model's (:class:`Outside`),
:func:`outside_line` as one line, e.g. ``shapes_d4.pt was trained at pitch 0.05 m; this scene's
pitch is 0.025 m (0.5x)``. Inside means: a pitch seen (within :data:`PITCH_TOLERANCE`, or in
the range), known materials, object count in range, sizes in range widened by
:data:`SIZE_TOLERANCE`, speed at most :data:`SPEED_TOLERANCE` times. Unknown fields are not
compared.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from hrn_pyg.data.graph import MATERIALS, STATIC
from hrn_pyg.data.io import episode_pitch

#: a scene's pitch differing from each of the model's by more than this fraction is outside
PITCH_TOLERANCE = 0.01
#: object sizes within [smallest / this, largest * this] of the model's are inside (its range
#: is measured on a sample of its episodes)
SIZE_TOLERANCE = 1.25
#: a fastest leaf up to this many times the model's fastest is inside
SPEED_TOLERANCE = 1.5
#: episodes a dataset folder's domain is read from at most (spread evenly over its files)
DATASET_EPISODES = 64


class DomainError(ValueError):
    """A scene outside a model's domain under ``strict``; the message is the one line of
    :func:`outside_line`."""


@dataclass(frozen=True)
class Domain:
    """What a set of episodes spans; see the module's docstring for each field."""

    pitches: tuple[float, ...] = ()
    materials: tuple[str, ...] = ()
    #: (smallest, largest) object size in m
    object_size: tuple[float, float] | None = None
    #: (fewest, most) moving objects in a scene
    objects: tuple[int, int] | None = None
    #: fastest leaf speed in m/s
    speed: float | None = None
    #: episodes measured
    episodes: int = 0
    #: the datasets or scenes measured
    sources: tuple[str, ...] = field(default=())
    #: (finest, coarsest) pitch in m of a pitch-aware model, which covers every pitch between;
    #: None: only the pitches listed
    pitch_range: tuple[float, float] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, as stored in a checkpoint (``domain``) and in ``manifest.json``
        (``pitch_range`` only when there is one)."""
        extra = {} if self.pitch_range is None else {"pitch_range": list(self.pitch_range)}
        return {
            "pitches": list(self.pitches),
            "materials": list(self.materials),
            "object_size": None if self.object_size is None else [_round(v) for v in self.object_size],
            "objects": None if self.objects is None else list(self.objects),
            "speed": None if self.speed is None else _round(self.speed),
            "episodes": self.episodes,
            "sources": list(self.sources),
            **extra,
        }

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> Domain:
        """The inverse of :meth:`to_dict`; raises ValueError naming a malformed field."""
        if not isinstance(raw, Mapping):
            raise ValueError(f"domain: expected a JSON object, got {type(raw).__name__}")
        unknown = sorted(set(raw) - {f for f in cls.__dataclass_fields__})
        if unknown:
            raise ValueError(f"domain: unknown fields {unknown}")
        try:
            materials = tuple(str(m) for m in raw.get("materials") or ())
            bad = sorted(set(materials) - set(MATERIALS))
            if bad:
                raise ValueError(f"unknown materials {bad}")
            size, count, span = raw.get("object_size"), raw.get("objects"), raw.get("pitch_range")
            return cls(
                pitches=tuple(float(p) for p in raw.get("pitches") or ()),
                materials=materials,
                object_size=None if size is None else (float(size[0]), float(size[1])),
                objects=None if count is None else (int(count[0]), int(count[1])),
                speed=None if raw.get("speed") is None else float(raw["speed"]),
                episodes=int(raw.get("episodes") or 0),
                sources=tuple(str(s) for s in raw.get("sources") or ()),
                pitch_range=None if span is None else (float(span[0]), float(span[1])),
            )
        except (TypeError, IndexError, ValueError) as exc:
            raise ValueError(f"domain: malformed ({exc})") from None

    def merge(self, other: Domain) -> Domain:
        """The domain spanning both."""
        return Domain(
            pitches=tuple(sorted(set(self.pitches) | set(other.pitches))),
            materials=_ordered_materials(set(self.materials) | set(other.materials)),
            object_size=_span(self.object_size, other.object_size),
            objects=_span(self.objects, other.objects),
            speed=_largest(self.speed, other.speed),
            episodes=self.episodes + other.episodes,
            sources=tuple(dict.fromkeys((*self.sources, *other.sources))),
            pitch_range=_span(self.pitch_range, other.pitch_range),
        )


@dataclass(frozen=True)
class Outside:
    """One way a scene lies outside a model's domain: what the model was trained on
    (``trained``, a phrase after "was trained") and what the scene has (``scene``, a clause)."""

    field: str
    trained: str
    scene: str


def with_pitch_range(domain: Domain) -> Domain:
    """``domain`` with ``pitch_range`` spanning its pitches (and its own range, if any): the
    domain of a pitch-aware model, which covers every pitch between its finest and coarsest."""
    values = [*domain.pitches, *(domain.pitch_range or ())]
    if not values:
        return domain
    return replace(domain, pitch_range=(min(values), max(values)))


def merge_all(domains: Iterable[Domain]) -> Domain:
    """The domain spanning all of ``domains`` (an empty :class:`Domain` for none)."""
    merged = Domain()
    for domain in domains:
        merged = merged.merge(domain)
    return merged


def frames_domain(positions: np.ndarray, leaf_object: np.ndarray, object_material: np.ndarray,
                  pitch: float | None, dt: float | None = None, source: str = "") -> Domain:
    """The domain of one episode's frames ``positions [T, L, 3]`` (``T >= 1``): sizes at the first
    frame, the fastest leaf over the frames when ``dt`` is given and ``T >= 2``."""
    positions = np.asarray(positions, dtype=np.float64)
    leaf_object = np.asarray(leaf_object)
    material = np.asarray(object_material)
    moving = [o for o in range(len(material)) if int(material[o]) != STATIC]
    pad = float(pitch) if pitch else 0.0
    sizes = [leaf_diameter(positions[0][leaf_object == o]) + pad for o in moving if np.any(leaf_object == o)]
    speed = None
    if dt and positions.shape[0] >= 2:
        steps = np.linalg.norm(np.diff(positions, axis=0), axis=-1)  # [T-1, L]
        movable = np.isin(leaf_object, moving)
        speed = float(steps[:, movable].max() / dt) if movable.any() else 0.0
    return Domain(
        pitches=() if not pitch else (float(pitch),),
        materials=_ordered_materials({MATERIALS[int(m)] for m in material}),
        object_size=(min(sizes), max(sizes)) if sizes else None,
        objects=(len(moving), len(moving)),
        speed=speed,
        episodes=1,
        sources=(source,) if source else (),
    )


def leaf_diameter(points: np.ndarray) -> float:
    """The largest distance between two of ``points [P, 3]`` (between two corners of their
    convex hull; joggled for flat or straight sets such as a cloth)."""
    from scipy.spatial import ConvexHull
    from scipy.spatial.distance import pdist

    points = np.asarray(points, dtype=np.float64)
    if len(points) > 4:
        points = points[ConvexHull(points, qhull_options="QJ").vertices]
    return float(pdist(points).max()) if len(points) > 1 else 0.0


def episode_domain(episode: Mapping[str, Any], source: str = "") -> Domain:
    """The domain of an episode dict (:func:`hrn_pyg.data.episodes.simulate_episode`'s keys)."""
    dt = float(episode["dt"]) if "dt" in episode else None
    return frames_domain(episode["positions"], episode["leaf_object"], episode["object_material"],
                         episode_pitch(episode), dt, source)


def episode_files(folder: str | Path, limit: int | None = DATASET_EPISODES) -> list[Path]:
    """Up to ``limit`` (None: all) of a dataset folder's ``episode_*.npz``, spread evenly."""
    files = sorted(Path(folder).glob("episode_*.npz"))
    if limit is None or len(files) <= limit:
        return files
    picks = np.linspace(0, len(files) - 1, limit).round().astype(int)
    return [files[i] for i in sorted(set(picks.tolist()))]


def dataset_domain(folders: str | Path | Sequence[str | Path], limit: int | None = DATASET_EPISODES) -> Domain:
    """The domain of dataset folders (``hrn-pyg generate``), from up to ``limit`` episodes of
    each; raises FileNotFoundError for a folder without episodes."""
    from hrn_pyg.data.io import load_episode

    folders = [folders] if isinstance(folders, (str, Path)) else list(folders)
    domains = []
    for folder in folders:
        files = episode_files(folder, limit)
        if not files:
            raise FileNotFoundError(f"no episode_*.npz in {folder}")
        name = Path(folder).name
        domains += [episode_domain(load_episode(f), name) for f in files]
    return merge_all(domains)


def outside(model: Domain, scene: Domain) -> list[Outside]:
    """What of ``scene`` lies outside ``model``, by how much; empty when it is all inside."""
    found: list[Outside] = []
    if model.pitch_range and scene.pitches:
        low, high = model.pitch_range
        unseen = [p for p in scene.pitches
                  if p < low * (1 - PITCH_TOLERANCE) or p > high * (1 + PITCH_TOLERANCE)]
        if unseen:
            near = low if unseen[0] < low else high
            found.append(Outside("pitch", f"at pitches {low:g}-{high:g} m",
                                 f"this scene's pitch is {_m(unseen)} ({unseen[0] / near:.2g}x the "
                                 f"{'finest' if near == low else 'coarsest'})"))
    elif model.pitches and scene.pitches:
        unseen = [p for p in scene.pitches
                  if all(abs(p - q) > PITCH_TOLERANCE * q for q in model.pitches)]
        if unseen:
            near = min(model.pitches, key=lambda q: abs(math.log(unseen[0] / q)))
            found.append(Outside("pitch", f"at pitch {_m(model.pitches)}",
                                 f"this scene's pitch is {_m(unseen)} ({unseen[0] / near:.2g}x)"))
    if model.materials and scene.materials:
        new = [m for m in scene.materials if m not in model.materials]
        if new:
            found.append(Outside("materials", f"on {_and(model.materials)} objects",
                                 f"this scene has {_and(new)}"))
    if model.objects and scene.objects:
        low, high = model.objects
        if scene.objects[1] > high or scene.objects[0] < low:
            count = scene.objects[1] if scene.objects[1] > high else scene.objects[0]
            trained = f"{low}" if low == high else f"{low}-{high}"
            found.append(Outside("objects", f"on {trained} moving object{'s' if high != 1 else ''}",
                                 f"this scene has {count}"))
    if model.object_size and scene.object_size:
        low, high = model.object_size
        span = f"{low:.2g}-{high:.2g} m across"
        if scene.object_size[1] > high * SIZE_TOLERANCE:
            found.append(Outside("object_size", f"on objects {span}",
                                 f"this scene has one {scene.object_size[1]:.2g} m across "
                                 f"({scene.object_size[1] / high:.2g}x the largest)"))
        elif scene.object_size[0] < low / SIZE_TOLERANCE:
            found.append(Outside("object_size", f"on objects {span}",
                                 f"this scene has one {scene.object_size[0]:.2g} m across "
                                 f"({scene.object_size[0] / low:.2g}x the smallest)"))
    if model.speed and scene.speed and scene.speed > model.speed * SPEED_TOLERANCE:
        found.append(Outside("speed", f"at leaf speeds up to {model.speed:.2g} m/s",
                             f"this scene reaches {scene.speed:.2g} m/s ({scene.speed / model.speed:.2g}x)"))
    return found


def outside_line(name: str, found: Sequence[Outside]) -> str:
    """One line naming what is outside, e.g. ``shapes_d4.pt was trained at pitch 0.05 m; this
    scene's pitch is 0.025 m (0.5x)``; several are joined by commas."""
    return f"{name} was trained {', '.join(o.trained for o in found)}; {', '.join(o.scene for o in found)}"


def check_scene(name: str, model: Domain | None, scene: Domain, strict: bool = False) -> str | None:
    """The line of :func:`outside_line` when ``scene`` lies outside ``model`` (None when inside
    or when the model's domain is unknown); under ``strict`` that raises :class:`DomainError`."""
    found = outside(model, scene) if model is not None else []
    if not found:
        return None
    line = outside_line(name, found)
    if strict:
        raise DomainError(f"{line} (--strict)")
    return line


def _ordered_materials(materials: Iterable[str]) -> tuple[str, ...]:
    return tuple(m for m in MATERIALS if m in set(materials))


def _span(a: tuple | None, b: tuple | None) -> tuple | None:
    if a is None or b is None:
        return a if b is None else b
    return (min(a[0], b[0]), max(a[1], b[1]))


def _largest(a: float | None, b: float | None) -> float | None:
    if a is None or b is None:
        return a if b is None else b
    return max(a, b)


def _round(value: float) -> float:
    return float(f"{value:.4g}")


def _m(values: Sequence[float]) -> str:
    return " and ".join(f"{v:g}" for v in values) + " m"


def _and(words: Sequence[str]) -> str:
    words = list(words)
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


def report_outside(model: Any, scene: Domain, strict: bool = False, prefix: str = "warning: ") -> str | None:
    """Check ``scene`` against the domain a loaded model carries (``model.domain`` and
    ``model.checkpoint_name``, set by :func:`hrn_pyg.checkpoints.load_model`): when outside,
    print :func:`outside_line` as one line on stderr after ``prefix`` and return it; under
    ``strict`` raise :class:`DomainError` instead. Nothing for a model with no recorded domain."""
    name = getattr(model, "checkpoint_name", None) or "the model"
    line = check_scene(name, getattr(model, "domain", None), scene, strict)
    if line is not None:
        print(f"{prefix}{line}", file=sys.stderr, flush=True)
    return line
