import pytest
import torch

from hrn_pyg.nn.collision import CollisionModule, safe_norm
from hrn_pyg.nn.mlp import MLPConfig

CFG = MLPConfig(hidden=16, depth=2)


def _inputs(seed=0):
    gen = torch.Generator().manual_seed(seed)
    state = torch.randn(5, 4, generator=gen)
    pos = torch.randn(5, 3, generator=gen)
    edge_index = torch.tensor([[1, 2, 0, 4], [0, 0, 3, 3]])  # j -> i
    return state, pos, edge_index


def test_matches_brute_force_sum():
    torch.manual_seed(0)
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    out = m(state, pos, ei)
    assert out.shape == (5, 6)
    expected = torch.zeros(5, 6)
    for j, i in ei.t().tolist():  # brute force over the 4 edges
        off = pos[i] - pos[j]
        feat = torch.cat([state[i], state[j], off, off.norm().reshape(1)])
        expected[i] += m.phi(feat[None])[0]
    torch.testing.assert_close(out, expected)
    # nodes 1, 2, 4 receive nothing: exact zero, no bias leaking
    assert torch.equal(out[[1, 2, 4]], torch.zeros(3, 6))


def test_empty_edge_set_gives_exact_zero():
    m = CollisionModule(4, 6, CFG)
    state, pos, _ = _inputs()
    out = m(state, pos, torch.empty(2, 0, dtype=torch.long))
    assert torch.equal(out, torch.zeros(5, 6))


def test_translation_invariant():
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    torch.testing.assert_close(m(state, pos, ei), m(state, pos + torch.tensor([3.0, -2.0, 1.0]), ei))


def test_gradient_finite_at_coincident_particles():
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    pos = pos.clone()
    pos[1] = pos[0]
    pos.requires_grad_(True)
    m(state, pos, ei).sum().backward()
    assert torch.isfinite(pos.grad).all()
    assert safe_norm(torch.zeros(1, 3)).item() > 0


def test_mask_indexed_by_destination_copy():
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    batch = torch.tensor([0, 0, 0, 1, 1])
    plain = m(state, pos, ei)
    assert torch.equal(m(state, pos, ei, torch.ones(2, 16), batch), plain)
    out = m(state, pos, ei, torch.stack([torch.ones(16), torch.zeros(16)]), batch)
    assert torch.equal(out[0], plain[0])
    # node 3 has two incoming edges whose hidden units are all dropped: 2 x output bias
    torch.testing.assert_close(out[3], 2 * m.phi.output_layer.bias)


def test_bad_input_and_repr():
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    with pytest.raises(ValueError, match="edge_index"):
        m(state, pos, ei[0])
    with pytest.raises(ValueError, match="pos"):
        m(state, pos[:, :2], ei)
    with pytest.raises(ValueError, match="batch"):
        m(state, pos, ei, torch.ones(1, 16))
    assert repr(m).startswith("CollisionModule(state_dim=4, effect_dim=6")


def test_inference_path_gives_the_autograd_numbers_and_leaves_inputs_alone():
    torch.manual_seed(0)
    m = CollisionModule(3, 5, MLPConfig(hidden=8, depth=2))
    gen = torch.Generator().manual_seed(2)
    s, x = torch.randn(4, 3, generator=gen), torch.randn(4, 3, generator=gen)
    ei = torch.tensor([[0, 1, 2, 3], [1, 0, 3, 2]])
    kept = s.clone(), x.clone()
    with_grad = m(s, x, ei)
    with torch.no_grad():  # the in-place path
        assert torch.equal(m(s, x, ei), with_grad.detach())
    assert torch.equal(kept[0], s) and torch.equal(kept[1], x)


def test_edge_weight_zero_removes_the_edge_exactly():
    """A candidate of weight 0 adds an exact zero and no bias: the result of the edge set without
    it (to rounding: the first layer's product runs over more rows), with autograd too (where the
    weight is not applied in place); a node whose edges all weigh 0 gets an exact zero."""
    torch.manual_seed(0)
    m = CollisionModule(4, 6, CFG)
    state, pos, ei = _inputs()
    weight = torch.tensor([1.0, 0.0, 1.0, 0.0])
    kept = ei[:, weight.bool()]
    with torch.no_grad():
        torch.testing.assert_close(m(state, pos, ei, edge_weight=weight), m(state, pos, kept))
        assert torch.equal(m(state, pos, ei, edge_weight=torch.ones(4)), m(state, pos, ei))
        one_edge_each = m(state, pos, ei, edge_weight=torch.tensor([1.0, 1.0, 0.0, 0.0]))
        assert torch.equal(one_edge_each[3], torch.zeros(6))
        assert torch.equal(m(state, pos, ei, edge_weight=torch.zeros(4)), torch.zeros(5, 6))
    torch.testing.assert_close(m(state, pos, ei, edge_weight=weight), m(state, pos, kept))
    with pytest.raises(ValueError, match=r"edge_weight must be \[4\]"):
        m(state, pos, ei, edge_weight=torch.ones(3))


def test_reading_the_force_matches_brute_force_and_a_push_reaches_the_other_body():
    torch.manual_seed(0)
    m = CollisionModule(4, 6, CFG, reads_force=True)
    state, pos, ei = _inputs()
    force = torch.randn(5, 3, generator=torch.Generator().manual_seed(3))
    out = m(state, pos, ei, force=force)
    expected = torch.zeros(5, 6)
    for j, i in ei.t().tolist():
        off = pos[i] - pos[j]
        feat = torch.cat([state[i], force[i], state[j], force[j], off, off.norm().reshape(1)])
        expected[i] += m.phi(feat[None])[0]
    torch.testing.assert_close(out, expected)
    pushed = force.clone()
    pushed[1] += torch.tensor([2.0, 0.0, 0.0])  # a push on a source reaches its destination (0) only
    changed = (m(state, pos, ei, force=pushed) - out).abs().amax(dim=-1)
    assert changed[0] > 1e-4 and torch.equal(changed[[1, 2, 3, 4]], torch.zeros(4))
    assert "reads_force=True" in repr(m)


def test_reading_the_force_needs_it():
    m = CollisionModule(4, 6, CFG, reads_force=True)
    state, pos, ei = _inputs()
    with pytest.raises(ValueError, match=r"reads_force needs force \[N, 3\], got None"):
        m(state, pos, ei)
    with pytest.raises(ValueError, match=r"got \(5, 2\)"):
        m(state, pos, ei, force=torch.zeros(5, 2))
