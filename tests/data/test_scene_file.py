"""Scenes from files (hrn_pyg.data.scene_file): pybullet_data meshes make a dataset, ranges are
drawn per seed, overlaps are redrawn or named, and every bad input is one line with nothing
written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pybullet_data
import pytest

from hrn_pyg.cli import main
from hrn_pyg.data import scene_file
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.scene_file import (
    FileScene,
    boxes_overlap,
    overlapping,
    read_scene_file,
    start_box,
)

DATA = Path(pybullet_data.getDataPath())

MESHES = f"""
steps = 6
pitch = 0.025

[[objects]]                       # rigid, several pieces and seams in the file
mesh = "pybullet_data:duck.obj"
material = "rigid"
size = {{ min = 0.15, max = 0.2 }}
mass = 0.4
position = [0.0, 0.0, 0.3]
yaw = {{ min = 0, max = 360 }}

[[objects]]                       # concave and open: collides as its convex parts
mesh = "{DATA / 'objects' / 'mug.obj'}"
material = "rigid"
size = 0.15
mass = 0.3
position = [0.35, 0.0, 0.1]
velocity = [-0.5, 0.0, 0.0]

[[objects]]                       # soft, from a mesh with 209 pieces before its seams are merged
mesh = "{DATA / 'torus' / 'torus_textured.obj'}"
material = "soft"
size = 0.2
mass = 0.3
position = [-0.35, 0.0, 0.15]
stiffness = {{ min = 0.3, max = 0.7 }}

[[pushes]]
object = 0
steps = [1, 2]
force = [2.0, 0.0, 0.0]
"""

PRIMITIVES_AND_CLOTH = """
steps = 3
pitch = 0.05

[[objects]]
mesh = "box"
material = "static"
scale = 0.4
position = [0.0, 0.0, 0.2]

[[objects]]
mesh = "capsule"
material = "rigid"
size = 0.2
position = [0.5, 0.0, 0.3]
spin = [0.0, 0.0, 3.0]

[[objects]]
mesh = "sheet"
material = "cloth"
size = 0.3
mass = 0.1
position = [0.0, 0.0, 0.6]
"""


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture(autouse=True)
def cache_in_tmp(tmp_path, monkeypatch):
    monkeypatch.setattr(scene_file, "CACHE_DIR", tmp_path / "cache")


def test_a_scene_file_of_pybullet_meshes_generates_a_dataset(tmp_path, capsys):
    path = write(tmp_path, MESHES)
    out = tmp_path / "data"
    assert main(["generate", "--scene-file", str(path), "--episodes", "2", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads((out / "meta.json").read_text())
    assert meta["scene"] == "scene" and meta["complete"] and meta["scene_text"] == MESHES
    for seed in (0, 1):
        episode = load_episode(out / f"episode_{seed:06d}.npz")
        assert episode["positions"].shape[0] == 7 and np.all(np.isfinite(episode["positions"]))
        assert episode["object_material"].tolist() == [RIGID, RIGID, SOFT]
        counts = np.bincount(episode["leaf_object"])
        assert np.all(counts > 50)
        pushed = episode["forces"][1:3, episode["leaf_object"] == 0].sum(axis=1)
        np.testing.assert_allclose(pushed, [[2.0, 0.0, 0.0]] * 2, atol=1e-5)
        assert np.all(episode["forces"][3:] == 0)
    assert main(["generate", "--scene-file", str(path), "--episodes", "2", "--out", str(out), "--no-progress"]) == 0
    assert json.loads((out / "meta.json").read_text())["already_done"] == 2  # a rerun redoes nothing


def test_primitives_a_static_body_and_a_cloth_sheet():
    episode = simulate_episode(read_scene_file_text(PRIMITIVES_AND_CLOTH), seed=4)
    assert episode["object_material"].tolist() == [STATIC, RIGID, CLOTH]
    x, obj = episode["positions"], episode["leaf_object"]
    assert np.array_equal(x[0, obj == 0], x[-1, obj == 0])  # the static box never moves
    capsule = x[:, obj == 1]
    assert np.ptp(capsule[-1, :, 0]) < 0.25  # a 20 cm capsule
    sheet = x[0, obj == 2]
    assert len(sheet) == 7 * 7 and np.ptp(sheet[:, 2]) < 1e-6  # a flat 30 cm sheet at pitch 5 cm


def read_scene_file_text(text: str, tmp: Path | None = None):
    import tempfile

    folder = Path(tempfile.mkdtemp()) if tmp is None else tmp
    return read_scene_file(write(folder, text))


def test_ranges_are_drawn_per_seed_within_their_bounds_and_repeat(tmp_path):
    spec = read_scene_file(write(tmp_path, MESHES))
    a, b, again = (FileScene(spec, s).params for s in (0, 1, 0))
    assert a == again and a != b
    for params in (a, b):
        duck, torus = params["objects"][0], params["objects"][2]
        assert 0.15 <= duck["size"] <= 0.2 and 0.0 <= duck["yaw"] <= 360.0
        assert 0.3 <= torus["stiffness"] <= 0.7
        assert params["objects"][1]["size"] == 0.15


def test_objects_that_may_overlap_are_redrawn_and_those_that_always_do_are_named(tmp_path):
    sometimes = """
