"""Training windows over a folder of episode files, as a PyG ``Dataset`` of ``HeteroData``.

An episode (``episode_<seed:06d>.npz``, docs/architecture.md) holds leaf positions at steps
``0..S`` and forces of steps ``0..S-1``. A window of horizon ``T`` at step ``t``
(``2 <= t <= S - T``) is one graph: the episode's structure
(:func:`hrn_pyg.data.graph.episode_structure`, cached), the state at ``t``, and per node

* ``pos_seq (N, T+3, 3)``: ``x_{t-2} .. x_{t+T}`` (ancestors: mass-weighted leaf means),
* ``force_seq (N, T, 3)``: the forces of steps ``t .. t+T-1`` (zero on ancestors),

plus ``episode_seed (1,)``, ``start_step (1,)`` and ``pitch (1,)``. Episodes are read lazily
(``allow_pickle=False``), a few kept decoded. Splits by seed: ``% 10 == 9`` test, ``== 8`` val.
"""

from __future__ import annotations

import json
import re
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch_geometric.data import Dataset, HeteroData

from hrn_pyg.data.graph import (
    HISTORY,
    NODE,
    episode_structure,
    leaf_to_ancestor_mean,
    set_state,
)
from hrn_pyg.data.io import episode_pitch, load_episode

SPLITS = ("train", "val", "test")
#: every episode of a folder, for scoring a dataset that is not split by seed (a scene file's)
ALL = "all"
#: Seeds with ``seed % SPLIT_MODULUS`` equal to these residues form the val and test splits.
SPLIT_MODULUS = 10
VAL_RESIDUE = 8
TEST_RESIDUE = 9
#: Episode file names, as written by ``hrn-pyg generate``.
EPISODE_PATTERN = re.compile(r"^episode_(\d+)\.npz$")
#: a folder's ``meta.json`` larger than this (bytes) is not read for its scene
MAX_META_BYTES = 1 << 20
#: The episode keys this dataset reads.
EPISODE_KEYS = (
    "positions",
    "forces",
    "leaf_mass",
    "leaf_object",
    "object_material",
    "object_stiffness",
    "hierarchy_parent",
)


def split_of_seed(seed: int) -> str:
    """The split (``train``/``val``/``test``) an episode seed belongs to."""
    residue = int(seed) % SPLIT_MODULUS
    return "test" if residue == TEST_RESIDUE else "val" if residue == VAL_RESIDUE else "train"


