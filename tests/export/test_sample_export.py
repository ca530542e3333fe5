"""``hrn-pyg sample --scene-file S --model shapes --k 8 --export glb,ply,vtk`` end to end, on a
pybullet_data duck: the files open in independent readers with the scene's meshes in every
frame of the truth and of every future, and samples.npz carries the scene."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
import pygltflib
import pytest
import trimesh

from hrn_pyg.cli import main
from hrn_pyg.export import GLB_NAME, SceneMeshes, export_npz

SCENE = Path(__file__).with_name("scenes") / "soft_duck.toml"
K, HORIZON = 8, 2
NAMES = ["truth"] + [f"future_{k:02d}" for k in range(K)]

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sample")
    assert main(["sample", "--scene-file", str(SCENE), "--model", "shapes", "--k", str(K), "--horizon", str(HORIZON),
                 "--export", "glb,ply,vtk", "--frames", "0,2", "--size", "640x240", "--camera", "30,-45",
                 "--out", str(out), "--no-progress"]) == 0
    return out


def test_samples_npz_carries_the_scene(result):
    with np.load(result / "samples.npz") as data:
        assert data["samples"].shape[:2] == (K, HORIZON) and data["truth"].shape[0] == HORIZON + 1
        meshes = SceneMeshes.from_arrays(data)
        np.testing.assert_array_equal(data["leaf_object"], meshes.leaf_object)
        assert data["object_material"].tolist() == [1, 0]  # soft duck, rigid box
        assert float(data["pitch"]) == 0.04 and abs(float(data["dt"]) - 8 / 240) < 1e-12
        assert len(data["leaf_object"]) == data["truth"].shape[1]


def test_the_glb_holds_every_trajectory(result):
    gltf = pygltflib.GLTF2().load(str(result / GLB_NAME))
    names = {n.name for n in gltf.nodes}
    assert set(NAMES) <= names
    assert {f"{name} object {i}" for name in NAMES for i in (0, 1)} <= names
    animation = gltf.animations[0]
    assert gltf.accessors[animation.samplers[0].input].count == HORIZON + 1
    duck = next(m for m in gltf.meshes if m.name == "future_03 object 0")
    assert len(duck.primitives[0].targets) == HORIZON
    scene = trimesh.load(result / GLB_NAME)
    assert len(scene.geometry) == 2 * len(NAMES)


def test_ply_and_vtk_have_the_meshes_in_every_frame(result):
    with np.load(result / "samples.npz") as data:
        faces = len(data["mesh_faces"])
    for name in NAMES:
        plys = sorted((result / "ply" / name).glob("frame_*.ply"))
        assert len(plys) == HORIZON + 1
        for path in plys:
            mesh = meshio.read(path)
            assert mesh.cells_dict["triangle"].shape == (faces, 3) and np.isfinite(mesh.points).all()
        datasets = ET.parse(result / "vtk" / f"{name}.pvd").getroot().findall("./Collection/DataSet")
        assert len(datasets) == HORIZON + 1
        last = meshio.read(result / "vtk" / datasets[-1].get("file"))
        np.testing.assert_allclose(last.points, meshio.read(plys[-1]).points, atol=1e-5)
    first = [meshio.read(result / "ply" / name / "frame_0000.ply").points for name in NAMES]
    assert all(np.allclose(points, first[0], atol=1e-5) for points in first)  # every future starts at the truth
    last = [meshio.read(result / "ply" / name / f"frame_{HORIZON:04d}.ply").points for name in NAMES]
    assert max(np.abs(points - last[0]).max() for points in last) > 1e-4  # and they end apart


def test_export_npz_writes_the_same_files_from_the_result(result, tmp_path):
    export_npz(result / "samples.npz", tmp_path, ("ply",))
    again = meshio.read(tmp_path / "ply" / "future_05" / f"frame_{HORIZON:04d}.ply").points
    np.testing.assert_allclose(again, meshio.read(result / "ply" / "future_05" / f"frame_{HORIZON:04d}.ply").points,
                               atol=1e-6)


def test_the_picture_options_apply(result):
    from PIL import Image

    assert Image.open(result / "samples.png").size == (640, 240)
    gif = Image.open(result / "samples.gif")
    assert gif.size == (640, 240) and gif.n_frames == HORIZON + 1


def test_a_dataset_window_exports_the_meshes_its_episode_drew(tmp_path, capsys):
    """With ``--data`` the meshes come from the draws the episode file records (a size and a
    yaw drawn per seed), and data of another scene is one line, exit code 2."""
    scene = SCENE.with_name("duck_throw.toml")
    data = tmp_path / "data"
    assert main(["generate", "--scene-file", str(scene), "--episodes", "1", "--first-seed", "3", "--out", str(data),
                 "--no-progress"]) == 0
    out = tmp_path / "sample"
    assert main(["sample", "--scene-file", str(scene), "--model", "shapes", "--data", str(data), "--split", "all",
                 "--k", "2", "--horizon", "2", "--export", "ply", "--out", str(out), "--no-progress"]) == 0
    with np.load(out / "samples.npz") as result:
        meshes = SceneMeshes.from_arrays(result)
        truth = result["truth"]
    from hrn_pyg.data.io import load_episode
    from hrn_pyg.export import rig

    episode = load_episode(data / "episode_000003.npz")
    np.testing.assert_allclose(meshes.rest_leaves, episode["positions"][0], atol=1e-6)  # the recorded draws
    frames = rig(meshes).animate(truth)
    points = meshio.read(out / "ply" / "truth" / "frame_0001.ply").points
    np.testing.assert_allclose(points, np.concatenate([f.vertices[1] for f in frames]), atol=1e-5)
    assert main(["sample", "--scene-file", str(SCENE), "--model", "shapes", "--data", str(data), "--split", "all",
                 "--k", "2", "--horizon", "2", "--out", str(tmp_path / "other"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "was the data made from this scene?" in err, err


def test_a_deterministic_rollout_exports_too(tmp_path):
    """``--rate 0`` draws no dropout mask: every future is the model's one rollout."""
    out = tmp_path / "rollout"
    assert main(["sample", "--scene-file", str(SCENE), "--model", "shapes", "--k", "2", "--rate", "0",
                 "--horizon", str(HORIZON), "--export", "glb,ply", "--out", str(out), "--no-progress"]) == 0
    names = {n.name for n in pygltflib.GLTF2().load(str(out / GLB_NAME)).nodes}
    assert {"truth", "future_00", "future_01"} <= names
    last = f"frame_{HORIZON:04d}.ply"
    np.testing.assert_array_equal(meshio.read(out / "ply" / "future_00" / last).points,
                                  meshio.read(out / "ply" / "future_01" / last).points)


def test_one_trajectory_without_a_truth_is_a_rollout():
    from hrn_pyg.export import sample_trajectories

    leaves = np.zeros((1, 3, 4, 3))
    assert list(sample_trajectories(None, leaves)) == ["rollout"]
    assert list(sample_trajectories(leaves[0], leaves)) == ["truth", "future_00"]
