"""Per-frame PLY and OBJ files read back by meshio and trimesh, and the VTK series (``.pvd`` and
``.vtu`` files) by meshio and an XML parser: the scene's meshes in every frame."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import trimesh

from hrn_pyg.export import export_trajectories, parse_formats, rig


@pytest.fixture(scope="module")
def exported(pybullet_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("files")
    leaves = pybullet_run.leaves[:4]
    export_trajectories(pybullet_run.meshes, {"truth": leaves, "future_00": leaves[::-1]}, out, ("ply", "obj", "vtk"))
    return out, rig(pybullet_run.meshes).animate(leaves)


def scene_vertices(frames, t: int) -> np.ndarray:
    return np.concatenate([f.vertices[t] for f in frames])


def test_ply_frames_hold_every_object_in_every_frame(exported, pybullet_run):
    out, frames = exported
    faces = sum(len(o.faces) for o in pybullet_run.meshes.objects)
    files = sorted((out / "ply" / "truth").glob("*.ply"))
    assert [f.name for f in files] == [f"frame_{t:04d}.ply" for t in range(4)]
    for t, path in enumerate(files):
        mesh = meshio.read(path)
        assert mesh.cells_dict["triangle"].shape == (faces, 3)
        np.testing.assert_allclose(mesh.points, scene_vertices(frames, t), atol=1e-6)
    future = meshio.read(out / "ply" / "future_00" / "frame_0000.ply")
    np.testing.assert_allclose(future.points, scene_vertices(frames, 3), atol=1e-6)


def test_obj_frames_load_in_trimesh(exported):
    out, frames = exported
    mesh = trimesh.load(out / "obj" / "truth" / "frame_0002.obj", process=False, force="mesh")
    np.testing.assert_allclose(mesh.vertices, scene_vertices(frames, 2), atol=1e-6)


def test_vtk_series_has_a_time_per_frame(exported, pybullet_run):
    out, frames = exported
    collection = ET.parse(out / "vtk" / "truth.pvd").getroot()
    datasets = collection.findall("./Collection/DataSet")
    times = [float(d.get("timestep")) for d in datasets]
    np.testing.assert_allclose(times, np.arange(4) * pybullet_run.meshes.dt, rtol=1e-8)
    for t, dataset in enumerate(datasets):
        mesh = meshio.read(out / "vtk" / dataset.get("file"))
        np.testing.assert_allclose(mesh.points, scene_vertices(frames, t), atol=1e-9)
        objects = mesh.cell_data["object"][0]
        assert sorted(np.unique(objects)) == [0, 1, 2]
        assert (objects == 1).sum() == len(pybullet_run.meshes.objects[1].faces)


def test_formats_are_checked():
    assert parse_formats("glb, PLY,vtk,glb") == ("glb", "ply", "vtk")
    for bad in ("", "stl", "glb,fbx"):
        with pytest.raises(ValueError, match="choose from glb, ply, obj, vtk"):
            parse_formats(bad)
