"""What one seed draws for a scene file's objects and [draw] table (hrn_pyg.data.scene_file):
fixed values take nothing from the seed's stream, a list of meshes is drawn from (one mesh is
not), expressions read the drawn names and the stream, and a bad drawn value names its object."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hrn_pyg.data.scene_file import drawn_mesh, parse_scene


def spec_of(text: str):
    return parse_scene(tomllib.loads(text), name="scene")


ONE_BOX = """
steps = 10
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
mass = 1.5
position = [0.0, 0.0, 0.1]
velocity = [0.0, 0.0, 0.0]
yaw = { min = 0, max = 360 }
"""


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_fixed_values_take_nothing_from_the_stream(seed):
    """The one ranged field gets the stream's first number: fixed and default fields drew none."""
    (obj,) = spec_of(ONE_BOX).draw(np.random.default_rng(seed))["objects"]
    assert obj["yaw"] == pytest.approx(np.random.default_rng(seed).uniform(0.0, 360.0), abs=0, rel=0)
    assert "mesh" not in obj  # one mesh: nothing drawn for it


@pytest.mark.parametrize("meshes", [["box", "sphere"], ["box", "sphere", "cylinder"]])
def test_a_list_of_meshes_is_drawn_from_and_the_draw_picks_the_mesh(meshes):
    text = ONE_BOX.replace('mesh = "box"', "mesh = [" + ", ".join(f'"{m}"' for m in meshes) + "]")
    spec = spec_of(text)
    (obj,) = spec.objects
    seen = set()
    for seed in range(24):
        (drawn,) = spec.draw(np.random.default_rng(seed))["objects"]
        assert 0 <= drawn["mesh"] < len(meshes)
        assert drawn_mesh(obj, drawn) == meshes[drawn["mesh"]]
        seen.add(drawn_mesh(obj, drawn))
    assert seen == set(meshes)


def test_draws_read_earlier_draws_and_objects_read_the_draws():
    text = """
steps = 10
[draw]
gap = "uniform(0.3, 0.6)"
twice = "gap * 2"
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
position = "[gap, 0, 0.1]"
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
position = "[-twice, 0, 0.1]"
"""
    for seed in range(3):
        drawn = spec_of(text).draw(np.random.default_rng(seed))
        assert 0.3 <= drawn["gap"] <= 0.6 and drawn["twice"] == 2 * drawn["gap"]
        assert drawn["objects"][0]["position"] == [drawn["gap"], 0.0, 0.1]
        assert drawn["objects"][1]["position"] == [-drawn["twice"], 0.0, 0.1]


def test_push_expressions_draw_from_the_seeds_stream():
    text = ONE_BOX.replace('material = "rigid"', 'material = "soft"\nstiffness = 0.5') + """
[[pushes]]
object = 0
steps = "[integer(2, 5), 8]"
random = { force = "[0, uniform(6, 8)]", hold = [2, 3], pause = [0, 1] }
"""
    spec = spec_of(text)
    starts, highs = set(), set()
    for seed in range(12):
        (push,) = spec.draw(np.random.default_rng(seed))["pushes"]
        assert 2 <= push["steps"][0] <= 5 and push["steps"][1] == 8
        assert push["random"]["force"][0] == 0.0 and 6.0 <= push["random"]["force"][1] <= 8.0
        starts.add(push["steps"][0])
        highs.add(push["random"]["force"][1])
    assert len(starts) > 1 and len(highs) == 12


def test_a_bad_drawn_object_value_names_its_object_and_key():
    text = ONE_BOX + """
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
mass = "1 - 2"
position = [0.5, 0.0, 0.1]
"""
    with pytest.raises(ValueError, match=r"^scene: objects\[1\]\.mass: must be > 0, got -1"):
        spec_of(text).draw(np.random.default_rng(0))


def test_a_scene_that_draws_nothing_is_named_and_generate_warns(tmp_path, capsys):
    """A scene file with only fixed values makes one episode for every seed: generate says so in
    one line; any range, draw, expression of uniform() or choice of meshes is a draw."""
    from hrn_pyg.cli import main
    from hrn_pyg.data.scene_file import read_scene_file

    fixed = tmp_path / "fixed.toml"
    fixed.write_text('steps = 4\npitch = 0.05\n\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\nsize = 0.2\n'
                     'position = [0.0, 0.0, 0.3]\n')
    assert not read_scene_file(fixed).draws_anything
    for change in ('yaw = { min = 0, max = 90 }', 'velocity = "[uniform(-1, 1), 0, 0]"'):
        drawn = tmp_path / "drawn.toml"
        drawn.write_text(fixed.read_text() + change + "\n")
        assert read_scene_file(drawn).draws_anything, change
    chosen = tmp_path / "chosen.toml"
    chosen.write_text(fixed.read_text().replace('mesh = "box"', 'mesh = ["box", "sphere"]'))
    assert read_scene_file(chosen).draws_anything
    assert main(["generate", "--scene-file", str(fixed), "--episodes", "2", "--out", str(tmp_path / "d"),
                 "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "draws nothing at random" in err and "its 2 episodes will all be the same" in err
