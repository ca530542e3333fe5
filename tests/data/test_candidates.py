"""The collision candidate list with a skin (hrn_pyg.data.candidates)."""

import pytest
import torch
from toy_scene import toy_scene

from hrn_pyg.data.candidates import (
    STALE_FRACTION,
    active_collisions,
    build_candidates,
    largest_move,
    move_limit,
    padded_size,
)
from hrn_pyg.data.graph import NODE, leaf_collision_edges

RADIUS = 0.08


def test_active_candidates_are_the_collision_edges_in_their_order():
    """Within the skin's limit, the candidates closer than the radius are exactly the search's
    edges at the moved positions, in the search's order."""
    graph = toy_scene(radius=None)
    pos = graph[NODE].pos
    cand = build_candidates(graph, pos, RADIUS, 0.5 * RADIUS)
    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        step = torch.randn(pos.shape, generator=gen)
        step = step / step.norm(dim=-1, keepdim=True).amax() * move_limit(cand.skin) * torch.rand(1, generator=gen)
        moved = pos + step
        assert float(largest_move(cand, moved)) <= move_limit(cand.skin)
        weight = active_collisions(cand, moved)
        assert torch.equal(cand.edge_index[:, weight.bool()], leaf_collision_edges(graph, moved, RADIUS))
    assert cand.pairs == cand.edge_index.size(1) > leaf_collision_edges(graph, pos, RADIUS).size(1)


def test_padding_is_never_active_and_sizes_are_powers_of_two():
    graph = toy_scene(radius=None)
    pos = graph[NODE].pos
    plain = build_candidates(graph, pos, RADIUS, 0.5 * RADIUS)
    padded = build_candidates(graph, pos, RADIUS, 0.5 * RADIUS, capacity=padded_size(plain.pairs))
    assert padded.edge_index.size(1) == 64 and padded.pairs == plain.pairs
    assert torch.equal(padded.edge_index[:, : plain.pairs], plain.edge_index)
    weight = active_collisions(padded, pos)
    assert torch.equal(weight[: plain.pairs], active_collisions(plain, pos))
    assert torch.equal(weight[plain.pairs :], torch.zeros(64 - plain.pairs))  # padding pairs 0 -> 0 are at distance 0
    assert [padded_size(n) for n in (0, 64, 65, 1000)] == [64, 64, 128, 1024]


def test_largest_move_and_the_limit():
    graph = toy_scene(radius=None)
    pos = graph[NODE].pos
    cand = build_candidates(graph, pos, RADIUS, 0.04)
    assert float(largest_move(cand, pos)) == 0.0
    shifted = pos.clone()
    shifted[3, 0] += 0.03
    assert float(largest_move(cand, shifted)) == pytest.approx(0.03)
    shifted[5, 2] = float("nan")
    assert float(largest_move(cand, shifted)) == float("inf")
    assert move_limit(0.04) == pytest.approx(STALE_FRACTION * 0.04) and STALE_FRACTION < 0.5


def test_bad_input():
    graph = toy_scene(radius=None)
    pos = graph[NODE].pos
    with pytest.raises(ValueError, match="radius and skin must be > 0"):
        build_candidates(graph, pos, RADIUS, 0.0)
    with pytest.raises(ValueError, match="capacity 1 is smaller"):
        build_candidates(graph, pos, RADIUS, 0.04, capacity=1)
