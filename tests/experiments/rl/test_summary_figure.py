import json

import pytest
from test_summary import RUNS, _save_policy, _write_runs

import experiments.rl.summary_figure as summary_figure
from experiments.rl.summary import main as summary_main
from experiments.rl.summary import task_summary
from experiments.rl.summary_figure import MODE_COLORS, plot_summary
from hrn_pyg.utils.files import json_safe


def _summary(root):
    _write_runs(root)
    return json.loads(json.dumps(json_safe(task_summary(root, "tower", resamples=50))))


@pytest.fixture
def drawn(monkeypatch):
    """The figures :func:`plot_summary` saves, kept open to be read back."""
    figures = []
    save = summary_figure.save_figure

    def keep(fig, path, **kwargs):
        figures.append(fig)
        save(fig, path, **kwargs)

    monkeypatch.setattr(summary_figure, "save_figure", keep)
    return figures


def _lines(ax):
    """``{colour: [(x, y), ...]}`` of the lines of one panel, in drawing order."""
    out = {}
    for line in ax.get_lines():
        out.setdefault(line.get_color(), []).append((list(line.get_xdata()), list(line.get_ydata())))
    return out


def assert_figure_shows(fig, summary):
    """The four panels hold the summary's numbers: IQM curves, the profile and the probability
    of improvement of every mode, each in its mode's colour, with a band per curve."""
    assert len(fig.axes) == 4
    modes = list(summary["modes"])
    curves, baseline = summary["iqm_curves"], summary["baseline"]
    success, lengths, profile, versus = (_lines(ax) for ax in fig.axes)
    for mode in modes:
        colour = MODE_COLORS[mode]
        closed = curves[mode]["closed_loop_success"]
        assert success[colour] == [([f / 1000 for f in closed["frames"]], closed["iqm"])]
        assert lengths[colour] == [(curves[mode]["episode_length"]["update"], curves[mode]["episode_length"]["iqm"])]
        p = summary["performance_profiles"]["closed_loop_success_auc"]["modes"][mode]
        assert profile[colour] == [(p["tau"], p["fraction"])]
    for ax in fig.axes[:3]:
        assert len(ax.collections) == len(modes)                    # one band per mode
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend == [f"{m} ({summary['modes'][m]['n']})" for m in modes]
    others = [m for m in modes if m != baseline]
    for mode in others:
        poi = summary["versus_" + baseline][mode]["closed_loop_success_auc"]
        row = others.index(mode)
        assert versus[MODE_COLORS[mode]] == [([poi["low"], poi["high"]], [row, row]), ([poi["value"]], [row])]
    assert [t.get_text() for t in fig.axes[3].get_yticklabels()] == others


def test_plot_summary_draws_from_the_json_alone(tmp_path, drawn):
    summary = _summary(tmp_path / "runs")
    assert summary["statistics"]["deterministic"]["pybullet_frames_to_50"]["value"] is None  # nulls are drawn around
    png = tmp_path / "summary.png"
    plot_summary(summary, png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob("*.tmp*"))  # written atomically
    assert len(drawn) == 1
    assert_figure_shows(drawn[0], summary)


def test_plot_summary_refuses_what_is_not_a_summary(tmp_path):
    with pytest.raises(ValueError, match="not a sweep summary: no 'iqm_curves'"):
        plot_summary({"task": "tower", "modes": {}}, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_summary_command_draws_the_figure(tmp_path, drawn):
    _write_runs(tmp_path)
    for mode, seeds in RUNS.items():
        for seed in seeds:
            _save_policy(tmp_path / mode / f"seed{seed}", 4, 4)
    png = tmp_path / "fig" / "s.svg"
    png.parent.mkdir()
    assert summary_main(["--task", "tower", "--runs", str(tmp_path), "--out", str(tmp_path / "s.json"),
                 "--resamples", "20", "--figure", str(png)]) == 0
    assert png.read_text().lstrip().startswith("<?xml")
    assert len(drawn) == 1
    assert_figure_shows(drawn[0], json.loads((tmp_path / "s.json").read_text()))
