"""A scene file is bounded: its length, counts, steps, sheets and expressions each have a limit
(just within passes, just past fails), and ``hrn-pyg generate`` answers a file past one with
exit 2, one line, in well under a second, writing nothing."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import hrn_pyg.data.generate  # noqa: F401  imported here, so the timings below are of the checks alone
from hrn_pyg.cli import main
from hrn_pyg.data.expressions import MAX_ELEMENTS, MAX_EXPRESSION_CHARS, LimitError, evaluate
from hrn_pyg.data.scene_file import (
    MAX_DRAWS,
    MAX_FILE_CHARS,
    MAX_LEAVES,
    MAX_MESH_CHOICES,
    MAX_NESTING,
    MAX_OBJECTS,
    MAX_PUSHES,
    MAX_SETTINGS,
    MAX_STEPS,
    MAX_SUBSTEPS,
    check_sheet,
    parse_scene,
    read_scene_file,
    toml_nesting,
)

BUILTIN = Path(hrn_pyg.data.generate.__file__).parent / "builtin_scenes"

BOX = {"mesh": "box", "material": "rigid", "size": 0.1, "position": [0.0, 0.0, 0.05]}
#: a one-box scene whose [draw] holds one expression
TEMPLATE = '''steps = 2
[draw]
x = "{expression}"
[[objects]]
mesh = "box"
material = "rigid"
size = 0.1
position = [0, 0, 0.05]
'''
#: what the answer to a bad file may take, once the program has started
SECONDS = 1.0


def scene(**top: object) -> dict:
    return {"steps": 2, "objects": [dict(BOX)], **top}


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


# -- the file ---------------------------------------------------------------------------------


def test_file_length_limit(tmp_path: Path) -> None:
    text = TEMPLATE.format(expression="1")
    path = write(tmp_path, text + "#" * (MAX_FILE_CHARS - len(text)))
    assert read_scene_file(path).draws == (("x", "1"),)
    path = write(tmp_path, text + "#" * (MAX_FILE_CHARS - len(text) + 1))
    with pytest.raises(LimitError, match=f"more than {MAX_FILE_CHARS} characters"):
        read_scene_file(path)


def test_deeply_nested_toml_is_one_line(tmp_path: Path) -> None:
    path = write(tmp_path, "steps = 2\nx = " + "[" * 2000 + "]" * 2000 + "\n")
    with pytest.raises(LimitError, match=f"nested 2000 deep, more than {MAX_NESTING}"):
        read_scene_file(path)


@pytest.mark.parametrize("parts", [5000, 60000])
def test_dotted_keys_count_as_nesting_before_parsing(tmp_path: Path, parts: int) -> None:
    """A key of many dotted parts nests a table per part: the parser took 9.5 GB on 60000."""
    path = write(tmp_path, TEMPLATE.format(expression="1") + "[settings]\n" + ".".join(["a"] * parts) + " = 1\n")
    start = time.perf_counter()
    with pytest.raises(LimitError, match=f"nested {parts - 1} deep, more than {MAX_NESTING}"):
        read_scene_file(path)
    assert time.perf_counter() - start < SECONDS


def test_toml_nesting_skips_strings_and_comments() -> None:
    assert toml_nesting('a = "x.y.z.w[[[["  # [[[[.....\nb = \'[[[\'\nc = """\\""".[[["""') == 0
    assert toml_nesting("a.b.c = [[1.5, 2.5], {d.e = 3}]") == 3
    assert max(toml_nesting(p.read_text()) for p in BUILTIN.glob("*.toml")) <= 3


def test_a_file_that_is_not_utf8_names_itself(tmp_path: Path) -> None:
    path = tmp_path / "latin.toml"
    path.write_bytes(b"steps = 2\n# caf\xe9\n")
    with pytest.raises(ValueError, match=r"latin\.toml: not UTF-8 text \(byte 0xe9"):
        read_scene_file(path)


