"""Rigid shape matching (hrn_pyg.nn.rigid) and its use in the model's decoder."""

import math

import pytest
import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.graph import NODE, build_structure, set_state
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.nn.rigid import fit_rigid_motion, polar_rotation
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.step import root_of, step

SMALL = dict(hidden=16, depth=2, effect_dim=8)


def _rotation(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _pairwise(x):
    return (x[..., :, None, :] - x[..., None, :, :]).norm(dim=-1)


def _cube(n=3, side=0.1):
    g = torch.linspace(-side / 2, side / 2, n, dtype=torch.float64)
    return torch.cartesian_prod(g, g, g)


def test_polar_rotation_recovers_the_rotation_of_a_stretched_rotation():
    r = _rotation([1.0, 2.0, -0.5], 0.7)
    p = torch.tensor([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 0.5]], dtype=torch.float64)
    q = polar_rotation((r @ p)[None])[0]
    assert torch.allclose(q, r, atol=1e-10)
    assert torch.allclose(q @ q.T, torch.eye(3, dtype=torch.float64), atol=1e-10)


def test_exact_rigid_motion_is_kept_and_shapes_hold_under_noise():
    gen = torch.Generator().manual_seed(0)
    a = torch.cat([_cube(), _cube() + torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)])
    group = torch.tensor([0] * 27 + [1] * 27)
    mass = torch.rand(54, generator=gen, dtype=torch.float64) + 0.5
    r0, r1 = _rotation([0, 0, 1], 0.3), _rotation([1, 1, 0], -1.1)
    exact = torch.cat([a[:27] @ r0.T + 0.2, a[27:] @ r1.T - 0.4])
    assert torch.allclose(fit_rigid_motion(a, exact, mass, group, 2), exact, atol=1e-9)

    noisy = exact + 0.003 * torch.randn(exact.shape, generator=gen, dtype=torch.float64)
    fitted = fit_rigid_motion(a, noisy, mass, group, 2)
    for sl in (slice(0, 27), slice(27, 54)):
        assert torch.allclose(_pairwise(fitted[sl]), _pairwise(a[sl]), atol=1e-9)
        # the mass-weighted centre moves exactly as predicted
        m = mass[sl, None]
        assert torch.allclose((m * fitted[sl]).sum(0), (m * noisy[sl]).sum(0), atol=1e-9)
    # and the fit is closer to the prediction than the unrotated shape at the same centre
    assert (fitted - noisy).norm() < (exact - noisy).norm() + 1e-9


def test_gradient_of_an_isotropic_cube_is_finite():
    """A cube's covariance has three equal singular values, where an SVD's gradient is not
    defined; the polar iteration's is."""
    a = _cube(2).float()
    pred = (a @ _rotation([0, 0, 1], 0.05).float().T + 0.01).requires_grad_(True)
    out = fit_rigid_motion(a, pred, torch.ones(8), torch.zeros(8, dtype=torch.long), 1)
    (out ** 2).sum().backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_a_group_without_weight_gives_no_nan():
    a = torch.randn(5, 3)
    out = fit_rigid_motion(a, a + 1.0, torch.tensor([1.0, 1.0, 0.0, 0.0, 0.0]),
                           torch.tensor([0, 0, 1, 1, 2]), 3)
    assert torch.isfinite(out).all()
    assert torch.allclose(out[:2], a[:2] + 1.0, atol=1e-5)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="current and predicted"):
        fit_rigid_motion(torch.zeros(4, 3), torch.zeros(4, 2), torch.ones(4), torch.zeros(4, dtype=torch.long), 1)
    with pytest.raises(ValueError, match="mass and group"):
        fit_rigid_motion(torch.zeros(4, 3), torch.zeros(4, 3), torch.ones(3), torch.zeros(4, dtype=torch.long), 1)
    with pytest.raises(ValueError, match=r"\[G, 3, 3\]"):
        polar_rotation(torch.eye(3))


def _model(**kw):
    torch.manual_seed(0)
    model = HRN(HRNConfig(**{**SMALL, **kw}))
    fit_normalizer([toy_window(4)], model.normalizer)
    return model


def test_root_of_the_toy_scene():
    roots = root_of(toy_scene())
    assert roots.tolist() == [16] * 8 + [17] * 4 + [18] * 2 + [16, 16, 16, 17, 18]


