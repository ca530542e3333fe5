import pytest
import torch

from hrn_pyg.nn.force import ForceModule
from hrn_pyg.nn.mlp import MLPConfig, dropout_mask

CFG = MLPConfig(hidden=16, depth=2)


def _inputs(n=6, s=5, seed=0):
    gen = torch.Generator().manual_seed(seed)
    state = torch.randn(n, s, generator=gen)
    force = torch.zeros(n, 3)
    force[1] = torch.tensor([1.0, 0.0, 0.0])
    force[4] = torch.tensor([0.0, -2.0, 0.5])
    return state, force


def test_shapes_and_only_forced_rows_nonzero():
    torch.manual_seed(0)
    m = ForceModule(5, 7, CFG)
    state, force = _inputs()
    out = m(state, force)
    assert out.shape == (6, 7)
    assert torch.equal(out[[0, 2, 3, 5]], torch.zeros(4, 7))
    expected = m.phi(torch.cat([state, force], -1))[[1, 4]]
    torch.testing.assert_close(out[[1, 4]], expected)


def test_no_force_gives_exact_zero():
    m = ForceModule(5, 7, CFG)
    state, _ = _inputs()
    out = m(state, torch.zeros(6, 3))
    assert torch.equal(out, torch.zeros(6, 7))
    assert m(state[:0], torch.zeros(0, 3)).shape == (0, 7)


def test_mask_rate_zero_is_deterministic_and_mask_follows_batch():
    torch.manual_seed(0)
    m = ForceModule(5, 7, CFG)
    state, force = _inputs()
    batch = torch.tensor([0, 0, 0, 1, 1, 1])
    plain = m(state, force)
    ones = dropout_mask(2, 16, 0.0)
    assert torch.equal(m(state, force, ones, batch), plain)
    # copy 1 dropped entirely: only row 4 (copy 1) changes, to phi's output bias path
    mask = torch.stack([torch.ones(16), torch.zeros(16)])
    out = m(state, force, mask, batch)
    assert torch.equal(out[1], plain[1])
    torch.testing.assert_close(out[4], m.phi.output_layer.bias)


def test_bad_input_and_repr():
    m = ForceModule(5, 7, CFG)
    state, force = _inputs()
    with pytest.raises(ValueError, match="force"):
        m(state, force[:, :2])
    with pytest.raises(ValueError, match="state"):
        m(state[:, :4], force)
    with pytest.raises(ValueError, match="batch index"):
        m(state, force, torch.ones(1, 16))
    assert "ForceModule(state_dim=5, effect_dim=7" in repr(m)
    before = m.phi.output_layer.weight.clone()
    m.reset_parameters()
    assert not torch.equal(before, m.phi.output_layer.weight)


def test_dense_path_equals_the_gathered_one():
    """``dense=True`` runs phi_F on every row and zeroes the unforced ones: the same effect, also
    with a mask per batch copy, and exact zeros where there is no force."""
    torch.manual_seed(0)
    m = ForceModule(5, 7, CFG)
    state, force = _inputs()
    torch.testing.assert_close(m(state, force, dense=True), m(state, force))
    assert torch.equal(m(state, force, dense=True)[[0, 2, 3, 5]], torch.zeros(4, 7))
    batch = torch.tensor([0, 0, 0, 1, 1, 1])
    mask = dropout_mask(2, 16, 0.5, torch.Generator().manual_seed(1))
    torch.testing.assert_close(m(state, force, mask, batch, dense=True), m(state, force, mask, batch))
    assert torch.equal(m(state, torch.zeros(6, 3), dense=True), torch.zeros(6, 7))
