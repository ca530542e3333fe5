"""The vertical-axis symmetry of training windows (hrn_pyg.data.symmetry)."""

from __future__ import annotations

import math

import pytest
import torch
from torch_geometric.data import Batch
from toy_scene import toy_window

from hrn_pyg.data.graph import NODE
from hrn_pyg.data.symmetry import (
    WORLD_VECTORS,
    apply_vertical_symmetry,
    random_vertical_symmetries,
)
from hrn_pyg.nn.normalizer import fit_normalizer, isotropic_horizontal


def _dihedral() -> torch.Tensor:
    """The 8 maps of the square's symmetry group (turns by 90 degrees, with and without a mirror)."""
    maps = []
    for k in range(4):
        c, s = round(math.cos(k * math.pi / 2)), round(math.sin(k * math.pi / 2))
        for sign in (1.0, -1.0):
            maps.append(torch.tensor([[sign * c, -s, 0.0], [sign * s, c, 0.0], [0.0, 0.0, 1.0]]))
    return torch.stack(maps)


def test_symmetries_are_orthogonal_keep_z_and_mirror_half_the_time():
    q = random_vertical_symmetries(2000, torch.Generator().manual_seed(0))
    eye = torch.eye(3).expand(2000, 3, 3)
    torch.testing.assert_close(q @ q.transpose(1, 2), eye, atol=1e-6, rtol=0)
    assert torch.equal(q[:, 2], torch.tensor([0.0, 0.0, 1.0]).expand(2000, 3))
    det = torch.linalg.det(q)
    torch.testing.assert_close(det.abs(), torch.ones(2000), atol=1e-6, rtol=0)
    assert 0.45 < float((det < 0).float().mean()) < 0.55
    assert (random_vertical_symmetries(50, torch.Generator().manual_seed(1), reflect=False).det() > 0).all()
    # seeded: the same generator state gives the same maps
    assert torch.equal(q, random_vertical_symmetries(2000, torch.Generator().manual_seed(0)))
    with pytest.raises(ValueError, match="num must be >= 1"):
        random_vertical_symmetries(0)


def test_each_copy_is_mapped_by_its_own_matrix_and_heights_and_distances_hold():
    a, b = toy_window(4, seed=0), toy_window(4, seed=1)
    a[NODE].rest_pos = a[NODE].pos.clone()
    b[NODE].rest_pos = b[NODE].pos.clone()
    batch = Batch.from_data_list([a, b])
    before = {name: batch[NODE][name].clone() for name in WORLD_VECTORS if name in batch[NODE]}
    q = random_vertical_symmetries(2, torch.Generator().manual_seed(3))
    mapped = apply_vertical_symmetry(batch, q)
    store, new = batch[NODE], mapped[NODE]
    first = store.batch == 0
    for name in WORLD_VECTORS:
        if name not in store:
            continue
        old, out = store[name], new[name]
        # hand-computed per copy: x' = Q_b x, row by row
        expected = torch.where((store.batch == 0).view(-1, *([1] * (old.dim() - 1))),
                               old @ q[0].T, old @ q[1].T)
        torch.testing.assert_close(out, expected, atol=1e-6, rtol=0)
        assert torch.equal(out[..., 2], old[..., 2]), name  # heights are untouched
    # distances within a copy are kept, so collision edges are the same
    d_old = torch.cdist(store.pos[first], store.pos[first])
    d_new = torch.cdist(new.pos[first], new.pos[first])
    torch.testing.assert_close(d_new, d_old, atol=1e-5, rtol=0)
    assert not torch.allclose(new.pos, store.pos)
    for name, value in before.items():  # the input window is not modified
        assert torch.equal(batch[NODE][name], value), name
    with pytest.raises(ValueError, match=r"one per copy"):
        apply_vertical_symmetry(batch, q[:1])


def test_isotropic_statistics_equal_those_of_the_symmetrised_data():
    windows = [toy_window(6, seed=s) for s in range(3)]
    plain = isotropic_horizontal(fit_normalizer(windows))
    group = _dihedral()
    # averaging over the 8 maps of the square's group is enough for first and second moments
    mapped = [apply_vertical_symmetry(w, q[None]) for w in windows for q in group]
    symmetric = fit_normalizer(mapped)
    for name in ("velocity_mean", "root_mean", "local_mean"):
        assert torch.equal(getattr(plain, name)[:2], torch.zeros(2)), name
        torch.testing.assert_close(getattr(symmetric, name)[:2], torch.zeros(2), atol=1e-7, rtol=0)
    for name in ("velocity_std", "root_std", "local_std", "velocity_mean", "root_mean", "local_mean",
                 "height_mean", "height_std", "length_scale"):
        torch.testing.assert_close(getattr(plain, name), getattr(symmetric, name), rtol=1e-4, atol=1e-8,
                                   msg=name)
