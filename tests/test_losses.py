import pytest
import torch
from toy_scene import toy_scene

from hrn_pyg.losses import (
    SMALL_GROUP,
    full_shape_loss,
    global_velocity_loss,
    group_shape_loss,
    local_velocity_loss,
    shape_groups,
)
from hrn_pyg.nn.normalizer import Normalizer


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


def _naive_full_shape_loss(pred: torch.Tensor, true: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
    """The formula as written: every ordered pair of one group, one dense matrix, autograd."""
    same = group[:, None] == group[None, :]
    d_pred = torch.sqrt(((pred[:, None] - pred[None]) ** 2).sum(-1) + 1e-12)
    d_true = torch.sqrt(((true[:, None] - true[None]) ** 2).sum(-1) + 1e-12)
    return ((d_pred - d_true) ** 2 * same).sum() / (same.sum() - group.numel())


@pytest.mark.parametrize("chunk", [1, 3, 7, 16, 1000])
def test_full_shape_loss_value_and_gradient_equal_the_dense_formula(chunk):
    """Objects of 1 to 150 leaves (small ones padded together, large ones in chunks), in any
    order, far from the origin: the loss with its hand-formed gradient equals the dense formula
    under autograd (float64)."""
    gen = torch.Generator().manual_seed(chunk)
    sizes = (40, 1, 150, 2, 17, SMALL_GROUP, 5, SMALL_GROUP - 1)
    group = torch.cat([torch.full((n,), k) for k, n in enumerate(sizes)])
    group = group[torch.randperm(group.numel(), generator=gen)]
    true = torch.randn(group.numel(), 3, generator=gen, dtype=torch.float64) + 50.0
    pred = (true + 0.05 * torch.randn(group.numel(), 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    value = full_shape_loss(pred, true, group, chunk_size=chunk, scale=0.5)
    (grad,) = torch.autograd.grad(value, pred)
    reference = _naive_full_shape_loss(pred / 0.5, true / 0.5, group)
    (grad_reference,) = torch.autograd.grad(reference, pred)
    torch.testing.assert_close(value, reference, rtol=1e-10, atol=0)
    torch.testing.assert_close(grad, grad_reference, rtol=1e-8, atol=1e-12)
    with torch.no_grad():  # the no-grad path (evaluation) gives the same value
        torch.testing.assert_close(full_shape_loss(pred, true, group, chunk_size=chunk, scale=0.5), reference)


def test_full_shape_loss_skips_fixed_groups_but_counts_their_pairs():
    """Fixed groups (rigid bodies under the rigid fit) add no error but keep the normaliser
    ``P``; the other groups' gradient is that of the whole loss."""
    gen = torch.Generator().manual_seed(2)
    true = torch.randn(30, 3, generator=gen)
    group = torch.randint(0, 4, (30,), generator=gen)
    fixed = group >= 2  # whole groups
    pred = (true + 0.1 * torch.randn(30, 3, generator=gen)).requires_grad_(True)
    whole = full_shape_loss(pred, true, group, chunk_size=5)
    whole.backward()
    grad_whole = pred.grad.clone()
    pred.grad = None
    skipped = full_shape_loss(pred, true, group, chunk_size=5, fixed=fixed)
    skipped.backward()
    counts = torch.bincount(group)
    pairs, fixed_pairs = int((counts * (counts - 1)).sum()), int((counts[2:] * (counts[2:] - 1)).sum())
    fixed_part = full_shape_loss(pred[fixed], true[fixed], group[fixed]) * fixed_pairs / pairs
    assert skipped.item() == pytest.approx((whole - fixed_part).item(), rel=1e-5)
    torch.testing.assert_close(pred.grad[~fixed], grad_whole[~fixed])
    assert pred.grad[fixed].abs().max() == 0
    assert full_shape_loss(pred, true, group, fixed=torch.ones(30, dtype=torch.bool)).item() == 0.0
    with pytest.raises(ValueError, match="fixed must be"):
        full_shape_loss(pred, true, group, fixed=fixed[:3])


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


def test_rest_velocity_loss_counts_only_the_objects_at_rest():
    from hrn_pyg.losses import rest_velocity_loss

    true = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    pred = torch.tensor([[3e-4, -1e-4, 0.0], [0.2, 0.0, 0.0], [5.0, 5.0, 5.0], [1.0, 1.0, 1.0]])
    is_root = torch.tensor([True, True, False, True])
    is_static = torch.tensor([False, False, False, True])
    # only node 0 is a movable root with a true speed under 1 mm: |3e-4| + |-1e-4| + 0 over 3, / 0.01
    loss = rest_velocity_loss(pred, true, is_root, is_static, 1e-3, 0.01)
    assert loss.item() == pytest.approx((3e-4 + 1e-4) / 3 / 0.01)
    # an absolute error: the pull towards zero creep does not fade as the creep shrinks
    small = pred.clone().requires_grad_(True)
    rest_velocity_loss(small, true, is_root, is_static, 1e-3, 0.01).backward()
    assert small.grad[0].tolist() == pytest.approx([1 / 0.03, -1 / 0.03, 0.0])
    assert small.grad[1:].abs().sum() == 0
    nothing_rests = rest_velocity_loss(pred, true + 1.0, is_root, is_static, 1e-3, 0.01)
    assert nothing_rests.item() == 0.0


