"""The meshes of a scene at rest, in the world frame, beside the leaves they were made from.

A scene file's object is a mesh sized and placed by what its seed drew
(:func:`hrn_pyg.data.scene_file.posed_mesh`); its leaves are made from the same posed mesh, so
mesh and leaves agree exactly at step 0. This module rebuilds both without running pybullet.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from hrn_pyg.data.kinds import CLOTH, MATERIALS, RIGID, SOFT, STATIC
from hrn_pyg.data.scene_file import (
    SceneSpec,
    check_sheet,
    leaves_of,
    posed_mesh,
    quaternion,
    scene_spec,
    soft_lattice,
    surface_leaves,
)
from hrn_pyg.data.voxelise import grid_sheet

__all__ = ["ObjectMesh", "SceneMeshes", "scene_meshes", "seed_meshes", "episode_meshes", "rotation_matrix"]


def rotation_matrix(q: list[float] | np.ndarray | None) -> np.ndarray:
    """The 3x3 rotation of a unit quaternion ``[x, y, z, w]`` (None: the identity)."""
    if q is None:
        return np.eye(3)
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


@dataclass(frozen=True)
class ObjectMesh:
    """One object's mesh and leaves at rest (step 0), world frame.

    **Shapes:** ``vertices (V, 3)`` float64, ``faces (F, 3)`` int64, ``leaves (n, 3)`` float64
    (rows ``leaf_start .. leaf_start + n - 1`` of the scene's leaves).
    """

    index: int
    material: int
    vertices: np.ndarray
    faces: np.ndarray
    leaves: np.ndarray
    leaf_start: int

    @property
    def leaf_slice(self) -> slice:
        return slice(self.leaf_start, self.leaf_start + len(self.leaves))

    @property
    def material_name(self) -> str:
        return MATERIALS[self.material]

    @property
    def moves_rigidly(self) -> bool:
        """Rigid and static objects keep their shape: their mesh follows one rigid transform."""
        return self.material in (RIGID, STATIC)


@dataclass(frozen=True)
class SceneMeshes:
    """Every object's :class:`ObjectMesh`, in the scene's object order, and the scene's
    ``pitch`` (m) and ``dt`` (s per model step)."""

    objects: tuple[ObjectMesh, ...]
    pitch: float
    dt: float

    @property
    def num_leaves(self) -> int:
        return sum(len(o.leaves) for o in self.objects)

    @property
    def leaf_object(self) -> np.ndarray:
        """The object id of every leaf ``(L,)`` int64."""
        return np.concatenate([np.full(len(o.leaves), o.index, dtype=np.int64) for o in self.objects])

    @property
    def object_material(self) -> np.ndarray:
        """The material code of every object ``(O,)`` int64 (:data:`hrn_pyg.data.kinds.MATERIALS`)."""
        return np.array([o.material for o in self.objects], dtype=np.int64)

    @property
    def rest_leaves(self) -> np.ndarray:
        """Every leaf at rest ``(L, 3)`` float64."""
        return np.concatenate([o.leaves for o in self.objects])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The meshes as flat arrays (what ``samples.npz`` stores; :meth:`from_arrays` reads
        them back): ``mesh_vertices (V, 3)``, ``mesh_faces (F, 3)`` into them, ``mesh_object
        (V,)`` and ``face_object (F,)`` object ids, ``rest_leaves (L, 3)``, ``leaf_object
        (L,)``, ``object_material (O,)``, ``pitch`` and ``dt``."""
        offsets = np.cumsum([0] + [len(o.vertices) for o in self.objects])
        return {
            "mesh_vertices": np.concatenate([o.vertices for o in self.objects]),
            "mesh_faces": np.concatenate([o.faces + offsets[i] for i, o in enumerate(self.objects)]).astype(np.int64),
            "mesh_object": np.concatenate([np.full(len(o.vertices), o.index) for o in self.objects]).astype(np.int64),
            "face_object": np.concatenate([np.full(len(o.faces), o.index) for o in self.objects]).astype(np.int64),
            "rest_leaves": self.rest_leaves,
            "leaf_object": self.leaf_object,
            "object_material": self.object_material,
            "pitch": np.array(self.pitch, dtype=np.float64),
            "dt": np.array(self.dt, dtype=np.float64),
        }

    @classmethod
    def from_arrays(cls, arrays) -> SceneMeshes:
        """The inverse of :meth:`to_arrays` (e.g. an opened ``samples.npz``); a missing key is a
        ValueError naming it."""
        keys = ("mesh_vertices", "mesh_faces", "mesh_object", "face_object", "rest_leaves", "leaf_object",
                "object_material", "pitch", "dt")
        missing = [k for k in keys if k not in arrays]
        if missing:
            raise ValueError(f"no scene meshes: the file lacks {', '.join(missing)}")
        vertices, faces = np.asarray(arrays["mesh_vertices"], np.float64), np.asarray(arrays["mesh_faces"], np.int64)
        mesh_object, face_object = np.asarray(arrays["mesh_object"]), np.asarray(arrays["face_object"])
        leaves, leaf_object = np.asarray(arrays["rest_leaves"], np.float64), np.asarray(arrays["leaf_object"])
        objects, start = [], 0
        for index, material in enumerate(np.asarray(arrays["object_material"]).tolist()):
            keep = np.flatnonzero(mesh_object == index)
            own = leaves[leaf_object == index]
            local = np.full(len(vertices), -1, dtype=np.int64)
            local[keep] = np.arange(len(keep))
            objects.append(ObjectMesh(index, int(material), vertices[keep], local[faces[face_object == index]],
                                      own, start))
            start += len(own)
        return cls(tuple(objects), float(arrays["pitch"]), float(arrays["dt"]))


def scene_meshes(scene: str | SceneSpec, params: dict) -> SceneMeshes:
    """The rest meshes and leaves of a scene for one seed's drawn ``params``, world frame: a rigid or
    static object's posed mesh and voxel leaves, a soft body's mesh and lattice nodes, a cloth's
    surface whose vertices are its leaves."""
    spec = scene_spec(scene)
    pitch = float(spec.config.pitch)
    objects, start = [], 0
    for index, (obj, drawn) in enumerate(zip(spec.objects, params["objects"])):
        where = f"{spec.name}: objects[{index}]"
        material = MATERIALS.index(obj.material)
        mesh = posed_mesh(obj, drawn)
        if mesh is None:  # a square sheet of cloth: the lattice is the mesh
            check_sheet(float(drawn["size"]), pitch, where)
            vertices, faces = grid_sheet(float(drawn["size"]), pitch)
            leaves = vertices
        else:
            vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
            if material == CLOTH:
                leaves = surface_leaves(mesh, where)
            elif material == SOFT:
                leaves = soft_lattice(mesh, pitch, where)[0]
            else:
                leaves = leaves_of(mesh, pitch, where)
        rotation = rotation_matrix(quaternion(drawn))
        position = np.asarray(drawn["position"], dtype=np.float64)
        objects.append(ObjectMesh(index, material, vertices @ rotation.T + position, faces,
                                  np.asarray(leaves, np.float64) @ rotation.T + position, start))
        start += len(leaves)
    return SceneMeshes(tuple(objects), pitch, float(spec.config.dt))


def seed_meshes(scene: str | SceneSpec, seed: int, steps: int | None = None) -> SceneMeshes:
    """:func:`scene_meshes` of the episode ``simulate_episode(scene, seed, steps)`` runs: the
    seed's draws, made without pybullet."""
    spec = scene_spec(scene)
    if steps is not None:
        spec = dataclasses.replace(spec, config=dataclasses.replace(spec.config, steps=int(steps)))
    return scene_meshes(spec, spec.make_scene(int(seed)).params)


def episode_meshes(scene: str | SceneSpec, episode: dict) -> SceneMeshes:
    """:func:`scene_meshes` of a recorded episode of ``scene``: the draws and settings its
    ``params`` JSON holds."""
    try:
        record = json.loads(str(episode["params"]))
        params, config = record["params"], record.get("config", {})
    except (KeyError, TypeError, ValueError):
        raise ValueError("the episode records no drawn params: its meshes cannot be rebuilt") from None
    return scene_meshes(scene_spec(scene).with_settings(**config), params)
