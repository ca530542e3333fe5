"""``experiments/generalist/unseen_shapes.py`` end to end on a tiny scene file: the generalist on two episodes
of meshes it never saw, against its own (tiny) test split and a specialist."""

from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from hrn_pyg.cli import main as cli
from hrn_pyg.data.io import load_episode
from hrn_pyg.data.scene_file import FileScene, drawn_mesh, read_scene_file

ROOT = Path(__file__).resolve().parents[3]
MESHES = ROOT / "data" / "shapes" / "meshes"

#: a box thrown at one of two convex procedural meshes (no decomposition to wait for)
TINY = f"""
steps = 10
pitch = 0.05

[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
mass = 1.0
position = [-0.4, 0.0, 0.3]
velocity = [2.0, 0.0, 0.5]

[[objects]]
mesh = ["{MESHES / 'random_hull_000.obj'}", "{MESHES / 'random_hull_001.obj'}"]
material = "rigid"
size = 0.3
mass = 1.0
position = [0.0, 0.0, 0.2]
"""


def _benchmark():
    return importlib.import_module("experiments.generalist.unseen_shapes")


def test_unseen_shapes_scores_a_tiny_scene(tmp_path, tiny_episodes, monkeypatch, capsys):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    unseen = tmp_path / "unseen"
    assert cli(["generate", "--scene-file", str(scene), "--episodes", "3", "--out", str(unseen), "--no-progress"]) == 0
    bench = _benchmark()
    out = tmp_path / "result.json"
    monkeypatch.setattr(sys, "argv", [
        "unseen_shapes.py", "--model", str(ROOT / "hrn_pyg/checkpoints/shapes.pt"), "--unseen", str(unseen),
        "--own", str(tiny_episodes), "--specialist", f"{tiny_episodes}={ROOT / 'hrn_pyg/checkpoints/cube_collision.pt'}",
        "--horizons", "2,4", "--stride", "3", "--rest-episodes", "1", "--rest-steps", "3", "--corotated-rest", "on",
        "--out", str(out)])
    assert bench.main() == 0
    result = json.loads(out.read_text())
    assert result["corotated_rest"] is True
    assert capsys.readouterr().out.strip().endswith(f"({result['seconds']:.0f} s)")

    # one group per mesh the seeds drew, named after its file; all of them pooled by material
    spec = read_scene_file(scene)
    drawn = set()
    for seed in range(3):
        params = FileScene(spec, seed).params["objects"]
        drawn |= {bench.mesh_name(drawn_mesh(obj, p)) for obj, p in zip(spec.objects, params)}
    groups, rigid = result["unseen"]["unseen"], result["unseen"]["unseen_by_material"]["rigid"]
    assert set(groups) == {f"{name} (rigid)" for name in drawn} and len(drawn) >= 2
    windows = 3 * 2                                               # per episode: starts 0 and 3
    assert rigid["objects"] == sum(g["objects"] for g in groups.values()) == 2 * windows
    # one folder: its per-folder errors are the material's (the ratios to shapes.pt pool folders)
    assert result["unseen"]["unseen_by_folder"] == {
        f"{unseen.name} (rigid)": {k: v for k, v in rigid.items() if not k.startswith("ratio_")}}
    own = result["unseen"]["own_test"]["rigid"]
    for horizon in (2, 4):
        for error in ("position", "shape"):
            key = f"{error}@{horizon}"
            pooled = sum(g[key] * g["objects"] for g in groups.values()) / rigid["objects"]
            assert rigid[key] == pytest.approx(pooled) and rigid[key] > 0
            assert rigid[f"ratio_{key}"] == pytest.approx(rigid[key] / own[key])
            versus = result["specialists"][tiny_episodes.name][key]
            assert versus["model"] == pytest.approx(own[key], rel=1e-5)   # the same test split
            assert versus["ratio"] == pytest.approx(versus["model"] / versus["specialist"])
            assert 0 < versus["specialist"] < math.inf
    time_row = result["time"][0]                                 # the rollout starts from two states
    assert time_row["steps"] == 10 - 2 and time_row["model_s_per_step"] > 0 and time_row["pybullet_s_per_step"] > 0
    assert "| **all rigid** | 12 |" in result["table"]


def test_pybullet_continues_an_episode_and_its_rest_is_scored(tmp_path):
    """``--pybullet-rest``: the same seed simulated longer repeats the episode's frames, is scored
    by the stability check over the frames after them, and is made once."""
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    folder, work = tmp_path / "unseen", tmp_path / "work"
    assert cli(["generate", "--scene-file", str(scene), "--episodes", "1", "--first-seed", "7",
                "--out", str(folder), "--no-progress"]) == 0
    bench = _benchmark()
    path = bench.pybullet_continuation(folder, 7, 4, work)
    assert path == bench.continuation_path(work, folder, 7, 4)
    episode, longer = load_episode(folder / "episode_000007.npz"), load_episode(path)
    assert longer["positions"].shape[0] == episode["positions"].shape[0] + 4
    report = bench.pybullet_rest_report(episode, longer, 4)
    assert report["same_run"] and report["replay_diff"] <= bench.REPLAY_TOLERANCE
    assert report["finite"] and {"holds", "rest_drift", "min_z", "rigid_shape"} <= set(report)
    # the drift is that of pybullet's own frames after the model's start state
    truth = torch.as_tensor(longer["positions"])
    end = episode["positions"].shape[0]
    leaf_move = (truth[end - 1:end + 3] - truth[end - 2]).abs().max()
    assert report["max_move"] == pytest.approx(float(leaf_move), abs=1e-6)

    stamp = path.stat().st_mtime_ns
    assert bench.pybullet_continuation(folder, 7, 4, work) == path and path.stat().st_mtime_ns == stamp

    moved = dict(episode, positions=episode["positions"] + 0.01)   # not the episode it continues
    assert not bench.pybullet_rest_report(moved, longer, 4)["same_run"]
    with pytest.raises(ValueError, match="needs"):
        bench.pybullet_rest_report(episode, longer, 6)


def test_pybullet_continuation_needs_the_scene_file(tmp_path):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    folder = tmp_path / "unseen"
    assert cli(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(folder), "--no-progress"]) == 0
    scene.unlink()
    with pytest.raises(FileNotFoundError, match="scene file"):
        _benchmark().pybullet_continuation(folder, 0, 4, tmp_path / "work")


def test_a_continuation_pybullet_loses_is_none(tmp_path, monkeypatch):
    """A seed pybullet loses is marked ``.rejected`` by generate and written nowhere: the
    continuation is None (the rest table says "lost by pybullet") rather than an error that
    stops the benchmark."""
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY)
    folder = tmp_path / "unseen"
    assert cli(["generate", "--scene-file", str(scene), "--episodes", "1", "--out", str(folder), "--no-progress"]) == 0
    bench = _benchmark()
    monkeypatch.setattr(bench.subprocess, "run", lambda *a, **k: None)   # generate writing nothing
    assert bench.pybullet_continuation(folder, 0, 4, tmp_path / "work") is None
    row = {"folder": "f", "seed": 0, "objects": ["box (rigid)"], "holds": True, "max_move": 0.0, "min_z": 0.0,
           "rigid_shape": 0.0, "rest_drift": 0.0, "pybullet": bench.LOST}
    empty = {"unseen": {"unseen": {}, "unseen_by_material": {}, "own_test": {}}}
    assert "lost by pybullet" in bench.markdown({**empty, "rest": [row]}, (15, 50))
