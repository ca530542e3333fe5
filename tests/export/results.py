"""A result folder as ``hrn-pyg sample`` writes it, made from the export tests' pybullet episode
(the truth, and futures shifted and lifted from it) without running a model."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_result(folder: Path, run, futures: int = 2, steps: int = 6, meshes: bool = True) -> Path:
    """``folder/samples.npz`` of ``futures`` futures over ``steps`` steps; returns the folder."""
    truth = run.leaves[: steps + 1]
    moving = run.meshes.object_material[run.meshes.leaf_object] != 3
    offsets = [np.array([0.05 * (k + 1), -0.04 * (k + 1), 0.02]) for k in range(futures)]
    samples = np.stack([truth[1:] + moving[:, None] * offset for offset in offsets]).astype(np.float32)
    folder.mkdir(parents=True, exist_ok=True)
    extra = run.meshes.to_arrays() if meshes else {}
    np.savez_compressed(folder / "samples.npz", samples=samples, truth=truth.astype(np.float32), **extra)
    return folder
