"""Long-horizon evaluation, the rest metrics and ``--device`` of ``hrn-pyg evaluate``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.cli import main
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.io import load_episode, save_episode
from hrn_pyg.evaluate import (
    episode_start_windows,
    evaluate_long,
    evaluate_model,
    guarded_rollout,
    horizon_label,
    select_windows,
    summarise,
    summarise_long,
)
from hrn_pyg.evaluate.rest import (
    REST_SPEED,
    REST_STEPS,
    ground_depth,
    object_centroids,
    objects_at_rest,
    rest_drift,
    rest_height_error,
    rest_metrics,
)
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.train import TrainConfig, train
from hrn_pyg.utils.device import default_device, resolve_device


def _steps(folder: Path, seed: int = 9) -> int:
    """``S`` of one episode of ``folder`` (the tiny test episode by default)."""
    return int(load_episode(folder / f"episode_{seed:06d}.npz")["forces"].shape[0])

# ---------------------------------------------------------------- rest metrics on hand-made tensors


def _hand_scene(steps: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ground truth ``[steps, 6, 3]`` of three 2-leaf objects: 0 resting at z=0.05 the whole
    time, 1 sliding 1 cm per step along x, 2 static (a wedge) 1 cm below ground."""
    t = torch.arange(steps, dtype=torch.float64)[:, None]
    truth = torch.zeros(steps, 6, 3, dtype=torch.float64)
    truth[:, 0] = torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64)
    truth[:, 1] = torch.tensor([0.1, 0.0, 0.05], dtype=torch.float64)
    truth[:, 2:4, 2] = 0.05
    truth[:, 2:4, 0] = torch.tensor([0.5, 0.6], dtype=torch.float64) + 0.01 * t
    truth[:, 4:6] = torch.tensor([[1.0, 0.0, -0.01], [1.1, 0.0, -0.01]], dtype=torch.float64)
    obj = torch.tensor([0, 0, 1, 1, 2, 2])
    movable = torch.tensor([True, True, True, True, False, False])
    return truth, obj, movable, t


def test_ground_depth_of_a_sinking_object_is_its_lowest_leaf_ignoring_static_leaves():
    truth, obj, movable, t = _hand_scene()
    pred = truth.clone()
    pred[:, 0, 2] = 0.05 - 0.08 * t[:, 0] / 7  # leaf 0 sinks to z = -0.03 at the last step
    group = torch.tensor([0, 0, 1, 1, 1, 1])  # two trajectories; the static leaves sit at z = -0.01
    depth = ground_depth(pred, movable, group, num_groups=2)
    assert torch.allclose(depth, torch.tensor([0.03, 0.0], dtype=torch.float64))
    assert float(ground_depth(truth, movable, group, 2).max()) == 0.0  # static leaves excluded
    everything = ground_depth(truth, torch.ones(6, dtype=torch.bool), group, 2)
    assert torch.allclose(everything, torch.tensor([0.0, 0.01], dtype=torch.float64))


def test_rest_height_error_and_drift_count_only_objects_at_rest():
    truth, obj, movable, t = _hand_scene()
    pred = truth.clone()
    pred[:, 0:2, 2] += 0.02  # the resting object predicted 2 cm too high
    pred[:, 0:2, 0] += 0.001 * t  # ... and creeping 1 mm per step along x
    pred[:, 2:4, 2] += 0.5  # the moving object far off: must not count
    rest = rest_metrics(pred, truth, obj, movable, group=torch.zeros(6, dtype=torch.long),
                        num_objects=3, num_groups=1)
    assert rest.at_rest.tolist() == [True, False, False]  # moving and static objects excluded
    assert rest.height_error[rest.at_rest].tolist() == pytest.approx([0.02])
    assert rest.drift[rest.at_rest].tolist() == pytest.approx([0.001 * REST_STEPS])
    assert rest.depth.tolist() == [0.0] and rest.truth_depth.tolist() == [0.0]


