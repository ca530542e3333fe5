"""The horizontally equivariant HRN (HRNConfig.equivariant): one pass commutes with every turn
about z and every mirror in a vertical plane, with or without the model's other options."""

import math

import pytest
import torch
from toy_scene import structure, toy_window, trajectory

from hrn_pyg.data.graph import set_pitch, set_state
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer, isotropic_horizontal
from hrn_pyg.sim.step import build_inputs, step

SMALL = dict(hidden=16, depth=2, effect_dim=8, vector_channels=4, dropout_modules=("force", "collision"))


def _model(seed: int = 0, **kw) -> HRN:
    """A fresh equivariant HRN with a fitted, isotropic normaliser and a random horizontal
    readout (a fresh one starts at zero, which would make every horizontal check trivial)."""
    torch.manual_seed(seed)
    model = HRN(HRNConfig(**{**SMALL, "equivariant": True, **kw}))
    torch.nn.init.normal_(model.state.vector.weight, std=0.5)
    torch.nn.init.normal_(model.state.vector.bias, std=0.5)
    windows = [set_pitch(toy_window(4, seed=s), 0.04) for s in range(3)]
    fit_normalizer(windows, model.normalizer, reference_pitch=0.05 if kw.get("pitch_aware") else None)
    isotropic_horizontal(model.normalizer)
    return model.eval()


def _map(angle: float, mirror: bool = False) -> torch.Tensor:
    """``[3, 3]``: a turn by ``angle`` about z, after the mirror y -> -y when ``mirror``."""
    c, s = math.cos(angle), math.sin(angle)
    turn = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return turn @ torch.diag(torch.tensor([1.0, -1.0 if mirror else 1.0, 1.0]))


def _scene(g: torch.Tensor | None = None, seed: int = 0):
    """The toy scene with a push on leaf 0 (x, y and z components), mapped by ``g``."""
    leaves = trajectory(2, seed)
    force = torch.zeros(14, 3)
    force[0] = torch.tensor([0.5, 0.2, 2.0])
    if g is not None:
        leaves, force = leaves @ g.T, force @ g.T
    return set_state(set_pitch(structure(), 0.04), leaves[0], leaves[1], leaves[2], radius=0.08, force=force)


MAPS = [(0.3, False), (math.pi / 2, False), (2.0, True), (0.0, True), (math.pi, False)]
OPTIONS = [{}, {"rigid_fit": True, "ground_contact": True}, {"rest_offsets": True, "corotated_rest": True},
           {"pitch_aware": True}, {"collision_force": True}]


@pytest.mark.parametrize("kw", OPTIONS, ids=["plain", "rigid-fit", "rest-offsets", "pitch-aware", "collision-force"])
@pytest.mark.parametrize("angle,mirror", MAPS)
def test_a_mapped_scene_gets_the_mapped_step(kw, angle, mirror):
    """step(g s) = g step(s) to float precision, for any turn about z and any vertical mirror,
    in one pass; the plain network of the same size misses by far more."""
    g = _map(angle, mirror)
    model = _model(**kw)
    with torch.no_grad():
        pos = step(model, _scene()).pos
        pos_g = step(model, _scene(g)).pos
    torch.testing.assert_close(pos_g, pos @ g.T, atol=2e-6, rtol=0)
    with torch.no_grad():
        horizontal = model(build_inputs(model, _scene()))[:, :2]
    assert horizontal.abs().max() > 1e-2  # the network does answer sideways


def test_the_plain_network_has_a_direction_of_its_own():
    """The check above can fail: a plain network of the same size maps a turned scene to a
    step that is not the turned step."""
    g = _map(0.3)
    torch.manual_seed(0)
    plain = HRN(HRNConfig(**SMALL))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], plain.normalizer)
    isotropic_horizontal(plain.normalizer)
    with torch.no_grad():
        gap = (step(plain.eval(), _scene(g)).pos - step(plain, _scene()).pos @ g.T).abs().max()
    assert gap > 2e-5  # ten times the tolerance the equivariant network meets


