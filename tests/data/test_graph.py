"""Edge sets and node attributes of the hierarchical graph, single and batched."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hrn_pyg.data.graph import (
    ANCESTOR_TO_DESCENDANT,
    CHILD_TO_PARENT,
    COLLISION,
    LEAF_TO_ANCESTOR,
    MATERIALS,
    NODE,
    WITHIN_SIBLINGS,
    build_structure,
    episode_structure,
    leaf_to_ancestor_mean,
    replicate,
    set_state,
)
from hrn_pyg.data.hierarchy import HierarchyConfig, build_hierarchy, start_hierarchy
from hrn_pyg.data.radius import collision_edges

RADIUS = 0.08


def _scene(seed: int = 0):
    """Three touching objects (rigid, soft, static) and their graph structure."""
    rng = np.random.default_rng(seed)
    sizes = (60, 45, 30)
    centres = np.array([[0.0, 0.0, 0.1], [0.18, 0.0, 0.1], [0.09, 0.15, 0.05]])
    leaves = np.concatenate([rng.uniform(-0.1, 0.1, size=(n, 3)) + c for n, c in zip(sizes, centres)])
    masses = rng.uniform(0.01, 0.1, size=leaves.shape[0])
    leaf_object = np.repeat(np.arange(3), sizes)
    parent = build_hierarchy(leaves, masses, leaf_object, HierarchyConfig(branching=3, leaf_group_size=5))
    graph = build_structure(
        torch.from_numpy(parent),
        torch.from_numpy(masses).float(),
        torch.from_numpy(leaf_object),
        torch.tensor([0, 1, 3]),
        torch.tensor([1.0, 0.4, 1.0]),
    )
    return graph, torch.from_numpy(leaves).float(), parent


def _pairs(edge_index: torch.Tensor) -> set[tuple[int, int]]:
    return set(map(tuple, edge_index.T.tolist()))


def test_hand_made_tree() -> None:
    # nodes: leaves 0, 1, 2; root 3; inner node 4 (child of 3) holds leaves 0 and 1; leaf 2 under root
    parent = torch.tensor([4, 4, 3, -1, 3])
    graph = build_structure(parent, torch.tensor([1.0, 2.0, 3.0]), torch.zeros(3, dtype=torch.long),
                            torch.tensor([1]), torch.tensor([0.5]))
    store = graph[NODE]
    assert store.mass[:, 0].tolist() == [1.0, 2.0, 3.0, 6.0, 3.0]
    assert store.depth.tolist() == [2, 2, 1, 0, 1]
    assert store.is_leaf.tolist() == [True, True, True, False, False]
    assert store.is_root.tolist() == [False, False, False, True, False]
    assert store.material.tolist() == [[0.0, 1.0, 0.0, 0.0]] * 5
    assert _pairs(graph[CHILD_TO_PARENT].edge_index) == {(0, 4), (1, 4), (2, 3), (4, 3)}
    assert _pairs(graph[LEAF_TO_ANCESTOR].edge_index) == {(0, 4), (0, 3), (1, 4), (1, 3), (2, 3), (4, 3)}
    assert _pairs(graph[WITHIN_SIBLINGS].edge_index) == {(0, 1), (1, 0), (2, 4), (4, 2)}
    x = torch.tensor([[0.0], [3.0], [6.0], [99.0], [99.0]]).expand(5, 1)
    assert leaf_to_ancestor_mean(x, graph)[:, 0].tolist() == [0.0, 3.0, 6.0, 4.0, 2.0]


def test_node_attributes() -> None:
    graph, leaves, parent = _scene()
    store = graph[NODE]
    n = parent.shape[0]
    assert store.num_nodes == n
    for name, shape in [("mass", (n, 1)), ("material", (n, 4)), ("stiffness", (n, 1)), ("object", (n,)),
                        ("depth", (n,)), ("is_leaf", (n,)), ("is_root", (n,)), ("is_static", (n,))]:
        assert tuple(store[name].shape) == shape, name
    assert torch.equal(store.material.sum(1), torch.ones(n))
    assert torch.equal(store.is_static, store.object == 2)
    assert torch.equal(store.is_static, store.material[:, MATERIALS.index("static")].bool())
    assert torch.equal(store.is_root, torch.from_numpy(parent == -1))
    assert int(store.is_root.sum()) == 3
    assert torch.equal(torch.unique(store.object[store.is_root]), torch.arange(3))


def test_child_to_parent_consistent_with_depth() -> None:
    graph, _, parent = _scene()
    store = graph[NODE]
    src, dst = graph[CHILD_TO_PARENT].edge_index
    assert torch.equal(dst, torch.from_numpy(parent)[src])
    assert torch.equal(torch.sort(src).values, torch.nonzero(~store.is_root).flatten())
    assert torch.equal(store.depth[src], store.depth[dst] + 1)
    assert (store.depth[store.is_root] == 0).all()
    assert torch.equal(store.object[src], store.object[dst])


def test_leaf_to_ancestor_and_reverse() -> None:
    graph, _, parent = _scene()
    l2a = graph[LEAF_TO_ANCESTOR].edge_index
    a2d = graph[ANCESTOR_TO_DESCENDANT].edge_index
    assert torch.equal(a2d, l2a.flip(0))
    expected = set()
    for node in range(parent.shape[0]):
        anc = node
        while parent[anc] >= 0:
            anc = int(parent[anc])
            expected.add((node, anc))
    assert _pairs(l2a) == expected and len(expected) == l2a.shape[1]
    store = graph[NODE]
    assert torch.equal(torch.bincount(l2a[0], minlength=store.num_nodes), store.depth)


def test_within_siblings() -> None:
    graph, _, parent = _scene()
    src, dst = graph[WITHIN_SIBLINGS].edge_index
    assert (src != dst).all()
    parent_t = torch.from_numpy(parent)
    assert torch.equal(parent_t[src], parent_t[dst]) and (parent_t[src] >= 0).all()
    sizes = np.bincount(parent[parent >= 0])
    assert src.shape[0] == int((sizes * (sizes - 1)).sum())
    assert len(_pairs(graph[WITHIN_SIBLINGS].edge_index)) == src.shape[0]


def test_set_state_derives_ancestors_and_collisions() -> None:
    graph, leaves, _ = _scene()
    store = graph[NODE]
    force = torch.randn(leaves.shape)
    state = set_state(graph, leaves - 0.02, leaves - 0.01, leaves, radius=RADIUS, force=force)
    assert "pos" not in graph[NODE]  # the input graph is left alone
    s = state[NODE]
    n_leaves = leaves.shape[0]
    assert torch.equal(s.pos[:n_leaves], leaves)
    assert torch.allclose(s.pos - s.prev_pos, torch.full_like(s.pos, 0.01), atol=1e-6)
    assert torch.equal(s.force[:n_leaves], force) and (s.force[n_leaves:] == 0).all()
    # ancestors: mass-weighted mean of leaves, also equal to the mass-weighted mean of children
    src, dst = graph[CHILD_TO_PARENT].edge_index
    weighted = torch.zeros_like(s.pos).index_add(0, dst, s.pos[src] * store.mass[src])
    assert torch.allclose(s.pos[n_leaves:], (weighted / store.mass)[n_leaves:], atol=1e-6)
    # the same state given for all nodes (ancestor rows garbage) gives the same graph
    full = torch.cat([leaves, torch.full((store.num_nodes - n_leaves, 3), 1e3)])
    again = set_state(graph, full, full, full, radius=RADIUS)
    assert torch.equal(again[NODE].pos, s.pos)
    # collisions: leaves of different objects only, equal to the leaf search, non-trivial
    col = state[COLLISION].edge_index
    assert col.shape[1] > 0
    assert s.is_leaf[col].all()
    assert (s.object[col[0]] != s.object[col[1]]).all()
    assert torch.equal(col, collision_edges(leaves, store.object[:n_leaves], RADIUS))
    assert set_state(graph, leaves, leaves, leaves, radius=None)[COLLISION].edge_index.shape == (2, 0)


def test_translation_in_x_y_leaves_edges_unchanged() -> None:
    graph, leaves, _ = _scene(seed=4)
    shift = torch.tensor([3.25, -7.5, 0.0])
    a = set_state(graph, leaves, leaves, leaves, radius=RADIUS)
    b = set_state(graph, leaves + shift, leaves + shift, leaves + shift, radius=RADIUS)
    for edge_type in a.edge_types:
        assert torch.equal(a[edge_type].edge_index, b[edge_type].edge_index), edge_type
    assert torch.allclose(b[NODE].pos - a[NODE].pos, shift.expand_as(a[NODE].pos), atol=1e-5)


def test_batched_copies_keep_invariants() -> None:
    graph, leaves, _ = _scene()
    k = 3
    batched = replicate(graph, k)
    store = batched[NODE]
    n = graph[NODE].num_nodes
    assert store.num_nodes == k * n
    assert torch.equal(store.batch, torch.arange(k).repeat_interleave(n))
    for edge_type in graph.edge_types:
        e, e1 = batched[edge_type].edge_index, graph[edge_type].edge_index
        assert torch.equal(e, torch.cat([e1 + c * n for c in range(k)], dim=1)), edge_type
    # every copy displaced differently; the state is set on the whole batch at once
    offsets = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0, 0.3]])
    per_copy = [leaves + o for o in offsets]
    state = set_state(batched, torch.cat(per_copy), torch.cat(per_copy), torch.cat(per_copy), radius=RADIUS)
    col = state[COLLISION].edge_index
    assert (store.batch[col[0]] == store.batch[col[1]]).all()
    assert (store.object[col[0]] != store.object[col[1]]).all()
    singles = [set_state(graph, x, x, x, radius=RADIUS) for x in per_copy]
    assert torch.equal(col, torch.cat([s[COLLISION].edge_index + c * n for c, s in enumerate(singles)], dim=1))
    assert torch.allclose(state[NODE].pos, torch.cat([s[NODE].pos for s in singles]))
    # copies overlap in space (copy 0 and 1 are 5 cm apart) but never collide with each other
    assert col.shape[1] > 0


def test_leaf_to_ancestor_mean_batched_dims_and_gradient() -> None:
    graph, leaves, _ = _scene()
    n = graph[NODE].num_nodes
    values = torch.randn(4, n, 3, requires_grad=True)
    out = leaf_to_ancestor_mean(values, graph)
    assert out.shape == (4, n, 3)
    for i in range(4):
        assert torch.allclose(out[i], leaf_to_ancestor_mean(values[i], graph))
    out.sum().backward()
    assert values.grad is not None and (values.grad[:, ~graph[NODE].is_leaf] == 0).all()
    with pytest.raises(ValueError, match="values"):
        leaf_to_ancestor_mean(torch.zeros(n + 1, 3), graph)


def test_set_state_bad_shapes() -> None:
    graph, leaves, _ = _scene()
    with pytest.raises(ValueError, match="pos"):
        set_state(graph, leaves, leaves, leaves[:-1], radius=RADIUS)
    with pytest.raises(ValueError, match="force"):
        set_state(graph, leaves, leaves, leaves, radius=RADIUS, force=torch.zeros(5, 3))
    with pytest.raises(ValueError, match="k"):
        replicate(graph, 0)


@pytest.mark.parametrize(
    "parent, match",
    [
        (torch.tensor([2, 2]), "more than"),  # no ancestor at all
        (torch.tensor([-1, 2, -1]), "every leaf"),  # a leaf without parent
        (torch.tensor([2, 2, 3, 2]), "cycle"),
        (torch.tensor([2, 2, -1, -1]), "leaf below"),  # ancestor 3 has no leaves
        (torch.tensor([2, 5, -1]), "parent"),
        (torch.tensor([2.0, 2.0, -1.0]), "parent"),
    ],
)
def test_bad_structure(parent, match) -> None:
    with pytest.raises(ValueError, match=match):
        build_structure(parent, torch.ones(2), torch.zeros(2, dtype=torch.long), torch.tensor([0]), torch.ones(1))


def test_ancestor_spanning_two_objects_is_rejected() -> None:
    with pytest.raises(ValueError, match="more than one object"):
        build_structure(torch.tensor([2, 2, -1]), torch.ones(2), torch.tensor([0, 1]), torch.tensor([0, 0]),
                        torch.ones(2))
    with pytest.raises(ValueError, match="object_material"):
        build_structure(torch.tensor([2, 2, -1]), torch.ones(2), torch.tensor([0, 0]), torch.tensor([4]),
                        torch.ones(1))
    with pytest.raises(ValueError, match="leaf_mass"):
        build_structure(torch.tensor([2, 2, -1]), torch.tensor([1.0, 0.0]), torch.tensor([0, 0]), torch.tensor([0]),
                        torch.ones(1))


def test_an_episodes_structure_has_its_tree_its_first_frame_at_rest_and_its_pitch():
    """:func:`episode_structure` of numpy or torch arrays: the episode's tree (that of
    :func:`start_hierarchy` on its first frame), ``rest_pos`` = the first frame (ancestors the
    mass-weighted means), the pitch its ``params`` record unless one is given."""
    rng = np.random.default_rng(0)
    positions = rng.normal(size=(3, 12, 3)).astype(np.float32)
    leaf_mass = rng.uniform(0.5, 1.5, 12).astype(np.float32)
    leaf_object = np.repeat([0, 1], 6)
    episode = {"positions": positions, "leaf_mass": leaf_mass, "leaf_object": leaf_object,
               "object_material": np.array([0, 1]), "object_stiffness": np.array([1.0, 0.5], dtype=np.float32),
               "hierarchy_parent": start_hierarchy(positions[0], leaf_mass, leaf_object),
               "params": '{"config": {"pitch": 0.05}}'}
    graph = episode_structure(episode)
    parent = torch.as_tensor(episode["hierarchy_parent"])
    assert torch.equal(parent, torch.as_tensor(build_hierarchy(positions[0].astype(np.float64),
                                                               leaf_mass.astype(np.float64), leaf_object)))
    assert graph[NODE].num_nodes == len(parent)
    full = torch.zeros(1, len(parent), 3)
    full[0, :12] = torch.from_numpy(positions[0])
    assert torch.allclose(graph[NODE].rest_pos, leaf_to_ancestor_mean(full, graph)[0])
    assert graph.pitch.item() == pytest.approx(0.05)
    as_torch = {key: torch.as_tensor(value) if key != "params" else value for key, value in episode.items()}
    other = episode_structure(as_torch, pitch=0.025)
    assert torch.equal(other[NODE].rest_pos, graph[NODE].rest_pos) and other.pitch.item() == pytest.approx(0.025)