def test_rest_needs_every_leaf_slow_over_only_the_last_steps():
    steps = REST_STEPS + 4
    truth = torch.zeros(steps, 3, 3, dtype=torch.float64)
    # object 0: fell fast until REST_STEPS steps before the end, then still
    truth[: steps - REST_STEPS, 0, 2] = torch.linspace(1.0, 0.0, steps - REST_STEPS, dtype=torch.float64)
    # object 1: one leaf still, the other creeping just under / over the threshold
    truth[:, 2, 0] = 0.9 * REST_SPEED * torch.arange(steps, dtype=torch.float64)
    obj = torch.tensor([0, 1, 1])
    movable = torch.ones(3, dtype=torch.bool)
    assert objects_at_rest(truth, obj, movable, num_objects=3).tolist() == [True, True, False]  # 2: no leaf
    truth[:, 2, 0] *= 1.2 / 0.9
    assert objects_at_rest(truth, obj, movable, num_objects=2).tolist() == [True, False]
    with pytest.raises(ValueError, match="at least 2 states"):
        objects_at_rest(truth[:1], obj, movable, 2)


def test_centroids_are_mass_weighted_and_height_error_uses_the_last_state():
    pos = torch.tensor([[[0.0, 0.0, 0.1], [0.04, 0.0, 0.1]]])  # [1, 2, 3]
    obj = torch.tensor([0, 0])
    c = object_centroids(pos, obj, 1, mass=torch.tensor([1.0, 3.0]))
    assert c[0, 0].tolist() == pytest.approx([0.03, 0.0, 0.1])
    truth = torch.cat([pos, pos])  # two states
    pred = truth.clone()
    pred[0, :, 2] += 1.0  # an early error does not count
    pred[1, :, 2] -= 0.02
    assert rest_height_error(pred, truth, obj, 1).tolist() == pytest.approx([0.02])
    assert rest_drift(pred, obj, 1, steps=10).tolist() == pytest.approx([0.0])  # K clipped to S-1


# ------------------------------------------------------------------------------ horizons and windows


def test_horizon_labels():
    assert horizon_label(50, np.array([50, 50])) == "t+50"
    assert horizon_label(50, np.array([47, 47])) == "t+47 (end)"
    assert horizon_label(100, np.array([40, 100])) == "t+40..100 (end)"


