"""``hrn-pyg check-data FOLDER``: is a folder of episode files one that training can read?

Each ``episode_<seed:06d>.npz`` is loaded (:func:`~hrn_pyg.data.io.load_episode`), its graph
built (:func:`~hrn_pyg.data.graph.build_structure`), and the rest of ``docs/data.md``'s "Episode
format" checked: one root per object, z up with no leaf more than a pitch under ``z = 0``, no
jump past :data:`~hrn_pyg.data.episodes.MAX_STEP_DISPLACEMENT`, ``dt > 0``, JSON ``params``, one
training window's length. Each problem is a line ``FILE: what is wrong`` (exit code 2); a clean
folder prints one summary line.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hrn_pyg.data.dataset import EPISODE_PATTERN, split_of_seed
from hrn_pyg.data.episodes import MAX_DISTANCE, MAX_STEP_DISPLACEMENT
from hrn_pyg.data.graph import HISTORY, build_structure
from hrn_pyg.data.io import episode_pitch, load_episode
from hrn_pyg.data.kinds import MATERIALS, STATIC

#: problems printed before the rest are only counted
MAX_PRINTED = 20


@dataclass(frozen=True)
class EpisodeSummary:
    """What a valid episode holds: its seed, model steps ``S``, leaves ``L``, the materials of its
    objects, its pitch (m; None when ``params`` records none) and ``dt`` (s)."""

    seed: int
    steps: int
    leaves: int
    materials: tuple[int, ...]
    pitch: float | None
    dt: float


def tree_roots(parent: np.ndarray) -> np.ndarray:
    """The root of every node of a parent array (roots have parent ``-1``), by pointer jumping;
    ValueError on a cycle. **Shapes** ``parent [N]`` -> ``[N]``."""
    n = len(parent)
    up = np.where(parent < 0, np.arange(n), parent)
    for _ in range(max(n, 1).bit_length() + 1):
        nxt = up[up]
        if np.array_equal(nxt, up):
            break
        up = nxt
    if np.any(parent[up] >= 0):
        raise ValueError("hierarchy_parent: the parents hold a cycle")
    return up


def check_episode(path: Path) -> EpisodeSummary:
    """The summary of one episode file; ValueError with one line naming the first problem."""
    episode = load_episode(path)
    positions, parent = episode["positions"], episode["hierarchy_parent"]
    leaf_object, material = episode["leaf_object"], episode["object_material"]
    steps, leaves = positions.shape[0] - 1, positions.shape[1]
    import torch  # the graph is built as training builds it

    build_structure(torch.from_numpy(parent).long(), torch.from_numpy(episode["leaf_mass"]).float(),
                    torch.from_numpy(leaf_object).long(), torch.from_numpy(material).long(),
                    torch.from_numpy(episode["object_stiffness"]).float())
    roots = tree_roots(parent)
    leaf_roots = roots[:leaves]
    for obj in range(len(material)):  # one root per object: a loop over objects, not leaves
        own = np.unique(leaf_roots[leaf_object == obj])
        if len(own) == 0:
            raise ValueError(f"object {obj} has no leaves")
        if len(own) > 1:
            raise ValueError(f"hierarchy_parent: the leaves of object {obj} hang under {len(own)} roots, not one")
    if len(np.unique(leaf_roots)) != len(material):
        raise ValueError("hierarchy_parent: two objects share a root")
    dt = float(episode["dt"])
    if not dt > 0:
        raise ValueError(f"dt: must be > 0 (seconds per model step), got {dt}")
    try:
        json.loads(str(episode["params"]))
    except json.JSONDecodeError:
        raise ValueError("params: not JSON") from None
    pitch = episode_pitch(episode)
    if pitch is not None and not 0 < pitch < float("inf"):
        raise ValueError(f"params: config.pitch must be > 0 (m), got {pitch}")
    if steps < HISTORY + 1:
        raise ValueError(f"positions: {steps} steps, fewer than the {HISTORY + 1} of one training window")
    farthest = float(np.abs(positions).max())
    if farthest > MAX_DISTANCE:
        raise ValueError(f"positions: a leaf {farthest:.4g} m from the origin (more than {MAX_DISTANCE} m; "
                         "positions are metres)")
    lowest, allowed = float(positions[..., 2].min()), pitch if pitch is not None else 0.0
    if lowest < -allowed:
        raise ValueError(f"positions: a leaf {-lowest:.3g} m under the ground z = 0 (more than one pitch); "
                         "z points up and the ground is z = 0")
    jump = float(np.abs(np.diff(positions, axis=0)).max())
    if jump > MAX_STEP_DISPLACEMENT:
        raise ValueError(f"positions: a leaf moves {jump:.3g} m in one step (more than {MAX_STEP_DISPLACEMENT} m)")
    moved = np.abs(positions - positions[:1]).max(axis=(0, 2)) > 0
    static_moves = moved & (material[leaf_object] == STATIC)
    if np.any(static_moves):
        raise ValueError(f"positions: object {int(leaf_object[static_moves][0])} is static and moves")
    return EpisodeSummary(seed=int(episode["seed"]), steps=steps, leaves=leaves,
                          materials=tuple(int(m) for m in material), pitch=pitch, dt=dt)


def episode_files(folder: Path) -> list[Path]:
    """The episode files of ``folder``, by seed; FileNotFoundError / ValueError when there are none."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a folder")
    found = sorted((int(m.group(1)), folder / p.name) for p in folder.iterdir()
                   if p.is_file() and (m := EPISODE_PATTERN.match(p.name)))
    if not found:
        raise ValueError(f"no episode_<seed>.npz files in {folder}")
    return [path for _, path in found]


