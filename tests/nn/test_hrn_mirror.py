"""The mirror average of HRNConfig.mirror_average: exact equivariance under x -> -x."""

import pytest
import torch

from hrn_pyg.data.graph import set_state
from hrn_pyg.nn.hrn import HRN, HRNConfig, reflect_normalised
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.rollout import build_inputs, step
from toy_scene import structure, toy_window, trajectory

SMALL = dict(hidden=16, depth=2, effect_dim=8, dropout_modules=("force", "collision"))
FLIP = torch.tensor([-1.0, 1.0, 1.0])


def _model(seed: int = 0, **kw) -> HRN:
    torch.manual_seed(seed)
    model = HRN(HRNConfig(**{**SMALL, **kw}))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()


def _scene(mirrored: bool, seed: int = 0):
    """The toy scene (a push on leaf 0 with an x component), or its mirror image in x = 0."""
    leaves = trajectory(2, seed)
    force = torch.zeros(14, 3)
    force[0] = torch.tensor([0.5, 0.2, 2.0])
    if mirrored:
        leaves, force = leaves * FLIP, force * FLIP
    return set_state(structure(), leaves[0], leaves[1], leaves[2], radius=0.08, force=force)


@pytest.mark.parametrize("kw", [{}, {"rigid_fit": True, "ground_contact": True}, {"rest_offsets": True}])
def test_a_mirrored_scene_gets_the_mirrored_step(kw):
    """f(M s) = M f(s) to float precision, for a network that is not symmetric by itself
    (the plain model's two answers differ by far more)."""
    model = _model(mirror_average=True, **kw)
    with torch.no_grad():
        pos = step(model, _scene(False)).pos
        pos_m = step(model, _scene(True)).pos
        torch.testing.assert_close(pos_m, pos * FLIP, atol=1e-6, rtol=0)
        plain = _model(**kw)
        gap = (step(plain, _scene(True)).pos - step(plain, _scene(False)).pos * FLIP).abs().max()
    assert gap > 1e-4


def test_masks_one_half_per_pass_and_swapped_halves_mirror_the_samples():
    """sample_masks draws 2 k rows; the mirrored scene with the halves swapped is the
    mirror image of the sample, so a sample has no side of its own either."""
    model = _model(mirror_average=True)
    masks = model.sample_masks(1, rate=0.4, generator=torch.Generator().manual_seed(1))
    assert {m.shape for m in masks.values()} == {(2, 16)}
    swapped = {k: m.flip(0) for k, m in masks.items()}
    with torch.no_grad():
        pos = step(model, _scene(False), masks=masks).pos
        pos_m = step(model, _scene(True), masks=swapped).pos
        inputs = build_inputs(model, _scene(False))
        masked, unmasked = model(inputs, masks), model(inputs)
    torch.testing.assert_close(pos_m, pos * FLIP, atol=1e-6, rtol=0)
    assert (masked - unmasked).abs().max() > 1e-2  # the masks act


def test_the_average_of_both_passes_by_hand():
    """out = (f(s) + reflect(f(M s))) / 2 with f the plain network of the same weights."""
    mirror = _model(mirror_average=True)
    plain = HRN(HRNConfig(**SMALL))
    plain.load_state_dict(mirror.state_dict())
    plain.eval()
    g, g_m = _scene(False), _scene(True)
    with torch.no_grad():
        a = plain(build_inputs(plain, g))
        b = plain(build_inputs(plain, g_m))
        mean, std = plain.normalizer.target_stats(g["particle"].is_root)
        torch.testing.assert_close(mirror(build_inputs(mirror, g)), 0.5 * (a + reflect_normalised(b, mean, std)))
    assert "mirror_average=True" in repr(mirror) and "mirror_average" not in repr(plain)


def test_reflect_normalised_is_an_involution_and_reflects_the_value():
    mean, std = torch.tensor([0.3, -0.1, 2.0]), torch.tensor([2.0, 1.0, 0.5])
    v = torch.randn(5, 3)
    x = (v - mean) / std
    torch.testing.assert_close(reflect_normalised(x, mean, std), (v * FLIP - mean) / std)
    torch.testing.assert_close(reflect_normalised(reflect_normalised(x, mean, std), mean, std), x)


def test_masks_with_an_odd_number_of_rows_say_why():
    model = _model(mirror_average=True)
    inputs = build_inputs(model, _scene(False))
    with pytest.raises(ValueError, match=r"mirror-averaged model takes masks of 2 x copies rows.*'force' has 1"):
        model(inputs, {"force": torch.ones(1, 16)})
    assert _model().sample_masks(3, rate=0.1)["force"].shape == (3, 16)
