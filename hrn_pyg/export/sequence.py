"""Per-frame mesh files: ``<out>/<trajectory>/frame_0000.ply`` (or ``.obj``), every object at that
frame, vertices coloured by object (PLY), for Blender's mesh-sequence import or ParaView."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import trimesh

from hrn_pyg.export.animate import ObjectFrames
from hrn_pyg.export.gltf import object_rgba
from hrn_pyg.utils.files import atomic_write

__all__ = ["frame_mesh", "write_sequence", "FRAME_NAME"]

#: a frame's file name (``.format(t)``), without the suffix
FRAME_NAME = "frame_{:04d}"


def frame_mesh(objects: tuple[ObjectFrames, ...], t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``t`` of every object as one mesh: ``vertices (V, 3)``, ``faces (F, 3)``,
    ``vertex_object (V,)`` and ``face_object (F,)``."""
    offsets = np.cumsum([0] + [f.vertices.shape[1] for f in objects])
    vertices = np.concatenate([f.vertices[t] for f in objects])
    faces = np.concatenate([f.object.faces + offsets[i] for i, f in enumerate(objects)])
    vertex_object = np.concatenate([np.full(f.vertices.shape[1], f.object.index) for f in objects])
    face_object = np.concatenate([np.full(len(f.object.faces), f.object.index) for f in objects])
    return vertices, faces, vertex_object.astype(np.int64), face_object.astype(np.int64)


def write_sequence(folder: str | os.PathLike, objects: tuple[ObjectFrames, ...], file_type: str = "ply",
                   truth: bool = True) -> list[Path]:
    """Write every frame of one trajectory into ``folder`` as ``file_type`` (``ply`` or ``obj``);
    returns the paths in frame order."""
    if file_type not in ("ply", "obj"):
        raise ValueError(f"a mesh sequence is ply or obj, got {file_type!r}")
    folder = Path(folder)
    colours = np.zeros((max(f.object.index for f in objects) + 1, 4), dtype=np.uint8)
    for f in objects:
        colours[f.object.index] = np.round(np.array(object_rgba(f.object.index, f.object.material, truth)) * 255)
    paths = []
    for t in range(objects[0].vertices.shape[0]):  # one file per frame
        vertices, faces, vertex_object, _ = frame_mesh(objects, t)
        mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colours[vertex_object], process=False)
        data = mesh.export(file_type=file_type)
        data = data.encode("utf-8") if isinstance(data, str) else data
        path = folder / f"{FRAME_NAME.format(t)}.{file_type}"
        atomic_write(path, lambda f: f.write(data))
        paths.append(path)
    return paths
