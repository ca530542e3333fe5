"""Side of the wedge's ridge (benchmarks.sides): shares, scores and clear errors."""

import json

import pytest
import torch

from benchmarks.sides import (
    ball_centres,
    brier_score,
    ridge_config,
    share_below,
    split_difference,
)


def test_ball_centre_is_the_mass_weighted_mean_of_object_0():
    pos = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0], [9.0, 9, 9]],
                        [[-1.0, 1, 0], [-3.0, 1, 0], [9.0, 9, 9]]])  # 2 trajectories, 3 leaves
    centres = ball_centres(pos, [0, 0, 1], [1.0, 3.0, 5.0])
    torch.testing.assert_close(centres, torch.tensor([[1.5, 0, 0], [-2.5, 1, 0]]))
    assert share_below(centres[:, 0]) == 0.5


def test_share_counts_the_ridge_itself_as_the_positive_side():
    assert share_below(torch.tensor([-1e-9, 0.0, 0.3, -0.2])) == 0.5
    with pytest.raises(ValueError, match="NaN"):
        share_below(torch.tensor([float("nan")]))
    with pytest.raises(ValueError, match=r"\[K>=1\]"):
        share_below(torch.zeros(0))


def test_scores_by_hand():
    truth = [0.0, 1.0, 0.5, 0.25]
    assert brier_score(truth, truth) == 0.0
    assert brier_score([0.5] * 4, truth) == pytest.approx((0.25 + 0.25 + 0 + 0.0625) / 4)
    assert brier_score([0.0] * 4, truth) == pytest.approx((0 + 1 + 0.25 + 0.0625) / 4)
    assert split_difference([1.0, 0.0, 0.5, 0.5], truth) == pytest.approx((1 + 1 + 0 + 0.25) / 4)
    with pytest.raises(ValueError, match="equal-length"):
        brier_score([0.5], [0.5, 0.5])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        split_difference([1.5], [0.5])


def test_ridge_config_reads_the_folder_and_refuses_other_scenes(tmp_path):
    (tmp_path / "meta.json").write_text(json.dumps({"scene": "wedge", "config": {"offset_range": [-0.003, 0.003]}}))
    assert ridge_config(tmp_path).settings["offset_range"].tolist() == [-0.003, 0.003]
    (tmp_path / "meta.json").write_text(json.dumps({"scene": "tower", "config": {}}))
    with pytest.raises(ValueError, match="not wedge"):
        ridge_config(tmp_path)
    with pytest.raises(FileNotFoundError, match="hrn-pyg generate"):
        ridge_config(tmp_path / "missing")
