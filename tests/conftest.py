"""Fixtures shared by every test folder."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

#: seeds of the tiny real-physics folder: 8 -> validation, 9 -> test, the rest train
TINY_SEEDS = tuple(range(10))
TINY_STEPS = 14


@pytest.fixture(autouse=True, scope="session")
def _single_thread():
    """Small graphs run fastest on one thread, and two test workers share two cores."""
    torch.set_num_threads(1)
    yield


@pytest.fixture(scope="session")
def tiny_episodes(tmp_path_factory) -> Path:
    """Ten short pybullet ``cube_collision`` episodes (about a second to make)."""
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.data.io import save_episode

    folder = tmp_path_factory.mktemp("cube_collision")
    for seed in TINY_SEEDS:
        save_episode(folder / f"episode_{seed:06d}.npz", simulate_episode("cube_collision", seed, steps=TINY_STEPS))
    return folder
