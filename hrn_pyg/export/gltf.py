"""glTF 2.0 binary (``.glb``): every trajectory's meshes, animated, in one file.

One node per trajectory (``truth``, ``future 00`` ...) under a root that turns z-up into glTF's
y-up. A rigid object is its rest mesh animated by ``translation`` and ``rotation``
(:mod:`hrn_pyg.export.rigid_fit`); a soft body or cloth has one morph target per frame and a
``weights`` channel; a static object is drawn once under ``truth``. The truth is opaque, futures
lighter and translucent. Written with :mod:`struct`, no library needed.
"""

from __future__ import annotations

import json
import os
import struct
from collections.abc import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from hrn_pyg.data.kinds import STATIC
from hrn_pyg.export.animate import ObjectFrames
from hrn_pyg.utils.files import atomic_write

__all__ = ["Z_UP_TO_Y_UP", "write_glb", "object_rgba"]

#: the root node's rotation, ``[x, y, z, w]``: -90 degrees about x takes z-up to y-up
Z_UP_TO_Y_UP = (-float(np.sqrt(0.5)), 0.0, 0.0, float(np.sqrt(0.5)))
#: object colours (the pictures' palette, :data:`hrn_pyg.viz.PALETTE`) as RGB in [0, 1]
PALETTE_RGB = ((0.0, 0.447, 0.698), (0.902, 0.624, 0.0), (0.0, 0.620, 0.451), (0.800, 0.475, 0.655),
               (0.835, 0.369, 0.0), (0.337, 0.706, 0.914), (0.941, 0.894, 0.259), (0.2, 0.2, 0.2))
STATIC_RGB = (0.77, 0.77, 0.77)
#: a future is its object's colour mixed this far towards white, at this opacity
FUTURE_LIGHTEN, FUTURE_ALPHA = 0.45, 0.45
#: component types and the binding targets of the specification
FLOAT, UNSIGNED_INT = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def object_rgba(index: int, material: int, truth: bool) -> list[float]:
    """An object's colour: the palette's (static grey), lighter and translucent in a future."""
    rgb = np.array(STATIC_RGB if material == STATIC else PALETTE_RGB[index % len(PALETTE_RGB)])
    if truth:
        return [*rgb.tolist(), 1.0]
    return [*(rgb + FUTURE_LIGHTEN * (1 - rgb)).tolist(), FUTURE_ALPHA]


