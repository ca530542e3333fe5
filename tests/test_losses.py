import pytest
import torch
from toy_scene import toy_scene

from hrn_pyg.losses import (
    SMALL_GROUP,
    contact_loss,
    fair_energy_score,
    full_shape_loss,
    global_velocity_loss,
    ground_loss,
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


def test_fair_energy_score_hand_case():
    # one 3-D point: samples (0,0,0) and (3,4,0), truth (3,0,0)
    # mean distance to the truth (3 + 4) / 2 = 3.5; the one pair at distance 5 counted twice:
    # 2 * 5 / (2 * 2 * 1) = 2.5; ES = 1.0
    samples = torch.tensor([[[0.0, 0, 0]], [[3.0, 4, 0]]])  # [K=2, 1, 3]
    truth = torch.tensor([[3.0, 0, 0]])
    assert fair_energy_score(samples, truth).tolist() == pytest.approx([1.0], abs=1e-5)
    assert fair_energy_score(samples, truth, scale=2.0).tolist() == pytest.approx([0.5], abs=1e-5)
    # per-axis scale divides each coordinate: x / 1, y / 4 -> samples (0,0,0), (3,1,0), truth (3,0,0):
    # (3 + 1) / 2 - sqrt(10) / 2
    scaled = fair_energy_score(samples, truth, scale=torch.tensor([1.0, 4.0, 1.0]))
    assert scaled.item() == pytest.approx(2.0 - 10 ** 0.5 / 2, abs=1e-5)
    # K = 3 on a line, two middle indices scored on their own: X = 0, 1, 3 and y = 2 -> 4/3 - 12/12
    line = torch.tensor([0.0, 1.0, 3.0])[:, None, None] * torch.tensor([1.0, 0, 0])
    both = torch.cat([line, samples.new_zeros(3, 1, 3)], dim=1)  # index 1: all at the origin, y there
    es = fair_energy_score(both, torch.tensor([[2.0, 0, 0], [0.0, 0, 0]]))
    assert es.shape == (2,) and es.tolist() == pytest.approx([1.0 / 3.0, 0.0], abs=1e-5)


def test_fair_energy_score_is_the_plug_in_score_with_the_unbiased_spread():
    from hrn_pyg.sampling.metrics import energy_score

    gen = torch.Generator().manual_seed(0)
    samples, truth = torch.randn(5, 7, 3, generator=gen), torch.randn(7, 3, generator=gen)
    pair_sum = (samples[:, None] - samples[None]).norm(dim=-1).sum(dim=(0, 1))
    k = 5
    expected = energy_score(samples, truth[None]) + pair_sum / (2 * k * k) - pair_sum / (2 * k * (k - 1))
    torch.testing.assert_close(fair_energy_score(samples, truth), expected, rtol=1e-5, atol=1e-5)


def test_fair_energy_score_is_minimised_by_the_true_distribution():
    # truth y ~ N(0, I_3); K = 4 samples ~ N(0, s^2 I_3). In expectation
    # E|X - y| = sqrt(1 + s^2) c and E|X - X'| = sqrt(2) s c with c = E|N(0, I_3)| = 2 sqrt(2 / pi),
    # so ES(s) = c (sqrt(1 + s^2) - s / sqrt(2)): smallest at s = 1 (the truth's own spread)
    n, k = 40_000, 4
    gen = torch.Generator().manual_seed(0)
    truth = torch.randn(n, 3, generator=gen)
    noise = torch.randn(k, n, 3, generator=gen)  # the same draws at every width (less variance)
    c = 2 * (2 / torch.pi) ** 0.5
    score = {}
    for s in (0.5, 1.0, 2.0):
        score[s] = fair_energy_score(s * noise, truth).mean().item()
        assert score[s] == pytest.approx(c * ((1 + s * s) ** 0.5 - s / 2 ** 0.5), rel=0.02), s
    assert score[1.0] < score[0.5] - 0.03 and score[1.0] < score[2.0] - 0.05
    # the plug-in (biased) form under-weights the spread by (K-1)/K and so prefers narrow samples
    from hrn_pyg.sampling.metrics import energy_score

    plug_in = {s: energy_score(s * noise, truth[None]).mean().item() for s in (0.5, 1.0)}
    assert plug_in[0.5] < plug_in[1.0]


def test_fair_energy_score_gradient_is_finite_where_samples_coincide():
    truth = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    samples = torch.stack([torch.tensor([[1.0, 2.0, 3.0], [1.0, 0.0, 0.0]])] * 3).requires_grad_(True)
    es = fair_energy_score(samples, truth, scale=torch.tensor([0.5, 1.0, 2.0]))
    es.sum().backward()
    assert torch.isfinite(samples.grad).all()
    # index 0: every sample on the truth: ES = 0, gradient 0; index 1: all three at (1,0,0), one
    # away from the truth: ES = |1 / 0.5| = 2, gradient of the mean distance (1/K) * (1/0.5) on x
    assert es.tolist() == pytest.approx([0.0, 2.0], abs=1e-5)
    torch.testing.assert_close(samples.grad[:, 0], torch.zeros(3, 3))
    torch.testing.assert_close(samples.grad[:, 1], torch.tensor([[2.0 / 3.0, 0.0, 0.0]] * 3))


def test_fair_energy_score_bad_input_says_which():
    with pytest.raises(ValueError, match=r"samples must be \[K>=2"):
        fair_energy_score(torch.zeros(1, 4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="one observation"):
        fair_energy_score(torch.zeros(3, 4, 3), torch.zeros(2, 4, 3))


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


def test_contact_loss_is_the_shortfall_of_touching_pairs_and_pushes_them_apart():
    true = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])
    edges = torch.tensor([[0, 1, 0], [1, 0, 2]])  # both directions of pair (0, 1), one of (0, 2)
    assert contact_loss(true, true, edges).item() == 0.0
    apart = true * 1.5  # every pair farther than the truth: nothing to pay
    assert contact_loss(apart, true, edges).item() == 0.0
    pred = true.clone()
    pred[1, 0] = 0.04  # pair (0, 1) 0.06 closer than the truth, pair (0, 2) as true
    pred.requires_grad_(True)
    loss = contact_loss(pred, true, edges, scale=0.5)
    assert loss.item() == pytest.approx((0.06 + 0.06 + 0.0) / 3 / 0.5, rel=1e-5)
    loss.backward()
    assert pred.grad[1, 0] < 0 and pred.grad[0, 0] > 0  # descent moves leaf 1 away from leaf 0
    assert pred.grad[2].abs().sum() == 0
    nothing = contact_loss(pred, true, torch.zeros(2, 0, dtype=torch.long))
    assert nothing.item() == 0.0 and nothing.requires_grad
    # a floor of 0.05: pair (0, 1) at 0.04 is 0.01 short of it, pair (0, 2) is past it
    floored = contact_loss(pred.detach(), true, edges, scale=0.5, floor=0.05)
    assert floored.item() == pytest.approx((0.01 + 0.01 + 0.0) / 3 / 0.5, rel=1e-4)
    per_pair = contact_loss(pred.detach(), true, edges, floor=torch.tensor([0.02, 0.02, 1.0]))
    assert per_pair.item() == pytest.approx(0.0, abs=1e-7)  # both pairs kept past their floors


