"""The pushes of a scene file as one seed draws them (hrn_pyg.data.scene_file): ranges drawn from
the seed's stream, expressions over the drawn names, vectors of the right length, random
schedules with whole steps, and every bad value one line that names the push and its key."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from hrn_pyg.data.scene_file import parse_scene

TWO_BOXES = """
steps = 40
[draw]
start = "integer(3, 6)"
push_size = "uniform(1.0, 2.0)"
[[objects]]
mesh = "box"
material = "soft"
stiffness = 0.5
size = 0.2
position = [0.0, 0.0, 0.1]
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
position = [0.5, 0.0, 0.1]
"""


def pushes_of(text: str, seed: int = 0) -> list[dict]:
    spec = parse_scene(tomllib.loads(TWO_BOXES + text), name="boxes")
    return spec.draw(np.random.default_rng(seed))["pushes"]


def draws_of(text: str, seed: int = 0) -> dict:
    spec = parse_scene(tomllib.loads(TWO_BOXES + text), name="boxes")
    return spec.draw(np.random.default_rng(seed))


def test_ranges_are_drawn_per_seed_within_their_bounds():
    push = '[[pushes]]\nobject = 0\nsteps = [1, 4]\nforce = { min = [0.0, -2.0, 0.0], max = [3.0, 2.0, 0.5] }\n' \
           'spin = { min = [0.0, 0.0, -1.0], max = [0.0, 0.0, 1.0] }\n'
    forces = [pushes_of(push, seed)[0]["force"] for seed in range(6)]
    for force in forces:
        assert len(force) == 3 and 0.0 <= force[0] <= 3.0 and -2.0 <= force[1] <= 2.0 and 0.0 <= force[2] <= 0.5
    assert len({tuple(f) for f in forces}) == 6  # the seed's stream decides
    assert pushes_of(push, 4) == pushes_of(push, 4)
    spins = [pushes_of(push, seed)[0]["spin"] for seed in range(4)]
    assert all(s[0] == 0.0 and s[1] == 0.0 and -1.0 <= s[2] <= 1.0 for s in spins)
    assert len({s[2] for s in spins}) == 4


def test_expressions_read_the_drawn_names_and_give_floats_and_whole_steps():
    push = ('[[pushes]]\nobject = 0\nsteps = "[start, start + 5]"\nforce = "[push_size, 0, 0]"\n'
            'spin = "[0, 0, 2]"\nevery = "2"\n')
    for seed in range(3):
        drawn = draws_of(push, seed)
        (got,) = drawn["pushes"]
        assert got["steps"] == [drawn["start"], drawn["start"] + 5] and all(type(s) is int for s in got["steps"])
        assert got["force"] == [drawn["push_size"], 0.0, 0.0] and all(type(f) is float for f in got["force"])
        assert got["spin"] == [0.0, 0.0, 2.0] and got["every"] == 2 and type(got["every"]) is int


def test_a_velocity_towards_an_object_is_a_speed_and_otherwise_a_vector():
    (towards,) = pushes_of('[[pushes]]\nobject = 0\nsteps = [2, 2]\nvelocity = "0.5"\ntowards = 1\n')
    assert towards["velocity"] == 0.5 and type(towards["velocity"]) is float
    (plain,) = pushes_of('[[pushes]]\nobject = 0\nsteps = [2, 2]\nvelocity = "[0.5, 0, 0]"\n')
    assert plain["velocity"] == [0.5, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"boxes: pushes\[0\]\.velocity: '0.5' gives 0.5, expected 3 numbers"):
        pushes_of('[[pushes]]\nobject = 0\nsteps = [2, 2]\nvelocity = "0.5"\n')
    with pytest.raises(ValueError, match=r"boxes: pushes\[0\]\.velocity: '\[0.5, 0, 0\]' gives .*, expected a number"):
        pushes_of('[[pushes]]\nobject = 0\nsteps = [2, 2]\nvelocity = "[0.5, 0, 0]"\ntowards = 1\n')


def test_a_random_schedule_is_drawn_with_whole_steps_and_an_aim():
    push = ('[[pushes]]\nobject = 0\nsteps = [3, 30]\n'
            'random = { force = [0.0, 8.0], hold = [3, 8], pause = [0, 5], aim = "1", aim_noise = [-0.3, 0.3] }\n')
    (got,) = pushes_of(push)
    schedule = got["random"]
    assert schedule == {"force": [0.0, 8.0], "hold": [3, 8], "pause": [0, 5], "aim": 1, "aim_noise": [-0.3, 0.3]}
    assert all(type(v) is int for v in schedule["hold"] + schedule["pause"]) and type(schedule["aim"]) is int
    # the schedule's values may be expressions of the drawn names too
    (drawn,) = pushes_of(push.replace("force = [0.0, 8.0]", 'force = "[0, push_size * 4]"'), seed=1)
    names = draws_of(push, seed=1)
    assert drawn["random"]["force"] == [0.0, names["push_size"] * 4]


@pytest.mark.parametrize("push, message", [
    ('steps = "[1, 2, 3]"\nforce = [1.0, 0.0, 0.0]', r"pushes\[0\]\.steps: '\[1, 2, 3\]' gives .*, expected 2 numbers"),
    ('steps = [1, 2]\nforce = "[1, 0]"', r"pushes\[0\]\.force: '\[1, 0\]' gives .*, expected 3 numbers"),
    ('steps = [1, 2]\nforce = [1.0, 0.0, 0.0]\nspin = "[0, 1]"', r"pushes\[0\]\.spin: .* expected 3 numbers"),
    ('steps = [1, 2]\nforce = [1.0, 0.0, 0.0]\nevery = "[1, 2]"', r"pushes\[0\]\.every: .* expected a number"),
    ('steps = [1, 2]\nforce = "[nope, 0, 0]"', r"pushes\[0\]\.force"),
    ('steps = [1, 2]\nforce = "[1e308 * 10, 0, 0]"', r"pushes\[0\]\.force: .* not finite"),
    ('steps = [1, 30]\nrandom = { force = "[0, 8, 1]", hold = [3, 8], pause = [0, 5] }',
     r"pushes\[0\]\.random\.force: .* expected 2 numbers"),
    ('steps = [1, 30]\nrandom = { force = [0.0, 8.0], hold = [3, 8], pause = [0, 5], aim = "[1, 0]" }',
     r"pushes\[0\]\.random\.aim: .* expected a number"),
    ('steps = [1, 30]\nrandom = { force = [0.0, 8.0], hold = [3, 8], pause = [0, 5], aim = "2" }',
     r"pushes\[0\]\.random\.aim: an index into objects \(0\.\.1\)"),
])
def test_a_bad_drawn_push_value_is_one_line_naming_its_key(push, message):
    with pytest.raises(ValueError, match=f"^boxes: {message}"):
        pushes_of(f"[[pushes]]\nobject = 0\n{push}\n")


def test_the_second_push_is_named_by_its_own_index():
    good = "[[pushes]]\nobject = 0\nsteps = [1, 2]\nforce = [1.0, 0.0, 0.0]\n"
    with pytest.raises(ValueError, match=r"^boxes: pushes\[1\]\.force"):
        pushes_of(good + '[[pushes]]\nobject = 1\nsteps = [1, 2]\nforce = "[1, 0]"\n')


def test_a_scalar_field_drawn_from_an_expression_is_a_float():
    drawn = draws_of("").get("objects")
    assert drawn is not None
    spec = parse_scene(tomllib.loads(TWO_BOXES.replace("size = 0.2\nposition = [0.5",
                                                       'size = "0.2"\nmass = "2"\nposition = [0.5')), name="boxes")
    second = spec.draw(np.random.default_rng(0))["objects"][1]
    assert second["mass"] == 2.0 and type(second["mass"]) is float and type(second["size"]) is float
