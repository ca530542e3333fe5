"""pybullet scenes: shapes, finiteness, physics sanity, determinism, actions, bad input."""

import json

import numpy as np
import pytest

from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.io import load_episode, save_episode
from hrn_pyg.data.scene_file import SCENES, builtin_scene, make_scene

STEPS = 3


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_scene_shapes_and_finite(scene):
    ep = simulate_episode(scene, seed=0, steps=STEPS)
    pos, forces = ep["positions"], ep["forces"]
    n_leaves, n_obj = pos.shape[1], len(ep["object_material"])
    assert pos.shape == (STEPS + 1, n_leaves, 3) and pos.dtype == np.float32
    assert forces.shape == (STEPS, n_leaves, 3) and forces.dtype == np.float32
    assert ep["leaf_mass"].shape == (n_leaves,) and np.all(ep["leaf_mass"] > 0)
    assert ep["leaf_object"].shape == (n_leaves,)
    assert set(np.unique(ep["leaf_object"])) == set(range(n_obj))
    assert ep["object_stiffness"].shape == (n_obj,)
    assert np.all((ep["object_stiffness"] >= 0) & (ep["object_stiffness"] <= 1))
    assert np.all(np.isfinite(pos)) and np.all(np.isfinite(forces))
    parent = ep["hierarchy_parent"]
    assert len(parent) > n_leaves and np.all(parent[:n_leaves] >= n_leaves)
    assert json.loads(str(ep["params"]))["config"]["steps"] == STEPS
    assert str(ep["scene"]) == scene and int(ep["seed"]) == 0
    assert float(ep["dt"]) == pytest.approx(8 / 240)


def test_rigid_leaves_keep_their_distances():
    ep = simulate_episode("cube_collision", seed=1, steps=12)
    x = ep["positions"].astype(np.float64)
    cube = ep["leaf_object"] == 0
    d0 = np.linalg.norm(x[0, cube][:, None] - x[0, cube][None], axis=-1)
    d1 = np.linalg.norm(x[-1, cube][:, None] - x[-1, cube][None], axis=-1)
    assert np.abs(d1 - d0).max() < 1e-5
    assert np.abs(x[-1] - x[0]).max() > 0.01  # but the impulse moved them


def test_soft_cube_deforms_on_landing():
    spec = builtin_scene("soft_bounce", kick_step_range=(2, 2), up_speed_range=(2.5, 2.5))
    ep = simulate_episode(spec, seed=0, steps=30)
    x = ep["positions"].astype(np.float64)
    rest = np.linalg.norm(x[0][:, None] - x[0][None], axis=-1)
    change = [np.abs(np.linalg.norm(xt[:, None] - xt[None], axis=-1) - rest).max() for xt in x]
    assert max(change) > 0.02  # pairwise distances change: it deforms
    assert x[:, :, 2].mean(axis=1).max() > x[0, :, 2].mean() + 0.1  # it was lifted
    kicked = np.abs(ep["forces"]).sum(axis=(1, 2)) > 0
    assert kicked.tolist() == [t == 2 for t in range(30)]


def test_seeded_generation_is_byte_identical(tmp_path):
    a = simulate_episode("soft_bounce", seed=3, steps=STEPS)
    b = simulate_episode("soft_bounce", seed=3, steps=STEPS)
    c = simulate_episode("soft_bounce", seed=4, steps=STEPS)
    save_episode(tmp_path / "a.npz", a)
    save_episode(tmp_path / "b.npz", b)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert str(a["params"]) != str(c["params"])
    loaded = load_episode(tmp_path / "a.npz")
    for key in a:
        np.testing.assert_array_equal(loaded[key], a[key])


def test_cube_push_cubes_pass_through_each_other():
    scene = make_scene("cube_push", seed=0)
    try:
        scene.reset()
        # put cube 1 onto cube 0 by pushing it there; they must not collide (stay on the ground)
        x = scene.leaf_positions()
        obj = scene.leaf_object
        centre0, centre1 = x[obj == 0].mean(axis=0), x[obj == 1].mean(axis=0)
        direction = (centre0 - centre1) * np.array([1, 1, 0])
        action = np.zeros((2, 3))
        action[1] = 30 * direction / np.linalg.norm(direction)
        for _ in range(10):
            x = scene.step(action)
        assert x[:, 2].max() < 0.12  # nobody got lifted onto the other cube
        assert np.allclose(scene.last_forces[obj == 1].sum(axis=0), action[1], atol=1e-6)
        assert np.allclose(scene.last_forces[obj == 0], 0)
    finally:
        scene.close()


def test_replay_is_deterministic():
    actions = np.random.default_rng(0).normal(size=(4, 4, 3)) * 5
    actions[:, :3] = 0  # tower: only the ball is pushed here
    runs = []
    for _ in range(2):
        scene = make_scene("tower", seed=2)
        scene.reset()
        runs.append(np.stack([scene.step(a) for a in actions]))
        scene.close()
    np.testing.assert_array_equal(runs[0], runs[1])


