"""Invariants of the per-object k-means hierarchy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hrn_pyg.data.graph import NODE, build_structure, leaf_to_ancestor_mean
from hrn_pyg.data.hierarchy import HierarchyConfig, build_hierarchy


def _scene(seed: int = 0, sizes: tuple[int, ...] = (150, 37, 1, 8)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Leaves of several objects (a big one, an odd one, a single leaf, exactly one group)."""
    rng = np.random.default_rng(seed)
    positions = np.concatenate([rng.normal(size=(n, 3)) * 0.1 + 2.0 * i for i, n in enumerate(sizes)])
    masses = rng.uniform(0.05, 0.5, size=positions.shape[0])
    leaf_object = np.repeat(np.arange(len(sizes)), sizes)
    return positions.astype(np.float32), masses.astype(np.float32), leaf_object


def _ancestors(parent: np.ndarray, node: int) -> list[int]:
    chain = []
    while parent[node] >= 0:
        node = int(parent[node])
        chain.append(node)
    return chain


def _structure(parent, masses, leaf_object):
    n_objects = int(leaf_object.max()) + 1
    return build_structure(
        torch.from_numpy(parent),
        torch.from_numpy(masses),
        torch.from_numpy(leaf_object),
        torch.zeros(n_objects, dtype=torch.long),
        torch.ones(n_objects),
    )


def test_layout_and_one_root_per_object() -> None:
    positions, masses, leaf_object = _scene()
    parent = build_hierarchy(positions, masses, leaf_object)
    n_leaves = positions.shape[0]
    assert parent.dtype == np.int64
    assert np.all(parent[:n_leaves] >= n_leaves)  # every leaf has an ancestor as parent
    roots = np.flatnonzero(parent == -1)
    assert np.all(roots >= n_leaves)
    leaf_roots = np.array([_ancestors(parent, i)[-1] for i in range(n_leaves)])
    for obj in np.unique(leaf_object):
        assert np.unique(leaf_roots[leaf_object == obj]).shape[0] == 1
    assert roots.shape[0] == np.unique(leaf_object).shape[0]
    # ancestors are numbered after their parents (breadth-first per object)
    anc = np.arange(n_leaves, parent.shape[0])
    assert np.all(parent[anc][parent[anc] >= 0] < anc[parent[anc] >= 0])


def test_single_leaf_object_gets_a_root() -> None:
    parent = build_hierarchy(np.zeros((1, 3)), np.ones(1), np.zeros(1, dtype=np.int64))
    np.testing.assert_array_equal(parent, [1, -1])


def test_small_object_hangs_directly_under_root() -> None:
    positions, masses, _ = _scene(sizes=(8,))
    parent = build_hierarchy(positions, masses, np.zeros(8, dtype=np.int64), HierarchyConfig(leaf_group_size=8))
    np.testing.assert_array_equal(parent, [8] * 8 + [-1])


def test_hand_made_clusters_are_found() -> None:
    # two tight, far-apart groups of 5: with branching 2 the root gets exactly those two children
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 3)) * 0.01
    b = rng.normal(size=(5, 3)) * 0.01 + 10.0
    positions = np.concatenate([a, b])[[0, 5, 1, 6, 2, 7, 3, 8, 4, 9]]
    parent = build_hierarchy(
        positions, np.ones(10), np.zeros(10, dtype=np.int64), HierarchyConfig(branching=2, leaf_group_size=5)
    )
    assert parent.shape == (13,)
    assert parent[10] == -1 and parent[11] == 10 and parent[12] == 10
    first = parent[:10][0]
    np.testing.assert_array_equal(parent[:10] == first, np.arange(10) % 2 == 0)


def test_bottom_groups_are_small_and_not_mixed() -> None:
    positions, masses, leaf_object = _scene()
    for branching, group in ((8, 8), (2, 3), (4, 1)):
        parent = build_hierarchy(positions, masses, leaf_object, HierarchyConfig(branching=branching, leaf_group_size=group))
        n_leaves = positions.shape[0]
        children = [np.flatnonzero(parent == a) for a in range(n_leaves, parent.shape[0])]
        for kids in children:
            assert kids.shape[0] >= 1
            is_leaf = kids < n_leaves
            assert is_leaf.all() or not is_leaf.any()  # never mixes leaves and ancestors
            if is_leaf.all():
                assert kids.shape[0] <= group
            else:
                assert kids.shape[0] <= branching


