"""Pictures of sampled futures (hrn_pyg.viz): what the view box keeps in sight."""

import numpy as np

from hrn_pyg.viz import SAMPLES_BULK, _bulk, _inside, scene_limits


def test_a_future_that_splits_late_keeps_both_branches_in_view():
    """16 samples over 5 steps: all together at first, then half go 1.5 m left and half 1.5 m
    right (as balls do on the wedge). Per-step quantiles keep both branches inside the box; the
    quantiles of all steps pooled would cut the late, far points."""
    rng = np.random.default_rng(0)
    k, t, leaves = 16, 5, 8
    samples = 0.01 * rng.standard_normal((k, t, leaves, 3)) + np.array([0.0, 0.0, 0.2])
    side = np.where(np.arange(k) < k // 2, -1.0, 1.0)
    samples[:, 3:, :, 0] += side[:, None, None] * np.array([1.0, 1.5])[None, :, None]
    limits = scene_limits(_bulk(samples), pad=0.1)
    last = samples[:, -1].reshape(-1, 3)
    assert _inside(last, limits).mean() >= 1.0 - 2 * SAMPLES_BULK
    pooled = np.quantile(samples.reshape(-1, 3), [0.1, 0.9], axis=0)
    assert _inside(last, scene_limits(pooled, pad=0.1)).mean() < 0.5


def test_bulk_ignores_non_finite_points_and_empty_input():
    samples = np.full((2, 3, 4, 3), np.nan)
    assert _bulk(samples).shape == (0, 3)
    samples[:, 1] = 1.0
    np.testing.assert_allclose(_bulk(samples), np.ones((2, 3)))
