"""The ``.glb`` read back by independent readers: pygltflib (the animation, evaluated here from
the file's own accessors) and trimesh's loader (the first frame's geometry)."""

from __future__ import annotations

import numpy as np
import pygltflib
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from hrn_pyg.export import GLB_NAME, export_trajectories, rig
from test_rigid_fit import TOLERANCE, pybullet_mesh

COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
DTYPES = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_INT: np.uint32}


def z_to_y_up(points: np.ndarray) -> np.ndarray:
    """glTF is y-up: the package's (x, y, z) is glTF's (x, z, -y)."""
    return np.stack([points[..., 0], points[..., 2], -points[..., 1]], axis=-1)


class Reader:
    """A .glb's accessors and animation channels, through pygltflib."""

    def __init__(self, path) -> None:
        self.gltf = pygltflib.GLTF2().load(str(path))
        self.blob = self.gltf.binary_blob()

    def accessor(self, index: int) -> np.ndarray:
        a = self.gltf.accessors[index]
        view = self.gltf.bufferViews[a.bufferView]
        n = COMPONENTS[a.type]
        return np.frombuffer(self.blob, DTYPES[a.componentType], count=a.count * n,
                             offset=view.byteOffset + (a.byteOffset or 0)).reshape(a.count, n)

    def node(self, name: str) -> int:
        return next(i for i, n in enumerate(self.gltf.nodes) if n.name == name)

    def channel(self, node: int, path: str) -> np.ndarray:
        animation = self.gltf.animations[0]
        channel = next(c for c in animation.channels if c.target.node == node and c.target.path == path)
        return self.accessor(animation.samplers[channel.sampler].output)

    def root_rotation(self) -> np.ndarray:
        root = self.gltf.nodes[self.gltf.scenes[0].nodes[0]]
        return Rotation.from_quat(root.rotation).as_matrix()


@pytest.fixture(scope="module")
def glb(pybullet_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("glb")
    leaves = pybullet_run.leaves
    future = leaves + np.array([0.0, 0.0, 0.01])  # a second trajectory, 1 cm higher
    export_trajectories(pybullet_run.meshes, {"truth": leaves, "future_00": future}, out, ("glb",))
    return Reader(out / GLB_NAME)


def test_a_rigid_node_follows_pybullets_pose(glb, pybullet_run):
    root = glb.root_rotation()
    steps = len(pybullet_run.leaves)
    assert len(glb.accessor(glb.gltf.animations[0].samplers[0].input)) == steps
    for index in (1, 2):
        node = glb.node(f"truth object {index}")
        local = glb.accessor(glb.gltf.meshes[glb.gltf.nodes[node].mesh].primitives[0].attributes.POSITION)
        translation, rotation = glb.channel(node, "translation"), glb.channel(node, "rotation")
        turns = Rotation.from_quat(rotation).as_matrix()
        world = (np.einsum("tij,vj->tvi", turns, local) + translation[:, None]) @ root.T  # y-up
        error = np.linalg.norm(world - z_to_y_up(pybullet_mesh(pybullet_run, index)), axis=-1).max()
        assert error < TOLERANCE, f"object {index}: {error * 1e3:.3f} mm"


def test_a_soft_mesh_is_morph_targets_one_per_frame(glb, pybullet_run):
    frames = rig(pybullet_run.meshes).animate(pybullet_run.leaves)
    node = glb.node("truth object 0")
    primitive = glb.gltf.meshes[glb.gltf.nodes[node].mesh].primitives[0]
    base = glb.accessor(primitive.attributes.POSITION)
    steps = len(pybullet_run.leaves)
    assert len(primitive.targets) == steps - 1
    weights = glb.channel(node, "weights").reshape(steps, steps - 1)
    root = glb.root_rotation()
    for t in (0, steps // 2, steps - 1):
        shown = base + sum(w * glb.accessor(target["POSITION"]) for w, target in zip(weights[t], primitive.targets))
        np.testing.assert_allclose(shown @ root.T, z_to_y_up(frames[0].vertices[t]), atol=1e-5)


def test_every_position_accessor_has_bounds_and_the_futures_are_translucent(glb):
    for mesh in glb.gltf.meshes:
        for primitive in mesh.primitives:
            for index in [primitive.attributes.POSITION, *(t["POSITION"] for t in primitive.targets or [])]:
                a = glb.gltf.accessors[index]
                data = glb.accessor(index)
                np.testing.assert_allclose(a.min, data.min(axis=0), atol=1e-6)
                np.testing.assert_allclose(a.max, data.max(axis=0), atol=1e-6)
    alpha = {m.name: m.pbrMetallicRoughness.baseColorFactor[3] for m in glb.gltf.materials}
    assert alpha["truth object 2"] == 1.0 and alpha["future_00 object 2"] < 1.0


def test_trimesh_loads_the_first_frame(pybullet_run, tmp_path):
    out = tmp_path / "t"
    export_trajectories(pybullet_run.meshes, {"truth": pybullet_run.leaves}, out, ("glb",))
    scene = trimesh.load(out / GLB_NAME)
    assert len(scene.geometry) == 3
    loaded = np.sort(z_to_y_up(np.concatenate([o.vertices for o in pybullet_run.meshes.objects])), axis=0)
    dumped = np.concatenate([g.vertices for g in scene.dump()])
    assert len(dumped) == len(loaded)
    np.testing.assert_allclose(np.sort(dumped, axis=0), loaded, atol=1e-5)
