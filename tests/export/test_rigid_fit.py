"""A rigid object's mesh follows pybullet's body: the best rigid fit of its leaves, applied to
the scene's mesh, is the body's pose applied to the mesh, within 1 mm at every step."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hrn_pyg.data.scene_file import posed_mesh
from hrn_pyg.export import fit_rigid_frames, rig

TOLERANCE = 1e-3  # m


def pybullet_mesh(run, index: int) -> np.ndarray:
    """The posed mesh moved by pybullet's pose of the body in every step ``[T, V, 3]``."""
    local = posed_mesh(run.spec.objects[index], run.params["objects"][index]).vertices
    return np.einsum("tij,vj->tvi", run.rotations[index], local) + run.positions[index][:, None]


def test_rigid_meshes_match_pybullets_poses(pybullet_run):
    frames = rig(pybullet_run.meshes).animate(pybullet_run.leaves)
    for index in (1, 2):
        expected = pybullet_mesh(pybullet_run, index)
        assert np.ptp(pybullet_run.positions[index], axis=0).max() > 0.02 or index == 1  # the duck moves
        error = np.linalg.norm(frames[index].vertices - expected, axis=-1).max()
        assert error < TOLERANCE, f"object {index}: {error * 1e3:.3f} mm"
    spin = Rotation.from_matrix(pybullet_run.rotations[2][-1] @ pybullet_run.rotations[2][0].T).magnitude()
    assert spin > 0.2  # the thrown duck turned, so the rotation is tested, not only the translation


def test_fit_recovers_a_known_rigid_motion():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(30, 3))
    turns = Rotation.random(5, random_state=1).as_matrix()
    shifts = rng.normal(size=(5, 3))
    frames = np.einsum("tij,nj->tni", turns, rest) + shifts[:, None]
    pose = fit_rigid_frames(rest, frames)
    # the fit's covariance carries a regulariser of 1e-6 of its scale (hrn_pyg.nn.rigid.COVARIANCE_EPS)
    np.testing.assert_allclose(pose.rotation, turns, atol=1e-5)
    vertices = rng.normal(size=(7, 3))
    np.testing.assert_allclose(pose.apply(vertices), np.einsum("tij,vj->tvi", turns, vertices) + shifts[:, None],
                               atol=1e-5)