def test_rigid_fit_keeps_the_rigid_square_exact_over_a_long_rollout():
    model = _model(rigid_fit=True)
    with torch.no_grad():  # a strong random output: the unfitted square deforms visibly
        model.state.psi.output_layer.weight.mul_(3.0)
    g = toy_scene(separate=True)
    square = slice(8, 12)
    rest = _pairwise(g[NODE].pos[square])
    with torch.no_grad():
        pos = rollout(model, g, 100)
        free = rollout(_model_like(model, rigid_fit=False), g, 100)
    assert torch.isfinite(pos).all()
    drift = (_pairwise(pos[:, square]) - rest).abs().max()
    assert drift < 1e-4
    assert (_pairwise(free[:, square]) - rest).abs().max() > 100 * drift


def _model_like(model, **kw):
    other = HRN(HRNConfig(**{**model.config.to_dict(), **kw}))
    other.load_state_dict(model.state_dict())
    return other


def test_rigid_fit_changes_only_rigid_rows_and_passes_gradients():
    fit = _model(rigid_fit=True)
    plain = _model_like(fit, rigid_fit=False)
    g = toy_scene()
    a, b = step(fit, g), step(plain, g)
    soft_and_static = torch.cat([torch.arange(0, 8), torch.arange(12, 16), torch.tensor([16, 18])])
    assert torch.equal(a.pos[soft_and_static], b.pos[soft_and_static])
    assert not torch.allclose(a.pos[8:12], b.pos[8:12])
    a.pos[8:12].sum().backward()
    grads = [p.grad for p in fit.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(gr).all() for gr in grads)


def test_rest_offsets_and_ground_contact_inputs():
    model = _model(rest_offsets=True, ground_contact=True)
    g = toy_scene()
    from hrn_pyg.sim.step import build_inputs

    inputs = build_inputs(model, g)
    assert inputs.state.shape[1] == model.config.state_dim == HRNConfig().state_dim + 1
    # the ground column is the height clipped at the collision radius
    z = g[NODE].pos[:, 2]
    assert torch.allclose(inputs.state[:, -1], (z / 0.08).clamp(-1, 1))
    # without a recorded rest shape the current one is used; shifting the rest shape as a whole
    # changes nothing (only offsets enter)
    out = model(inputs)
    g2 = g.clone()
    g2[NODE].rest_pos = g[NODE].pos + 3.0
    assert torch.allclose(model(build_inputs(model, g2)), out, atol=1e-5)
    g2[NODE].rest_pos = g[NODE].pos * 1.5  # a different rest shape is seen
    assert not torch.allclose(model(build_inputs(model, g2)), out, atol=1e-4)
    with pytest.raises(ValueError, match="rest_pos"):
        model(inputs._replace(rest_pos=None))
    with pytest.raises(ValueError, match="ground_contact"):
        HRNConfig(ground_contact=True, collision_radius=0.0)


def test_build_structure_stores_the_rest_shape():
    from toy_scene import LEAF_OBJECT, MATERIAL, PARENT, STIFFNESS, leaf_rest_positions

    mass = torch.ones(14)
    rest = leaf_rest_positions()
    s = build_structure(PARENT, mass, LEAF_OBJECT, MATERIAL, STIFFNESS, rest_pos=rest)
    assert torch.equal(s[NODE].rest_pos[:14], rest)
    assert torch.allclose(s[NODE].rest_pos[17], rest[8:12].mean(0))
    with pytest.raises(ValueError, match="rest_pos"):
        build_structure(PARENT, mass, LEAF_OBJECT, MATERIAL, STIFFNESS, rest_pos=rest[:5])
    set_state(s, rest, rest, rest, radius=0.08)  # a state can be set on it as before


def _hard_matrices(gen: torch.Generator) -> torch.Tensor:
    """Covariances as rigid fits see them: random, rotations times SPD factors of condition 1 to
    1e6, isotropic (a cube), rank one (collinear leaves), zero (no weight) and tiny ones."""
    out = [torch.randn(64, 3, 3, generator=gen, dtype=torch.float64)]
    for cond in (1.0, 1e2, 1e6):
        q, _ = torch.linalg.qr(torch.randn(64, 3, 3, generator=gen, dtype=torch.float64))
        u, _ = torch.linalg.qr(torch.randn(64, 3, 3, generator=gen, dtype=torch.float64))
        s = torch.exp(torch.rand(64, 3, generator=gen, dtype=torch.float64) * math.log(cond))
        out.append(q @ u @ torch.diag_embed(s) @ u.transpose(1, 2))
    v = torch.randn(8, 3, 1, generator=gen, dtype=torch.float64)
    out += [v @ v.transpose(1, 2), torch.zeros(2, 3, 3, dtype=torch.float64),
            1e-30 * torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)]
    return torch.cat(out).float()


