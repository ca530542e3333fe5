"""Leaf trajectories as the scene's own meshes, frame by frame: a rigid or static object's mesh
follows its leaves' best rigid transform (:mod:`hrn_pyg.export.rigid_fit`), a soft body's or
cloth's is skinned to them (:mod:`hrn_pyg.export.skinning`). Every leaf output of the package
(``[T, L, 3]``, ``[K, T, L, 3]``, ``samples.npz``) turns into meshes here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrn_pyg.export.rigid_fit import RigidFrames, fit_rigid_frames
from hrn_pyg.export.scene_meshes import ObjectMesh, SceneMeshes
from hrn_pyg.export.skinning import SkinWeights, skin_weights

__all__ = ["ObjectFrames", "Rig", "rig"]


@dataclass(frozen=True)
class ObjectFrames:
    """One object's mesh in every frame: ``vertices (T, V, 3)`` (faces are ``object.faces``);
    ``rigid`` holds the pose of a rigid or static object (None: a skinned one)."""

    object: ObjectMesh
    vertices: np.ndarray
    rigid: RigidFrames | None


@dataclass(frozen=True)
class Rig:
    """A scene's meshes with the skinning weights of its deformables, computed once at rest
    (:func:`rig`) and applied to any number of trajectories."""

    meshes: SceneMeshes
    skins: dict[int, SkinWeights]

    def animate(self, leaves: np.ndarray) -> tuple[ObjectFrames, ...]:
        """Every object's mesh along one trajectory of leaves ``(T, L, 3)``."""
        leaves = np.asarray(leaves, np.float64)
        if leaves.ndim != 3 or leaves.shape[1:] != (self.meshes.num_leaves, 3):
            raise ValueError(f"leaves must be [T, {self.meshes.num_leaves}, 3] (the scene's leaves), "
                             f"got {list(leaves.shape)}")
        frames = []
        for obj in self.meshes.objects:  # a handful of objects, not a loop over particles
            own = leaves[:, obj.leaf_slice]
            if obj.moves_rigidly:
                pose = fit_rigid_frames(obj.leaves, own)
                frames.append(ObjectFrames(obj, pose.apply(obj.vertices), pose))
            else:
                frames.append(ObjectFrames(obj, self.skins[obj.index].apply(own), None))
        return tuple(frames)


def rig(meshes: SceneMeshes) -> Rig:
    """The :class:`Rig` of a scene: skinning weights of every soft body and cloth."""
    skins = {o.index: skin_weights(o.vertices, o.leaves, meshes.pitch)
             for o in meshes.objects if not o.moves_rigidly}
    return Rig(meshes, skins)
