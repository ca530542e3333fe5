"""The rest meshes and leaves rebuilt from a scene's draws are where pybullet put them."""

from __future__ import annotations

import numpy as np
import pytest

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.kinds import RIGID, SOFT
from hrn_pyg.data.scene_file import SCENES, posed_mesh
from hrn_pyg.export import SceneMeshes, rig
from hrn_pyg.export.scene_meshes import rotation_matrix, seed_meshes


def test_rest_leaves_are_pybullets_first_positions(pybullet_run):
    meshes = pybullet_run.meshes
    assert [o.material for o in meshes.objects] == [SOFT, RIGID, RIGID]
    np.testing.assert_allclose(meshes.rest_leaves, pybullet_run.leaves[0], atol=1e-6)
    assert meshes.pitch == 0.04 and abs(meshes.dt - 8 / 240) < 1e-12


def test_a_rigid_rest_mesh_is_the_body_pose_applied_to_the_posed_mesh(pybullet_run):
    for index in (1, 2):
        local = posed_mesh(pybullet_run.spec.objects[index], pybullet_run.params["objects"][index]).vertices
        expected = local @ pybullet_run.rotations[index][0].T + pybullet_run.positions[index][0]
        np.testing.assert_allclose(pybullet_run.meshes.objects[index].vertices, expected, atol=1e-9)


def test_the_arrays_round_trip(pybullet_run):
    meshes = pybullet_run.meshes
    back = SceneMeshes.from_arrays(meshes.to_arrays())
    assert back.pitch == meshes.pitch and back.dt == meshes.dt
    for a, b in zip(meshes.objects, back.objects):
        assert (a.index, a.material, a.leaf_start) == (b.index, b.material, b.leaf_start)
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.leaves, b.leaves)


def test_seed_meshes_draw_what_the_episode_drew(pybullet_run):
    again = seed_meshes(pybullet_run.spec, 0)
    np.testing.assert_array_equal(again.rest_leaves, pybullet_run.meshes.rest_leaves)


def test_rotation_matrix_of_a_quaternion():
    q = np.array([0.3, 0.2, 0.1, 0.9])
    q /= np.linalg.norm(q)
    r = rotation_matrix(q)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    half = np.arccos(q[3])
    axis = q[:3] / np.sin(half)
    np.testing.assert_allclose(r @ axis, axis, atol=1e-12)  # the axis stays
    assert np.isclose(np.trace(r), 1 + 2 * np.cos(2 * half))  # the angle is twice the half angle


@pytest.mark.parametrize("name", SCENES)
def test_every_builtin_scene_rebuilds_where_pybullet_starts(name):
    """Cloth sheets, static objects, the wedge and soft cubes too."""
    episode = simulate_episode(name, 1, steps=1)
    meshes = seed_meshes(name, 1, 1)
    np.testing.assert_array_equal(meshes.leaf_object, episode["leaf_object"])
    np.testing.assert_allclose(meshes.rest_leaves, episode["positions"][0], atol=1e-6)
    frames = rig(meshes).animate(episode["positions"])
    assert all(np.isfinite(f.vertices).all() and f.vertices.shape[1] == len(f.object.vertices) for f in frames)
