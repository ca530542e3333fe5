"""A scene file's ``up``: a mesh file modelled with another up axis is turned so that axis is z."""

from __future__ import annotations

import numpy as np
import pytest

from hrn_pyg.cli import main
from hrn_pyg.data.scene_file import parse_scene, posed_mesh

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def object_table(**extra) -> dict:
    return {"steps": 5, "pitch": 0.04, "objects": [{"mesh": "pybullet_data:duck.obj", "material": "rigid",
                                                    "scale": 0.1, "position": [0, 0, 0.3], **extra}]}


def posed(**extra):
    spec = parse_scene(object_table(**extra))
    return posed_mesh(spec.objects[0], spec.draw(np.random.default_rng(0))["objects"][0])


def test_up_y_turns_the_mesh_y_axis_to_z():
    z_up, y_up = posed(), posed(up="y")
    # the quarter turn about x takes (x, y, z) to (x, -z, y): the extents swap, the box stays centred
    np.testing.assert_allclose(y_up.extents, z_up.extents[[0, 2, 1]], atol=1e-12)
    np.testing.assert_allclose(y_up.vertices, z_up.vertices @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]).T,
                               atol=1e-12)
    np.testing.assert_allclose(y_up.bounds.mean(axis=0), z_up.bounds.mean(axis=0)[[0, 2, 1]] * [1, -1, 1],
                               atol=1e-12)


def test_up_x_turns_the_mesh_x_axis_to_z():
    np.testing.assert_allclose(posed(up="x").extents, posed().extents[[2, 1, 0]], atol=1e-12)
    assert parse_scene(object_table()).objects[0].up == "z"


def test_an_unknown_up_axis_is_one_line(tmp_path, capsys):
    scene = tmp_path / "bad.toml"
    scene.write_text('steps = 5\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\nsize = 0.1\n'
                     'position = [0, 0, 0.1]\nup = "w"\n')
    assert main(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "objects[0].up" in err and "x, y, z" in err, err
