"""Episodes of a scene kept on disk between runs, with pybullet's time per model step measured anew.

Used by the benchmarks that score one model on scenes they generate themselves
(``many_objects.py``, the one-model mode of ``accuracy_vs_time.py``). A scene's episodes live in
one folder whose name carries a digest of the scene's text and settings (both written there as
``scene.json``), so a changed scene never reuses another's files. An episode file already there
is reused; a missing one is simulated and written atomically, so an interrupted run resumes where
it stopped. A seed pybullet loses (:class:`~hrn_pyg.data.episodes.DivergedEpisode`) is marked
with a ``.rejected`` file, as ``hrn-pyg generate`` does, and skipped.

pybullet's time is not cached: the first seed that pybullet keeps is simulated again in every
run, each ``Scene.step`` (one model step: ``substeps`` physics steps and the leaves read back)
timed, and the median taken, so the engine and the model are timed in the same process.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.episodes import DivergedEpisode, simulate_episode
from hrn_pyg.data.io import save_episode
from hrn_pyg.evaluate import select_windows
from hrn_pyg.utils.files import atomic_write_json, atomic_write_text

from benchmarks.common import time_pybullet


def scene_digest(spec) -> str:
    """Ten hex digits that change whenever the scene's text or any of its settings does."""
    settings = json.dumps(spec.settings_dict(), sort_keys=True, default=str)
    return hashlib.sha256((spec.text + "\n" + settings).encode()).hexdigest()[:10]


def episode_file(folder: Path, seed: int) -> Path:
    return folder / f"episode_{seed:06d}.npz"


def cached_episodes(spec, folder: Path, seeds: list[int]) -> dict:
    """The episodes of ``seeds`` in ``folder`` (made where missing) and pybullet's time.

    Returns ``seeds`` (those pybullet kept, in order), ``rejected`` (those it lost),
    ``made`` (how many were simulated and written in this call), ``pybullet_s_per_step`` (the
    median over the model steps of the first kept seed, simulated in this call) and
    ``timed_episode`` (that episode's arrays).
    """
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder / "scene.json", {"text": spec.text, "settings": spec.settings_dict()})
    kept, rejected, made = [], [], 0
    timed, seconds = None, None
    for seed in seeds:
        path, lost = episode_file(folder, seed), folder / f"episode_{seed:06d}.rejected"
        if lost.is_file():
            rejected.append(seed)
            continue
        try:
            if timed is None:  # simulated again for its time even when the file is there
                episode, seconds = time_pybullet(spec, seed)
                timed = episode
            elif path.is_file():
                kept.append(seed)
                continue
            else:
                episode = simulate_episode(spec, seed)
        except DivergedEpisode as exc:
            atomic_write_text(lost, f"{exc}\n")
            print(f"rejected: {exc}", file=sys.stderr, flush=True)
            rejected.append(seed)
            continue
        if not path.is_file():
            save_episode(path, episode)
            made += 1
        kept.append(seed)
    if timed is None:
        raise RuntimeError(f"pybullet lost every seed of {folder}: {rejected}")
    return {"seeds": kept, "rejected": rejected, "made": made, "pybullet_s_per_step": seconds,
            "timed_episode": timed}


def episode_leaves(path: Path) -> int:
    """The leaf count of an episode file, from its ``positions`` array."""
    with np.load(path) as episode:
        return int(episode["positions"].shape[1])


def windows_of(folder: Path, seeds: list[int], horizon: int, stride: int, limit: int | None = None) -> list:
    """The windows of horizon ``horizon`` of the episodes of ``seeds`` in ``folder``, starting
    at step 2 and then every ``stride`` steps (:func:`hrn_pyg.evaluate.select_windows`; episodes
    of other seeds in the folder are left out); at most ``limit``."""
    wanted = set(seeds)
    windows = [w for w in select_windows(EpisodeWindows(folder, "all", horizon=horizon), stride, None)
               if int(w.episode_seed) in wanted]
    return windows if limit is None else windows[:limit]