@pytest.mark.parametrize("key, limit, make", [
    ("objects", MAX_OBJECTS, lambda n: {"objects": [dict(BOX) for _ in range(n)]}),
    ("pushes", MAX_PUSHES, lambda n: {"pushes": [{"object": 0, "steps": [0, 1], "force": [1, 0, 0]}] * n}),
    ("draws", MAX_DRAWS, lambda n: {"draw": {f"d{i}": "1" for i in range(n)}}),
    ("settings", MAX_SETTINGS, lambda n: {"settings": {f"s{i}": 1 for i in range(n)}}),
    ("meshes", MAX_MESH_CHOICES, lambda n: {"objects": [dict(BOX, mesh=["box"] * n)]}),
])
def test_count_limits(key: str, limit: int, make) -> None:
    parse_scene(scene(**make(limit)))
    with pytest.raises(LimitError, match=f"{limit + 1} {key}, more than {limit}"):
        parse_scene(scene(**make(limit + 1)))


def test_steps_limits() -> None:
    spec = parse_scene(scene(steps=MAX_STEPS, substeps=MAX_SUBSTEPS))
    with pytest.raises(LimitError, match=f"steps = {MAX_STEPS + 1}, more than {MAX_STEPS}"):
        parse_scene(scene(steps=MAX_STEPS + 1))
    with pytest.raises(LimitError, match=f"substeps = {MAX_SUBSTEPS + 1}, more than {MAX_SUBSTEPS}"):
        parse_scene(scene(substeps=MAX_SUBSTEPS + 1))
    assert spec.with_settings(steps=MAX_STEPS).config.steps == MAX_STEPS
    with pytest.raises(LimitError, match="steps"):
        spec.with_settings(steps=MAX_STEPS + 1)


def test_settings_are_bounded() -> None:
    spec = parse_scene(scene(settings={"a": [0.0] * MAX_ELEMENTS, "b": 2**63}))
    assert spec.settings["a"].size == MAX_ELEMENTS
    with pytest.raises(LimitError, match=f"settings.a: a list of {MAX_ELEMENTS + 1} elements"):
        parse_scene(scene(settings={"a": [0.0] * (MAX_ELEMENTS + 1)}))
    with pytest.raises(LimitError, match="settings.b: a whole number of 2001 bits"):
        spec.with_settings(b=2**2000)


@pytest.mark.parametrize("table", ["settings", "draw"])
def test_names_of_settings_and_draws_are_names(table: str) -> None:
    value = 1 if table == "settings" else "1"
    assert parse_scene(scene(**{table: {"_a1": value}}))
    for key in ("1a", "a b", "a\nb", ""):
        with pytest.raises(ValueError, match="is not a name") as info:
            parse_scene(scene(**{table: {key: value}}))
        assert "\n" not in str(info.value)


def test_sheet_limit() -> None:
    side = int(MAX_LEAVES**0.5)  # 141 x 141 = 19,881 leaves
    assert side * side <= MAX_LEAVES < (side + 1) ** 2
    check_sheet((side - 1) * 0.01, 0.01, "sheet")
    with pytest.raises(LimitError, match=f"{(side + 1) ** 2} leaves at pitch 0.01 m, more than {MAX_LEAVES}"):
        check_sheet(side * 0.01, 0.01, "sheet")
    with pytest.raises(LimitError, match="sheet"):
        check_sheet(1e300, 1e-300, "sheet")
    cloth = {"mesh": "sheet", "material": "cloth", "size": 100.0, "position": [0.0, 0.0, 0.5]}
    spec = parse_scene({"steps": 2, "pitch": 0.01, "objects": [cloth]})
    start = time.perf_counter()
    with pytest.raises(LimitError, match="objects\\[0\\]: a sheet of"):
        spec.check(0)
    assert time.perf_counter() - start < SECONDS


def test_expression_limits_keep_their_kind_through_the_file() -> None:
    with pytest.raises(LimitError, match="draw.x: an expression of"):
        parse_scene(scene(draw={"x": "1".ljust(MAX_EXPRESSION_CHARS + 1)}))
    spec = parse_scene(scene(draw={"x": "9 ** 9 ** 9"}))
    with pytest.raises(LimitError, match="scene: draw.x: '9 \\*\\* 9 \\*\\* 9': \\*\\* gives"):
        spec.draw(np.random.default_rng(0))
    spec = parse_scene(scene(objects=[dict(BOX, position="zeros(100001)")]))
    with pytest.raises(LimitError, match="objects\\[0\\].position"):
        spec.draw(np.random.default_rng(0))


