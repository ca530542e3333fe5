"""Graphs that know their voxel pitch, and the collision search at a radius per graph."""

import itertools
import json

import numpy as np
import pytest
import torch
from torch_geometric.data import Batch

from hrn_pyg.data.dataset import EpisodeWindows
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, graph_pitch, node_pitch, set_pitch, set_state
from hrn_pyg.data.io import episode_pitch, save_episode
from hrn_pyg.data.radius import DENSE_MAX_POINTS, collision_edges
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.nn.pitch import collision_radius_of

PITCH_AWARE = HRNConfig(pitch_aware=True)  # collision radius 0.08 at the reference pitch 0.05


def _lattice_scene(pitch: float, side: int, seed: int = 0, dtype=torch.float32):
    """Two cubes of ``side**3`` leaves on a lattice of ``pitch``, a seeded gap apart (about a
    lattice step, so the radius 1.6 p cuts through the pairs across it), each leaf jittered by
    a few percent of the pitch, each cube its own root."""
    gen = torch.Generator().manual_seed(seed)
    grid = torch.tensor(list(itertools.product(range(side), repeat=3)), dtype=torch.float64) * pitch
    gap = (side - 1) * pitch + pitch * (0.8 + 0.6 * float(torch.rand((), generator=gen, dtype=torch.float64)))
    leaves = torch.cat([grid, grid + torch.tensor([gap, 0.0, 0.0], dtype=torch.float64)])
    leaves = leaves + (torch.rand(leaves.shape, generator=gen, dtype=torch.float64) - 0.5) * 0.1 * pitch
    n = grid.shape[0]
    parent = torch.tensor([2 * n] * n + [2 * n + 1] * n + [-1, -1])
    structure = build_structure(parent, torch.ones(2 * n), torch.tensor([0] * n + [1] * n),
                                torch.tensor([0, 1]), torch.tensor([1.0, 1.0]), pitch=pitch)
    leaves = leaves.to(dtype)
    return structure, leaves


def _brute_force(leaves: torch.Tensor, leaf_object: torch.Tensor, radius: float) -> set[tuple[int, int]]:
    """Every ordered pair of leaves of different objects closer than ``radius``, one pair at a
    time, in float64."""
    x = leaves.double().tolist()
    obj = leaf_object.tolist()
    pairs = set()
    for i, j in itertools.permutations(range(len(x)), 2):
        if obj[i] != obj[j] and sum((a - b) ** 2 for a, b in zip(x[i], x[j])) < radius * radius:
            pairs.add((j, i))
    return pairs


@pytest.mark.parametrize("pitch", [0.025, 0.05, 0.08])
@pytest.mark.parametrize("side", [3, 6])  # 54 leaves: every pair tested; 432: the cell grid
def test_a_pitch_aware_graph_at_pitch_p_gets_the_pairs_within_1_6_p(pitch, side):
    structure, leaves = _lattice_scene(pitch, side, seed=int(pitch * 1000) + side)
    assert (2 * side**3 > DENSE_MAX_POINTS) == (side == 6)
    radius = collision_radius_of(PITCH_AWARE, structure)
    assert radius == pytest.approx(1.6 * pitch, rel=1e-12)
    graph = set_state(structure, leaves, leaves, leaves, radius=radius)
    found = {tuple(e) for e in graph[COLLISION].edge_index.t().tolist()}
    expected = _brute_force(leaves, structure[NODE].object[: leaves.shape[0]], 1.6 * pitch)
    assert found == expected
    assert len(expected) > 0
    # the radius decides: a smaller one keeps fewer pairs
    assert len(found) > len(_brute_force(leaves, structure[NODE].object[: leaves.shape[0]], 1.2 * pitch))


@pytest.mark.parametrize("side", [3, 6])
def test_one_search_of_a_batch_of_pitches_gives_each_graph_its_own_radius(side):
    scenes = [_lattice_scene(p, side, seed=s) for s, p in enumerate((0.025, 0.08, 0.05))]
    singles = [set_state(g, x, x, x, radius=collision_radius_of(PITCH_AWARE, g)) for g, x in scenes]
    batch = Batch.from_data_list([g for g, _ in scenes])
    pos = torch.cat([x for _, x in scenes])
    radius = collision_radius_of(PITCH_AWARE, batch)
    assert isinstance(radius, torch.Tensor) and radius.shape == (3,)
    together = set_state(batch, pos, pos, pos, radius=radius)
    offset, expected = 0, []
    for single in singles:
        expected.append(single[COLLISION].edge_index + offset)
        offset += single[NODE].num_nodes
    assert torch.equal(together[COLLISION].edge_index, torch.cat(expected, dim=1))


