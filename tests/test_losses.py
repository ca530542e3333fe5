import pytest
import torch

from hrn_pyg.losses import (
    full_shape_loss,
    global_velocity_loss,
    group_shape_loss,
    local_velocity_loss,
    shape_groups,
)
from hrn_pyg.nn.normalizer import Normalizer
from toy_scene import toy_scene


def test_local_velocity_loss_hand_case():
    norm = Normalizer()
    norm.local_std.fill_(2.0)
    norm.root_std.fill_(0.5)
    pred = torch.tensor([[2.0, 0, 0], [0, 0, 1.0], [5.0, 5, 5]])
    true = torch.zeros(3, 3)
    is_root = torch.tensor([False, True, False])
    is_static = torch.tensor([False, False, True])
    # node 0: (2/2)^2 = 1; node 1: (1/0.5)^2 = 4; node 2 static: left out; mean over 2 x 3 entries
    loss = local_velocity_loss(pred, true, is_root, is_static, norm)
    assert loss.item() == pytest.approx(5.0 / 6.0)


def test_global_velocity_loss_hand_case():
    pred = torch.tensor([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 3.0], [1.0, 1, 1]])
    true = torch.zeros(4, 3)
    is_root = torch.tensor([False, False, True, True])
    is_leaf = torch.tensor([True, False, False, False])
    is_static = torch.tensor([False, False, False, True])
    # kept: node 0 (leaf) -> 1, node 2 (root) -> 9; node 1 is a middle node, node 3 static
    loss = global_velocity_loss(pred, true, is_root, is_leaf, is_static, scale=1.0)
    assert loss.item() == pytest.approx(10.0 / 6.0)
    halved = global_velocity_loss(pred, true, is_root, is_leaf, is_static, scale=2.0)
    assert halved.item() == pytest.approx(10.0 / 24.0)


def test_group_shape_loss_hand_case():
    true = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    pred = torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [0, 1.0, 0]])
    ws = torch.tensor([[0, 1], [1, 0]])  # siblings 0 and 1 only: distance 1 -> 2
    assert group_shape_loss(pred, true, ws).item() == pytest.approx(1.0)
    # translation and rotation of the prediction leave it unchanged
    rot = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    assert group_shape_loss(pred @ rot.T + 3.0, true, ws).item() == pytest.approx(1.0, rel=1e-5)
    assert group_shape_loss(pred, true, torch.empty(2, 0, dtype=torch.long)).item() == 0.0


def test_full_shape_loss_hand_case_and_groups():
    true = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [5.0, 5, 5], [6.0, 5, 5]])
    pred = true.clone()
    pred[1] = torch.tensor([2.0, 0, 0])  # d01: 1 -> 2, d12: sqrt2 -> sqrt5, d02 unchanged
    pred[4] = torch.tensor([9.0, 5, 5])  # other object: d34 1 -> 4, but 1 <-> 4 are not a pair
    group = torch.tensor([0, 0, 0, 1, 1])
    err = 2 * (1.0 + (5**0.5 - 2**0.5) ** 2) + 2 * 9.0
    expected = err / (3 * 2 + 2 * 1)
    for chunk in (1, 2, 3, 100):
        assert full_shape_loss(pred, true, group, chunk_size=chunk).item() == pytest.approx(expected, rel=1e-5)
    # shuffled rows: same value (rows are sorted by group inside)
    perm = torch.tensor([4, 2, 0, 3, 1])
    assert full_shape_loss(pred[perm], true[perm], group[perm], chunk_size=2).item() == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match="chunk_size"):
        full_shape_loss(pred, true, group, chunk_size=0)


def test_full_shape_loss_chunked_gradient_equals_unchunked():
    gen = torch.Generator().manual_seed(0)
    true = torch.randn(40, 3, generator=gen)
    group = torch.randint(0, 3, (40,), generator=gen)
    grads = []
    for chunk in (7, 1000):
        pred = (true + 0.1 * torch.randn(40, 3, generator=torch.Generator().manual_seed(1))).requires_grad_(True)
        full_shape_loss(pred, true, group, chunk_size=chunk).backward()
        grads.append(pred.grad)
    torch.testing.assert_close(grads[0], grads[1])


def test_full_shape_covers_more_pairs_than_group_shape():
    g = toy_scene()
    s = g["particle"]
    leaf, group = shape_groups(g)
    assert leaf.numel() == 12 and group.unique().numel() == 2  # static leaves left out
    # stretch the soft cube between its two groups: groups keep their inner distances
    pred = s.pos.clone()
    pred[4:8] += torch.tensor([0.0, 0.0, 0.05])
    pred[15] += torch.tensor([0.0, 0.0, 0.05])
    ws = g["particle", "within_siblings", "particle"].edge_index
    leaf_ws = ws[:, s.is_leaf[ws[0]]]
    assert group_shape_loss(pred, s.pos, leaf_ws).item() == pytest.approx(0.0, abs=1e-10)
    assert full_shape_loss(pred[leaf], s.pos[leaf], group).item() > 1e-5
