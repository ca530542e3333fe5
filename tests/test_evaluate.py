import json

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from hrn_pyg.cli import main
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import NODE
from hrn_pyg.evaluate import per_trajectory_errors, summarise
from hrn_pyg.nn.hrn import HRNConfig
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


def test_evaluate_cli_writes_table_json_and_figure(tiny_episodes, tmp_path, capsys):
    cfg = TrainConfig.for_preset("hrn", data=str(tiny_episodes), out=str(tmp_path / "m"), steps=2, batch_size=1)
    train(cfg, HRNConfig(hidden=16, depth=1, effect_dim=16), progress=False)
    code = main(["evaluate", "--data", str(tiny_episodes), "--model", f"a={tmp_path / 'm' / 'model.pt'}",
                 "--model", f"b={tmp_path / 'm' / 'model.pt'}", "--out", str(tmp_path / "e"),
                 "--horizons", "2,5", "--stride", "3"])
    assert code == 0
    result = json.loads((tmp_path / "e" / "results.json").read_text())
    assert result["results"]["a"] == result["results"]["b"]
    assert np.isfinite(result["results"]["a"]["shape"]["t+5"]["mean"])
    assert "| a |" in (tmp_path / "e" / "table.md").read_text()
    figures = list((tmp_path / "e").glob("rollout_*.png"))
    assert len(figures) == 1 and figures[0].stat().st_size > 1000
    assert main(["evaluate", "--data", str(tiny_episodes), "--model", "nonsense", "--out", str(tmp_path / "x")]) == 2
