"""``experiments.recipe.weights``: the weighted mean of checkpoints' weights, and only of their
weights."""

from __future__ import annotations

import pytest
import torch

from hrn_pyg.checkpoints import checkpoint_path, load_model
from experiments.recipe.weights import check_average_weights, write_average
from hrn_pyg.utils.checkpoint import load_checkpoint, save_checkpoint


def _shifted_copy(tmp_path, shift: float, name: str = "shifted.pt"):
    """multi_material.pt with every parameter (not the normaliser) moved by ``shift`` and the
    normaliser's velocity scale doubled: a second checkpoint of the same network."""
    ckpt = load_checkpoint(checkpoint_path("multi_material"))
    parameters = {n for n, _ in load_model(checkpoint_path("multi_material")).named_parameters()}
    state = {k: v + shift if k in parameters else v for k, v in ckpt["model"].items()}
    state["normalizer.velocity_std"] = 2 * state["normalizer.velocity_std"]
    path = tmp_path / name
    save_checkpoint(path, {**{k: v for k, v in ckpt.items() if k != "format"}, "model": state, "step": 7})
    return path, parameters


def test_parameters_are_the_weighted_mean_and_the_rest_is_the_last_checkpoints(tmp_path):
    shifted, parameters = _shifted_copy(tmp_path, 1.0)
    target = tmp_path / "mean.pt"
    write_average([checkpoint_path("multi_material"), shifted], [0.25, 0.75], target)
    original, last, mean = (load_checkpoint(p) for p in (checkpoint_path("multi_material"), shifted, target))
    assert set(mean["model"]) == set(original["model"])
    for name, tensor in mean["model"].items():
        if name in parameters:
            torch.testing.assert_close(tensor, original["model"][name] + 0.75, rtol=0, atol=1e-6)
        else:  # buffers (the normaliser) are the last checkpoint's, not a mean
            assert torch.equal(tensor, last["model"][name]), name
    assert mean["config"] == last["config"] and mean["step"] == 7
    assert load_model(target).normalizer.velocity_std.equal(2 * load_model("multi_material").normalizer.velocity_std)


def test_the_mean_of_a_checkpoint_with_itself_is_itself_bit_for_bit(tmp_path):
    target = tmp_path / "mean.pt"
    write_average(["multi_material", "multi_material"], [0.5, 0.5], target)
    before, after = load_checkpoint(checkpoint_path("multi_material")), load_checkpoint(target)
    for name, tensor in before["model"].items():
        assert torch.equal(tensor, after["model"][name]), name


@pytest.mark.parametrize(("weights", "count", "word"), [
    ([1.0], 1, "at least two"), ([0.5, 0.5, 0.0], 3, "> 0"), ([0.6, 0.6], 2, "sum to 1"),
    ([0.5], 2, "1 weights for 2"), ([float("nan"), 1.0], 2, "finite")])
def test_bad_weights_are_refused(weights, count, word):
    with pytest.raises(ValueError, match=word):
        check_average_weights(weights, count)


@pytest.mark.parametrize("change", ["drop", "shape"])
def test_checkpoints_of_different_networks_are_refused_and_nothing_is_written(tmp_path, change):
    ckpt = load_checkpoint(checkpoint_path("multi_material"))
    state = dict(ckpt["model"])
    name = next(k for k in state if k.endswith("weight"))
    if change == "drop":
        del state[name]
    else:
        state[name] = torch.zeros(*state[name].shape[:-1], state[name].shape[-1] + 1)
    other = tmp_path / "other.pt"
    save_checkpoint(other, {**{k: v for k, v in ckpt.items() if k != "format"}, "model": state})
    target = tmp_path / "mean.pt"
    with pytest.raises(ValueError, match="different tensors" if change == "drop" else "shape"):
        write_average([other, "multi_material"], [0.5, 0.5], target)
    assert not target.exists()
