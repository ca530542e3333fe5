"""Export trajectories of a scene's leaves as mesh files: ``glb``, ``ply``, ``obj``, ``vtk``.

The trajectories are named: ``truth`` (the simulator's, when there is one) and ``future_00``,
``future_01`` ... (sampled futures) or ``rollout`` (a deterministic one). Under ``out``:

========  ====================================================================
``glb``   ``rollout.glb``: every trajectory, animated, in one file (:mod:`~hrn_pyg.export.gltf`)
``ply``   ``ply/<name>/frame_0000.ply`` ... (:mod:`~hrn_pyg.export.sequence`)
``obj``   ``obj/<name>/frame_0000.obj`` ...
``vtk``   ``vtk/<name>.pvd`` and ``vtk/<name>/frame_0000.vtu`` ... (:mod:`~hrn_pyg.export.vtk`)
========  ====================================================================
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from hrn_pyg.export.animate import Rig, rig
from hrn_pyg.export.gltf import write_glb
from hrn_pyg.export.scene_meshes import SceneMeshes
from hrn_pyg.export.sequence import write_sequence
from hrn_pyg.export.vtk import write_vtk_series

__all__ = ["FORMATS", "GLB_NAME", "parse_formats", "sample_trajectories", "export_trajectories", "export_npz"]

#: the formats :func:`export_trajectories` writes
FORMATS = ("glb", "ply", "obj", "vtk")
#: the ``.glb`` file's name in the output folder
GLB_NAME = "rollout.glb"


def parse_formats(text: str) -> tuple[str, ...]:
    """``"glb,ply,vtk"`` -> ``("glb", "ply", "vtk")``; an unknown or empty list is a ValueError."""
    formats = tuple(dict.fromkeys(f.strip().lower() for f in str(text).split(",") if f.strip()))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"--export: choose from {', '.join(FORMATS)} (comma-separated), got {text!r}")
    return formats


def sample_trajectories(truth: np.ndarray | None, futures: np.ndarray) -> dict[str, np.ndarray]:
    """``truth (T, L, 3)`` and ``futures (K, T, L, 3)`` as named trajectories: ``truth``, then
    ``future_00`` ...; one future without a truth is a ``rollout``."""
    futures = np.asarray(futures)
    named = {} if truth is None else {"truth": np.asarray(truth)}
    if truth is None and len(futures) == 1:
        return {"rollout": futures[0]}
    named.update({f"future_{k:02d}": futures[k] for k in range(len(futures))})
    return named


def export_trajectories(scene: SceneMeshes | Rig, trajectories: Mapping[str, np.ndarray],
                        out: str | os.PathLike, formats: tuple[str, ...] = FORMATS) -> list[Path]:
    """Write each named trajectory of leaves ``(T, L, 3)`` as the scene's meshes in ``formats``
    under ``out``; returns the files written (a ``.pvd`` stands for its frames, a sequence's
    folder for its files). The first trajectory is drawn as the ground truth."""
    formats = parse_formats(",".join(formats))
    scene_rig = scene if isinstance(scene, Rig) else rig(scene)
    if not trajectories:
        raise ValueError("export: no trajectories")
    animated = {name: scene_rig.animate(leaves) for name, leaves in trajectories.items()}
    out = Path(out)
    written: list[Path] = []
    if "glb" in formats:
        write_glb(out / GLB_NAME, animated, scene_rig.meshes.dt)
        written.append(out / GLB_NAME)
    for file_type in ("ply", "obj"):
        if file_type in formats:
            for number, (name, objects) in enumerate(animated.items()):
                write_sequence(out / file_type / name, objects, file_type, truth=number == 0)
                written.append(out / file_type / name)
    if "vtk" in formats:
        written += [write_vtk_series(out / "vtk", name, objects, scene_rig.meshes.dt)
                    for name, objects in animated.items()]
    return written


def export_npz(path: str | os.PathLike, out: str | os.PathLike, formats: tuple[str, ...] = FORMATS) -> list[Path]:
    """Export a ``samples.npz`` of ``hrn-pyg sample`` (its ``truth``, ``samples`` and scene
    meshes) into ``out``."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such file: {path}")
    with np.load(path, allow_pickle=False) as data:
        meshes = SceneMeshes.from_arrays(data)
        truth, samples = data["truth"], data["samples"]
    futures = np.concatenate([np.broadcast_to(truth[:1], (len(samples), 1) + truth.shape[1:]), samples], axis=1)
    return export_trajectories(meshes, sample_trajectories(truth, futures), out, formats)
