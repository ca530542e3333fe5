"""Rollouts of a pitch-aware model over a batch of scenes at different pitches: each scene
rolls out as it does alone, sleeping objects included; the fixed-shape steps refuse a mix."""

import pytest
import torch
from toy_scene import structure, toy_window, trajectory
from torch_geometric.data import Batch

from hrn_pyg.data.graph import COLLISION, NODE, leaf_collision_edges, set_pitch, set_state
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.sim.fixed_shape import fixed_shape_rollout
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.sleeping import SleepConfig, next_collision_edges


def _model(**kw) -> HRN:
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=16, depth=2, effect_dim=8, pitch_aware=True, **kw))
    windows = [set_pitch(toy_window(4, seed=s), 0.05) for s in range(3)]
    fit_normalizer(windows, model.normalizer, reference_pitch=0.05)
    return model.eval()


def _scene(pitch: float, scale: float, seed: int = 0, still_square: bool = False):
    """The toy scene at ``pitch``, ``scale`` times as large; ``still_square``: the rigid square
    out of reach and at rest (it starts asleep while the soft cube falls)."""
    leaves = trajectory(2, seed, separate=still_square) * scale
    if still_square:
        leaves[:, 8:12] = leaves[2, 8:12]
    graph = set_pitch(structure(), pitch)
    return set_state(graph, leaves[0], leaves[1], leaves[2], radius=None)


@pytest.mark.parametrize("sleep", [None, SleepConfig(patience=1)], ids=["network alone", "a square asleep"])
def test_a_batch_of_two_pitches_rolls_out_as_each_scene_alone(sleep):
    model = _model(ground_contact=True)
    fine, coarse = _scene(0.05, 1.0, still_square=True), _scene(0.08, 1.3, seed=1, still_square=sleep is not None)
    with torch.no_grad():
        alone = [rollout(model, g, 6, sleep=sleep) for g in (fine, coarse)]
        together = rollout(model, Batch.from_data_list([fine, coarse]), 6, sleep=sleep)
    torch.testing.assert_close(together, torch.cat(alone, dim=1), atol=1e-6, rtol=0)


def test_the_search_near_awake_leaves_gives_each_graph_its_own_radius():
    """next_collision_edges with one radius per graph (some objects asleep) finds the edges of
    a full search at each graph's radius."""
    model = _model()
    batch = Batch.from_data_list([_scene(0.05, 1.0), _scene(0.08, 1.3, seed=1)])
    radius = collision_radius_of(model.config, batch)
    assert isinstance(radius, torch.Tensor)
    store = batch[NODE]
    batch[COLLISION].edge_index = leaf_collision_edges(batch, store.pos, radius)
    asleep = torch.zeros(store.num_nodes, dtype=torch.bool)
    asleep[store.object == 2] = True  # the static bodies sleep
    asleep[(store.object == 1) & (store.batch == 1)] = True  # and the coarse scene's rigid square
    moved = store.pos + torch.where(asleep.unsqueeze(-1), 0.0, torch.tensor([0.01, 0.0, -0.01]))
    found = next_collision_edges(batch, asleep, moved, radius)
    assert torch.equal(found, leaf_collision_edges(batch, moved, radius))
    assert found.size(1) > 0


def test_the_fixed_shape_steps_refuse_a_mix_of_pitches_and_take_one():
    model = _model()
    with pytest.raises(ValueError, match="pitches"):
        fixed_shape_rollout(model, Batch.from_data_list([_scene(0.05, 1.0), _scene(0.08, 1.3)]), 2)
    one = Batch.from_data_list([_scene(0.08, 1.3), _scene(0.08, 1.3, seed=1)])
    with torch.no_grad():
        fixed = fixed_shape_rollout(model, one, 3).pos
        plain = rollout(model, one, 3, sleep=None)
    torch.testing.assert_close(fixed, plain, atol=1e-5, rtol=0)