def test_a_per_leaf_radius_equal_to_a_number_keeps_the_same_pairs_bit_for_bit():
    gen = torch.Generator().manual_seed(3)
    for n in (40, 400):
        pos = torch.rand(n, 3, generator=gen)
        obj = torch.randint(0, 5, (n,), generator=gen)
        for r in (0.05, 0.112, 0.0123456789):
            alone = collision_edges(pos, obj, r)
            per_leaf = collision_edges(pos, obj, torch.full((n,), r, dtype=torch.float64))
            assert torch.equal(alone, per_leaf)


def test_a_per_leaf_radius_must_fit_the_leaves():
    pos, obj = torch.rand(5, 3), torch.arange(5)
    with pytest.raises(ValueError, match="per-leaf radius"):
        collision_edges(pos, obj, torch.full((4,), 0.1))
    with pytest.raises(ValueError, match="per-leaf radius"):
        collision_edges(pos, obj, torch.tensor([0.1, 0.1, -1.0, 0.1, 0.1]))
    assert collision_edges(pos, obj, torch.zeros(5)).shape == (2, 0)


def test_graphs_carry_their_pitch_and_batches_one_per_graph():
    structure, _ = _lattice_scene(0.04, 2)
    assert graph_pitch(structure).dtype == torch.float64 and graph_pitch(structure).tolist() == [0.04]
    assert node_pitch(structure).shape == (structure[NODE].num_nodes,)
    other, _ = _lattice_scene(0.07, 3)
    batch = Batch.from_data_list([structure, other, structure])
    assert graph_pitch(batch).tolist() == [0.04, 0.07, 0.04]
    expected = [0.04] * structure[NODE].num_nodes + [0.07] * other[NODE].num_nodes + [0.04] * structure[NODE].num_nodes
    assert node_pitch(batch).tolist() == expected
    with pytest.raises(ValueError, match="pitch"):
        set_pitch(structure, 0.0)
    bare = build_structure(torch.tensor([1, -1]), torch.ones(1), torch.tensor([0]), torch.tensor([0]), torch.ones(1))
    assert graph_pitch(bare) is None
    with pytest.raises(ValueError, match="no voxel pitch"):
        node_pitch(bare)


def test_episodes_record_their_pitch_in_params(tiny_episodes):
    """Episodes of ``hrn-pyg generate`` record their pitch; dataset windows carry it."""
    from hrn_pyg.data.io import load_episode

    episode = load_episode(next(iter(sorted(tiny_episodes.glob("episode_*.npz")))))
    assert episode_pitch(episode) == 0.05
    windows = EpisodeWindows(tiny_episodes, "train", horizon=2)
    assert graph_pitch(windows[0]).tolist() == [0.05]
    batch = Batch.from_data_list([windows[0], windows[len(windows) - 1]])
    assert graph_pitch(batch).tolist() == [0.05, 0.05]
    assert episode_pitch({"params": json.dumps({"config": {}})}) is None


def _episode_at(pitch: float, seed: int) -> dict:
    """A hand-made two-object episode at ``pitch``: two leaves 1.2 pitches apart, resting."""
    positions = np.zeros((6, 2, 3), dtype=np.float32)
    positions[:, 1, 0] = 1.2 * pitch
    positions[:, :, 2] = pitch
    return {
        "positions": positions, "forces": np.zeros((5, 2, 3), dtype=np.float32),
        "leaf_mass": np.ones(2, dtype=np.float32), "leaf_object": np.array([0, 1]),
        "object_material": np.array([0, 0]), "object_stiffness": np.ones(2, dtype=np.float32),
        "hierarchy_parent": np.array([2, 3, -1, -1]), "seed": np.array(seed), "scene": np.array("pair"),
        "params": np.array(json.dumps({"config": {"pitch": pitch}})), "dt": np.array(1 / 30, dtype=np.float32),
    }


def test_windows_scale_the_radius_with_their_episode_pitch(tmp_path):
    """With a reference pitch, a window's radius is r_c p / p_ref: the pair 1.2 pitches apart
    meets at every pitch; at a fixed radius only at the fine one."""
    fine, coarse = tmp_path / "fine", tmp_path / "coarse"
    fine.mkdir(), coarse.mkdir()
    save_episode(fine / "episode_000000.npz", _episode_at(0.05, 0))
    save_episode(coarse / "episode_000001.npz", _episode_at(0.08, 1))
    scaled = EpisodeWindows([fine, coarse], "train", collision_radius=0.08, reference_pitch=0.05)
    fixed = EpisodeWindows([fine, coarse], "train", collision_radius=0.08)
    assert [scaled.pitch(i) for i in range(2)] == [0.05, 0.08]
    assert scaled.window_radius(1) == pytest.approx(0.128)
    last = len(scaled) - 1  # a window of the coarse episode
    assert graph_pitch(scaled[last]).tolist() == [0.08]
    assert scaled[0][COLLISION].edge_index.size(1) == 2 and scaled[last][COLLISION].edge_index.size(1) == 2
    assert fixed[0][COLLISION].edge_index.size(1) == 2 and fixed[last][COLLISION].edge_index.size(1) == 0
