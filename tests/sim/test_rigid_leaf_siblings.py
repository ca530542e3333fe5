"""``HRNConfig.rigid_leaf_siblings``: off, the within-siblings phase drops exactly the edges into
rigid leaves; the soft leaves' edges and every other edge set stay; a scene without rigid leaves
steps the same bit for bit; the option applies to trained weights."""

import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, RIGID, SOFT, WITHIN_SIBLINGS
from hrn_pyg.nn.hrn import HRN, HRNConfig, within_siblings_of
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.step import build_inputs, step


def _model(**kw):
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=16, depth=2, effect_dim=8, rigid_fit=True, rest_offsets=True, **kw))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()


def test_only_the_edges_into_rigid_leaves_are_dropped():
    graph = toy_scene()
    store = graph[NODE]
    rigid_leaf = store.is_leaf & store.material[:, RIGID].bool()
    edges = graph[WITHIN_SIBLINGS].edge_index
    kept = within_siblings_of(edges, rigid_leaf)
    assert bool(rigid_leaf.any()) and kept.size(1) < edges.size(1)
    assert not bool(rigid_leaf[kept[1]].any())
    dropped = edges.size(1) - kept.size(1)
    assert dropped == int(rigid_leaf[edges[1]].sum())
    in_order = [tuple(e) for e in edges.T.tolist() if not rigid_leaf[e[1]]]
    assert [tuple(e) for e in kept.T.tolist()] == in_order

    plain = _model()
    pruned = with_applied_options(plain, rigid_leaf_siblings=False)
    assert pruned.config.rigid_leaf_siblings is False and plain.config.rigid_leaf_siblings is True
    a, b = build_inputs(plain, graph), build_inputs(pruned, graph)
    assert torch.equal(a.within_siblings, edges) and torch.equal(b.within_siblings, kept)
    for name in ("leaf_to_ancestor", "ancestor_to_descendant", "collision"):
        assert torch.equal(getattr(a, name), getattr(b, name))


def test_without_rigid_leaves_the_step_is_unchanged_and_with_them_it_differs():
    plain = _model()
    pruned = with_applied_options(plain, rigid_leaf_siblings=False)
    graph = toy_scene()
    with torch.no_grad():
        assert not torch.equal(step(plain, graph).pos, step(pruned, graph).pos)
    soft = toy_scene()
    material = soft[NODE].material.clone()
    material[:, SOFT] += material[:, RIGID]  # the rigid square becomes soft
    material[:, RIGID] = 0.0
    soft[NODE].material = material
    with torch.no_grad():
        assert torch.equal(rollout(plain, soft, 3), rollout(pruned, soft, 3))
