"""The invariants and vector sums of hrn_pyg.nn.equivariant.features."""

import math

import torch

from hrn_pyg.nn.equivariant.features import (channel_dot, channel_length, dot, horizontal_length, invariant_state,
                                             mean_vectors_by_index, squash, weighted_sum,
                                             weighted_sum_elementwise)


def _turn(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s], [s, c]])


def test_invariants_do_not_change_under_a_turn_or_a_mirror():
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(5, 2, generator=gen), torch.randn(5, 2, generator=gen)
    channels = torch.randn(5, 3, 2, generator=gen)
    for g in (_turn(0.4), _turn(2.0) @ torch.diag(torch.tensor([1.0, -1.0]))):
        torch.testing.assert_close(dot(a @ g.T, b @ g.T), dot(a, b))
        torch.testing.assert_close(horizontal_length(a @ g.T), horizontal_length(a))
        torch.testing.assert_close(channel_dot(channels @ g.T, a @ g.T), channel_dot(channels, a))
        torch.testing.assert_close(channel_length(channels @ g.T), channel_length(channels))


def test_the_invariant_state_reads_the_horizontal_velocity_as_its_length():
    state = torch.tensor([[3.0, 4.0, -1.0, 7.0, 8.0]])
    torch.testing.assert_close(invariant_state(state), torch.tensor([[5.0, -1.0, 7.0, 8.0]]))


def test_weighted_sum_by_hand():
    weights = torch.tensor([[[1.0, 0.0], [2.0, -1.0]]])  # [1, K=2, C=2]
    basis = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])  # [1, K=2, 2]
    torch.testing.assert_close(weighted_sum(weights, basis), torch.tensor([[[1.0, 2.0], [0.0, -1.0]]]))


def test_the_compiled_form_of_the_weighted_sum_is_the_eager_one():
    """The elementwise form taken under ``torch.compile`` gives the batched product's numbers, for
    the module's shapes (K = 2, 3 basis vectors of C = 8 channels; K = C + 1 of one channel)."""
    gen = torch.Generator().manual_seed(3)
    for m, k, c in ((50, 2, 8), (50, 3, 8), (20, 9, 1)):
        weights, basis = torch.randn(m, k, c, generator=gen), torch.randn(m, k, 2, generator=gen)
        torch.testing.assert_close(weighted_sum_elementwise(weights, basis), weighted_sum(weights, basis))
        compiled = torch.compile(weighted_sum, backend="eager", fullgraph=True)
        torch.testing.assert_close(compiled(weights, basis), weighted_sum(weights, basis))


def test_the_mean_over_edges_divides_by_the_in_degree_and_leaves_silent_nodes_at_zero():
    vectors = torch.tensor([[[1.0, 0.0]], [[3.0, 2.0]], [[5.0, 5.0]]])  # three edges, one channel
    index = torch.tensor([0, 0, 2])
    out = mean_vectors_by_index(vectors, index, torch.tensor([2.0, 0.0, 1.0]))
    torch.testing.assert_close(out, torch.tensor([[[2.0, 1.0]], [[0.0, 0.0]], [[5.0, 5.0]]]))


def test_squash_keeps_directions_and_bounds_lengths_below_one():
    channels = torch.tensor([[[3.0, 4.0], [0.0, 0.0], [-1e6, 0.0]]])
    out = squash(channels)
    torch.testing.assert_close(out[0, 0], torch.tensor([0.5, 4.0 / 6.0]))  # length 5 -> 5/6
    assert torch.equal(out[0, 1], torch.zeros(2)) and -1.0 < out[0, 2, 0] < -0.99
    g = _turn(0.9)
    torch.testing.assert_close(squash(channels[:, :2] @ g.T), squash(channels[:, :2]) @ g.T)
