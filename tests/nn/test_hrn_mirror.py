"""The mirror average of HRNConfig.mirror_average: exact equivariance under x -> -x, with
``mirror_planes="xy"`` under y -> -y and the half-turn about z too, and with ``"d4"`` under the
quarter-turns about z and the diagonal mirrors as well."""

import pytest
import torch
from toy_scene import structure, toy_window, trajectory

from hrn_pyg.data.graph import set_state
from hrn_pyg.nn.hrn import (
    HRN,
    HRNConfig,
    transform_normalised,
    untransform_normalised,
)
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim.step import build_inputs, step

SMALL = dict(hidden=16, depth=2, effect_dim=8, dropout_modules=("force", "collision"))
FLIP = torch.tensor([-1.0, 1.0, 1.0])


def _model(seed: int = 0, **kw) -> HRN:
    torch.manual_seed(seed)
    model = HRN(HRNConfig(**{**SMALL, **kw}))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()


def _scene(mirrored: bool, seed: int = 0, flip: torch.Tensor = FLIP):
    """The toy scene (a push on leaf 0 with an x and a y component), or its image under the
    diagonal reflection ``flip``."""
    leaves = trajectory(2, seed)
    force = torch.zeros(14, 3)
    force[0] = torch.tensor([0.5, 0.2, 2.0])
    if mirrored:
        leaves, force = leaves * flip, force * flip
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
        torch.testing.assert_close(mirror(build_inputs(mirror, g)), 0.5 * (a + transform_normalised(b, mean, std, FLIP)))
    assert "mirror_average=True" in repr(mirror) and "mirror_average" not in repr(plain)


def test_a_normalised_reflection_is_an_involution_and_reflects_the_value():
    mean, std = torch.tensor([0.3, -0.1, 2.0]), torch.tensor([2.0, 1.0, 0.5])
    v = torch.randn(5, 3)
    x = (v - mean) / std
    reflected = transform_normalised(x, mean, std, FLIP)
    torch.testing.assert_close(reflected, (v * FLIP - mean) / std)
    torch.testing.assert_close(transform_normalised(reflected, mean, std, FLIP), x)
    torch.testing.assert_close(untransform_normalised(reflected, mean, std, FLIP), x)


def test_masks_with_an_odd_number_of_rows_say_why():
    model = _model(mirror_average=True)
    inputs = build_inputs(model, _scene(False))
    with pytest.raises(ValueError, match=r"mirror-averaged model takes masks of 2 x copies rows.*'force' has 1"):
        model(inputs, {"force": torch.ones(1, 16)})
    assert _model().sample_masks(3, rate=0.1)["force"].shape == (3, 16)


