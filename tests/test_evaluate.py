import json

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.cli import main
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import NODE
from hrn_pyg.evaluate import per_trajectory_errors, summarise
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.train import TrainConfig, train

def test_errors_are_zero_for_the_truth_and_match_a_hand_case(tiny_episodes):
    ds = EpisodeWindows(tiny_episodes, "test", horizon=3)
    graph = Batch.from_data_list([ds[0], ds[1]])
    truth = graph[NODE].pos_seq[:, 3]
    prev = graph[NODE].pos_seq[:, 2]
    zero = per_trajectory_errors(truth, truth, graph, prev, prev)
    for name, value in zero.items():
        assert value.shape == (2,) and torch.all(value == 0), name
    moved = truth.clone()
    moved[graph[NODE].is_leaf] += torch.tensor([0.1, 0.0, 0.0])  # a rigid shift of every leaf
    err = per_trajectory_errors(moved, truth, graph, prev, prev)
    assert torch.allclose(err["position"], torch.full((2,), 0.01 / 3))
    assert torch.allclose(err["velocity"], torch.full((2,), 0.01 / 3))
    assert torch.allclose(err["shape"], torch.zeros(2), atol=1e-10)  # a shift keeps the shape


def test_summary_mean_and_standard_error():
    s = summarise({"position": {5: np.array([1.0, 3.0])}})
    assert s["position"]["t+5"]["mean"] == 2.0
    assert s["position"]["t+5"]["sem"] == pytest.approx(np.std([1.0, 3.0], ddof=1) / np.sqrt(2))


def _train_tiny(data, out, seed: int):
    """A two-step ``hrn`` model; different seeds give different weights and windows."""
    cfg = TrainConfig.for_preset("hrn", data=str(data), out=str(out), steps=2, batch_size=1, seed=seed)
    train(cfg, HRNConfig(hidden=16, depth=1, effect_dim=16), progress=False)
    return out / "model.pt"


def _expected_summary(model_path, windows: list, horizons: tuple[int, ...]) -> dict[str, dict[str, dict]]:
    """Mean, standard error and count of :func:`per_trajectory_errors` over ``windows``, each window
    rolled out on its own (the CLI batches them all), ``{metric: {"t+h": {mean, sem, n, diverged}}}``."""
    model = load_model(model_path)
    per_window: dict[str, dict[int, list[float]]] = {}
    for window in windows:
        graph = Batch.from_data_list([window])
        store = graph[NODE]
        forces = store.force_seq[:, : max(horizons)].transpose(0, 1)
        with torch.no_grad():
            pred = torch.cat([store.pos[None], rollout(model, graph, max(horizons), forces)])  # x_t .. x_{t+H}
        truth = store.pos_seq.transpose(0, 1)[2:]  # x_t .. x_{t+H}
        for h in horizons:
            errors = per_trajectory_errors(pred[h], truth[h], graph, truth[h - 1], pred[h - 1])
            for metric, value in errors.items():
                per_window.setdefault(metric, {}).setdefault(h, []).append(float(value[0]))
    return {metric: {f"t+{h}": {"mean": float(np.mean(v)), "sem": float(np.std(v, ddof=1) / np.sqrt(len(v))),
                                "n": len(v), "diverged": 0} for h, v in by_h.items()}
            for metric, by_h in per_window.items()}


def test_evaluate_cli_writes_table_json_and_figure(tiny_episodes, tmp_path):
    models = {"a": _train_tiny(tiny_episodes, tmp_path / "a", seed=0),
              "b": _train_tiny(tiny_episodes, tmp_path / "b", seed=1)}
    horizons = (2, 5)
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={models['a']}", "--model",
                 f"b={models['b']}", "--out", str(tmp_path / "e"), "--horizons", "2,5", "--stride", "1"])
    assert code == 0
    result = json.loads((tmp_path / "e" / "results.json").read_text())

    # stride 1: every window of the test split, with room for the longest horizon
    dataset = EpisodeWindows(tiny_episodes, "test", horizon=max(horizons))
    windows = [dataset[i] for i in range(len(dataset))]
    assert result["trajectories"] == len(windows) > 1
    expected = {name: _expected_summary(path, windows, horizons) for name, path in models.items()}
    # the two models really differ, so scoring one in place of the other would show
    assert expected["a"]["position"]["t+5"]["mean"] != pytest.approx(expected["b"]["position"]["t+5"]["mean"],
                                                                     rel=0.05)
    compared = 0
    for name in models:
        got = result["results"][name]
        for metric in ("position", "velocity", "shape"):  # metrics and horizons of both (others may be added)
            for key in expected[name][metric].keys() & got[metric].keys():
                want = expected[name][metric][key]
                assert got[metric][key]["n"] == want["n"], (name, metric, key)
                assert got[metric][key]["mean"] == pytest.approx(want["mean"], rel=1e-5, abs=1e-12), (name, metric, key)
                assert got[metric][key]["sem"] == pytest.approx(want["sem"], rel=1e-5, abs=1e-12), (name, metric, key)
                compared += 1
    assert compared == 2 * 3 * len(horizons)

    assert "| a |" in (tmp_path / "e" / "table.md").read_text()
    figures = list((tmp_path / "e").glob("rollout_*.png"))
    assert len(figures) == 1 and figures[0].stat().st_size > 1000
    assert main(["evaluate", "--data", str(tiny_episodes), "--model", "nonsense", "--out", str(tmp_path / "x")]) == 2