@pytest.fixture(scope="module")
def tiny_model(tiny_episodes, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("long_model")
    cfg = TrainConfig.for_preset("hrn", data=str(tiny_episodes), out=str(out), steps=2, batch_size=1)
    train(cfg, HRNConfig(hidden=16, depth=1, effect_dim=16), progress=False)
    return out / "model.pt"


@pytest.fixture(scope="module")
def mixed_lengths(tiny_episodes, tmp_path_factory) -> Path:
    """The tiny folder plus test episode 19: episode 9 cut to 10 steps."""
    folder = tmp_path_factory.mktemp("mixed")
    for path in tiny_episodes.glob("episode_*.npz"):
        shutil.copy(path, folder / path.name)
    episode = load_episode(tiny_episodes / "episode_000009.npz")
    episode["positions"] = episode["positions"][:11]
    episode["forces"] = episode["forces"][:10]
    episode["seed"] = np.asarray(19)
    save_episode(folder / "episode_000019.npz", episode)
    return folder


def test_start_windows_cover_each_whole_episode(mixed_lengths):
    windows = episode_start_windows(mixed_lengths, "test")
    assert [int(w.episode_seed) for w in windows] == [9, 19]
    assert [int(w.start_step) for w in windows] == [2, 2]
    steps = _steps(mixed_lengths)
    assert [w["particle"].force_seq.shape[1] for w in windows] == [steps - 2, 8]
    assert [w["particle"].pos_seq.shape[1] for w in windows] == [steps + 1, 11]
    episode = load_episode(mixed_lengths / "episode_000009.npz")
    leaves = windows[0]["particle"].is_leaf
    assert torch.equal(windows[0]["particle"].pos_seq[leaves].transpose(0, 1),
                       torch.from_numpy(episode["positions"]).float())
    assert len(episode_start_windows(mixed_lengths, "test", limit=1)) == 1


def test_long_horizons_clip_to_each_episodes_end_and_match_the_short_path(mixed_lengths, tiny_model):
    model = load_model(tiny_model)
    windows = episode_start_windows(mixed_lengths, "test")
    result = evaluate_long(model, windows, (5, 50, 100))
    end = _steps(mixed_lengths) - 2
    assert result["steps"][5].tolist() == [5, 5]
    assert result["steps"][50].tolist() == [end, 8] and result["steps"][100].tolist() == [end, 8]
    for m, by_h in result["errors"].items():
        assert np.array_equal(by_h[50], by_h[100]), m
        assert np.all(np.isfinite(by_h[50])) and by_h[50].shape == (2,)
    # the same numbers as Table 1's code path on the same start window, at h=5 and at the end
    full = EpisodeWindows(mixed_lengths, "test", horizon=end)
    reference = evaluate_model(model, [full[0]], (5, end))
    for m in result["errors"]:
        assert result["errors"][m][5][0] == pytest.approx(reference[m][5][0], rel=1e-6, abs=1e-12)
        assert result["errors"][m][50][0] == pytest.approx(reference[m][end][0], rel=1e-6, abs=1e-12)
    assert result["ground_depth"].shape == (2,) and np.all(result["ground_depth"] >= 0)
    summary = summarise_long(result)
    assert summary["long"]["position"]["t+50"]["label"] == f"t+8..{end} (end)"
    assert summary["long"]["position"]["t+5"]["label"] == "t+5"
    assert summary["rest"]["ground_depth"]["n"] == 2


# ---------------------------------------------------------------------------- diverged rollouts


#: a trained model, whose response to a force near float32's largest overflows in that step
#: (a two-step tiny model's does not: it stays near 1e35)
SHIPPED = Path(__file__).resolve().parents[1] / "hrn_pyg" / "checkpoints" / "cube_collision.pt"


def _poisoned(windows: list, which: int, step: int) -> list:
    """Copies of ``windows`` whose window ``which`` gets a force near float32's largest at ``step``
    (0-based), so with :data:`SHIPPED` its rollout leaves the finite numbers there and only there."""
    out = [w.clone() for w in windows]
    out[which]["particle"].force_seq[:, step] = 3e38
    return out


def test_a_diverged_window_is_counted_and_the_others_are_scored_as_alone(mixed_lengths):
    model = load_model(SHIPPED)
    clean = select_windows(EpisodeWindows(mixed_lengths, "test", horizon=6), 1, 4)
    assert len(clean) == 4
    windows = _poisoned(clean, which=2, step=3)
    pred, diverged_at = guarded_rollout(model, windows, 6)
    assert diverged_at.tolist() == [0, 0, 4, 0]  # steps 1..3 finite, step 4 not
    counts = [w["particle"].num_nodes for w in windows]
    bad = slice(sum(counts[:2]), sum(counts[:3]))
    assert torch.isfinite(pred[:3, bad]).all() and torch.isnan(pred[3:, bad]).all()
    keep = [0, 1, 3]
    assert torch.isfinite(pred[:, [i for i in range(pred.shape[1]) if not bad.start <= i < bad.stop]]).all()
    errors = evaluate_model(model, windows, (2, 6))
    alone = evaluate_model(model, [clean[i] for i in keep], (2, 6))
    for m in errors:
        assert np.isfinite(errors[m][2]).all()  # before the failing step every window counts
        assert np.isnan(errors[m][6][2]) and np.allclose(errors[m][6][keep], alone[m][6], rtol=1e-5, atol=1e-12)
    summary = summarise(errors)
    assert summary["position"]["t+6"]["n"] == 3 and summary["position"]["t+6"]["diverged"] == 1
    assert summary["position"]["t+2"]["n"] == 4 and summary["position"]["t+2"]["diverged"] == 0
    assert summary["position"]["t+6"]["mean"] == pytest.approx(float(np.mean(alone["position"][6])), rel=1e-5)


def test_long_evaluation_reports_where_a_whole_episode_diverged(mixed_lengths):
    model = load_model(SHIPPED)
    windows = _poisoned(episode_start_windows(mixed_lengths, "test"), which=1, step=2)
    result = evaluate_long(model, windows, (5, 50))
    assert result["diverged_at"].tolist() == [0, 3]
    assert np.isfinite(result["ground_depth"][0]) and np.isnan(result["ground_depth"][1])
    summary = summarise_long(result)
    assert summary["long"]["position"]["t+5"]["diverged"] == 1
    assert summary["rest"]["ground_depth"]["n"] == 1 and summary["rest"]["ground_depth"]["diverged"] == 1


# ------------------------------------------------------------------------------------------ the CLI


def _spy_on_evaluation(monkeypatch) -> list[tuple[str, torch.device, torch.device]]:
    """Per call of Table 1's and the long evaluation: which, the model's device, the device asked."""
    import hrn_pyg.evaluate as evaluate_module

    calls = []
    for name in ("evaluate_model", "evaluate_long"):
        def spy(model, starts, horizons, device="cpu", _name=name, _f=getattr(evaluate_module, name)):
            calls.append((_name, next(model.parameters()).device, torch.device(device)))
            return _f(model, starts, horizons, device)

        monkeypatch.setattr(evaluate_module, name, spy)
    return calls


def test_evaluate_cli_long_table_and_device_cpu(tiny_episodes, tiny_model, tmp_path, capsys, monkeypatch):
    """The default device is made ``meta`` here: a command that ignored ``--device cpu`` would
    evaluate there (and fail); both evaluations must run with the model on the CPU."""
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("meta"))
    calls = _spy_on_evaluation(monkeypatch)
    out = tmp_path / "e"
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={tiny_model}", "--out", str(out),
                 "--horizons", "2,5", "--stride", "3", "--long-horizons", "8,50,100", "--device", "cpu",
                 "--no-figure"])
    assert code == 0
    cpu = torch.device("cpu")
    assert calls == [("evaluate_model", cpu, cpu), ("evaluate_long", cpu, cpu)]
    printed = capsys.readouterr().out
    print(printed)  # shown with -s: the table format of the report
    result = json.loads((out / "results.json").read_text())
    assert result["device"] == "cpu"
    end = _steps(tiny_episodes) - 2
    assert result["long_results"]["a"]["position"]["t+8"]["label"] == "t+8"
    assert result["long_results"]["a"]["position"]["t+100"]["label"] == f"t+{end} (end)"
    assert result["rest"]["a"]["ground_depth"]["n"] == result["long_trajectories"] == 1
    assert set(result["rest"]["a"]) == {"ground_depth", "rest_height_error", "rest_drift"}
    table = (out / "table.md").read_text()
    header = [line for line in table.splitlines() if line.startswith("| scene") and "rest drift" in line]
    assert len(header) == 1 and header[0].count(f"t+{end} (end)") == 3  # t+50 and t+100 share a column
    assert "position MSE t+8 |" in header[0] and table in printed
    # Table 1 is computed exactly as before the long horizons existed
    windows = select_windows(EpisodeWindows(tiny_episodes, "test", horizon=5), 3, None)
    before = summarise(evaluate_model(load_model(tiny_model), windows, (2, 5)))
    assert result["results"]["a"] == before


