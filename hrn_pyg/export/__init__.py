"""Rollouts as the scene's own meshes, and the files other tools open (glTF, PLY, OBJ, VTK).

>>> from hrn_pyg.export import scene_meshes, export_trajectories
>>> meshes = scene_meshes(spec, scene.params)            # rest meshes and leaves, world frame
>>> export_trajectories(meshes, {"truth": truth, "future_00": future}, "out", ("glb", "vtk"))
"""

from hrn_pyg.export.animate import ObjectFrames, Rig, rig
from hrn_pyg.export.files import FORMATS, GLB_NAME, export_npz, export_trajectories, parse_formats, sample_trajectories
from hrn_pyg.export.rigid_fit import RigidFrames, fit_rigid_frames
from hrn_pyg.export.scene_meshes import ObjectMesh, SceneMeshes, scene_meshes
from hrn_pyg.export.skinning import SkinWeights, skin_weights

__all__ = ["FORMATS", "GLB_NAME", "ObjectFrames", "ObjectMesh", "Rig", "RigidFrames", "SceneMeshes", "SkinWeights",
           "export_npz", "export_trajectories", "fit_rigid_frames", "parse_formats", "rig", "sample_trajectories",
           "scene_meshes", "skin_weights"]
