"""Episode files: one ``.npz`` per episode, written atomically with fixed zip timestamps (the same
episode gives the same bytes), read without pickle; keys and shapes in ``docs/architecture.md``."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Mapping
from typing import Any

import numpy as np

from hrn_pyg.utils.files import atomic_path

#: key -> (dtype kind(s), number of dimensions). Shapes are cross-checked in ``validate_episode``.
EPISODE_KEYS: dict[str, tuple[str, int]] = {
    "positions": ("f", 3),
    "forces": ("f", 3),
    "leaf_mass": ("f", 1),
    "leaf_object": ("i", 1),
    "object_material": ("i", 1),
    "object_stiffness": ("f", 1),
    "hierarchy_parent": ("i", 1),
    "seed": ("i", 0),
    "scene": ("U", 0),
    "params": ("U", 0),
    "dt": ("f", 0),
}

#: zip member timestamp (the earliest zip allows): identical content -> identical bytes.
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def validate_episode(episode: dict[str, np.ndarray]) -> None:
    """Raise ``ValueError`` naming the first missing key, wrong dtype/shape or non-finite value.

    **Shapes** ``positions [S+1, L, 3]``, ``forces [S, L, 3]``, ``leaf_mass [L]``,
    ``leaf_object [L]`` in ``0..O-1``, ``object_material [O]`` in ``0..3``,
    ``object_stiffness [O]``, ``hierarchy_parent [N]`` with ``N >= L``.
    """
    for key, (kinds, ndim) in EPISODE_KEYS.items():
        if key not in episode:
            raise ValueError(f"episode: missing key {key!r}")
        value = np.asarray(episode[key])
        if value.dtype.kind not in kinds or value.ndim != ndim:
            raise ValueError(f"episode[{key!r}]: expected {ndim}-d of kind {kinds!r}, "
                             f"got {value.dtype} {value.shape}")
        if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
            raise ValueError(f"episode[{key!r}]: contains NaN or inf")
    pos, forces = episode["positions"], episode["forces"]
    steps, leaves = pos.shape[0] - 1, pos.shape[1]
    n_obj = len(episode["object_material"])
    if steps < 1 or pos.shape[2] != 3:
        raise ValueError(f"episode['positions']: expected [S+1, L, 3] with S >= 1, got {pos.shape}")
    if forces.shape != (steps, leaves, 3):
        raise ValueError(f"episode['forces']: expected {(steps, leaves, 3)}, got {forces.shape}")
    for key in ("leaf_mass", "leaf_object"):
        if episode[key].shape != (leaves,):
            raise ValueError(f"episode[{key!r}]: expected ({leaves},), got {episode[key].shape}")
    if episode["object_stiffness"].shape != (n_obj,):
        raise ValueError(f"episode['object_stiffness']: expected ({n_obj},)")
    obj = episode["leaf_object"]
    if leaves and (obj.min() < 0 or obj.max() >= n_obj):
        raise ValueError(f"episode['leaf_object']: values must lie in 0..{n_obj - 1}")
    mat = episode["object_material"]
    if n_obj and (mat.min() < 0 or mat.max() > 3):
        raise ValueError("episode['object_material']: values must lie in 0..3")
    parent = episode["hierarchy_parent"]
    if len(parent) < leaves or np.any((parent < -1) | (parent >= len(parent))):
        raise ValueError("episode['hierarchy_parent']: must have N >= L entries in -1..N-1")


def episode_pitch(episode: Mapping[str, Any]) -> float | None:
    """The voxel pitch (m) an episode was made at: its ``params`` JSON's ``config.pitch``
    (every episode ``hrn-pyg generate`` writes records it), or None when it has none."""
    try:
        pitch = json.loads(str(episode["params"]))["config"]["pitch"]
    except (KeyError, TypeError, ValueError):
        return None
    return float(pitch) if pitch else None


def save_episode(path: str | os.PathLike, episode: dict[str, np.ndarray]) -> None:
    """Validate and write ``episode`` to ``path`` (``.npz``): temp file in the same folder,
    then ``os.replace``, so a reader never sees half a file."""
    episode = {k: np.asarray(v) for k, v in episode.items()}
    validate_episode(episode)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as f, zipfile.ZipFile(f, "w", zipfile.ZIP_DEFLATED) as zf:
            for key in sorted(episode):
                buffer = io.BytesIO()
                np.lib.format.write_array(buffer, episode[key], allow_pickle=False)
                info = zipfile.ZipInfo(f"{key}.npy", date_time=ZIP_EPOCH)
                info.compress_type = zipfile.ZIP_DEFLATED
                zf.writestr(info, buffer.getvalue())


def load_episode(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read and validate an episode written by :func:`save_episode` (no pickle)."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"episode file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            episode = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise ValueError(f"{path}: not a readable episode file ({exc})") from exc
    try:
        validate_episode(episode)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    return episode