def test_the_numpy_polar_rotation_is_the_torch_one_bit_for_bit():
    from hrn_pyg.nn.rigid import polar_rotation_numpy, polar_rotation_torch

    m = _hard_matrices(torch.Generator().manual_seed(5))
    fast = polar_rotation_numpy(m)
    assert fast.dtype == torch.float32
    assert torch.equal(fast, polar_rotation_torch(m))
    with torch.no_grad():
        assert torch.equal(polar_rotation(m), fast)
    nan = torch.full((1, 3, 3), float("nan"))
    assert torch.isnan(polar_rotation_numpy(nan)).all() and torch.isnan(polar_rotation_torch(nan)).all()


def test_polar_rotation_takes_the_torch_path_for_a_gradient():
    m = _hard_matrices(torch.Generator().manual_seed(6))[:8].requires_grad_(True)
    polar_rotation(m).sum().backward()
    assert m.grad is not None and torch.isfinite(m.grad).all()


def _rotation_about(axis_angle: torch.Tensor) -> torch.Tensor:
    return _rotation(axis_angle.tolist(), float(axis_angle.norm())).float()


def test_a_fit_from_the_rest_shape_carries_no_rounding_from_step_to_step():
    """1000 fits of a rigid square, each to a slightly noisy turn of the last: fitted from the
    current leaves the square's pairwise distances drift by the rounding of every step; fitted
    from its rest shape they stay those of the rest shape to less than one float32 rounding."""
    from hrn_pyg.sim.step import rigid_leaf_positions

    g = toy_scene(separate=True)
    g[NODE].rest_pos = g[NODE].pos.clone()
    square = slice(8, 12)
    rest = _pairwise(g[NODE].rest_pos[square].double())
    drift = {}
    for from_rest in (False, True):
        gen = torch.Generator().manual_seed(0)
        h = g.clone()
        for _ in range(1000):
            turn = _rotation_about(0.05 * torch.randn(3, generator=gen, dtype=torch.float64))
            centre = h[NODE].pos[square].mean(0)
            pred = h[NODE].pos.clone()
            pred[square] = (pred[square] - centre) @ turn.T + centre + 1e-3 * torch.randn(4, 3, generator=gen)
            h[NODE].pos = rigid_leaf_positions(h, pred, None, from_rest)
        assert h[NODE].pos[square].abs().max() < 2.0  # near the origin: one rounding is below 2.4e-7
        drift[from_rest] = float((_pairwise(h[NODE].pos[square].double()) - rest).abs().max())
    assert drift[True] < 1.2e-7
    assert drift[False] > 5 * drift[True]


def test_rigid_fit_rest_moves_a_rigid_body_as_the_fit_from_its_leaves_does():
    current = _model(rigid_fit=True)
    from_rest = _model_like(current, rigid_fit_rest=True)
    g = toy_scene(separate=True)
    # no rest shape in the graph: fitted from the current leaves, bit for bit
    assert torch.equal(step(from_rest, g).pos, step(current, g).pos)
    # the rest shape elsewhere and turned: the same motion to rounding, other rows untouched
    turn = _rotation_about(torch.tensor([0.2, -0.4, 0.9], dtype=torch.float64))
    g[NODE].rest_pos = g[NODE].pos @ turn.T + torch.tensor([2.0, -1.0, 0.5])
    a, b = step(from_rest, g).pos, step(current, g).pos
    assert torch.allclose(a, b, rtol=0, atol=1e-6)
    others = torch.cat([torch.arange(0, 8), torch.arange(12, 17), torch.tensor([18])])
    assert torch.equal(a[others], b[others])
    assert "rigid_fit_rest=True" in repr(from_rest)


def test_rigid_fit_rest_can_be_named_alone_for_a_fine_tuning(tmp_path):
    """``--model-rigid-fit-rest true`` named alone: without ``--init-from`` the command line's
    config is the defaults with that option, so it must be a valid config on its own, and
    without the rigid fit it changes nothing."""
    import argparse

    from hrn_pyg.train import add_arguments, config_from_args

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    _, config = config_from_args(parser.parse_args(
        ["--preset", "ours", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--model-rigid-fit-rest", "true"]))
    assert config.rigid_fit_rest and not config.rigid_fit
    plain = _model()
    inert = _model_like(plain, rigid_fit_rest=True)
    g = toy_scene(separate=True)
    g[NODE].rest_pos = g[NODE].pos + 1.0
    assert torch.equal(step(inert, g).pos, step(plain, g).pos)
