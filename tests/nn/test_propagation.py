import pytest
import torch

from hrn_pyg.nn.mlp import MLPConfig
from hrn_pyg.nn.propagation import PropagationModule


def _inputs():
    gen = torch.Generator().manual_seed(1)
    return torch.randn(4, 3, generator=gen), torch.randn(4, 5, generator=gen), torch.randn(4, 3, generator=gen)


def test_matches_brute_force_and_direction():
    torch.manual_seed(0)
    m = PropagationModule(3, 5, MLPConfig(hidden=8, depth=2), name="l2a")
    s, e, x = _inputs()
    ei = torch.tensor([[0, 1, 2], [3, 3, 2 - 2]])  # 0->3, 1->3, 2->0
    out = m(s, e, x, ei)
    assert out.shape == (4, 5)
    expected = torch.zeros(4, 5)
    for j, i in ei.t().tolist():
        expected[i] += m.eta(torch.cat([s[j], s[i], e[j], x[j] - x[i]])[None])[0]
    torch.testing.assert_close(out, expected)
    assert torch.equal(out[[1, 2]], torch.zeros(2, 5))


def test_empty_and_translation():
    m = PropagationModule(3, 5, MLPConfig(hidden=8, depth=2))
    s, e, x = _inputs()
    assert torch.equal(m(s, e, x, torch.empty(2, 0, dtype=torch.long)), torch.zeros(4, 5))
    ei = torch.tensor([[0, 1], [1, 0]])
    torch.testing.assert_close(m(s, e, x, ei), m(s, e, x + 5.0, ei))


def test_errors_and_repr():
    m = PropagationModule(3, 5, MLPConfig(hidden=8, depth=2), name="ws")
    s, e, x = _inputs()
    with pytest.raises(ValueError, match="effect"):
        m(s, e[:, :4], x, torch.empty(2, 0, dtype=torch.long))
    assert repr(m).startswith("PropagationModule(ws, state_dim=3")


def test_inference_path_gives_the_autograd_numbers_and_leaves_inputs_alone():
    torch.manual_seed(0)
    m = PropagationModule(3, 5, MLPConfig(hidden=8, depth=2), rest_offsets=True)
    s, e, x = _inputs()
    rest = x + 0.1
    ei = torch.tensor([[0, 1, 2, 3, 0], [3, 3, 0, 1, 2]])
    batch = torch.tensor([0, 0, 1, 1])
    mask = torch.tensor([[2.0] * 4 + [0.0] * 4, [0.0] * 4 + [2.0] * 4])
    kept = [t.clone() for t in (s, e, x, rest)]
    with_grad = m(s, e, x, ei, mask, batch, rest)
    with torch.no_grad():  # the in-place path
        assert torch.equal(m(s, e, x, ei, mask, batch, rest), with_grad.detach())
    for before, after in zip(kept, (s, e, x, rest)):
        assert torch.equal(before, after)