def read_episode(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of one episode file (the keys in :data:`EPISODE_KEYS`, and ``params``, the
    JSON record its pitch is read from), validated, no pickle."""
    episode = load_episode(path)
    return {key: np.asarray(episode[key]) for key in (*EPISODE_KEYS, "params")}


def episode_steps(path: Path) -> int:
    """``S`` of an episode from the header of its ``positions`` array, without reading data."""
    try:
        with zipfile.ZipFile(path) as archive, archive.open("positions.npy") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, _, _ = np.lib.format.read_array_header_1_0(f)
            else:
                shape, _, _ = np.lib.format.read_array_header_2_0(f)
    except (zipfile.BadZipFile, KeyError, OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable episode file (positions: {exc})") from exc
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"{path}: positions must have shape [S+1, L, 3], got {list(shape)}")
    return shape[0] - 1


def _check_episode(path: Path, ep: dict[str, np.ndarray]) -> None:
    pos, forces = ep["positions"], ep["forces"]
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ValueError(f"{path}: positions must have shape [S+1, L, 3], got {list(pos.shape)}")
    steps, n_leaves = pos.shape[0] - 1, pos.shape[1]
    if forces.shape != (steps, n_leaves, 3):
        raise ValueError(f"{path}: forces must have shape [{steps}, {n_leaves}, 3], got {list(forces.shape)}")
    for key in ("leaf_mass", "leaf_object"):
        if ep[key].shape != (n_leaves,):
            raise ValueError(f"{path}: {key} must have shape [{n_leaves}], got {list(ep[key].shape)}")
    if not np.all(np.isfinite(pos)) or not np.all(np.isfinite(forces)):
        raise ValueError(f"{path}: positions or forces contain NaN or infinite values")


class EpisodeWindows(Dataset):
    """Windows of ``T + 3`` consecutive model states from one split of an episode folder.

    Args:
        root: folder of ``episode_<seed:06d>.npz`` files, or several pooled (a seed twice only for
            different scenes).
        split: ``train``, ``val``, ``test`` (:func:`split_of_seed`) or ``all``.
        horizon: ``T``, predicted steps per window.
        collision_radius: ``r_c`` of the window's ``collision`` edges at ``t``; None: none.
        reference_pitch: scale the radius to :math:`r_c p / p_{ref}` per episode (pitch-aware).
        cache_episodes: decoded episodes kept in memory (per worker).
        transform: PyG transform applied to each window.

    **Shapes** of one window (``N`` nodes): the attributes of
    :func:`~hrn_pyg.data.graph.build_structure`; ``pos``, ``prev_pos``, ``prev_prev_pos``,
    ``force`` ``(N, 3)``; ``pos_seq (N, T+3, 3)``; ``force_seq (N, T, 3)``.
    """

    def __init__(
        self,
        root: str | Path | Sequence[str | Path],
        split: str = "train",
        horizon: int = 1,
        collision_radius: float | None = None,
        cache_episodes: int = 4,
        transform: Callable[[HeteroData], HeteroData] | None = None,
        reference_pitch: float | None = None,
    ) -> None:
        if split not in SPLITS + (ALL,):
            raise ValueError(f"split must be one of {SPLITS + (ALL,)}, got {split!r}")
        if int(horizon) < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if collision_radius is not None and not float(collision_radius) >= 0:
            raise ValueError(f"collision_radius must be >= 0, got {collision_radius}")
        if int(cache_episodes) < 1:
            raise ValueError(f"cache_episodes must be >= 1, got {cache_episodes}")
        if reference_pitch is not None and not 0 < float(reference_pitch) < float("inf"):
            raise ValueError(f"reference_pitch must be a finite number > 0, got {reference_pitch}")
        folders = [Path(root)] if isinstance(root, (str, Path)) else [Path(r) for r in root]
        if not folders:
            raise ValueError("no episode folder given")
        for folder in folders:
            if not folder.is_dir():
                raise FileNotFoundError(f"episode folder {folder} does not exist")
        self.split = split
        self.horizon = int(horizon)
        self.collision_radius = None if collision_radius is None else float(collision_radius)
        self.cache_episodes = int(cache_episodes)
        self.reference_pitch = None if reference_pitch is None else float(reference_pitch)

        found = []
        for folder in folders:
            here = [(int(m.group(1)), folder / name) for name in _listdir(folder) if (m := EPISODE_PATTERN.match(name))]
            if not here:
                raise ValueError(f"no episode_<seed>.npz files in {folder}")
            found += here
        found.sort()
        scenes = {folder: scene_of(folder) for folder in folders}
        twice = repeated_episodes([(seed, scenes[path.parent]) for seed, path in found])
        if twice:
            raise ValueError(f"episode seed(s) {twice[:5]} occur in more than one of the folders "
                             f"{[str(f) for f in folders]} of the same (or an unrecorded) scene: give "
                             "each dataset of a scene its own seed range")
        chosen = [(seed, path) for seed, path in found if split == ALL or split_of_seed(seed) == split]
        if not chosen:
            raise ValueError(f"no episodes of split {split!r} among the {len(found)} in "
                             f"{', '.join(str(f) for f in folders)} (seeds ending in 9 are test, 8 validation; "
                             "--split all takes every episode, as for a dataset not split by seed)")
        self.seeds = [seed for seed, _ in chosen]
        self.paths = [path for _, path in chosen]

        # windows start at t = HISTORY .. S - T
        counts = np.array([max(episode_steps(p) - self.horizon - HISTORY + 1, 0) for p in self.paths])
        if counts.sum() == 0:
            raise ValueError(f"every {split} episode in {folder} is shorter than {self.horizon + HISTORY} steps")
        self._window_episode = np.repeat(np.arange(len(self.paths)), counts)
        first = np.cumsum(counts) - counts
        self._window_start = np.arange(counts.sum()) - np.repeat(first, counts) + HISTORY

        self._episodes: OrderedDict[int, dict[str, Tensor]] = OrderedDict()
        self._structures: dict[int, HeteroData] = {}
        self._pitches: dict[int, float | None] = {}
        super().__init__(root=str(folders[0]), transform=transform, log=False)

    @property
    def raw_file_names(self) -> list[str]:
        return [p.name for p in self.paths]

    @property
    def processed_file_names(self) -> list[str]:
        return []

    def len(self) -> int:
        return int(self._window_episode.shape[0])

    @property
    def window_episodes(self) -> np.ndarray:
        """``(W,)`` the episode (index into :attr:`paths`) of each window."""
        return self._window_episode

    def _episode(self, index: int) -> dict[str, Tensor]:
        """Decoded arrays of episode ``index`` (a small least-recently-used cache)."""
        if index in self._episodes:
            self._episodes.move_to_end(index)
            return self._episodes[index]
        path = self.paths[index]
        arrays = read_episode(path)
        _check_episode(path, arrays)
        self._pitches[index] = episode_pitch(arrays)
        episode = {key: torch.from_numpy(np.ascontiguousarray(arrays[key])) for key in EPISODE_KEYS}
        self._episodes[index] = episode
        if len(self._episodes) > self.cache_episodes:
            self._episodes.popitem(last=False)
        return episode

    def structure(self, index: int) -> HeteroData:
        """The static graph of episode ``index`` (built once, then cached)."""
        if index not in self._structures:
            self._structures[index] = episode_structure(self._episode(index), self._pitches[index])
        return self._structures[index]

    def pitch(self, index: int) -> float | None:
        """The voxel pitch (m) episode ``index`` was made at (None when its ``params`` lack it)."""
        if index not in self._pitches:
            self._episode(index)
        return self._pitches[index]

    def window_radius(self, index: int) -> float | None:
        """The collision radius of the windows of episode ``index``: ``collision_radius``, scaled
        by the episode's pitch over ``reference_pitch`` when that is given."""
        radius = self.collision_radius
        if radius is None or self.reference_pitch is None:
            return radius
        pitch = self.pitch(index)
        if pitch is None:
            raise ValueError(f"{self.paths[index]}: its params record no pitch, which a radius that "
                             "scales with the pitch needs")
        return radius * pitch / self.reference_pitch

    def get(self, idx: int) -> HeteroData:
        index, t = int(self._window_episode[idx]), int(self._window_start[idx])
        ep, structure = self._episode(index), self.structure(index)
        horizon, num_nodes = self.horizon, structure[NODE].num_nodes
        positions = ep["positions"][t - HISTORY : t + horizon + 1].float()  # [T+3, L, 3]
        forces = ep["forces"][t : t + horizon].float()  # [T, L, 3]
        n_leaves = positions.shape[1]

        pad = positions.new_zeros(positions.shape[0], num_nodes - n_leaves, 3)
        pos_seq = leaf_to_ancestor_mean(torch.cat([positions, pad], dim=1), structure)  # [T+3, N, 3]
        force_seq = torch.cat([forces, forces.new_zeros(horizon, num_nodes - n_leaves, 3)], dim=1)

        window = set_state(
            structure,
            pos_seq[0],
            pos_seq[1],
            pos_seq[2],
            radius=self.window_radius(index),
            force=force_seq[0],
        )
        window[NODE].pos_seq = pos_seq.transpose(0, 1).contiguous()
        window[NODE].force_seq = force_seq.transpose(0, 1).contiguous()
        window.episode_seed = torch.tensor([self.seeds[index]], dtype=torch.long)
        window.start_step = torch.tensor([t], dtype=torch.long)
        return window


def scene_of(folder: Path) -> str | None:
    """What made the episodes of ``folder``: its ``meta.json``'s scene file text, else its
    built-in scene name, with the engine when it is not pybullet; None when the folder records
    neither."""
    meta = folder / "meta.json"
    if not meta.is_file() or meta.stat().st_size > MAX_META_BYTES:
        return None
    try:
        record = json.loads(meta.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(record, dict):
        return None
    engine = record.get("engine")
    by = f" in {engine}" if isinstance(engine, str) and engine != "pybullet" else ""
    for key in ("scene_text", "scene"):
        if isinstance(record.get(key), str) and record[key]:
            return f"{key}:{record[key]}{by}"
    return None


def repeated_episodes(found: Sequence[tuple[int, str | None]]) -> list[int]:
    """The seeds of ``(seed, scene)`` pairs that name one episode twice: a seed listed again
    with the same scene, or with a scene that is unknown (None) either time."""
    scenes_of: dict[int, list[str | None]] = {}
    for seed, scene in found:
        scenes_of.setdefault(seed, []).append(scene)
    return sorted(seed for seed, scenes in scenes_of.items()
                  if len(scenes) > 1 and (None in scenes or len(set(scenes)) < len(scenes)))


def _listdir(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.is_file()]