FLIPS_XY = [torch.tensor(f) for f in ([-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [-1.0, -1.0, 1.0])]


@pytest.mark.parametrize("flip", FLIPS_XY, ids=["x", "y", "half-turn"])
def test_the_xy_average_is_equivariant_under_both_mirrors_and_the_half_turn(flip):
    """mirror_planes="xy": f(g s) = g f(s) for each of the group's three reflections; the
    x-only average is not equivariant under y -> -y (so the test can tell them apart)."""
    model = _model(mirror_average=True, mirror_planes="xy", rigid_fit=True, ground_contact=True)
    with torch.no_grad():
        pos = step(model, _scene(False)).pos
        pos_g = step(model, _scene(True, flip=flip)).pos
        torch.testing.assert_close(pos_g, pos * flip, atol=1e-6, rtol=0)
        x_only = _model(mirror_average=True, rigid_fit=True, ground_contact=True)
        y_flip = FLIPS_XY[1]
        gap = (step(x_only, _scene(True, flip=y_flip)).pos - step(x_only, _scene(False)).pos * y_flip).abs().max()
    assert gap > 1e-4


@pytest.mark.parametrize("kw", [{}, {"rigid_fit": True, "ground_contact": True}])
def test_a_half_turn_symmetric_body_at_rest_gets_no_horizontal_velocity_of_its_own(kw):
    """The toy cube and the square, each mapped onto itself by a half-turn about its own vertical
    axis, at rest and out of each other's reach: with the xy average their centres move only
    along z, whatever the weights; the plain network of the same weights moves them sideways."""
    from toy_scene import LEAF_OBJECT, leaf_rest_positions

    rest = leaf_rest_positions(separate=True)
    g = set_state(structure(), rest, rest, rest, radius=0.08)
    model = _model(mirror_average=True, mirror_planes="xy", **kw)
    plain = HRN(HRNConfig(**{**SMALL, **kw}))
    plain.load_state_dict(model.state_dict())
    plain.eval()
    with torch.no_grad():
        moved = step(model, g).pos[:14] - rest
        moved_plain = step(plain, g).pos[:14] - rest
    for obj in (0, 1):
        rows = LEAF_OBJECT == obj
        assert moved[rows, :2].mean(dim=0).abs().max() < 1e-7
        assert moved_plain[rows, :2].mean(dim=0).abs().max() > 1e-5


def test_bad_mirror_planes_say_which_are_allowed():
    with pytest.raises(ValueError, match=r"mirror_planes must be one of \['d4', 'x', 'xy'\], got 'z'"):
        HRNConfig(mirror_planes="z")
    assert HRNConfig(mirror_average=True, mirror_planes="xy").mirror_group == ((), (0,), (1,), (0, 1))
    assert HRNConfig(mirror_planes="xy").mirror_group == ((),)  # the planes act only with the average
    model = _model(mirror_average=True, mirror_planes="xy")
    assert model.sample_masks(3, rate=0.1)["force"].shape == (12, 16)
    with pytest.raises(ValueError, match=r"masks of 4 x copies rows.*'force' has 2"):
        model(build_inputs(model, _scene(False)), {"force": torch.ones(2, 16)})


def test_the_reflection_signs_are_a_buffer_of_the_module_not_of_the_checkpoint():
    """The group's signs are made once and move with the module (a step builds no tensor from
    host data); they stay out of the state dict, so checkpoints are unchanged."""
    model = _model(mirror_average=True, mirror_planes="xy")
    expected = torch.tensor([[1.0, 1.0, 1.0], [-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [-1.0, -1.0, 1.0]])
    assert torch.equal(model.mirror_signs, expected)
    assert "mirror_signs" not in model.state_dict()
    plain = HRN(HRNConfig(**SMALL))
    plain.load_state_dict(model.state_dict())  # the same keys with and without the average
    assert torch.equal(plain.mirror_signs, torch.ones(1, 3))
    with torch.no_grad():
        single = step(model, _scene(False)).pos
        model.double()
        assert model.mirror_signs.dtype == torch.float64
        g = _scene(False)
        for store in g.node_stores:
            for key, value in list(store.items()):
                if torch.is_tensor(value) and value.is_floating_point():
                    store[key] = value.double()
        doubled = step(model, g).pos
    torch.testing.assert_close(doubled.float(), single, atol=1e-5, rtol=0)


def _turned(v: torch.Tensor, flip: torch.Tensor) -> torch.Tensor:
    """``f * P v``: x and y exchanged, then the axes where ``flip`` is -1 negated."""
    return v[..., [1, 0, 2]] * flip


@pytest.mark.parametrize("flip", [torch.tensor(f) for f in ([-1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 1.0])],
                         ids=["quarter-turn", "diagonal", "three-quarter-turn"])
@pytest.mark.parametrize("kw", [{"rigid_fit": True, "ground_contact": True}, {"rest_offsets": True}])
def test_the_d4_average_is_equivariant_under_the_quarter_turns_and_diagonal_mirrors(flip, kw):
    """mirror_planes="d4": f(g s) = g f(s) for g = f * P (P exchanges x and y), though the
    normaliser's x and y statistics differ; the xy average is not equivariant under them."""
    model = _model(mirror_average=True, mirror_planes="d4", **kw)
    assert not torch.allclose(model.normalizer.velocity_std[0], model.normalizer.velocity_std[1])
    leaves = trajectory(2, 0)
    force = torch.zeros(14, 3)
    force[0] = torch.tensor([0.5, 0.2, 2.0])

    def scene(turn: bool):
        ls, fs = (_turned(leaves, flip), _turned(force, flip)) if turn else (leaves, force)
        return set_state(structure(), ls[0], ls[1], ls[2], radius=0.08, force=fs)

    with torch.no_grad():
        pos = step(model, scene(False)).pos
        pos_g = step(model, scene(True)).pos
        torch.testing.assert_close(pos_g, _turned(pos, flip), atol=1e-6, rtol=0)
        xy = _model(mirror_average=True, mirror_planes="xy", **kw)
        gap = (step(xy, scene(True)).pos - _turned(step(xy, scene(False)).pos, flip)).abs().max()
    assert gap > 1e-5  # against a tolerance of 1e-6 above


def test_a_normalised_swap_turns_the_value_and_its_inverse_undoes_it():
    mean, std = torch.tensor([0.3, -0.1, 2.0]), torch.tensor([2.0, 1.0, 0.5])
    flip = torch.tensor([1.0, -1.0, 1.0])
    v = torch.randn(5, 4)
    x = torch.cat([(v[:, :3] - mean) / std, v[:, 3:]], dim=-1)
    turned = transform_normalised(x, mean, std, flip, swap=True)
    torch.testing.assert_close(turned[:, :3], (_turned(v[:, :3], flip) - mean) / std)
    torch.testing.assert_close(turned[:, 3:], x[:, 3:])  # other columns untouched
    torch.testing.assert_close(untransform_normalised(turned, mean, std, flip, swap=True), x)


def test_d4_draws_eight_mask_blocks():
    model = _model(mirror_average=True, mirror_planes="d4")
    assert len(model.config.mirror_group) == 8 and model.sample_masks(2, rate=0.1)["force"].shape == (16, 16)
    masks = model.sample_masks(1, rate=0.3, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        inputs = build_inputs(model, _scene(False))
        assert (model(inputs, masks) - model(inputs)).abs().max() > 1e-3
