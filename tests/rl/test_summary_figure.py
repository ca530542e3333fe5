import json

import pytest
from test_summary import RUNS, _save_policy, _write_runs

from hrn_pyg.cli import main
from hrn_pyg.rl.stats import json_safe
from hrn_pyg.rl.summary import task_summary
from hrn_pyg.rl.summary_figure import plot_summary


def _summary(root):
    _write_runs(root)
    return json.loads(json.dumps(json_safe(task_summary(root, "tower", resamples=50))))


def test_plot_summary_draws_from_the_json_alone(tmp_path):
    summary = _summary(tmp_path / "runs")
    assert summary["statistics"]["deterministic"]["pybullet_frames_to_50"]["value"] is None  # nulls are drawn around
    png = tmp_path / "summary.png"
    plot_summary(summary, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.tmp*"))  # written atomically


def test_plot_summary_refuses_what_is_not_a_summary(tmp_path):
    with pytest.raises(ValueError, match="not a sweep summary: no 'iqm_curves'"):
        plot_summary({"task": "tower", "modes": {}}, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_summary_command_draws_the_figure(tmp_path):
    _write_runs(tmp_path)
    for mode, seeds in RUNS.items():
        for seed in seeds:
            _save_policy(tmp_path / mode / f"seed{seed}", 4, 4)
    png = tmp_path / "fig" / "s.svg"
    png.parent.mkdir()
    assert main(["rl", "summary", "--task", "tower", "--runs", str(tmp_path), "--out", str(tmp_path / "s.json"),
                 "--resamples", "20", "--figure", str(png)]) == 0
    assert png.read_text().lstrip().startswith("<?xml")