def test_evaluate_cli_device_meta_is_refused_in_one_line(tiny_episodes, tiny_model, tmp_path, monkeypatch, capsys):
    """``--device meta`` is no device the package runs on: one line, exit 2, nothing evaluated or
    written."""
    calls = _spy_on_evaluation(monkeypatch)
    out = tmp_path / "e"
    assert main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={tiny_model}", "--out", str(out),
                 "--horizons", "2", "--stride", "3", "--device", "meta", "--no-figure"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "meta" in err[0]
    assert calls == [] and not (out / "results.json").exists()


def test_evaluate_cli_rejects_an_unknown_device_in_one_line(tiny_episodes, tmp_path, capsys):
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={tmp_path / 'missing.pt'}",
                 "--out", str(tmp_path / "x"), "--device", "nonsense"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "unknown device 'nonsense'" in err


def test_evaluate_cli_rejects_cuda_without_cuda(tiny_episodes, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={tmp_path / 'missing.pt'}",
                 "--out", str(tmp_path / "x"), "--device", "cuda"])
    assert code == 2
    assert "cuda requested but torch.cuda.is_available() is False" in capsys.readouterr().err


# ------------------------------------------------------------------------------------ device helper


def test_resolve_device(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(None) == default_device()
    with pytest.raises(ValueError, match=r"^unknown device 'nonsense'"):
        resolve_device("nonsense")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert default_device() == torch.device("cpu") and resolve_device("") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"^cuda requested but torch\.cuda\.is_available\(\) is False$"):
        resolve_device("cuda:0")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert default_device() == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ValueError, match="only 1 CUDA device"):
        resolve_device("cuda:3")
