"""Hand-computed cases for hrn_pyg.sampling.metrics."""

from __future__ import annotations

import math

import pytest
import torch

from hrn_pyg.sampling.metrics import energy_score, root_spread


def test_energy_score_one_dimension():
    # E|X - y| = (1 + 1) / 2 = 1; E|X - X'| = (0 + 2 + 2 + 0) / 4 = 1; ES = 1 - 0.5
    samples = torch.tensor([[0.0], [2.0]])
    truth = torch.tensor([[1.0]])
    assert energy_score(samples, truth).item() == pytest.approx(0.5)


def test_energy_score_euclidean_and_member_average():
    samples = torch.tensor([[0.0, 0.0], [3.0, 4.0]])
    # member (0, 0): distances 0 and 5 -> 2.5; member (3, 4): 5 and 0 -> 2.5; pairs: (0+5+5+0)/4
    truth = torch.tensor([[0.0, 0.0], [3.0, 4.0]])
    assert energy_score(samples, truth).item() == pytest.approx(2.5 - 0.5 * 2.5)


def test_energy_score_single_sample_is_the_distance():
    samples = torch.tensor([[1.0, 2.0, 2.0]])
    truth = torch.tensor([[0.0, 0.0, 0.0]])
    assert energy_score(samples, truth).item() == pytest.approx(3.0)


def test_energy_score_keeps_middle_dimensions():
    samples = torch.zeros(2, 5, 3)
    samples[1, :, 0] = torch.arange(5.0)  # the two samples are t apart at time t
    truth = torch.zeros(1, 5, 3)
    # E|X - y| = t / 2, E|X - X'| = 2t / 4 -> ES = t/2 - t/4 = t/4
    torch.testing.assert_close(energy_score(samples, truth), torch.arange(5.0) / 4)


def test_root_spread():
    centres = torch.tensor([[[0.0, 0, 0]], [[2.0, 0, 0]]])  # [K=2, O=1, 3]: mean (1, 0, 0), each 1 away
    torch.testing.assert_close(root_spread(centres), torch.tensor([1.0]))
    three = torch.tensor([[0.0, 0, 0], [0.0, 3, 0], [0.0, 0, 3]])  # mean (0, 1, 1)
    expected = math.sqrt((2 + 5 + 5) / 3)
    assert root_spread(three).item() == pytest.approx(expected)
    assert root_spread(torch.ones(4, 7, 2, 3)).shape == (7, 2)
    assert root_spread(torch.ones(4, 7, 2, 3)).abs().max() == 0


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: energy_score(torch.zeros(2, 3), torch.zeros(1, 4)), r"truth must be \[M>=1, 3\], got \(1, 4\)"),
        (lambda: root_spread(torch.zeros(2, 2)), r"centres must be \[K>=1, \.\.\., 3\], got \(2, 2\)"),
    ],
)
def test_bad_input_raises(call, message):
    with pytest.raises(ValueError, match=message):
        call()
