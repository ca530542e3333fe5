"""experiments.scores: each object's errors, and a model's hold from a resting episode's end."""

from pathlib import Path

import torch
from torch_geometric.data import Batch

from experiments.scores import per_object_errors, rest_check
from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import NODE
from hrn_pyg.data.scene_file import read_scene_file
from hrn_pyg.evaluate import per_trajectory_errors

ROOT = Path(__file__).resolve().parents[2]


def test_per_object_errors_split_the_trajectory_error_by_object(tiny_episodes):
    ds = EpisodeWindows(tiny_episodes, "test", horizon=3)
    graph = Batch.from_data_list([ds[0], ds[1]])
    store = graph[NODE]
    truth, prev = store.pos_seq[:, 3], store.pos_seq[:, 2]
    moved = truth.clone()
    first = store.is_leaf & (store.object == 0) & (store.batch == 1)
    moved[first] += torch.tensor([0.0, 0.3, 0.0])  # object 0 of copy 1 shifted 30 cm
    centre = truth[first].mean(0)
    moved[first] = centre + 1.1 * (moved[first] - centre - torch.tensor([0.0, 0.3, 0.0])) + torch.tensor([0.0, 0.3, 0.0])
    per_object = per_object_errors(moved, truth, graph)
    per_copy = per_trajectory_errors(moved, truth, graph, prev, prev)
    objects = int(store.object.max()) + 1
    assert per_object["position"].shape == per_object["shape"].shape == (2 * objects,)
    changed = torch.zeros(2 * objects, dtype=torch.bool)
    changed[objects] = True  # row c * O + o
    assert torch.all(per_object["position"][~changed] == 0) and torch.all(per_object["shape"][~changed] == 0)
    assert per_object["position"][objects] > 0.03 / 3 and per_object["shape"][objects] > 0
    # the copy's error is the leaf-weighted mean of its objects' errors
    leaves = torch.stack([(store.is_leaf & ~store.is_static & (store.batch == 1) & (store.object == o)).sum()
                          for o in range(objects)]).float()
    weighted = (per_object["position"][objects:] * leaves).sum() / leaves.sum()
    assert torch.allclose(weighted, per_copy["position"][1])


def test_rest_check_runs_from_a_resting_end_and_skips_a_moving_one():
    """A scene of objects set down at rest: the shipped generalist holds five steps from its end;
    pushed cubes still sliding at their episode's end: None (nothing to check)."""
    model = load_model("shapes")
    resting = simulate_episode(read_scene_file(ROOT / "data" / "shapes" / "shapes_rest.toml"), 1000, steps=20)
    report = rest_check(model, resting, 5)
    assert report is not None and report["finite"] and report["holds"] and report["rest_drift"] < 0.01
    assert rest_check(model, simulate_episode("cube_collision", 0, steps=10), 5) is None
