"""The one-model mode of ``experiments/accuracy_vs_time.py`` end to end on a tiny case: two
pitches of the generalist's validation scene, one short episode each, scored and timed with the
plain eight-pass ``shapes_d4`` model (warned about the pitch it never saw), with the same model
widened into a pitch-aware one (the same errors at the reference pitch, others where the pitch
differs), and with the shipped ``shapes``, which reads the pitch (no warning at either)."""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path

import pytest

from hrn_pyg.checkpoints import load_model
from hrn_pyg.nn.widen import widen_to_pitch_aware



def _benchmark(monkeypatch):
    return importlib.import_module("experiments.accuracy_vs_time")


def _argv(tmp_path: Path, out: str, model: str = "shapes_d4") -> list[str]:
    return ["--model", model, "--pitches", "0.05,0.08", "--episodes", "1", "--episode-steps", "8",
            "--horizons", "2,5", "--stride", "1", "--repeats", "1", "--work", str(tmp_path / "work"),
            "--out", str(tmp_path / out)]


def test_one_model_across_pitches_plain_then_pitch_aware(tmp_path, monkeypatch, capsys):
    bench = _benchmark(monkeypatch)
    plain = bench.main(_argv(tmp_path, "plain.json"))
    rows = {r["pitch"]: r for r in plain["rows"]}
    assert list(rows) == [0.05, 0.08]
    assert rows[0.08]["leaves"] < rows[0.05]["leaves"]                    # the same scene, coarser
    for row in rows.values():
        assert row["made"] == 1 and row["windows"] == 8 - 5 - 2 + 1
        assert row["pybullet_ms"] > 0 and row["model_ms"] > 0
        for m in ("position", "shape"):
            for h in (2, 5):
                assert row["errors"][m][f"t+{h}"]["n"] == row["windows"]
                assert row[f"ratio_{m}@{h}"] == pytest.approx(
                    row["errors"][m][f"t+{h}"]["mean"] / rows[0.05]["errors"][m][f"t+{h}"]["mean"])
    assert rows[0.05]["outside"] is None and "pitch is 0.08 m" in rows[0.08]["outside"]
    captured = capsys.readouterr()
    assert "pitch is 0.08 m" in captured.err                              # the warning is not silenced
    assert "| pitch (m) | leaves | pybullet ms/step | model ms/step |" in captured.out

    shapes_d4 = load_model("shapes_d4")
    wide = widen_to_pitch_aware(shapes_d4).eval()
    wide.domain = dataclasses.replace(shapes_d4.domain, pitch_range=(0.025, 0.08))
    wide.checkpoint_name = "shapes_d4 widened"
    monkeypatch.setattr(bench, "load_model", lambda name: wide)
    aware = bench.main(_argv(tmp_path, "aware.json"))
    again = {r["pitch"]: r for r in aware["rows"]}
    assert [r["made"] for r in again.values()] == [0, 0]                  # the episodes were kept
    assert all(r["outside"] is None for r in again.values())              # inside its pitch range
    assert again[0.05]["errors"] == rows[0.05]["errors"]                  # zero pitch column at 0.05
    assert again[0.08]["errors"]["position"] != rows[0.08]["errors"]["position"]  # it reads the pitch

    monkeypatch.setattr(bench, "load_model", load_model)
    shipped = {r["pitch"]: r for r in bench.main(_argv(tmp_path, "shipped.json", "shapes"))["rows"]}
    assert [r["outside"] for r in shipped.values()] == [None, None]
    assert "pitch is" not in capsys.readouterr().err


def test_compile_adds_the_fixed_shape_steps_time_beside_pybullets(tmp_path, monkeypatch, capsys):
    """``--compile``: each pitch also times the rollout as fixed-shape steps (here uncompiled, the
    same steps without the compiler's minute), its median over the repeats, and its ratio to
    pybullet's time at that pitch."""
    from hrn_pyg.data.graph import NODE
    from hrn_pyg.sim.fixed_shape import FixedShapeConfig, FixedShapeSimulator

    bench = _benchmark(monkeypatch)
    made = []

    def fixed_shape_rollout(model, state, steps):
        simulator = FixedShapeSimulator(model, state, FixedShapeConfig(compile=False))
        made.append(state)
        return 1.0, lambda: (0.002 * len(made), simulator.rollout(steps).pos)

    monkeypatch.setattr(bench, "compiled_rollout", fixed_shape_rollout)
    argv = _argv(tmp_path, "compiled.json")
    argv[argv.index("--repeats") + 1] = "3"
    result = bench.main(argv + ["--compile"])
    assert result["compile"] and len(made) == 2                          # one simulator per pitch
    for i, row in enumerate(result["rows"]):
        assert row["compiled_ms_runs"] == [2.0 * (i + 1)] * 3 and row["compiled_ms"] == 2.0 * (i + 1)
        assert row["compiled_x_pybullet"] == pytest.approx(row["compiled_ms"] / row["pybullet_ms"])
        assert row["compile_s"] == 1.0
    assert made[0][NODE].pos.shape[0] > made[1][NODE].pos.shape[0]      # 0.05 m has more leaves than 0.08
    assert "| compiled ms/step | compiled / pybullet |" in capsys.readouterr().out


def test_a_model_the_fixed_shape_steps_refuse_is_timed_eagerly_and_says_why(tmp_path, monkeypatch, capsys):
    bench = _benchmark(monkeypatch)

    def refused(model, state, steps):
        raise ValueError("fixed_shape_rollout: this model moves leaves out of the objects they enter")

    monkeypatch.setattr(bench, "compiled_rollout", refused)
    result = bench.main(_argv(tmp_path, "refused.json") + ["--compile"])
    for row in result["rows"]:
        assert row["compiled_skipped"].startswith("fixed_shape_rollout: this model moves leaves")
        assert "compiled_ms" not in row and row["model_ms"] > 0
    out = capsys.readouterr().out
    assert "compiled: not timed (fixed_shape_rollout" in out and "compiled ms/step" not in out