def test_bad_input():
    with pytest.raises(ValueError, match="scene"):
        simulate_episode("nope", seed=0)
    with pytest.raises(ValueError, match="pitch"):
        builtin_scene("cube_collision", pitch=0.0)
    with pytest.raises(ValueError, match="unknown setting 'cube_sides'; the settings are .*cube_side"):
        builtin_scene("cube_collision", cube_sides=0.2)
    with pytest.raises(ValueError, match=r"draw.masses: .*mass_range.*low 2.0 > high 1.0"):
        make_scene(builtin_scene("cube_collision", mass_range=(2.0, 1.0)), 0)
    with pytest.raises(ValueError, match="steps"):
        simulate_episode("cube_collision", seed=0, steps=0)
    scene = make_scene("wedge", seed=0)
    scene.reset()
    try:
        with pytest.raises(ValueError, match="static"):
            scene.step(np.array([[0, 0, 0], [1.0, 0, 0]]))
        with pytest.raises(ValueError, match="action_forces"):
            scene.step(np.zeros((3, 3)))
    finally:
        scene.close()


def _max_leaf_speed(ep, steps):
    """Per object, the largest leaf speed (m/s) over the episode's last ``steps`` steps."""
    x = ep["positions"].astype(np.float64)[-(steps + 1):]
    speed = np.linalg.norm(np.diff(x, axis=0), axis=-1) / float(ep["dt"])
    obj = ep["leaf_object"]
    return np.array([speed[:, obj == o].max() for o in range(obj.max() + 1)])


def test_long_episode_defaults():
    steps = {name: builtin_scene(name).config.steps for name in SCENES}
    assert steps == {"soft_bounce": 160, "cube_collision": 160, "wedge": 140,
                     "multi_material": 150, "cube_push": 150, "tower": 150}
    for name in ("cube_collision", "cube_push", "tower"):  # pushes stop well before the end
        spec = builtin_scene(name)
        assert spec.settings["last_push_step_range"][1] <= spec.config.steps - 70


@pytest.mark.parametrize("scene", ["cube_collision", "wedge", "cube_push", "tower"])
def test_rigid_scenes_end_at_rest(scene):
    ep = simulate_episode(scene, seed=0)
    assert len(ep["forces"]) == builtin_scene(scene).config.steps
    assert np.abs(ep["forces"][-40:]).max() == 0
    assert _max_leaf_speed(ep, 40).max() < 0.01
    assert _max_leaf_speed(ep, len(ep["forces"])).max() > 0.5  # but things did move


def test_cube_collision_pushes_stop_after_last_push_step():
    spec = builtin_scene("cube_collision", steps=30, first_push_range=(2, 2), push_every_range=(5, 5),
                         last_push_step_range=(12, 12))
    ep = simulate_episode(spec, seed=0)
    pushed = np.nonzero(np.abs(ep["forces"]).sum(axis=(1, 2)) > 0)[0].tolist()
    assert pushed == [2, 7, 12]
    assert json.loads(str(ep["params"]))["params"]["last_push_step"] == 12


def test_random_forces_alternate_pushes_and_pauses():
    spec = builtin_scene("cube_push", steps=16, force_range=(5.0, 10.0), hold_range=(2, 2),
                         pause_range=(3, 3), last_push_step_range=(10, 10))
    ep = simulate_episode(spec, seed=0)
    pushed = np.nonzero(np.abs(ep["forces"]).sum(axis=(1, 2)) > 0)[0].tolist()
    assert pushed == [0, 1, 5, 6, 10]


def test_schedule_does_not_change_the_initial_state():
    """The RL pools start from make_scene(name, seed): the push schedule is drawn last."""
    for name in ("cube_push", "tower"):
        a = make_scene(name, seed=3)
        b = make_scene(builtin_scene(name, last_push_step_range=(5, 9)), seed=3)
        assert a.params["last_push_step"] != b.params["last_push_step"]
        for params in (a.params, b.params):
            params.pop("last_push_step")
            params.pop("pushes")
        assert a.params == b.params


def test_ground_rolling_friction_stops_a_rolling_ball():
    rolls = builtin_scene("wedge", rolling_friction=0.0)
    assert _max_leaf_speed(simulate_episode(rolls, seed=0), 40).max() > 0.5
    with pytest.raises(ValueError, match="rolling_friction"):
        builtin_scene("wedge", rolling_friction=-0.1)


def test_tower_stack_offsets_leave_straight_stacks_alone_and_stand_still_unpushed():
    """``stack_offset_range`` moves each cube off the stack's axis by at most the range; the
    default (none) gives the same episode as before the option existed (zero offsets, nothing
    else drawn); an unpushed off-centre stack stands: pybullet's cubes move under 5 mm in 40 steps."""
    straight = simulate_episode("tower", seed=4, steps=2)
    assert make_scene("tower", seed=4).params["stack_offsets"] == [[0.0, 0.0]] * 3
    spec = builtin_scene("tower", stack_offset_range=(-0.015, 0.015), force_range=(0.0, 0.0))
    offset = simulate_episode(spec, seed=4, steps=40)
    cubes = straight["leaf_object"] < 3
    start = offset["positions"][0]
    for cube in range(3):
        rows = offset["leaf_object"] == cube
        shift = start[rows, :2].mean(axis=0) - straight["positions"][0][rows, :2].mean(axis=0)
        assert 0 < np.abs(shift).max() <= 0.015 + 1e-4
    assert np.abs(offset["positions"][-1][cubes] - start[cubes]).max() < 0.005
    with pytest.raises(ValueError, match="stack_offset_range"):
        make_scene(builtin_scene("tower", stack_offset_range=(0.01, -0.01)), 0)
