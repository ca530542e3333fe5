"""Many copies of a scene run as groups of copies (hrn_pyg.sim.copy_groups): the groups cover the
copies in order within the node budget, and the grouped pass gives the one-pass answer, with
per-copy dropout masks, collision edges, collision weights and a mirror average."""

import dataclasses

import pytest
import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.graph import replicate
from hrn_pyg.nn.hrn import HRN, HRNConfig, StepOptions
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim import copy_groups as cg
from hrn_pyg.sim.step import build_inputs, run_network

SMALL = dict(hidden=16, depth=2, effect_dim=8, dropout_modules=("force", "collision"))
NODES = 19  # nodes of one toy scene


def _model(**kw) -> HRN:
    torch.manual_seed(0)
    model = HRN(HRNConfig(**{**SMALL, **kw}))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()


def _inputs(model: HRN, k: int, options: StepOptions = StepOptions()):
    graph = replicate(toy_scene(force=True), k)
    return build_inputs(model, graph, options=options)


def test_groups_are_whole_copies_in_order_within_the_budget():
    inputs = _inputs(_model(), 7)
    groups = cg.copy_groups(inputs, max_nodes=3 * NODES)
    assert groups == [cg.CopyGroup(0, 57, 0, 3), cg.CopyGroup(57, 114, 3, 6), cg.CopyGroup(114, 133, 6, 7)]
    # a copy larger than the budget is a group of its own
    assert [g.copy_stop - g.copy_start for g in cg.copy_groups(inputs, max_nodes=NODES - 1)] == [1] * 7


def test_one_pass_where_grouping_does_not_pay_or_cannot_be_done():
    model = _model()
    inputs = _inputs(model, 4)
    assert cg.copy_groups(inputs, max_nodes=4 * NODES) is None  # fits in one group
    assert cg.copy_groups(_inputs(model, 4, StepOptions(fixed_shape=True)), max_nodes=NODES) is None
    shuffled = inputs._replace(batch=inputs.batch.flip(0))
    assert cg.copy_groups(shuffled, max_nodes=NODES) is None  # copies not one after another
    groups = cg.copy_groups(inputs, max_nodes=2 * NODES)
    crossing = inputs._replace(collision=torch.tensor([[0], [NODES * 3]]))
    assert cg.group_inputs(crossing, {}, groups) is None  # an edge between two groups
    assert cg.group_inputs(inputs, {"force": torch.ones(3, 16)}, groups) is None  # a mask row short


def test_edges_and_per_edge_values_are_cut_by_copy_and_renumbered():
    groups = [cg.CopyGroup(0, 4, 0, 2), cg.CopyGroup(4, 6, 2, 3)]
    edges = torch.tensor([[4, 0, 5, 3], [5, 1, 4, 2]])
    cut = cg.edge_groups(edges, groups)
    assert cut[0].tolist() == [[0, 3], [1, 2]] and cut[1].tolist() == [[0, 1], [1, 0]]
    values = cg.edge_groups(torch.tensor([[10.0, 11.0, 12.0, 13.0]]), groups, by=edges)
    assert values[0].tolist() == [[11.0, 13.0]] and values[1].tolist() == [[10.0, 12.0]]


@pytest.mark.parametrize("kw", [{}, dict(mirror_average=True, mirror_planes="d4")])
def test_the_grouped_pass_gives_the_one_pass_answer(monkeypatch, kw):
    model = _model(**kw)
    k = 6
    inputs = _inputs(model, k)
    assert inputs.collision.size(1) > 0  # collisions in every copy
    weight = (torch.arange(inputs.collision.size(1)) % 3 != 0).float()
    inputs = inputs._replace(options=dataclasses.replace(inputs.options, collision_weight=weight))
    masks = model.sample_masks(k, rate=0.3, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        whole = run_network(model, inputs, masks)  # 114 nodes: one pass
        monkeypatch.setattr("hrn_pyg.sim.step.copy_groups",
                            lambda inp: cg.copy_groups(inp, max_nodes=2 * NODES))
        grouped = run_network(model, inputs, masks)
    assert cg.copy_groups(inputs, max_nodes=2 * NODES) is not None
    torch.testing.assert_close(grouped, whole, rtol=0, atol=1e-5)
    # the copies differ (their masks do), so a mix-up of rows or masks would show
    per_copy = whole.reshape(k, NODES, 3)
    assert (per_copy[0] - per_copy[1]).abs().max() > 1e-3
