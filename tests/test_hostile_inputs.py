"""Files from someone else, drawn by hypothesis: checkpoints, meshes and scene files that are
hostile (too deep, too large, too many, malformed) each end the command in one line on stderr,
exit code 2 and nothing written, within a time limit and under a memory limit.

Each input kind runs in a process of its own whose address space is capped at what the
imports take plus :data:`HEADROOM` (``resource.setrlimit``): an input that made the command
allocate more would end in a MemoryError, not in the one line. Run a kind by hand with
``python tests/test_hostile_inputs.py <kind> <folder>``.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

#: what a command may allocate past its imports before the process's address space runs out
HEADROOM = 1 << 30
#: the most one hostile input may take, start-up excluded (about a second on an idle machine;
#: the margin is for a loaded one)
EXAMPLE_SECONDS = 10.0
#: examples per kind: the three kinds together stay under a minute
EXAMPLES = 20
KINDS = ("checkpoint", "mesh", "scene")


def _answer(argv: list[str], out: Path, case: object) -> None:
    """Run ``hrn-pyg argv`` in this process; assert exit 2, one line, nothing at ``out``, in time
    (``case`` names the input in a failure)."""
    from hrn_pyg.cli import main

    err = io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stderr(err):
        code = main(argv)
    seconds = time.perf_counter() - start
    text = err.getvalue()
    shown = repr(case)[:300]
    assert code == 2 and text.count("\n") == 1 and text.startswith("hrn-pyg "), (shown, code, text)
    assert not out.exists(), (shown, f"{out} was written")
    assert seconds < EXAMPLE_SECONDS, (shown, seconds, text)


# -- checkpoints ------------------------------------------------------------------------------

_SIZES = st.one_of(st.integers(17, 10**15), st.integers(-10, 0), st.floats(allow_nan=True),
                   st.text(max_size=5), st.none())


def _deep_json(depth: int, opener: str) -> str:
    """JSON text nested ``depth`` deep in lists (``opener`` ``[``) or objects (``{``)."""
    if opener == "[":
        return "[" * depth + "]" * depth
    return '{"a": ' * depth + "1" + "}" * depth


@st.composite
def hostile_checkpoints(draw) -> tuple[str, object]:
    """``(how, change)``: one change that makes the shipped cube_collision.pt unusable."""
    how = draw(st.sampled_from(["size", "config", "domain", "tensor", "model", "format", "truncate"]))
    if how == "size":
        return how, (draw(st.sampled_from(["hidden", "depth", "effect_dim"])), draw(_SIZES))
    if how in ("config", "domain"):
        return how, draw(st.one_of(
            st.builds(_deep_json, st.integers(33, 300_000), st.sampled_from("[{")),
            st.text(max_size=200).map(lambda t: "x" + t),  # never JSON
            st.just('{"model": ' + '{"a": [' * 20 + "]}" * 20 + "}"),  # within the depth, not a config
        ))
    if how == "tensor":
        return how, (draw(st.integers(0, 10**6)), draw(st.lists(st.integers(0, 5), max_size=3)))
    if how == "model":
        return how, draw(st.sampled_from(["tensor", "empty", "text"]))
    if how == "format":
        return how, draw(st.text(max_size=30).filter(lambda t: t != "hrn_pyg.checkpoint.v1"))
    return how, draw(st.floats(0.0, 0.999))


def _hostile_checkpoint(folder: Path, how: str, change: object) -> Path:
    import torch

    from hrn_pyg.checkpoints import checkpoint_path

    source = checkpoint_path("cube_collision")
    path = folder / "hostile.pt"
    if how == "truncate":
        data = source.read_bytes()
        path.write_bytes(data[: int(change * len(data))])
        return path
    ckpt = torch.load(source, weights_only=True)
    if how == "size":
        config = json.loads(ckpt["config"])
        field, value = change
        if value == config["model"][field]:
            value = -1
        config["model"][field] = value
        ckpt["config"] = json.dumps(config)
    elif how in ("config", "domain"):
        ckpt[how] = change
    elif how == "tensor":
        keys = sorted(ckpt["model"])
        index, shape = change
        key = keys[index % len(keys)]
        if list(ckpt["model"][key].shape) == shape:
            shape = [*shape, 7]
        ckpt["model"] = {**ckpt["model"], key: torch.zeros(shape)}
    elif how == "model":
        ckpt["model"] = {"tensor": torch.zeros(3), "empty": {}, "text": "weights"}[change]
    else:
        ckpt["format"] = change
    torch.save(ckpt, path)
    return path


def fuzz_checkpoint(folder: Path) -> None:
    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(hostile_checkpoints())
    def check(case: tuple[str, object]) -> None:
        path = _hostile_checkpoint(folder, *case)
        out = folder / "out"
        _answer(["sample", "--scene", "cube_collision", "--model", str(path), "--k", "2", "--horizon", "2",
                 "--out", str(out), "--no-progress"], out, case)

    check()


# -- meshes -----------------------------------------------------------------------------------

_SCENE = '''steps = 5
pitch = {pitch!r}
[[objects]]
mesh = "{mesh}"
material = "{material}"
size = {size!r}
position = [0.0, 0.0, 1.0]
'''


@st.composite
def hostile_meshes(draw) -> tuple[str, dict]:
    """``(how, values)``: a mesh file, and the pitch and size it is used at, that no scene takes."""
    how = draw(st.sampled_from(["faces", "bytes", "nan", "garbage", "flat", "open", "tiny", "huge"]))
    values = {"material": draw(st.sampled_from(["rigid", "soft", "static"])), "pitch": 0.02, "size": 0.2,
              "seed": draw(st.integers(0, 2**16))}
    if how == "flat":
        values.update(apex=draw(st.floats(1e-12, 1e-4)), size=1.0, pitch=draw(st.floats(1e-4, 4e-3)))
    elif how == "open":
        values.update(size=draw(st.floats(0.5, 2.0)), pitch=draw(st.floats(0.004, 0.03)))
    elif how == "tiny":
        values.update(size=draw(st.floats(1e-9, 1e-3)))
    elif how == "huge":
        values.update(size=draw(st.floats(50.0, 1e4)))
    elif how == "faces":
        values.update(extra=draw(st.integers(1, 5000)))
    elif how == "bytes":
        values.update(extra=draw(st.integers(1, 2**20)), suffix=draw(st.sampled_from([".obj", ".stl", ".ply"])))
    elif how == "garbage":
        # no magic of either format first (random bytes may be a whole binary STL or OBJ)
        values.update(data=b"\xff" + draw(st.binary(max_size=4000)), suffix=draw(st.sampled_from([".ply", ".glb"])))
    return how, values


_NAMES = itertools.count()


def _hostile_mesh(folder: Path, how: str, values: dict) -> Path:
    import trimesh

    from hrn_pyg.data.meshes import MAX_FACES, MAX_MESH_BYTES

    rng = np.random.default_rng(values["seed"])
    # a new name each time: scene files keep the meshes they read in memory, by path
    mesh = folder / f"hostile_{next(_NAMES)}{values.get('suffix', '.obj')}"
    if how == "faces":
        faces = rng.integers(1, 41, size=(MAX_FACES + values["extra"], 3))
        lines = ["v %f %f %f" % tuple(v) for v in rng.random((40, 3))]
        mesh.write_text("\n".join(lines) + "\n" + "\n".join(map("f {} {} {}".format, *faces.T)) + "\n")
    elif how == "bytes":
        with open(mesh, "wb") as f:
            f.truncate(MAX_MESH_BYTES + values["extra"])  # sparse: nothing is written
    elif how == "garbage":
        mesh.write_bytes(values["data"])
    else:
        if how == "flat":
            made = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, values["apex"]]],
                                   [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]], process=False)
        elif how == "open":
            sphere = trimesh.creation.icosphere(subdivisions=5)
            made = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
        else:
            made = trimesh.creation.box()
            if how == "nan":
                made.vertices[rng.integers(0, len(made.vertices))] = rng.choice([np.nan, np.inf, -np.inf])
        made.export(mesh)
    scene = folder / "hostile_mesh.toml"
    scene.write_text(_SCENE.format(mesh=mesh.name, **{k: values[k] for k in ("pitch", "material", "size")}))
    return scene


def fuzz_mesh(folder: Path) -> None:
    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(hostile_meshes())
    def check(case: tuple[str, dict]) -> None:
        scene = _hostile_mesh(folder, *case)
        out = folder / "out"
        _answer(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(out), "--no-progress"],
                out, case)
        for made in folder.glob("hostile_*"):
            made.unlink()

    check()


# -- scene files ------------------------------------------------------------------------------

_BASE = 'steps = 5\n[[objects]]\nmesh = "box"\nmaterial = "rigid"\nsize = 0.1\nposition = [0, 0, 0.05]\n'


def _scene_text(how: str, n: int) -> str:
    if how == "dotted":
        return _BASE + "[settings]\n" + ".".join(["a"] * n) + " = 1\n"
    if how == "header":
        return _BASE + "[" + ".".join(["a"] * n) + "]\n"
    if how == "array":
        return "x = " + "[" * n + "]" * n + "\n" + _BASE
    if how == "inline":
        return "x = " + "{a = " * n + "1" + "}" * n + "\n" + _BASE
    from hrn_pyg.data.scene_file import MAX_FILE_CHARS

    return _BASE + "#" * (MAX_FILE_CHARS + n) + "\n"


hostile_scene_files = st.one_of(
    st.builds(_scene_text, st.sampled_from(["dotted", "header", "array", "inline", "long"]), st.integers(33, 100_000))
    .map(str.encode),
    st.binary(max_size=2000).map(lambda b: b"\xff" + b),  # never UTF-8
    st.text(max_size=400).map(str.encode),  # never a whole scene: no objects or no steps
)


def fuzz_scene(folder: Path) -> None:
    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(hostile_scene_files)
    def check(data: bytes) -> None:
        scene = folder / "hostile.toml"
        scene.write_bytes(data)
        out = folder / "out"
        _answer(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(out), "--no-progress"],
                out, data[:200])

    check()


# -- each kind in a process with its memory capped --------------------------------------------


def _cap_memory() -> int:
    """Cap this process's address space at its present size plus :data:`HEADROOM`; the cap."""
    size = int(re.search(r"VmSize:\s+(\d+) kB", Path("/proc/self/status").read_text()).group(1)) * 1024
    cap = size + HEADROOM
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    return cap


def _main(kind: str, folder: str) -> None:
    import hrn_pyg.checkpoints  # noqa: F401  the imports before the cap: they are not the input's
    import hrn_pyg.cli  # noqa: F401
    import hrn_pyg.data.generate  # noqa: F401
    import hrn_pyg.sampling.cli  # noqa: F401
    import trimesh  # noqa: F401

    Path(folder).mkdir(parents=True, exist_ok=True)
    _cap_memory()
    {"checkpoint": fuzz_checkpoint, "mesh": fuzz_mesh, "scene": fuzz_scene}[kind](Path(folder))
    print("fuzzed", kind)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the process size from /proc")
@pytest.mark.parametrize("kind", KINDS)
def test_hostile_inputs_end_in_one_line(kind: str, tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, __file__, kind, str(tmp_path)], capture_output=True, text=True,
                          timeout=EXAMPLES * EXAMPLE_SECONDS + 60, env={**os.environ, "PYTHONHASHSEED": "0"})
    assert done.returncode == 0 and f"fuzzed {kind}" in done.stdout, done.stdout[-3000:] + done.stderr[-3000:]


if __name__ == "__main__":
    _main(*sys.argv[1:3])