def test_parent_mass_and_position_through_structure() -> None:
    positions, masses, leaf_object = _scene(seed=1)
    parent = build_hierarchy(positions, masses, leaf_object)
    graph = _structure(parent, masses, leaf_object)
    mass = graph[NODE].mass[:, 0].double().numpy()
    n_leaves, num_nodes = positions.shape[0], parent.shape[0]
    # parent mass = sum of its children's masses
    child_sum = np.zeros(num_nodes)
    np.add.at(child_sum, parent[parent >= 0], mass[parent >= 0])
    np.testing.assert_allclose(mass[n_leaves:], child_sum[n_leaves:], rtol=1e-5)
    # parent position = mass-weighted mean of its leaves, computed here by walking the tree
    pos = torch.zeros(num_nodes, 3)
    pos[:n_leaves] = torch.from_numpy(positions)
    derived = leaf_to_ancestor_mean(pos, graph).double().numpy()
    expected = np.zeros((num_nodes, 3))
    total = np.zeros(num_nodes)
    for leaf in range(n_leaves):
        for anc in _ancestors(parent, leaf):
            expected[anc] += masses[leaf] * positions[leaf]
            total[anc] += masses[leaf]
    np.testing.assert_allclose(derived[n_leaves:], expected[n_leaves:] / total[n_leaves:, None], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(derived[:n_leaves], positions)


def test_deterministic_for_a_seed_and_uses_velocity() -> None:
    positions, masses, leaf_object = _scene(seed=2)
    velocities = np.random.default_rng(5).normal(size=positions.shape)
    config = HierarchyConfig(seed=7, velocity_weight=5.0, mass_weight=1.0)
    first = build_hierarchy(positions, masses, leaf_object, config, velocities)
    second = build_hierarchy(positions.copy(), masses.copy(), leaf_object.copy(), config, velocities.copy())
    np.testing.assert_array_equal(first, second)
    no_velocity = build_hierarchy(positions, masses, leaf_object, HierarchyConfig(seed=7))
    assert first.shape != no_velocity.shape or not np.array_equal(first, no_velocity)


def test_identical_points_terminate() -> None:
    parent = build_hierarchy(np.ones((40, 3)), np.ones(40), np.zeros(40, dtype=np.int64))
    n_leaves = 40
    for a in range(n_leaves, parent.shape[0]):
        kids = np.flatnonzero(parent == a)
        assert kids.shape[0] >= 1
        if (kids < n_leaves).all():
            assert kids.shape[0] <= 8


def test_non_contiguous_object_ids() -> None:
    positions, masses, _ = _scene(sizes=(20, 20))
    leaf_object = np.repeat([3, 11], 20)
    parent = build_hierarchy(positions, masses, leaf_object)
    assert (parent == -1).sum() == 2


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda p, m, o, c: (p[:, :2], m, o, c), "positions"),
        (lambda p, m, o, c: (np.where(np.arange(p.size).reshape(p.shape) == 4, np.nan, p), m, o, c), "positions"),
        (lambda p, m, o, c: (p, m[:-1], o, c), "masses"),
        (lambda p, m, o, c: (p, -m, o, c), "masses"),
        (lambda p, m, o, c: (p, m, o.astype(float), c), "leaf_object"),
        (lambda p, m, o, c: (p, m, o - 1, c), "leaf_object"),
        (lambda p, m, o, c: (p, m, o, HierarchyConfig(branching=1)), "branching"),
        (lambda p, m, o, c: (p, m, o, HierarchyConfig(leaf_group_size=0)), "leaf_group_size"),
        (lambda p, m, o, c: (p, m, o, HierarchyConfig(mass_weight=-1.0)), "mass_weight"),
        (lambda p, m, o, c: (p, m, o, HierarchyConfig(velocity_weight=1.0)), "velocities"),
    ],
)
def test_bad_input(change, match) -> None:
    positions, masses, leaf_object = _scene(sizes=(10, 10))
    args = change(positions, masses, leaf_object, HierarchyConfig())
    with pytest.raises(ValueError, match=match):
        build_hierarchy(*args)


def test_empty_and_bad_velocities() -> None:
    with pytest.raises(ValueError, match="positions"):
        build_hierarchy(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64))
    positions, masses, leaf_object = _scene(sizes=(10,))
    with pytest.raises(ValueError, match="velocities"):
        build_hierarchy(positions, masses, leaf_object, HierarchyConfig(velocity_weight=1.0), np.zeros((9, 3)))
