"""``experiments/many_objects.py`` end to end on a tiny case: piles of 2 and 3 procedural meshes,
one short episode each, scored and timed; a second run reuses the episodes it finds."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest

from experiments import scores

ROOT = Path(__file__).resolve().parents[2]
MESHES = ROOT / "data" / "shapes" / "meshes"


def _benchmark():
    return importlib.import_module("experiments.many_objects")


def test_many_objects_scores_and_times_tiny_piles(tmp_path, capsys):
    bench = _benchmark()
    meshes = f"{MESHES / 'random_hull_000.obj'},{MESHES / 'random_hull_001.obj'}"
    out, work = tmp_path / "result.json", tmp_path / "work"
    argv = ["--model", str(ROOT / "hrn_pyg/checkpoints/shapes.pt"), "--counts", "2,3", "--meshes", meshes,
            "--episodes", "1", "--steps", "8", "--horizons", "2,5", "--stride", "1", "--repeats", "1",
            "--work", str(work), "--out", str(out)]
    result = bench.main(argv)
    assert json.loads(out.read_text())["rows"] == json.loads(json.dumps(result["rows"]))
    rows = result["rows"]
    assert [r["objects"] for r in rows] == [2, 3]
    for row in rows:
        assert row["made"] == 1 and row["episodes"] == 1 and row["rejected"] == []
        assert row["windows"] == 8 - 5 - 2 + 1                     # starts 2, 3 with --stride 1
        assert row["leaves"] > 0 and row["pybullet_ms"] > 0 and row["model_ms"] > 0
        for h in (2, 5):
            stats = row["errors"]["position"][f"t+{h}"]
            assert stats["n"] == row["windows"] and stats["mean"] > 0
            first = rows[0]["errors"]["position"][f"t+{h}"]["mean"]
            assert row[f"ratio_position@{h}"] == pytest.approx(stats["mean"] / first)
    assert rows[1]["leaves"] > rows[0]["leaves"]
    assert rows[0]["ratio_position@5"] == 1.0
    table = capsys.readouterr().out
    assert "| objects | leaves | pybullet ms/step | model ms/step |" in table and "| x 2 objects |" in table

    again = bench.main(argv)                                       # the episodes are on disk now
    assert [r["made"] for r in again["rows"]] == [0, 0]
    for first, second in zip(rows, again["rows"]):
        assert second["errors"] == first["errors"]


def test_the_rest_section_checks_piles_that_end_at_rest(tmp_path, capsys, monkeypatch):
    """``--rest-steps``: an episode whose objects are still falling at its end is counted as not at
    rest; one whose end is at rest (here: the rest test made to say so) gets the stability check
    of that many steps, and the table gains the column."""
    bench = _benchmark()
    meshes = f"{MESHES / 'random_hull_000.obj'}"
    argv = ["--model", str(ROOT / "hrn_pyg/checkpoints/shapes.pt"), "--counts", "2", "--meshes", meshes,
            "--episodes", "1", "--steps", "8", "--horizons", "2,5", "--stride", "1", "--repeats", "1",
            "--rest-steps", "3", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "r.json")]
    falling = bench.main(argv)["rows"][0]["rest"]
    assert falling == [{"seed": 0, "at_rest": False}]
    monkeypatch.setattr(scores, "objects_at_rest", lambda truth, obj, mask, count: mask[:count])
    rows = bench.main(argv)["rows"][0]["rest"]
    assert len(rows) == 1 and rows[0]["at_rest"] and rows[0]["finite"] and isinstance(rows[0]["holds"], bool)
    assert "rest: holds / at rest, largest drift" in capsys.readouterr().out
    assert bench.rest_summary([{"at_rest": True, "holds": True, "rest_drift": 0.01},
                               {"at_rest": True, "holds": False, "rest_drift": 0.07},
                               {"at_rest": False}]) == "1 / 2 (1 not at rest), drift <= 0.07 m"
    with pytest.raises(SystemExit):
        bench.main(argv[:-4] + ["--rest-steps", "-1"] + argv[-4:])
