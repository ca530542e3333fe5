import torch
from toy_scene import structure

from hrn_pyg.data.graph import CHILD_TO_PARENT, LEAF_TO_ANCESTOR
from hrn_pyg.nn.mlp import MLPConfig
from hrn_pyg.nn.state import NextStateModule, to_global_velocity, to_local_velocity


def test_shape_and_static_rows_zero():
    torch.manual_seed(0)
    m = NextStateModule(4, 6, MLPConfig(hidden=8, depth=2))
    s, e = torch.randn(5, 4), torch.randn(5, 6)
    static = torch.tensor([False, True, False, False, True])
    out = m(s, e, static)
    assert out.shape == (5, 3)
    assert torch.equal(out[static], torch.zeros(2, 3))
    torch.testing.assert_close(out[~static], m.psi(torch.cat([s, e], -1))[~static])
    assert "NextStateModule" in repr(m)


def test_local_velocity_hand_case():
    # chain 0 -> 1 -> 2 (root), plus 3 -> 2
    c2p = torch.tensor([[0, 1, 3], [1, 2, 2]])
    l2a = torch.tensor([[0, 0, 1, 3], [1, 2, 2, 2]])
    v = torch.tensor([[1.0, 0, 0], [0.5, 0, 0], [0.25, 1, 0], [0, 0, 2]])
    local = to_local_velocity(v, c2p)
    expected = torch.tensor([[0.5, 0, 0], [0.25, -1, 0], [0.25, 1, 0], [-0.25, -1, 2]])
    torch.testing.assert_close(local, expected)
    torch.testing.assert_close(to_global_velocity(local, l2a), v)


def test_local_global_inverse_on_toy_tree():
    g = structure()
    v = torch.randn(g["particle"].num_nodes, 2, 3)  # extra time axis works too
    local = to_local_velocity(v, g[CHILD_TO_PARENT].edge_index)
    torch.testing.assert_close(to_global_velocity(local, g[LEAF_TO_ANCESTOR].edge_index), v)
    torch.testing.assert_close(local[g["particle"].is_root], v[g["particle"].is_root])