def test_ground_loss_is_the_depth_under_the_true_height_or_the_floor():
    # leaf 0 truly at 0.01 (near the ground), leaf 1 at 0.5 (high), leaf 2 static, leaf 3 not a moving leaf
    true = torch.tensor([[0.0, 0.0, 0.01], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    moving_leaf = torch.tensor([True, True, False, False])
    assert ground_loss(true, true, moving_leaf, 0.05).item() == 0.0
    lifted = true.clone()
    lifted[:, 2] += 0.3  # lifting a leaf costs nothing: the term is one-sided
    assert ground_loss(lifted, true, moving_leaf, 0.05).item() == 0.0
    pred = true.clone()
    pred[0, 2] = -0.02  # 0.03 under its true height
    pred[1, 2] = 0.04  # 0.01 under the floor of 0.05 (its true height does not matter up there)
    pred[2, 2] = -1.0  # static: ignored
    pred[3, 2] = -1.0  # not a moving leaf: ignored
    pred.requires_grad_(True)
    loss = ground_loss(pred, true, moving_leaf, 0.05, scale=0.5)
    assert loss.item() == pytest.approx((0.03 + 0.01) / 2 / 0.5, rel=1e-5)  # mean over the moving leaves
    loss.backward()
    assert pred.grad[0, 2] < 0 and pred.grad[1, 2] < 0  # descent lifts both leaves
    assert pred.grad[:, :2].abs().sum() == 0 and pred.grad[2:].abs().sum() == 0
    # per-leaf floors: a floor of 0.03 for leaf 1 makes its 0.04 free
    per_leaf = ground_loss(pred.detach(), true, moving_leaf, torch.tensor([0.05, 0.03, 0.05, 0.05]))
    assert per_leaf.item() == pytest.approx(0.03 / 2, rel=1e-5)
    # a floor under the plane: only the depth past it counts (leaf 0 is 0.01 past -0.01)
    under = ground_loss(pred.detach(), true, moving_leaf, -0.01)
    assert under.item() == pytest.approx(0.01 / 2, rel=1e-4)
    nothing = ground_loss(pred, true, torch.zeros(4, dtype=torch.bool), 0.05)
    assert nothing.item() == 0.0 and nothing.requires_grad