def test_dropout_samples_are_equivariant_mask_by_mask():
    """One mask per trajectory copy acts on invariant hidden units: each sample of the mapped
    scene is the mapped sample, and the masks change the answer."""
    g = _map(1.1, mirror=True)
    model = _model()
    masks = model.sample_masks(1, rate=0.4, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        pos = step(model, _scene(), masks=masks).pos
        pos_g = step(model, _scene(g), masks=masks).pos
        unmasked = step(model, _scene()).pos
    torch.testing.assert_close(pos_g, pos @ g.T, atol=2e-6, rtol=0)
    assert (pos - unmasked).abs().max() > 1e-6


def test_a_body_symmetric_under_a_quarter_turn_gets_no_horizontal_velocity():
    """A scene that a quarter-turn about the z-axis through the origin maps onto itself (leaves
    at rest, here the toy cube centred on the axis alone) gets no horizontal motion of its centre
    whatever the weights: its own image under the turn must get the turned answer."""
    model = _model(seed=5, rigid_fit=True, ground_contact=True)
    leaves = trajectory(0, 0)[0]
    rest = torch.cat([leaves[:8], torch.tensor([[5.0, 5.0, 0.3]] * 4), leaves[12:] + torch.tensor([0.0, 3.0, 0.0])])
    graph = set_state(structure(), rest, rest, rest, radius=0.08)
    with torch.no_grad():
        out = step(model, graph).pos[:8]
    assert out[:, :2].mean(0).abs().max() < 1e-6


def test_gradients_reach_every_module():
    model = _model(rest_offsets=True).train()
    inputs = build_inputs(model, _scene())
    model(inputs).square().sum().backward()
    for name in ("force", "collision", "history", "l2a", "ws", "a2d", "state"):
        grads = [p.grad for p in getattr(model, name).parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads), name
        assert any(g.abs().sum() > 0 for g in grads), name


def test_skipping_idle_modules_changes_nothing():
    """With no force the force module is skipped; running it on zero input gives the same."""
    model = _model()
    graph = set_state(structure(), *trajectory(2, 1), radius=0.08)
    run_all = HRN(HRNConfig(**{**SMALL, "equivariant": True, "skip_idle_modules": False}))
    assert model.state.vector.weight.abs().sum() > 0
    run_all.load_state_dict(model.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(step(run_all.eval(), graph).pos, step(model, graph).pos, atol=1e-7, rtol=0)


@pytest.mark.parametrize("kw,words", [
    ({"mirror_average": True}, "mirror_average"),
    ({"vector_channels": 0}, "vector_channels"),
])
def test_bad_settings_say_what_is_wrong(kw, words):
    with pytest.raises(ValueError, match=words):
        HRNConfig(**{**SMALL, "equivariant": True, **kw})


def test_the_config_round_trips_and_says_it_is_equivariant():
    config = HRNConfig(**{**SMALL, "equivariant": True})
    assert HRNConfig.from_dict(config.to_dict()) == config
    assert "equivariant=True, vector_channels=4" in repr(HRN(config))


def test_a_fresh_model_predicts_no_horizontal_change():
    """The horizontal readout starts at zero: an unrolled rollout of a fresh model cannot grow
    sideways without bound before training has begun."""
    torch.manual_seed(0)
    model = HRN(HRNConfig(**{**SMALL, "equivariant": True})).eval()
    with torch.no_grad():
        out = model(build_inputs(model, _scene()))
    assert torch.equal(out[:, :2], torch.zeros_like(out[:, :2])) and out[:, 2].abs().max() > 0


def test_the_output_grows_at_most_linearly_with_the_speed():
    """Every velocity times 1e3 and then 1e4: the output grows about tenfold, not a hundredfold
    (no input or vector of the readout grows with the speed's square), as a plain MLP's would."""
    model = _model(rest_offsets=True)
    inputs = build_inputs(model, _scene())

    def output_at(speed: float) -> float:
        scale = torch.ones(inputs.state.size(1))
        scale[:3] = speed
        fast = inputs._replace(state=inputs.state * scale, prev_state=inputs.prev_state * scale)
        with torch.no_grad():
            return float(model(fast).abs().max())

    ratio = output_at(1e4) / output_at(1e3)
    assert 2.0 < ratio < 15.0
