"""MuJoCo as the second engine: the same scene file and seed start the same leaves as in pybullet;
a rigid push slides as far as pybullet's, a soft cube lands and keeps its shape, a cloth lies
flat, pushes are recorded as the format says, datasets pass the validator, and what MuJoCo cannot
do is one line."""

import json
import re
import textwrap

import numpy as np
import pytest

pytest.importorskip("mujoco")

from hrn_pyg.cli import main  # noqa: E402
from hrn_pyg.data.dataset import EpisodeWindows  # noqa: E402
from hrn_pyg.data.episodes import simulate_episode  # noqa: E402
from hrn_pyg.data.io import load_episode  # noqa: E402
from hrn_pyg.data.kinds import CLOTH, RIGID, SOFT, STATIC  # noqa: E402
from hrn_pyg.data.mujoco_scene import LIMITS, MujocoScene  # noqa: E402
from hrn_pyg.data.scene_file import read_scene_file  # noqa: E402


def _scene(tmp_path, body: str, steps: int = 20, engine: str = "mujoco"):
    path = tmp_path / "scene.toml"
    path.write_text(f'steps = {steps}\nengine = "{engine}"\npitch = 0.05\n' + textwrap.dedent(body))
    return read_scene_file(path)


ALL_MATERIALS = """
    [[objects]]
    mesh = "box"
    material = "rigid"
    size = 0.1
    mass = 1.0
    position = [0.0, 0.0, 0.2]
    yaw = 30
    [[objects]]
    mesh = "box"
    material = "soft"
    size = 0.2
    mass = 1.0
    stiffness = 0.8
    position = [0.5, 0.0, 0.15]
    [[objects]]
    mesh = "sheet"
    material = "cloth"
    size = 0.3
    mass = 0.1
    position = [-0.5, 0.0, 0.1]
    [[objects]]
    mesh = "wedge"
    material = "static"
    extents = [0.3, 0.3, 0.15]
    position = [0.0, 0.6, 0.0]
"""


def test_a_seed_starts_the_same_leaves_in_both_engines(tmp_path):
    spec = _scene(tmp_path, ALL_MATERIALS)
    mj = spec.make_scene(3)
    assert isinstance(mj, MujocoScene)
    pb = spec.with_engine("pybullet").make_scene(3)
    try:
        np.testing.assert_allclose(mj.reset(), pb.reset(), atol=1e-6)
        assert mj.object_material.tolist() == pb.object_material.tolist() == [RIGID, SOFT, CLOTH, STATIC]
        np.testing.assert_array_equal(mj.leaf_mass, pb.leaf_mass)
        np.testing.assert_allclose(mj.object_stiffness, pb.object_stiffness)
    finally:
        mj.close()
        pb.close()


PUSHED_CUBE = """
    [[objects]]
    mesh = "box"
    material = "rigid"
    size = 0.1
    mass = 1.0
    position = [0.0, 0.0, 0.05]
    [[pushes]]
    object = 0
    steps = [2, 7]
    force = [5.0, 0.0, 0.0]
"""


def test_a_pushed_cube_slides_as_far_as_in_pybullet(tmp_path):
    """5 N for 6 steps against sliding friction 0.5 x 0.5 (pybullet's product, which the MuJoCo
    scene copies): the cube slides ~0.1 m in both engines."""
    spec = _scene(tmp_path, PUSHED_CUBE, steps=30)
    moved = {engine: simulate_episode(spec.with_engine(engine), 0)["positions"][[0, -1], :, 0].mean(axis=1)
             for engine in ("mujoco", "pybullet")}
    slide = {engine: float(x[1] - x[0]) for engine, x in moved.items()}
    assert slide["pybullet"] > 0.05
    assert slide["mujoco"] == pytest.approx(slide["pybullet"], rel=0.1)


def test_soft_and_cloth_land_and_keep_their_shape(tmp_path):
    episode = simulate_episode(_scene(tmp_path, ALL_MATERIALS, steps=30), 0)
    x, obj = episode["positions"], episode["leaf_object"]
    assert np.all(np.isfinite(x)) and x[..., 2].min() > -0.015  # the rigid cube sinks 0.9 cm on impact
    soft, cloth = x[:, obj == 1], x[:, obj == 2]
    height = soft[-1, :, 2].max() - soft[-1, :, 2].min()
    assert 0.17 < height < 0.21  # the 0.2 m cube stands (stiffness 0.8)
    assert cloth[-1, :, 2].max() < 0.02 and np.ptp(cloth[-1, :, 0]) == pytest.approx(0.3, abs=0.03)  # flat, unstretched
    assert np.ptp(x[:, obj == 3], axis=0).max() == 0.0  # the static wedge never moves