steps = 2
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
position = [0.0, 0.0, 0.1]
[[objects]]
mesh = "sphere"
material = "rigid"
size = 0.2
position = { min = [-0.5, 0.0, 0.1], max = [0.5, 0.0, 0.1] }
"""
    spec = read_scene_file(write(tmp_path, sometimes))
    for seed in range(20):
        drawn = FileScene(spec, seed).params["objects"]
        assert overlapping(spec, drawn) == []
        assert abs(drawn[1]["position"][0]) >= 0.2
    always = sometimes.replace("position = { min = [-0.5, 0.0, 0.1], max = [0.5, 0.0, 0.1] }",
                               "position = [0.05, 0.0, 0.1]")
    with pytest.raises(ValueError, match="objects 0 and 1 overlap"):
        FileScene(read_scene_file(write(tmp_path, always, "always.toml")), 0)
    centre, axes, half = start_box(spec.objects[0], {"size": 0.2, "position": [0.0, 0.0, 0.1], "yaw": 45.0})
    np.testing.assert_allclose(half, [0.1, 0.1, 0.1])
    np.testing.assert_allclose(axes[0], [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-12)


def test_oriented_boxes_overlap_only_where_they_do():
    """A cube turned by 45 degrees reaches sqrt(2) times further along x than it does square on:
    axis-aligned boxes would call the first pair overlapping, the oriented test does not."""
    spec = read_scene_file_text(BASE)
    cube = spec.objects[0]
    turned = start_box(cube, {"size": 0.2, "position": [0.0, 0.0, 0.1], "yaw": 45.0})
    square = start_box(cube, {"size": 0.2, "position": [0.2, 0.2, 0.1], "yaw": 0.0})  # beside its slanted face
    assert not boxes_overlap(turned, square)
    near = start_box(cube, {"size": 0.2, "position": [0.22, 0.0, 0.1], "yaw": 0.0})  # into its corner
    assert boxes_overlap(turned, near)
    below = start_box(cube, {"size": 0.2, "position": [0.0, 0.0, 0.3], "yaw": 10.0})  # stacked: touching only
    assert not boxes_overlap(turned, below)


BASE = """
steps = 4
[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
position = [0.0, 0.0, 0.1]
"""

BAD = [
    (BASE.replace('material = "rigid"', 'material = "jelly"'), "unknown material 'jelly'"),
    (BASE.replace('mesh = "box"', 'mesh = "pyramid"'), "unknown primitive 'pyramid'"),
    (BASE.replace('mesh = "box"', 'mesh = "no/such/file.obj"'), "mesh file not found"),
    (BASE.replace("size = 0.2", "size = { min = 0.3, max = 0.2 }"), r"min \[?0.3\]? > max"),
    (BASE.replace("size = 0.2", "colour = 1\nsize = 0.2"), "unknown key 'colour'; the keys are mesh, material"),
    (BASE.replace("steps = 4", "steps = 4\nsubsteps = 0"), "substeps"),
    (BASE.replace("steps = 4\n", ""), "steps .* is required"),
    (BASE.replace("size = 0.2", "size = 0.2\nscale = 2"), "one of size"),
    (BASE.replace("position = [0.0, 0.0, 0.1]", "position = [0.0, 0.1]"), "list of 3 numbers"),
    (BASE.replace("size = 0.2", "size = nan"), "finite"),
    (BASE.replace("size = 0.2", "size = 0.001"), "make it at least 0.1 m long, or use a pitch of at most"),
    (BASE.replace("size = 0.2", "size = 20.0"), "a pitch of .* m fits"),
    (BASE + '[[pushes]]\nobject = 3\nsteps = [0, 1]\nforce = [1.0, 0.0, 0.0]\n', "an index into objects"),
    (BASE + '[[pushes]]\nobject = 0\nsteps = [2, 9]\nforce = [1.0, 0.0, 0.0]\n', "within 0..3"),
    (BASE.replace('material = "rigid"', 'material = "static"') + '[[pushes]]\nobject = 0\nsteps = [0, 1]\n'
     'force = [1.0, 0.0, 0.0]\n', "static and cannot be pushed"),
    (BASE + '[[objects]]\nmesh = "sphere"\nmaterial = "rigid"\nsize = 0.2\nposition = [0.05, 0.0, 0.1]\n',
     "objects 0 and 1 overlap"),
    ("steps = 4\n[objects\n", "not TOML"),
    (BASE.replace('material = "rigid"', 'material = "soft"').replace('mesh = "box"', 'mesh = "cylinder"').replace(
        "size = 0.2", "extents = [0.3, 0.3, 0.05]"), "too thin for a soft body at pitch 0.05 m"),
]


@pytest.mark.parametrize("text, message", BAD, ids=[m for _, m in BAD])
def test_bad_scene_files_are_one_line_and_write_nothing(tmp_path, capsys, text, message):
    path = write(tmp_path, text)
    out = tmp_path / "data"
    code = main(["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    import re

    assert re.search(message, err), err
    assert not out.exists()


def test_a_missing_scene_file_and_a_mesh_that_is_not_a_mesh(tmp_path, capsys):
    out = tmp_path / "data"
    assert main(["generate", "--scene-file", str(tmp_path / "none.toml"), "--episodes", "1", "--out", str(out)]) == 2
    assert "scene file not found" in capsys.readouterr().err
    (tmp_path / "notes.obj").write_text("not a mesh\n")
    path = write(tmp_path, BASE.replace('mesh = "box"', 'mesh = "notes.obj"'))
    assert main(["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "notes.obj" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_any_model_samples_and_scores_a_scene_file_dataset(tmp_path, capsys):
    """``hrn-pyg sample --scene-file`` and ``hrn-pyg evaluate --split all`` on a scene file's
    episodes (seeds 0 and 1: none of them in the seed-based test split)."""
    from hrn_pyg.nn.hrn import HRN, HRNConfig
    from hrn_pyg.train import TrainConfig, model_payload
    from hrn_pyg.utils.checkpoint import save_checkpoint

    path = write(tmp_path, PRIMITIVES_AND_CLOTH.replace("steps = 3", "steps = 12"))
    data = tmp_path / "data"
    assert main(["generate", "--scene-file", str(path), "--episodes", "2", "--out", str(data), "--no-progress"]) == 0
    checkpoint = tmp_path / "model.pt"
    save_checkpoint(checkpoint, model_payload(HRN(HRNConfig(hidden=16, effect_dim=16)), TrainConfig(), 0))
    out = tmp_path / "eval"
    assert main(["evaluate", "--data", str(data), "--split", "all", "--model", f"a={checkpoint}", "--out", str(out),
                 "--horizons", "2,4", "--stride", "4", "--long-horizons", "8", "--no-figure", "--device", "cpu"]) == 0
    result = json.loads((out / "results.json").read_text())
    assert result["split"] == "all" and result["long_trajectories"] == 2
    assert main(["evaluate", "--data", str(data), "--model", f"a={checkpoint}", "--out", str(tmp_path / "e2"),
                 "--no-figure"]) == 2  # the default test split of seeds 0, 1 is empty: one clear line
    err = capsys.readouterr().err
    assert "no episodes of split 'test'" in err and "--split all" in err
    samples = tmp_path / "samples"
    assert main(["sample", "--scene-file", str(path), "--model", str(checkpoint), "--k", "2", "--rate", "0.2",
                 "--horizon", "3", "--episode-seed", "1", "--out", str(samples), "--device", "cpu"]) == 0
    record = json.loads((samples / "samples.json").read_text())
    assert record["scene_file"] == str(path) and record["k"] == 2 and (samples / "samples.png").is_file()
    assert main(["sample", "--scene-file", str(path), "--out", str(samples)]) == 2
    assert "--scene-file needs --model" in capsys.readouterr().err


# ---- property-based: malformed scene files are refused in one line, never with a crash --------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from hrn_pyg.data.scene_file import parse_scene  # noqa: E402

VALID_OBJECT = {"mesh": "box", "material": "rigid", "size": 0.2, "position": [0.0, 0.0, 0.1]}
ANY_VALUE = st.recursive(
    st.none() | st.booleans() | st.integers(-10, 10) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.sampled_from(["min", "max", "x"]), inner, max_size=3),
    max_leaves=8,
)
OBJECT_KEYS_AND_MORE = st.sampled_from(list(scene_file.OBJECT_KEYS) + ["colour", "Mesh"])


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=OBJECT_KEYS_AND_MORE, value=ANY_VALUE, steps=ANY_VALUE)
def test_a_malformed_field_is_a_value_error_naming_where(tmp_path, key, value, steps):
    table = {"steps": steps, "objects": [{**VALID_OBJECT, key: value}]}
    try:
        spec = parse_scene(table, name="fuzz", base=tmp_path)
    except (ValueError, FileNotFoundError) as exc:
        message = str(exc)
        assert message.startswith("fuzz") and "\n" not in message, message
        return
    assert spec.objects[0].material in ("rigid", "soft", "cloth", "static")
    assert isinstance(spec.config.steps, int) and spec.config.steps >= 1


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet=st.sampled_from(list('steps=1[]{}"objects.mesh =box\n,0')), max_size=60))
def test_any_text_is_a_scene_or_one_line_of_error(tmp_path, text):
    path = tmp_path / "fuzz.toml"
    path.write_text(text)
    try:
        read_scene_file(path)
    except (ValueError, FileNotFoundError) as exc:
        assert str(exc).strip() and "\n" not in str(exc).strip()


def test_a_flat_mesh_has_no_volume(tmp_path, capsys):
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    path = write(tmp_path, BASE.replace('mesh = "box"', 'mesh = "flat.obj"'))
    assert main(["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err.strip()
    assert "the mesh has no volume" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "d").exists()


def test_a_cloth_from_a_surface_mesh_has_its_vertices_as_leaves(tmp_path):
    import trimesh

    from hrn_pyg.data.voxelise import grid_sheet as sheet

    vertices, faces = sheet(0.3, 0.05)
    vertices[:, 2] = 0.02 * np.cos(vertices[:, 0] * 10)  # a wavy cloth
    trimesh.Trimesh(vertices=vertices, faces=faces, process=False).export(tmp_path / "wavy.obj")
    text = BASE + '[[objects]]\nmesh = "wavy.obj"\nmaterial = "cloth"\nsize = 0.3\nmass = 0.1\nposition = [0.0, 0.0, 0.5]\n'
    episode = simulate_episode(read_scene_file(write(tmp_path, text)), seed=0)
    assert episode["object_material"].tolist() == [RIGID, CLOTH]
    cloth = episode["positions"][0, episode["leaf_object"] == 1]
    assert len(cloth) == len(vertices)
    assert np.ptp(cloth[:, 2]) > 0.015  # the wave (0.019 m from crest to trough) is kept


def test_a_mesh_is_drawn_per_seed_from_a_list_and_primitives_take_extents(tmp_path):
    text = BASE.replace('mesh = "box"', 'mesh = ["box", "cylinder", "wedge"]').replace(
        "size = 0.2", 'extents = "[uniform(0.1, 0.3), uniform(0.1, 0.3), uniform(0.1, 0.3)]"')
    spec = read_scene_file(write(tmp_path, text))
    chosen = {}
    for seed in range(12):
        drawn = FileScene(spec, seed).params["objects"][0]
        chosen.setdefault(drawn["mesh"], []).append(drawn["extents"])
    assert sorted(chosen) == [0, 1, 2]  # every mesh is drawn
    episode = simulate_episode(spec, seed=0)
    x = episode["positions"][0]
    extents = FileScene(spec, 0).params["objects"][0]["extents"]
    name = spec.objects[0].meshes[FileScene(spec, 0).params["objects"][0]["mesh"]]
    # the leaves fill the drawn box (voxels that meet the surface count: up to a pitch beyond it)
    reach = np.ptp(x, axis=0)
    assert np.all(reach <= np.array(extents) + 0.05 + 1e-6), (name, reach, extents)
    assert np.all(reach >= np.array(extents) - 0.05 - 1e-6), (name, reach, extents)
    with pytest.raises(ValueError, match="extents are for primitives"):
        read_scene_file(write(tmp_path, text.replace('"wedge"]', '"pybullet_data:duck.obj"]'), "duck.toml"))


def test_a_mesh_pattern_draws_among_the_files_it_matches(tmp_path, capsys):
    import trimesh

    (tmp_path / "meshes").mkdir()
    for i, size in enumerate((0.2, 0.3)):
        trimesh.creation.box(extents=(size, 0.1, 0.1)).export(tmp_path / "meshes" / f"bar_{i}.obj")
    spec = read_scene_file(write(tmp_path, BASE.replace('mesh = "box"', 'mesh = ["sphere", "meshes/bar_*.obj"]')))
    assert [Path(m).name for m in spec.objects[0].meshes] == ["sphere", "bar_0.obj", "bar_1.obj"]
    out = tmp_path / "data"
    path = write(tmp_path, BASE.replace('mesh = "box"', 'mesh = "meshes/none_*.obj"'), "none.toml")
    assert main(["generate", "--scene-file", str(path), "--episodes", "1", "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no mesh file matches" in err and len(err.splitlines()) == 1 and not out.exists()


def _extents_by_hand(mesh: str, extents: list[float]) -> np.ndarray:
    """What a primitive's drawn ``[x, y, z]`` makes (round ones: diameter ``x``; a capsule never
    shorter than wide)."""
    x, y, z = extents
    return np.array({"sphere": [x, x, x], "cylinder": [x, x, z], "cone": [x, x, z],
                     "capsule": [x, x, max(x, z)]}.get(mesh, [x, y, z]))


def test_every_primitive_collides_and_is_filled_at_its_drawn_extents():
    import pybullet

    drawn = '"[uniform(0.1, 0.3), uniform(0.1, 0.3), uniform(0.1, 0.3)]"'
    names = ["box", "sphere", "cylinder", "capsule", "cone", "wedge"]
    text = "steps = 2\npitch = 0.02\n" + "".join(
        f'[[objects]]\nmesh = "{m}"\nmaterial = "rigid"\nextents = {drawn}\nposition = [{0.5 * i}, 0.0, 0.5]\n'
        for i, m in enumerate(names))
    text += '[[objects]]\nmesh = "capsule"\nmaterial = "rigid"\nextents = [0.2, 0.1, 0.1]\nposition = [3.0, 0.0, 0.5]\n'
    spec = read_scene_file_text(text)
    for seed in (0, 1):
        with FileScene(spec, seed) as scene:
            scene.reset()
            for obj, params, name in zip(scene._objects, scene.params["objects"], names + ["capsule"]):
                want = _extents_by_hand(name, params["extents"])
                low, high = pybullet.getAABB(obj.body, physicsClientId=scene._client)
                # the collision shape (a mesh's margin adds up to 4 mm) ...
                np.testing.assert_allclose(np.subtract(high, low), want, atol=0.005, err_msg=name)
                # ... and the leaves, voxel centres that lie within a pitch of the surface
                reach = np.ptp(obj.local_leaves, axis=0)
                assert np.all(np.abs(reach - want) <= 0.02 + 1e-9), (name, reach, want)


def test_round_primitives_read_their_diameter_from_x():
    from hrn_pyg.data.scene_file import primitive_extents

    assert primitive_extents("sphere", {"extents": [0.2, 0.1, 0.3]}).tolist() == [0.2, 0.2, 0.2]
    assert primitive_extents("cylinder", {"extents": [0.2, 0.1, 0.3]}).tolist() == [0.2, 0.2, 0.3]
    assert primitive_extents("capsule", {"extents": [0.2, 0.1, 0.1]}).tolist() == [0.2, 0.2, 0.2]  # never shorter than wide
    assert primitive_extents("box", {"extents": [0.2, 0.1, 0.3]}).tolist() == [0.2, 0.1, 0.3]
    short = BASE.replace('mesh = "box"', 'mesh = "capsule"').replace("size = 0.2", "extents = [0.2, 0.1, 0.1]")
    episode = simulate_episode(read_scene_file_text(short), seed=0)  # pybullet takes the capsule
    assert np.all(np.isfinite(episode["positions"]))
