"""Skinning fixed at rest: the rest leaves give back the rest mesh, and leaves moved by an affine
map move every vertex of the skinned soft mesh by the same map."""

from __future__ import annotations

import numpy as np
import pytest

from hrn_pyg.data.voxelise import grid_sheet
from hrn_pyg.export import rig, skin_weights


def test_rest_leaves_give_the_rest_mesh(pybullet_run):
    soft = pybullet_run.meshes.objects[0]
    frames = rig(pybullet_run.meshes).animate(pybullet_run.meshes.rest_leaves[None])
    np.testing.assert_allclose(frames[0].vertices[0], soft.vertices, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_an_affine_map_of_the_leaves_moves_the_mesh_by_the_same_map(pybullet_run, seed):
    rng = np.random.default_rng(seed)
    matrix = np.eye(3) + 0.4 * rng.normal(size=(3, 3))  # stretch, shear and turn
    shift = rng.normal(size=3)
    meshes = pybullet_run.meshes
    frames = rig(meshes).animate((meshes.rest_leaves @ matrix.T + shift)[None])
    soft = meshes.objects[0]
    assert soft.material_name == "soft" and len(soft.vertices) > 1000
    np.testing.assert_allclose(frames[0].vertices[0], soft.vertices @ matrix.T + shift, atol=1e-9)


def test_weights_sum_to_one_and_a_vertex_on_a_leaf_follows_it():
    vertices, _ = grid_sheet(0.2, 0.05)  # a cloth: its vertices are its leaves (a flat neighbourhood)
    weights = skin_weights(vertices, vertices, 0.05)
    np.testing.assert_allclose(weights.weight.sum(axis=1), 1.0, atol=1e-12)
    moved = vertices + np.random.default_rng(0).normal(scale=0.01, size=vertices.shape)
    np.testing.assert_allclose(weights.apply(moved), moved, atol=1e-6)


def test_an_object_without_leaves_is_an_error():
    with pytest.raises(ValueError, match="without leaves"):
        skin_weights(np.zeros((3, 3)), np.zeros((0, 3)), 0.05)
