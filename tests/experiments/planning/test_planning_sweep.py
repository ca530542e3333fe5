"""The planning sweep resumes where it stopped and refuses other settings; the summary's
statistics on hand-made episodes."""

import json

import pytest

from experiments.planning import summary as summary_mod
from experiments.planning import sweep
from hrn_pyg.rl.hrn_dynamics import HRNDynamics
from hrn_pyg.rl.planning import PlannerConfig

TINY = ["--task", "cube_push_stop", "--model", "cube_push", "--num-scenes", "1", "--num-seeds", "1",
        "--modes", "deterministic", "--candidates", "2", "--elites", "1", "--iterations", "1",
        "--horizon", "1", "--k", "2"]


@pytest.fixture
def one_scene_pool(monkeypatch):
    """The sweep's dynamics on a pool of one pybullet scene (the fixed scenes then differ by goal)."""
    original = HRNDynamics.from_checkpoint.__func__

    def small(cls, path, task, *args, **kwargs):
        return original(cls, path, task, pool_seeds=(10_000,))

    monkeypatch.setattr(HRNDynamics, "from_checkpoint", classmethod(small))


def test_sweep_writes_one_line_per_episode_and_skips_them_on_a_rerun(tmp_path, one_scene_pool):
    out = tmp_path / "sweep"
    assert sweep.main(TINY + ["--out", str(out)]) == 0
    lines = (out / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 1
    episode = json.loads(lines[0])
    assert episode["mode"] == "deterministic" and episode["scene_seed"] == 10_000 and episode["steps"] >= 1
    assert sweep.main(TINY + ["--out", str(out)]) == 0                 # nothing left to do
    assert (out / "episodes.jsonl").read_text().splitlines() == lines
    assert sweep.main(TINY[:-2] + ["--k", "3", "--out", str(out)]) == 2  # other settings: refused


def test_mode_config_and_bad_modes():
    base = PlannerConfig(refine_steps=3)
    assert sweep.mode_config(base, "deterministic_refine").refine_steps == 3
    assert sweep.mode_config(base, "risk") == PlannerConfig(score="risk", refine_steps=0)
    with pytest.raises(ValueError, match="mode"):
        sweep.mode_config(base, "optimistic")


def test_summary_by_hand(tmp_path):
    episodes = []
    for seed in range(4):
        for scene in range(2):
            episodes.append({"mode": "deterministic", "seed": seed, "scene": scene, "success": scene == 0,
                             "steps": 5, "plan_seconds": 0.1, "physics_seconds": 0.001})
            episodes.append({"mode": "mean", "seed": seed, "scene": scene, "success": True,
                             "steps": 4, "plan_seconds": 0.4, "physics_seconds": 0.001})
    out = summary_mod.summarise(episodes, "cube_push_stop", tmp_path / "missing.json")
    det, mean = out["modes"]["deterministic"], out["modes"]["mean"]
    assert det["success_rate"]["value"] == 0.5 and mean["success_rate"]["value"] == 1.0
    assert det["steps"]["value"] == (5 + 20) / 2                      # a failure counts the step limit
    assert mean["versus_deterministic"]["success_rate"]["value"] == 1.0
    assert mean["versus_deterministic"]["plan_seconds"]["value"] == 0.0  # slower: never better
    assert "versus_deterministic" not in det and "ppo" not in out


def test_validation_scenes_are_other_pybullet_scenes_with_their_own_goals(tmp_path):
    out = tmp_path / "validation"
    assert sweep.main(TINY + ["--validation", "--out", str(out)]) == 0
    episode = json.loads((out / "episodes.jsonl").read_text())
    assert episode["scene_seed"] == 20_000 and episode["pool_index"] == 0
    assert json.loads((out / "sweep.json").read_text())["scenes"] == "validation"
    dynamics = HRNDynamics.from_checkpoint("cube_push", "cube_push_stop", pool_seeds=(20_000, 20_001))
    scenes = sweep.validation_scenes(sweep.get_task("cube_push_stop"), dynamics, 2)
    assert [s["scene_seed"] for s in scenes] == [20_000, 20_001] and scenes[0]["goal"] != scenes[1]["goal"]
    with pytest.raises(ValueError, match="num-scenes"):
        sweep.validation_scenes(sweep.get_task("cube_push_stop"), dynamics, 3)
def _write_sweep(folder, settings, episodes):
    folder.mkdir()
    (folder / "sweep.json").write_text(json.dumps(settings))
    (folder / "episodes.jsonl").write_text("".join(json.dumps(e) + "\n" for e in episodes))


def test_a_sweep_split_by_modes_is_read_from_its_folders(tmp_path):
    settings = {"task": "cube_push_stop", "planner": {"k": 2}}
    one = {"mode": "deterministic", "seed": 0, "scene": 0, "success": True, "steps": 3}
    other = {**one, "mode": "mean"}
    _write_sweep(tmp_path / "a", settings, [one])
    _write_sweep(tmp_path / "b", settings, [other])
    assert summary_mod.read_sweeps([tmp_path / "a", tmp_path / "b"]) == [one, other]
    _write_sweep(tmp_path / "twice", settings, [one])
    with pytest.raises(ValueError, match="appears twice"):
        summary_mod.read_sweeps([tmp_path / "a", tmp_path / "twice"])
    _write_sweep(tmp_path / "other", {**settings, "planner": {"k": 3}}, [other])
    with pytest.raises(ValueError, match="other settings"):
        summary_mod.read_sweeps([tmp_path / "a", tmp_path / "other"])
    with pytest.raises(FileNotFoundError):
        summary_mod.read_sweeps([tmp_path / "missing"])
