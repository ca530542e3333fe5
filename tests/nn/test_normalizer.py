import torch
from toy_scene import toy_window

from hrn_pyg.nn.normalizer import STD_EPSILON, Normalizer, fit_normalizer


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
    # rms per axis; y never varies and takes the mean of the axes that do (not 1 / STD_EPSILON)
    torch.testing.assert_close(n.force_std, torch.tensor([3.0, 3.5, 4.0]))
    assert bool(n.fitted) and n.extra_repr() == "fitted=True"
    assert STD_EPSILON < 1e-6
    # the statistics are buffers: they travel with a state_dict
    assert {"velocity_std", "local_std", "root_std", "length_scale", "fitted"} <= set(n.state_dict())


def test_a_planar_scene_keeps_its_unused_axis_at_the_scale_of_the_others():
    # the wedge: nothing ever moves along y. That axis must not be decoded at 1 m/step (what a
    # fallback of 1 gave): the target scale along y is the mean of x and z's
    w = toy_window(4)
    s = w["particle"]
    s.pos_seq[..., 1] = s.pos_seq[:, :1, 1]  # freeze y over time
    n = fit_normalizer([w])
    for name in ("velocity_std", "root_std", "local_std"):
        std = getattr(n, name)
        torch.testing.assert_close(std[1], std[[0, 2]].mean(), msg=name)
        assert std[1] < 0.5
    # a quantity with no varying column at all keeps the fallback: no force anywhere -> 1
    assert torch.equal(n.force_std, torch.ones(3))