def summary_line(folder: Path, summaries: list[EpisodeSummary]) -> str:
    """One line of what a valid folder holds."""
    splits = {name: sum(split_of_seed(s.seed) == name for s in summaries) for name in ("train", "val", "test")}
    steps = sorted({s.steps for s in summaries})
    leaves = [s.leaves for s in summaries]
    materials = sorted({MATERIALS[m] for s in summaries for m in s.materials})
    pitches = sorted({s.pitch for s in summaries if s.pitch is not None})
    dts = sorted({round(s.dt, 9) for s in summaries})
    span = lambda values: f"{values[0]:g}" if len(values) == 1 else f"{values[0]:g}-{values[-1]:g}"  # noqa: E731
    return (f"{folder}: {len(summaries)} episodes (train {splits['train']}, val {splits['val']}, test "
            f"{splits['test']}), {span(steps)} steps, {span(sorted(set(leaves)))} leaves, {', '.join(materials)}, "
            f"pitch {span(pitches) + ' m' if pitches else 'not recorded'}, dt {span(dts)} s: ok")


def check_folder(folder: str | Path) -> tuple[list[EpisodeSummary], list[str]]:
    """The summaries of the valid episodes of ``folder`` and one line per invalid one."""
    summaries, problems = [], []
    for path in episode_files(Path(folder)):
        try:
            summaries.append(check_episode(path))
        except (ValueError, FileNotFoundError) as exc:
            text = str(exc)
            problems.append(text if text.startswith(str(path)) else f"{path}: {text}")
    return summaries, problems


def run(args: argparse.Namespace) -> int:
    folder = Path(args.folder)
    summaries, problems = check_folder(folder)
    for line in problems[:MAX_PRINTED]:
        print(line, file=sys.stderr)
    if problems:
        more = f" (the first {MAX_PRINTED} above)" if len(problems) > MAX_PRINTED else ""
        raise ValueError(f"{len(problems)} of {len(problems) + len(summaries)} episode files in {folder} "
                         f"fail the checks{more}")
    print(summary_line(folder, summaries))
    return 0