# -- hrn-pyg generate ---------------------------------------------------------------------------

BAD = {"power": "9 ** 9 ** 9", "shape": "uniform(0, 1, [100000, 100000])"}


def _generate(path: Path, out: Path) -> list[str]:
    return ["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(out), "--no-progress"]


@pytest.mark.parametrize("expression", BAD.values(), ids=BAD.keys())
def test_generate_answers_a_bad_file_at_once_writing_nothing(tmp_path: Path, capsys, expression: str) -> None:
    out = tmp_path / "out"
    start = time.perf_counter()
    code = main(_generate(write(tmp_path, TEMPLATE.format(expression=expression)), out))
    seconds = time.perf_counter() - start
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "draw.x" in err and not out.exists()
    assert seconds < SECONDS, seconds


#: the whole command on a bad file, start-up included (under a second on an idle machine; the
#: margin is for a loaded one)
COMMAND_SECONDS = 10.0
#: what the command may not import before it answers a bad file (each takes seconds)
HEAVY = ("torch", "torch_geometric", "sklearn", "torchrl")


@pytest.mark.parametrize("expression", BAD.values(), ids=BAD.keys())
def test_the_hrn_pyg_command_exits_2_with_one_line(tmp_path: Path, expression: str) -> None:
    command = Path(sys.executable).with_name("hrn-pyg")
    if not command.exists():
        pytest.skip("no hrn-pyg script beside this Python")
    out = tmp_path / "out"
    done = subprocess.run([str(command), *_generate(write(tmp_path, TEMPLATE.format(expression=expression)), out)],
                          capture_output=True, text=True, timeout=COMMAND_SECONDS)
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("hrn-pyg generate: error: bad: draw.x: ") and not out.exists()


def test_a_bad_file_is_answered_before_torch_is_imported(tmp_path: Path) -> None:
    """The check of a scene file needs numpy, trimesh and pybullet only, so the answer does not
    wait for torch (seconds to import)."""
    out = tmp_path / "out"
    argv = _generate(write(tmp_path, TEMPLATE.format(expression=BAD["power"])), out)
    script = ("import sys\nfrom hrn_pyg.cli import main\n"
              f"code = main({argv!r})\n"
              f"print(code, sorted(m for m in {HEAVY!r} if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=COMMAND_SECONDS)
    assert done.stdout.split() == ["2", "[]"], done.stdout + done.stderr


_HOSTILE = st.one_of(
    st.integers(3, 12).map(lambda n: " ** ".join(["9"] * n)),
    st.tuples(st.integers(5, 12), st.integers(5, 12)).map(lambda t: f"uniform(0, 1, [1e{t[0]}, 1e{t[1]}])"),
    st.integers(5, 9).map(lambda k: f"zeros(10 ** {k})"),
    st.integers(33, 300).map(lambda n: "-" * n + "1"),
    st.integers(MAX_EXPRESSION_CHARS + 1, 5000).map(lambda n: "1".ljust(n)),
    st.integers(11, 40).map(lambda n: "(" + "2 ** 1000 * " * n + "1)"),
    st.sampled_from(["1e308 * 10", "(-1) ** 0.5", "[1e308] * [1e308]", "integer(0, 10 ** 300)", "1 / 0",
                     "uniform(0, 1, [1e4, 1]) + uniform(0, 1, [1, 1e4])", "__import__('os')", "pi.real"]),
)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                               HealthCheck.function_scoped_fixture])
@given(_HOSTILE)
def test_hostile_files_end_in_one_line_writing_nothing(tmp_path: Path, capsys, expression: str) -> None:
    with pytest.raises(ValueError):
        evaluate(expression, {}, np.random.default_rng(0))
    out = tmp_path / "hostile_out"
    path = tmp_path / "hostile.toml"
    path.write_text(TEMPLATE.format(expression=expression))  # none holds a " or a backslash
    start = time.perf_counter()
    code = main(_generate(path, out))
    seconds = time.perf_counter() - start
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and not out.exists(), err
    assert seconds < SECONDS, (expression, seconds)
