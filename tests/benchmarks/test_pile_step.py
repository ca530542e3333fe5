"""``benchmarks/pile_step.py``: paired rounds of pybullet and model timing, end to end on a tiny pile."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
MESHES = ROOT / "data" / "shapes" / "meshes"


def test_rounds_alternate_pybullet_and_every_run():
    bench = importlib.import_module("benchmarks.pile_step")
    calls: list[str] = []

    def bullet() -> float:
        calls.append("pybullet")
        return 2.0

    def run(label: str, seconds: float):
        def timed():
            calls.append(label)
            return seconds, torch.full((1,), seconds)
        return timed

    bullet_s, seconds, positions = bench.paired_times(bullet, {"a": run("a", 1.0), "b": run("b", 4.0)}, 3)
    assert calls == ["pybullet", "a", "b"] * 3
    assert bullet_s == [2.0] * 3 and seconds == {"a": [1.0] * 3, "b": [4.0] * 3}
    assert positions["b"].item() == 4.0


def test_the_ratio_is_the_median_of_paired_ratios():
    """A machine that slows down in the middle round slows both sides of that round: the paired
    ratio stays, where the ratio of the two medians would not."""
    bench = importlib.import_module("benchmarks.pile_step")
    summary = bench.paired_summary([1.0, 3.0, 1.0, 1.0], [0.9, 2.7, 0.9, 2.0])
    assert summary["x_pybullet"] == pytest.approx(0.9)
    assert summary["x_pybullet_range"] == pytest.approx([0.9, 2.0])
    assert summary["ms"] == pytest.approx(1e3 * 1.45)


def test_a_tiny_pile_is_timed_against_pybullet(tmp_path, capsys):
    bench = importlib.import_module("benchmarks.pile_step")
    out = tmp_path / "pile.json"
    result = bench.main(["--counts", "2", "--steps", "6", "--repeats", "2", "--meshes",
                         str(MESHES / "random_hull_000.obj"), "--model", "shapes", "--model", "shapes_d4",
                         "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(result))
    (row,) = result["rows"]
    assert row["objects"] == 2 and row["leaves"] > 0
    assert len(row["pybullet_ms_runs"]) == 2 * 2 and row["pybullet_ms"] > 0  # each model its own paired rounds
    assert set(row["models"]["shapes"]) == {"as loaded"}               # one pass a step already
    results = row["models"]["shapes_d4"]
    assert set(results) == {"as loaded", "one pass"}                  # the eight-pass model, and one of its passes
    for timing in [*results.values(), row["models"]["shapes"]["as loaded"]]:
        assert len(timing["ms_runs"]) == 2 and timing["ms"] > 0
        low, high = timing["x_pybullet_range"]
        assert low <= timing["x_pybullet"] <= high
    assert results["one pass"]["mse_to_averaged_last_step"] >= 0
    assert "| objects | leaves | pybullet (ms) |" in capsys.readouterr().out


def test_sizes_are_width_channels_layers():
    bench = importlib.import_module("benchmarks.pile_step")
    assert bench.parse_sizes("48:4:2,32:8:1") == [(48, 4, 2), (32, 8, 1)]
    assert bench.parse_sizes("") == []
    for bad in ("48:4", "48:0:2", "a:4:2", "48:4:2:1"):
        with pytest.raises(SystemExit, match="WIDTH:CHANNELS:LAYERS"):
            bench.parse_sizes(bad)


def test_a_sized_network_keeps_the_config_and_normaliser_its_readout_zeroed():
    from hrn_pyg.checkpoints import load_model
    bench = importlib.import_module("benchmarks.pile_step")
    model = load_model("shapes")
    network = bench.sized_network(model, 16, 2, 1)
    config = network.config
    assert (config.hidden, config.effect_dim, config.vector_channels, config.depth) == (16, 16, 2, 1)
    assert not config.mirror_average and config.pitch_aware == model.config.pitch_aware
    for name, value in model.normalizer.state_dict().items():
        assert torch.equal(network.normalizer.state_dict()[name], value)
    assert all(not p.any() for p in network.state.parameters())
    assert any(p.any() for p in network.collision.parameters())   # the rest is a fresh network


def test_a_tiny_pile_times_the_sizes_too(tmp_path):
    bench = importlib.import_module("benchmarks.pile_step")
    result = bench.main(["--counts", "2", "--steps", "6", "--repeats", "1", "--meshes",
                         str(MESHES / "random_hull_000.obj"), "--sizes", "16:2:1"])
    (row,) = result["rows"]
    timing = row["models"]["shapes"]["fresh 16:2:1"]
    assert timing["ms"] > 0 and len(timing["ms_runs"]) == 1
    assert result["sizes"] == [[16, 2, 1]]


def test_a_model_whose_rules_read_the_contacts_is_compiled_with_them(capsys):
    """The shipped ``shapes`` keeps bodies out of each other, a rule that reads the step's
    contacts: ``--compile`` times its compiled network with the rules after it, and its leaves
    stay within rounding of the eager rollout's over a few steps."""
    bench = importlib.import_module("benchmarks.pile_step")
    result = bench.main(["--counts", "2", "--steps", "6", "--repeats", "1", "--meshes",
                         str(MESHES / "random_hull_000.obj"), "--model", "shapes", "--compile"])
    (row,) = result["rows"]
    assert "compiled_skipped" not in row
    compiled = row["models"]["shapes"]["compiled"]
    assert compiled["ms"] > 0 and compiled["max_abs_diff_to_eager_m"] < 1e-4
    assert "not timed" not in capsys.readouterr().out
