"""``benchmarks/cloth_pass_through.py`` on a tiny case: a small sheet dropped on a box for a few
steps, rolled out by the shipped multi_material model and counted against pybullet's episode."""

from __future__ import annotations

import importlib
import json

import numpy as np
import pytest
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.cli import main as cli
from hrn_pyg.data.io import load_episode
from hrn_pyg.sim.penetration import cloth_inside_counts, episode_solids

#: a small sheet just over a box: a few steps, the sheet's leaves around the box's top
TINY = """
steps = 8
pitch = 0.05

[[objects]]
mesh = "box"
material = "rigid"
size = 0.2
mass = 1.0
position = [0.0, 0.0, 0.1]

[[objects]]
mesh = "sheet"
material = "cloth"
size = 0.3
mass = 0.1
log10_spring_k = 1.5
position = [0.02, 0.0, 0.26]
"""


def _benchmark():
    return importlib.import_module("benchmarks.cloth_pass_through")


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cloth")
    scene = folder / "tiny.toml"
    scene.write_text(TINY)
    out = folder / "episodes"
    assert cli(["generate", "--scene-file", str(scene), "--episodes", "2", "--out", str(out), "--no-progress"]) == 0
    return out


def test_the_core_counts_the_model_and_pybullet_at_the_same_steps(episodes):
    bench = _benchmark()
    torch.set_num_threads(1)
    result = bench.score_folders(load_model("multi_material"), [episodes])
    folder = result[episodes.name]
    assert [r["seed"] for r in folder["episodes"]] == [0, 1]
    for row in folder["episodes"]:
        episode = load_episode(episodes / f"episode_{row['seed']:06d}.npz")
        truth = torch.from_numpy(np.asarray(episode["positions"], dtype=np.float32))[3:]  # x_3 .. x_8
        assert row["steps"] == 6 == len(row["model_counts"]) == len(row["pybullet_counts"])
        assert row["pybullet_counts"] == cloth_inside_counts(truth, episode_solids(episode)).tolist()
        assert row["cloth_leaves"] == 7 * 7 and row["error"] is None
        for source in bench.SOURCES:
            counts = row[f"{source}_counts"]
            assert row[source]["mean"] == pytest.approx(sum(counts) / 6) and row[source]["max"] == max(counts)
        assert row["seconds_per_step"] > 0
    summary = folder["summary"]
    assert summary["episodes"] == 2 and summary["diverged"] == 0
    timed = [r["seconds_per_step"] for r in folder["episodes"]]
    assert summary["model_ms_per_step"] == pytest.approx(1e3 * np.median(timed))
    every = [c for r in folder["episodes"] for c in r["pybullet_counts"]]
    assert summary["pybullet"]["mean"] == pytest.approx(np.mean(every))
    assert summary["pybullet"]["steps_with_any"] == pytest.approx(np.mean([c > 0 for c in every]))
    assert summary["pybullet"]["mean_share"] == pytest.approx(np.mean(every) / 49)


def test_a_diverged_rollout_is_counted_not_averaged():
    bench = _benchmark()
    rows = [{"model_counts": [0, 2], "pybullet_counts": [0, 1], "cloth_leaves": 10},
            {"model_counts": None, "pybullet_counts": [3, 0], "cloth_leaves": 20}]
    summary = bench.pooled(rows)
    assert summary["diverged"] == 1 and summary["episodes"] == 2
    assert summary["model"] == {"mean": 1.0, "max": 2, "mean_share": 0.1, "steps_with_any": 0.5, "episodes_with_any": 1}
    assert summary["pybullet"]["mean"] == 1.0 and summary["pybullet"]["mean_share"] == pytest.approx((0.1 + 0.15) / 4)
    assert bench.pooled([rows[1]])["model"] is None


def test_the_command_writes_json_and_a_table(episodes, tmp_path, capsys):
    bench = _benchmark()
    out = tmp_path / "result.json"
    assert bench.main(["--model", "multi_material", "--episodes", str(episodes), "--limit", "1", "--out", str(out),
                       "--cloth-clearance", "0,0.25"]) == 0
    result = json.loads(out.read_text())
    assert [run["cloth_clearance"] for run in result["runs"]] == [0.0, 0.25]
    off, kept = (run["folders"][episodes.name] for run in result["runs"])
    assert off["summary"]["episodes"] == kept["summary"]["episodes"] == 1
    assert off["episodes"][0]["pybullet_counts"] == kept["episodes"][0]["pybullet_counts"]
    assert sum(kept["episodes"][0]["model_counts"]) <= sum(off["episodes"][0]["model_counts"])
    printed = capsys.readouterr().out
    assert f"| {episodes.name} | 0 | 1 |" in printed and f"| {episodes.name} | 0.25 | 1 |" in printed
    assert printed.strip().endswith(f"({result['seconds']:.0f} s)")
    with pytest.raises(SystemExit):
        bench.main(["--model", "multi_material", "--episodes", str(episodes), "--out", str(out),
                    "--cloth-clearance", "a"])
    with pytest.raises(FileNotFoundError, match="no episode"):
        bench.score_folders(load_model("multi_material"), [tmp_path])
