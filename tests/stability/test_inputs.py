"""NaN or inf in any input gives a ValueError naming the field, before any compute."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from stability_helpers import fitted_model
from torch_geometric.data import Batch
from toy_scene import (
    LEAF_OBJECT,
    MATERIAL,
    PARENT,
    STIFFNESS,
    structure,
    toy_scene,
    trajectory,
)

import hrn_pyg.data.graph as graph_module
from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import NODE, build_structure, set_state
from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.step import build_inputs, step

BAD = (float("nan"), float("inf"), float("-inf"))


def _poison(x: torch.Tensor, value: float, row: int = 3) -> torch.Tensor:
    x = x.clone()
    x[row, 1] = value
    return x


@pytest.mark.parametrize("value", BAD)
@pytest.mark.parametrize("field", ["prev_prev_pos", "prev_pos", "pos", "force"])
def test_set_state_names_the_bad_field_before_any_compute(field, value, monkeypatch):
    leaves = trajectory(2)
    args = {"prev_prev_pos": leaves[0], "prev_pos": leaves[1], "pos": leaves[2], "force": torch.zeros(14, 3)}
    args[field] = _poison(args[field], value)

    def no_compute(*a, **k):
        raise AssertionError("computed before validating")

    base = structure()
    monkeypatch.setattr(graph_module, "leaf_to_ancestor_mean", no_compute)
    monkeypatch.setattr(graph_module, "collision_edges", no_compute)
    with pytest.raises(ValueError, match=rf"\b{field}\b.*NaN or infinite"):
        set_state(base, args["prev_prev_pos"], args["prev_pos"], args["pos"], radius=0.08, force=args["force"])


@pytest.mark.parametrize("value", BAD)
def test_build_structure_rejects_bad_mass_and_stiffness(value):
    mass = torch.full((14,), 0.1)
    with pytest.raises(ValueError, match="leaf_mass"):
        build_structure(PARENT, _poison(mass[:, None].expand(14, 3), value)[:, 1].contiguous(), LEAF_OBJECT,
                        MATERIAL, STIFFNESS)
    bad = STIFFNESS.clone()
    bad[1] = value
    with pytest.raises(ValueError, match="object_stiffness"):
        build_structure(PARENT, mass, LEAF_OBJECT, MATERIAL, bad)


@pytest.mark.parametrize("value", BAD)
def test_rollout_rejects_bad_forces_and_states(value):
    model = fitted_model()
    g = toy_scene()
    n = g[NODE].num_nodes
    forces = torch.zeros(4, n, 3)
    forces[2, 5, 0] = value  # a bad value at a later step is still caught before step 0
    with pytest.raises(ValueError, match="forces contains NaN"):
        rollout(model, g, 4, forces)
    for field in ("pos", "prev_pos", "prev_prev_pos"):
        bad = g.clone()
        bad[NODE][field] = _poison(bad[NODE][field], value)
        with pytest.raises(ValueError, match=field):
            rollout(model, bad, 2)
        with pytest.raises(ValueError, match=field):
            build_inputs(model, bad)
    with pytest.raises(ValueError, match="force contains NaN"):
        step(model, g, _poison(torch.zeros(n, 3), value))
    bad = g.clone()
    bad[NODE].force = _poison(bad[NODE].force, value)
    with pytest.raises(ValueError, match="force"):
        step(model, bad)


@pytest.mark.parametrize("value", BAD)
def test_sample_rejects_bad_state_and_forces(value):
    model = fitted_model()
    g = toy_scene()
    bad = g.clone()
    bad[NODE].prev_pos = _poison(bad[NODE].prev_pos, value)
    with pytest.raises(ValueError, match="prev_pos"):
        sample(model, bad, 2, 3, 0.1)
    forces = torch.zeros(3, 14, 3)
    forces[0, 0, 2] = value
    with pytest.raises(ValueError, match="forces"):
        sample(model, g, 2, 3, 0.1, forces=forces)


@pytest.mark.parametrize("value", BAD)
def test_hierarchy_rejects_bad_positions(value):
    x = trajectory(0)[0].double().numpy()
    x[2, 0] = value
    with pytest.raises(ValueError, match="positions"):
        build_hierarchy(x, np.ones(14), LEAF_OBJECT.numpy())


@pytest.mark.parametrize("key", ["positions", "forces", "leaf_mass", "object_stiffness"])
def test_dataset_rejects_an_episode_file_with_nan(tmp_path, key):
    steps, leaves = 8, trajectory(8)
    episode = {
        "positions": leaves.numpy(), "forces": np.zeros((steps, 14, 3), np.float32),
        "leaf_mass": np.full(14, 0.1, np.float32), "leaf_object": LEAF_OBJECT.numpy(),
        "object_material": MATERIAL.numpy(), "object_stiffness": STIFFNESS.numpy(),
        "hierarchy_parent": PARENT.numpy(), "seed": np.array(0), "scene": np.array("toy"),
        "params": np.array("{}"), "dt": np.array(1 / 30),
    }
    episode[key] = episode[key].copy()
    episode[key].reshape(-1)[0] = np.nan
    np.savez(tmp_path / "episode_000000.npz", **episode)  # written raw: save_episode would refuse it
    dataset = EpisodeWindows(tmp_path, "train", horizon=1)
    with pytest.raises(ValueError, match=key):
        dataset[0]


def test_a_batched_graph_is_checked_too():
    model = fitted_model()
    g = Batch.from_data_list([toy_scene(seed=0), toy_scene(seed=1)])
    g[NODE].pos = _poison(g[NODE].pos, float("nan"), row=20)
    with pytest.raises(ValueError, match="pos"):
        rollout(model, g, 1)
