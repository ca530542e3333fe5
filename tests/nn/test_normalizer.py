import torch

from hrn_pyg.nn.normalizer import STD_EPSILON, Normalizer, fit_normalizer
from toy_scene import toy_window


def test_unfitted_is_identity():
    n = Normalizer()
    v = torch.randn(4, 3)
    assert torch.equal(n.velocity(v), v) and torch.equal(n.force(v), v) and not bool(n.fitted)
    is_root = torch.tensor([True, False, False, True])
    assert torch.equal(n.denormalize_target(n.normalize_target(v, is_root), is_root), v)


def test_fit_matches_brute_force_statistics():
    w = toy_window(4)
    s = w["particle"]
    s.force_seq[0, 1] = torch.tensor([3.0, 0.0, -4.0])  # one nonzero force row
    n = fit_normalizer([w])
    moving = ~s.is_static
    v = (s.pos_seq[:, 1:] - s.pos_seq[:, :-1])[moving].reshape(-1, 3)
    torch.testing.assert_close(n.velocity_mean, v.mean(0))
    torch.testing.assert_close(n.velocity_std, v.std(0, unbiased=False), rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(n.force_std, torch.tensor([3.0, 1.0, 4.0]))  # rms; y never varies -> 1
    assert bool(n.fitted) and n.extra_repr() == "fitted=True"
    # a component that never varies gets scale 1, not 1 / STD_EPSILON
    assert STD_EPSILON < 1e-6 and n.force_std[1] == 1.0
    # the statistics are buffers: they travel with a state_dict
    assert {"velocity_std", "local_std", "root_std", "length_scale", "fitted"} <= set(n.state_dict())
