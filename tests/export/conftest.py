"""One short pybullet episode of a scene file with a soft and a rigid pybullet_data duck and a
box, run once for the export tests, with the body poses pybullet reports at every step."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.export import SceneMeshes, scene_meshes

SCENE = Path(__file__).with_name("scenes") / "duck_on_box.toml"


@dataclass(frozen=True)
class Run:
    spec: object
    params: dict
    leaves: np.ndarray  # [T, L, 3] as pybullet placed them
    positions: dict[int, np.ndarray]  # rigid object -> [T, 3] base positions
    rotations: dict[int, np.ndarray]  # rigid object -> [T, 3, 3]
    meshes: SceneMeshes


@pytest.fixture(scope="session")
def pybullet_run() -> Run:
    spec = read_scene_file(SCENE)
    scene = spec.make_scene(0)
    leaves, positions, rotations = [scene.reset()], {}, {}

    def record() -> None:
        for index, obj in enumerate(scene._objects):  # the test reads pybullet's own pose of each rigid body
            if obj.material == 0:
                pos, quat = p.getBasePositionAndOrientation(obj.body, physicsClientId=scene._client)
                positions.setdefault(index, []).append(np.asarray(pos))
                rotations.setdefault(index, []).append(np.asarray(p.getMatrixFromQuaternion(quat)).reshape(3, 3))

    record()
    for t in range(spec.config.steps):
        forces, spins = scene.scripted_action(t)
        leaves.append(scene.step(forces, spins))
        record()
    params = scene.params
    scene.close()
    return Run(spec, params, np.stack(leaves), {k: np.stack(v) for k, v in positions.items()},
               {k: np.stack(v) for k, v in rotations.items()}, scene_meshes(spec, params))
