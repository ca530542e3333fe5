"""``benchmarks/many_objects.py`` end to end on a tiny case: piles of 2 and 3 procedural meshes,
one short episode each, scored and timed; a second run reuses the episodes it finds."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MESHES = ROOT / "data" / "shapes" / "meshes"


def _benchmark():
    spec = importlib.util.spec_from_file_location("many_objects", ROOT / "benchmarks" / "many_objects.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
