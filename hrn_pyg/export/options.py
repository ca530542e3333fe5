"""The picture and export options of ``hrn-pyg sample`` (``--frames``, ``--size``, ``--fps``,
``--camera``, ``--mp4``, ``--export``), checked before anything runs, and the result's meshes."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrn_pyg.export.files import parse_formats
from hrn_pyg.export.scene_meshes import SceneMeshes, episode_meshes, seed_meshes

__all__ = ["PictureOptions", "check_picture_options", "result_meshes", "MAX_PIXELS"]

#: the longest side of a picture (pixels): a typo such as 16000x400 fails at once, not in matplotlib
MAX_PIXELS = 8192


@dataclass(frozen=True)
class PictureOptions:
    """What the user chose: ``frames`` (steps of the PNG's columns, None: the default
    fractions), ``size`` (width, height) pixels or None, ``fps``, ``camera`` (elevation,
    azimuth) degrees, ``export`` formats."""

    frames: tuple[int, ...] | None
    size: tuple[int, int] | None
    fps: float
    camera: tuple[float, float]
    export: tuple[str, ...]

    def times(self, steps: int, fractions: Sequence[float]) -> list[int]:
        """The PNG's columns: the chosen steps (each in ``0..steps``), or ``fractions`` of ``steps``."""
        if self.frames is None:
            return sorted({int(round(f * steps)) for f in fractions})
        late = [t for t in self.frames if t > steps]
        if late:
            raise ValueError(f"--frames: step {late[0]} is past the horizon ({steps})")
        return sorted(set(self.frames))


def _numbers(text: str, option: str, count: int | None, kind=float) -> tuple:
    try:
        values = tuple(kind(v) for v in str(text).replace(" ", "").split(",") if v != "")
    except ValueError:
        raise ValueError(f"{option}: expected comma-separated numbers, got {text!r}") from None
    if not values or (count is not None and len(values) != count) or not all(np.isfinite(values)):
        raise ValueError(f"{option}: expected {count or 'some'} comma-separated finite numbers, got {text!r}")
    return values


def check_picture_options(args: argparse.Namespace) -> PictureOptions:
    """The checked options (a bad one is a ValueError naming it)."""
    frames = None
    if args.frames is not None:
        frames = _numbers(args.frames, "--frames", None, int)
        if min(frames) < 0:
            raise ValueError(f"--frames: steps are >= 0, got {args.frames!r}")
        if getattr(args, "steps", None) is not None and max(frames) > args.steps:
            raise ValueError(f"--frames: step {max(frames)} is past the horizon ({args.steps})")
    size = None
    if args.size is not None:
        parts = str(args.size).lower().split("x")
        if len(parts) != 2 or not all(p.isdigit() for p in parts):
            raise ValueError(f"--size: expected WIDTHxHEIGHT in pixels, e.g. 1600x400, got {args.size!r}")
        size = (int(parts[0]), int(parts[1]))
        if not all(32 <= s <= MAX_PIXELS for s in size):
            raise ValueError(f"--size: each side must be in [32, {MAX_PIXELS}] pixels, got {args.size!r}")
    if not (np.isfinite(args.fps) and 0 < args.fps <= 120):
        raise ValueError(f"--fps must be in (0, 120], got {args.fps}")
    camera = _numbers(args.camera, "--camera", 2)
    if getattr(args, "mp4", False):
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ValueError("--mp4 needs imageio-ffmpeg: pip install 'hrn_pyg[viewer]'") from None
    export = parse_formats(args.export) if args.export is not None else ()
    if "vtk" in export:
        try:
            import meshio  # noqa: F401
        except ImportError:
            raise ValueError("--export vtk needs meshio: pip install 'hrn_pyg[viewer]'") from None
    return PictureOptions(frames, size, float(args.fps), (float(camera[0]), float(camera[1])), export)


def result_meshes(args: argparse.Namespace, source, leaf_object: np.ndarray, steps: int, origin: dict) -> SceneMeshes:
    """The meshes of the episode a sample started from: a fresh one's seed (``--episode-seed``),
    or the draws the ``--data`` episode records; checked against the start graph's leaves."""
    if args.data:
        from hrn_pyg.data.io import load_episode

        episode = load_episode(Path(args.data) / f"episode_{int(origin['episode_seed']):06d}.npz")
        meshes = episode_meshes(source, episode)
    else:
        meshes = seed_meshes(source, int(args.seed), int(args.start) + int(steps))
    if meshes.num_leaves != len(leaf_object) or not np.array_equal(meshes.leaf_object, leaf_object):
        raise ValueError(f"the scene's meshes have {meshes.num_leaves} leaves, the episode {len(leaf_object)}: "
                         "was the data made from this scene?")
    return meshes
