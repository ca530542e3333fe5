"""A rollout's collision list with a skin (hrn_pyg.data.candidates.VerletSearch) gives every step
the edges of a search at that step's positions, in the search's order."""

import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.candidates import VerletSearch
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, leaf_collision_edges
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim import rollout as rollout_module
from hrn_pyg.sim.rollout import unroll, verlet_search


def _blobs(count: int = 6, leaves: int = 60, seed: int = 0):
    """``count`` objects of ``leaves`` leaves each (one level: leaves under a root), enough
    leaves for the grid search."""
    parent = torch.cat([torch.full((leaves,), count * leaves + o) for o in range(count)] + [torch.full((count,), -1)])
    leaf_object = torch.arange(count).repeat_interleave(leaves)
    graph = build_structure(parent, torch.ones(count * leaves), leaf_object, torch.zeros(count, dtype=torch.long),
                            torch.ones(count))
    gen = torch.Generator().manual_seed(seed)
    centre = torch.rand(count, 3, generator=gen) * 0.6
    pos = centre.repeat_interleave(leaves, 0) + 0.08 * torch.randn(count * leaves, 3, generator=gen)
    return graph, pos, gen


def test_every_call_gives_the_edges_of_a_search():
    graph, pos, gen = _blobs()
    nodes = graph[NODE].num_nodes
    radius = 0.05
    search = VerletSearch(radius, 0.5 * radius)
    velocity = 0.003 * torch.randn(6, 3, generator=gen).repeat_interleave(60, 0)
    for _ in range(40):
        pos = pos + velocity + 0.001 * torch.randn(pos.shape, generator=gen)
        full = torch.cat([pos, torch.zeros(nodes - pos.size(0), 3)])  # ancestors: any rows
        edges = search(graph, full)
        expected = leaf_collision_edges(graph, full, radius)
        assert edges.size(1) > 0 and torch.equal(edges, expected)
    assert 1 < search.searches < 40  # the list was reused, and searched again when stale


def test_a_rollout_steps_with_the_edges_a_search_gives():
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=16, depth=2, effect_dim=8, rigid_fit=True)).eval()
    fit_normalizer([toy_window(6, seed=s) for s in range(3)], model.normalizer)
    graph = toy_scene()
    made = []

    def counted(radius, skin=rollout_module.VERLET_SKIN):
        made.append(verlet_search(radius, skin))
        return made[-1]

    original = rollout_module.verlet_search
    rollout_module.verlet_search = counted
    try:
        with torch.no_grad():
            steps = unroll(model, graph, 8, sleep=None)
    finally:
        rollout_module.verlet_search = original
    assert len(made) == 1 and made[0] is not None
    radius = model.config.collision_radius
    for st in steps:
        expected = leaf_collision_edges(st.graph, st.graph[NODE].pos, radius)
        assert torch.equal(st.graph[COLLISION].edge_index, expected)
    assert any(st.graph[COLLISION].edge_index.size(1) > 0 for st in steps)


def test_no_list_without_a_single_radius():
    assert verlet_search(None) is None
    assert verlet_search(0.0) is None
    assert verlet_search(torch.tensor([0.08, 0.1])) is None
    assert verlet_search(0.08).skin == 0.5 * 0.08