def test_a_velocity_push_on_a_soft_body_is_recorded_as_its_momentum(tmp_path):
    spec = _scene(tmp_path, """
        [[objects]]
        mesh = "box"
        material = "soft"
        size = 0.2
        mass = 1.5
        stiffness = 0.8
        position = [0.0, 0.0, 0.11]
        [[pushes]]
        object = 0
        steps = [4, 4]
        velocity = [0.0, 0.0, 2.0]
    """, steps=8)
    episode = simulate_episode(spec, 0)
    impulse = episode["forces"].sum(axis=1) * episode["dt"]  # [S, 3]: the momentum each step added
    np.testing.assert_allclose(impulse[4], [0.0, 0.0, 3.0], atol=0.05)  # mass 1.5 x 2 m/s
    assert np.abs(np.delete(impulse, 4, axis=0)).max() == 0.0
    centre = episode["positions"][:, :, 2].mean(axis=1)
    assert centre[6] - centre[5] > 0.04  # it flies up


def test_mujoco_datasets_pass_the_validator(tmp_path, capsys):
    path = tmp_path / "scene.toml"
    path.write_text('steps = 6\nengine = "mujoco"\npitch = 0.05\n' + textwrap.dedent(ALL_MATERIALS))
    assert main(["generate", "--scene-file", str(path), "--episodes", "2", "--out", str(tmp_path / "d"),
                 "--no-progress"]) == 0
    assert main(["check-data", str(tmp_path / "d")]) == 0
    assert "2 episodes" in capsys.readouterr().out


def test_what_mujoco_cannot_do_is_one_line(tmp_path):
    with pytest.raises(ValueError, match="engine: one of pybullet, mujoco, got 'ode'"):
        _scene(tmp_path, ALL_MATERIALS, engine="ode")
    spec = _scene(tmp_path, "pass_through = [[0, 1]]\n" + ALL_MATERIALS)
    with pytest.raises(ValueError, match="pass_through pairs are rigid or static bodies only"):
        spec.make_scene(0).reset()
    scene = _scene(tmp_path, ALL_MATERIALS).make_scene(0)
    scene.reset()
    with pytest.raises(ValueError, match=re.escape(LIMITS["nudge"])):
        scene.nudge(np.zeros((4, 3)))


def test_generate_engine_runs_a_pybullet_scene_in_mujoco(tmp_path):
    """``--engine mujoco`` on a scene file without an engine; meta.json says so, and the same
    folder refuses the other engine."""
    path = tmp_path / "scene.toml"
    path.write_text("steps = 8\npitch = 0.05\n" + textwrap.dedent(PUSHED_CUBE))
    out = tmp_path / "d"
    args = ["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(out), "--no-progress"]
    assert main([*args, "--engine", "mujoco"]) == 0
    assert json.loads((out / "meta.json").read_text())["engine"] == "mujoco"
    assert json.loads(str(load_episode(out / "episode_000000.npz")["params"]))["engine"] == "mujoco"
    assert main(args) == 2  # the pybullet default into the mujoco folder
    assert main([*args[:-2], str(tmp_path / "e"), "--no-progress", "--engine", "ode"]) == 2


def test_one_scene_in_both_engines_pools_into_one_training_set(tmp_path):
    """The same seeds of one scene file, once per engine, are different episodes: a dataset of
    both folders keeps every one (the same seeds twice in one engine stay an error)."""
    path = tmp_path / "scene.toml"
    path.write_text("steps = 8\npitch = 0.05\n" + textwrap.dedent(PUSHED_CUBE))
    for engine in ("pybullet", "mujoco"):
        assert main(["generate", "--scene-file", str(path), "--episodes", "2", "--out", str(tmp_path / engine),
                     "--engine", engine, "--no-progress"]) == 0
    windows = EpisodeWindows([tmp_path / "pybullet", tmp_path / "mujoco"], split="train")
    assert windows.seeds == [0, 0, 1, 1]
    with pytest.raises(ValueError, match="occur in more than one of the folders"):
        EpisodeWindows([tmp_path / "mujoco", tmp_path / "mujoco"], split="train")