class _Builder:
    """Buffer views and accessors of one binary buffer, each view 4-byte aligned."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, kind: str, target: int | None = None, bounds: bool = False) -> int:
        array = np.ascontiguousarray(array, dtype=np.uint32 if kind == "SCALAR_INDEX" else np.float32)
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.blob.extend(array.tobytes())
        self.views.append(view)
        types = {"SCALAR": 1, "SCALAR_INDEX": 1, "VEC3": 3, "VEC4": 4}
        accessor = {"bufferView": len(self.views) - 1, "componentType": UNSIGNED_INT if kind == "SCALAR_INDEX" else FLOAT,
                    "count": int(array.size // types[kind]), "type": "SCALAR" if kind == "SCALAR_INDEX" else kind}
        if bounds:
            flat = array.reshape(accessor["count"], -1)
            accessor["min"] = flat.min(axis=0).astype(float).tolist()
            accessor["max"] = flat.max(axis=0).astype(float).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _quaternions(rotation: np.ndarray) -> np.ndarray:
    """``[x, y, z, w]`` of each rotation ``(T, 3, 3)``, signs chosen so neighbours are near (a
    linear blend of keyframes then turns the short way)."""
    q = Rotation.from_matrix(rotation).as_quat()
    for t in range(1, len(q)):  # keyframes in order: each sign depends on the previous one
        if float(q[t] @ q[t - 1]) < 0:
            q[t] = -q[t]
    return q


def write_glb(path: str | os.PathLike, trajectories: Mapping[str, tuple[ObjectFrames, ...]], dt: float) -> None:
    """Write ``trajectories`` (name -> every object's :class:`~hrn_pyg.export.animate.ObjectFrames`,
    the first the ground truth) as one animated ``.glb`` at ``dt`` seconds per frame."""
    b = _Builder()
    meshes, materials, nodes, samplers, channels = [], [], [], [], []
    steps = next(iter(trajectories.values()))[0].vertices.shape[0]
    times = b.add(np.arange(steps) * float(dt), "SCALAR", bounds=True)
    faces_of: dict[int, int] = {}
    root_children = []
    for number, (name, objects) in enumerate(trajectories.items()):
        truth = number == 0
        children = []
        for frames in objects:
            obj = frames.object
            if obj.material == STATIC and not truth:
                continue
            if obj.index not in faces_of:
                faces_of[obj.index] = b.add(obj.faces.reshape(-1), "SCALAR_INDEX", ELEMENT_ARRAY_BUFFER)
            materials.append({"name": f"{name} object {obj.index}",
                              "pbrMetallicRoughness": {"baseColorFactor": object_rgba(obj.index, obj.material, truth),
                                                       "metallicFactor": 0.0, "roughnessFactor": 0.8},
                              "doubleSided": True, **({} if truth else {"alphaMode": "BLEND"})})
            primitive = {"indices": faces_of[obj.index], "material": len(materials) - 1, "mode": 4}
            node = {"name": f"{name} object {obj.index}", "mesh": len(meshes)}
            if frames.rigid is not None:
                pose = frames.rigid
                primitive["attributes"] = {"POSITION": b.add(obj.vertices - pose.centre, "VEC3", ARRAY_BUFFER, True)}
                meshes.append({"name": node["name"], "primitives": [primitive]})
                node["translation"] = pose.translation[0].tolist()
                node["rotation"] = _quaternions(pose.rotation[:1])[0].tolist()
                if obj.material != STATIC:
                    for path_name, values in (("translation", b.add(pose.translation, "VEC3")),
                                              ("rotation", b.add(_quaternions(pose.rotation), "VEC4"))):
                        samplers.append({"input": times, "output": values, "interpolation": "LINEAR"})
                        channels.append({"sampler": len(samplers) - 1,
                                         "target": {"node": len(nodes), "path": path_name}})
            else:
                base = frames.vertices[0]
                primitive["attributes"] = {"POSITION": b.add(base, "VEC3", ARRAY_BUFFER, True)}
                primitive["targets"] = [{"POSITION": b.add(frames.vertices[t] - base, "VEC3", ARRAY_BUFFER, True)}
                                        for t in range(1, steps)]
                meshes.append({"name": node["name"], "primitives": [primitive], "weights": [0.0] * (steps - 1),
                               "extras": {"targetNames": [f"frame {t}" for t in range(1, steps)]}})
                if steps > 1:
                    weights = np.eye(steps, steps - 1, k=-1)  # keyframe t shows target t (frame t)
                    samplers.append({"input": times, "output": b.add(weights.reshape(-1), "SCALAR"),
                                     "interpolation": "LINEAR"})
                    channels.append({"sampler": len(samplers) - 1, "target": {"node": len(nodes), "path": "weights"}})
            nodes.append(node)
            children.append(len(nodes) - 1)
        nodes.append({"name": name, "children": children})
        root_children.append(len(nodes) - 1)
    nodes.append({"name": "z-up world", "rotation": list(Z_UP_TO_Y_UP), "children": root_children})
    document = {
        "asset": {"version": "2.0", "generator": "hrn_pyg.export"},
        "scene": 0, "scenes": [{"name": "rollout", "nodes": [len(nodes) - 1]}],
        "nodes": nodes, "meshes": meshes, "materials": materials,
        "accessors": b.accessors, "bufferViews": b.views, "buffers": [{"byteLength": len(b.blob)}],
    }
    if channels:
        document["animations"] = [{"name": "rollout", "samplers": samplers, "channels": channels}]
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    blob = bytes(b.blob) + b"\0" * (-len(b.blob) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)

    def write(f) -> None:
        f.write(struct.pack("<III", GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), JSON_CHUNK) + text)
        f.write(struct.pack("<II", len(blob), BIN_CHUNK) + blob)

    atomic_write(path, write)
