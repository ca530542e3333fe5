"""Hand-computed cases for the benchmarks' scores of sampled futures (benchmarks.common)."""

from __future__ import annotations

import pytest
import torch

from benchmarks.common import best_of_k_error, coverage, object_centres, side_fractions


def test_best_of_k_error():
    samples = torch.tensor([[[0.0, 0, 0], [0, 0, 0]], [[1.0, 0, 0], [1, 0, 0]]])  # [K=2, L=2, 3]
    truth = torch.tensor([[[0.9, 0, 0], [1.2, 0, 0]], [[0.0, 0, 0], [0.0, 0, 0.4]]])  # [M=2, L=2, 3]
    # member 0: sample 0 -> (0.9 + 1.2) / 2 = 1.05, sample 1 -> (0.1 + 0.2) / 2 = 0.15 -> 0.15
    # member 1: sample 0 -> (0 + 0.4) / 2 = 0.2, sample 1 -> (1 + sqrt(1.16)) / 2 -> 0.2
    assert best_of_k_error(samples, truth).item() == pytest.approx((0.15 + 0.2) / 2)


def test_coverage_per_coordinate_and_per_member():
    samples = torch.tensor([[0.0, 1.0], [2.0, 3.0]])  # range x in [0, 2], y in [1, 3]
    truth = torch.tensor([[1.0, 2.0], [3.0, 2.0], [0.0, 3.0]])  # in/in, out/in, bounds/bounds
    assert coverage(samples, truth).item() == pytest.approx(5 / 6)
    assert coverage(samples, truth, per="member").item() == pytest.approx(2 / 3)


def test_coverage_of_one_sample_is_a_point():
    samples = torch.tensor([[1.0, 1.0]])
    truth = torch.tensor([[1.0, 1.0], [1.0, 1.5]])
    assert coverage(samples, truth).item() == pytest.approx(3 / 4)
    assert coverage(samples, truth, per="member").item() == pytest.approx(1 / 2)


def test_object_centres_are_mass_weighted():
    positions = torch.tensor([[0.0, 0, 0], [4.0, 0, 0], [1.0, 2, 3]])
    centres = object_centres(positions, torch.tensor([0, 0, 1]), torch.tensor([1.0, 3.0, 2.0]))
    torch.testing.assert_close(centres, torch.tensor([[3.0, 0, 0], [1.0, 2, 3]]))
    batched = object_centres(positions.expand(2, 4, 3, 3), torch.tensor([0, 0, 1]), torch.tensor([1.0, 3.0, 2.0]))
    assert batched.shape == (2, 4, 2, 3)


def test_side_fractions():
    torch.testing.assert_close(side_fractions(torch.tensor([-1.0, -0.5, 0.2, 0.0])),
                               torch.tensor([0.5, 0.5], dtype=torch.float64))
    torch.testing.assert_close(side_fractions(torch.tensor([0.3, 0.4, 0.1]), ridge=0.35),
                               torch.tensor([2 / 3, 1 / 3], dtype=torch.float64))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: best_of_k_error(torch.zeros(2, 4, 2), torch.zeros(1, 4, 2)),
         r"samples must be \[K, \.\.\., L, 3\], got \(2, 4, 2\)"),
        (lambda: coverage(torch.zeros(2, 3), torch.zeros(1, 3), per="all"),
         r"per must be 'coordinate' or 'member', got 'all'"),
        (lambda: object_centres(torch.zeros(3, 3), torch.tensor([0, 1]), torch.ones(3)),
         r"leaf_object and leaf_mass must be \[3\], got \(2,\), \(3,\)"),
        (lambda: side_fractions(torch.tensor([float("nan")])), r"coordinate contains NaN or infinite values"),
        (lambda: side_fractions(torch.zeros(0)), r"coordinate must be \[K>=1\], got \(0,\)"),
    ],
)
def test_bad_input_raises(call, message):
    with pytest.raises(ValueError, match=message):
        call()
