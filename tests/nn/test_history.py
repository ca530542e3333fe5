import pytest
import torch

from hrn_pyg.nn.history import HistoryModule
from hrn_pyg.nn.mlp import MLPConfig


def test_shapes_and_formula():
    torch.manual_seed(0)
    m = HistoryModule(4, 6, MLPConfig(hidden=8, depth=1))
    s, p = torch.randn(3, 4), torch.randn(3, 4)
    out = m(s, p)
    assert out.shape == (3, 6)
    torch.testing.assert_close(out, m.phi(torch.cat([s, p], -1)))
    # the order matters: current state first, previous second
    assert not torch.allclose(out, m(p, s))


def test_mask_and_errors():
    m = HistoryModule(4, 6, MLPConfig(hidden=8, depth=1))
    s, p = torch.randn(3, 4), torch.randn(3, 4)
    batch = torch.tensor([0, 1, 1])
    assert torch.equal(m(s, p, torch.ones(2, 8), batch), m(s, p))
    with pytest.raises(ValueError, match="prev_state"):
        m(s, p[:2])
    with pytest.raises(ValueError, match=r"mask must be \[B, 8\]"):
        m(s, p, torch.ones(2, 7), batch)
    assert "HistoryModule" in repr(m)
