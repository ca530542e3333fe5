"""``benchmarks/shape_loss_cost.py``: both ways of the shape loss time a step on the same batches
with the same gradients, end to end on tiny cube_collision episodes."""

from __future__ import annotations

import importlib
import json
import sys

import pytest


@pytest.fixture(scope="module")
def bench():
    return importlib.import_module("benchmarks.shape_loss_cost")


def test_the_two_ways_agree_and_are_timed(bench, tiny_episodes, tmp_path, monkeypatch, capsys):
    out = tmp_path / "cost.json"
    monkeypatch.setattr(sys, "argv", ["shape_loss_cost.py", "--model", "wedge", "--data", str(tiny_episodes),
                                      "--batch-size", "2", "--seq-len", "2", "--steps", "1", "--out", str(out)])
    bench.main()
    result = json.loads(out.read_text())
    assert len(result["steps"]) == 1 and result["median_skip_s"] > 0 and result["median_every_pair_s"] > 0
    assert result["steps"][0]["max_relative_gradient_difference"] < 1e-5
    assert "| rigid pairs skipped (the package) |" in capsys.readouterr().out


def test_a_model_without_the_rigid_fit_is_refused(bench, tiny_episodes, tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["shape_loss_cost.py", "--model", "cube_collision_hrn", "--data",
                                      str(tiny_episodes), "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match="has no rigid fit"):
        bench.main()
