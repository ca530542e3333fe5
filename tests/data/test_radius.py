"""The collision search against an O(L^2) brute force, on both of its paths: the cell grid and
the every-pair test it uses for small scenes (each test runs once per path)."""

from __future__ import annotations

import pytest
import torch

from hrn_pyg.data import radius
from hrn_pyg.data.radius import collision_edges


@pytest.fixture(autouse=True, params=["grid", "dense"])
def search_path(request, monkeypatch):
    """Force one path whatever the size: the grid (threshold 0) or the dense test (no limit)."""
    monkeypatch.setattr(radius, "DENSE_MAX_POINTS", 0 if request.param == "grid" else 10**9)
    return request.param


def brute_force(leaf_pos: torch.Tensor, leaf_object: torch.Tensor, radius: float, batch=None) -> torch.Tensor:
    """Every (src, dst) pair of different objects, same copy, |x_i - x_j|^2 < r^2, sorted by (dst, src)."""
    diff = leaf_pos[:, None, :] - leaf_pos[None, :, :]  # [dst, src, 3]
    close = (diff * diff).sum(-1) < radius * radius
    close &= leaf_object[:, None] != leaf_object[None, :]
    if batch is not None:
        close &= batch[:, None] == batch[None, :]
    dst, src = close.nonzero(as_tuple=True)
    return torch.stack([src, dst])


def _cloud(seed: int, n: int, n_objects: int, n_copies: int, scale: float = 1.0):
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(n, 3, generator=g) - 0.3) * scale
    obj = torch.randint(0, n_objects, (n,), generator=g)
    batch = torch.randint(0, n_copies, (n,), generator=g) if n_copies > 1 else None
    return pos, obj, batch


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("radius", [0.03, 0.1, 0.37, 5.0])
def test_equals_brute_force(seed: int, radius: float) -> None:
    pos, obj, batch = _cloud(seed, 600, n_objects=1 + seed, n_copies=seed + 1)
    expected = brute_force(pos, obj, radius, batch)
    got = collision_edges(pos, obj, radius, batch)
    assert got.dtype == torch.long
    assert torch.equal(got, expected)
    if seed > 0 and radius >= 0.1:
        assert got.shape[1] > 0  # the comparison is not vacuous


def test_spread_out_scene_and_float64_input() -> None:
    pos, obj, batch = _cloud(11, 500, n_objects=5, n_copies=3, scale=40.0)
    pos = pos.double()
    got = collision_edges(pos, obj.int(), 1.5, batch)
    assert torch.equal(got, brute_force(pos, obj, 1.5, batch))
    assert got.shape[1] > 0


def test_dense_objects_touching() -> None:
    # two voxel cubes (pitch 0.05) side by side, 0.05 apart: only the facing layers collide
    axis = torch.arange(4) * 0.05
    cube = torch.cartesian_prod(axis, axis, axis)
    pos = torch.cat([cube, cube + torch.tensor([0.2, 0.0, 0.0])])
    obj = torch.repeat_interleave(torch.tensor([0, 1]), 64)
    got = collision_edges(pos, obj, 0.06)
    assert torch.equal(got, brute_force(pos, obj, 0.06))
    assert got.shape[1] == 2 * 16  # 16 facing pairs, both directions
    assert (obj[got[0]] != obj[got[1]]).all()


def test_strict_radius_and_symmetry() -> None:
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.25, 0.0]])
    obj = torch.tensor([0, 1, 2])
    # |x0 - x1| = 0.5 exactly: excluded at r = 0.5, included just above
    assert torch.equal(collision_edges(pos, obj, 0.5), torch.tensor([[2, 0], [0, 2]]))
    got = collision_edges(pos, obj, 0.5001)
    assert torch.equal(got, torch.tensor([[1, 2, 0, 0], [0, 0, 1, 2]]))
    pairs = set(map(tuple, got.T.tolist()))
    assert pairs == {(j, i) for i, j in pairs}


def test_no_same_object_pairs_and_no_self_loops() -> None:
    pos, obj, batch = _cloud(5, 400, n_objects=3, n_copies=2)
    got = collision_edges(pos, obj, 0.2, batch)
    assert (obj[got[0]] != obj[got[1]]).all()
    assert (got[0] != got[1]).all()
    assert (batch[got[0]] == batch[got[1]]).all()


def test_copies_never_collide_with_each_other() -> None:
    pos, obj, _ = _cloud(6, 100, n_objects=2, n_copies=1)
    both = torch.cat([pos, pos])
    batch = torch.repeat_interleave(torch.tensor([0, 1]), 100)
    got = collision_edges(both, torch.cat([obj, obj]), 0.2, batch)
    single = collision_edges(pos, obj, 0.2)
    assert torch.equal(got, torch.cat([single, single + 100], dim=1))


@pytest.mark.parametrize(
    "pos, obj, radius",
    [
        (torch.zeros(0, 3), torch.zeros(0, dtype=torch.long), 0.1),
        (torch.zeros(1, 3), torch.zeros(1, dtype=torch.long), 0.1),
        (torch.rand(50, 3), torch.zeros(50, dtype=torch.long), 0.5),  # one object only
        (torch.rand(50, 3), torch.arange(50), 0.0),  # radius 0
        (torch.tensor([[0.0, 0, 0], [0.0, 0, 0]]), torch.tensor([0, 1]), 0.0),  # coincident, r = 0
    ],
)
def test_empty_results(pos, obj, radius) -> None:
    got = collision_edges(pos, obj, radius)
    assert got.shape == (2, 0) and got.dtype == torch.long


def test_coincident_points_collide() -> None:
    pos = torch.zeros(3, 3)
    got = collision_edges(pos, torch.tensor([0, 1, 1]), 1e-3)
    assert torch.equal(got, torch.tensor([[1, 2, 0, 0], [0, 0, 1, 2]]))


def test_does_not_track_gradients() -> None:
    pos = torch.rand(30, 3, requires_grad=True)
    got = collision_edges(pos, torch.arange(30) % 2, 0.5)
    assert not got.requires_grad


@pytest.mark.parametrize(
    "pos, obj, radius, batch, match",
    [
        (torch.zeros(4, 2), torch.zeros(4, dtype=torch.long), 0.1, None, "leaf_pos"),
        (torch.zeros(4, 3, dtype=torch.long), torch.zeros(4, dtype=torch.long), 0.1, None, "leaf_pos"),
        (torch.zeros(4, 3), torch.zeros(3, dtype=torch.long), 0.1, None, "leaf_object"),
        (torch.zeros(4, 3), torch.zeros(4), 0.1, None, "leaf_object"),
        (torch.zeros(4, 3), torch.zeros(4, dtype=torch.long), -0.1, None, "radius"),
        (torch.zeros(4, 3), torch.zeros(4, dtype=torch.long), float("nan"), None, "radius"),
        (torch.zeros(4, 3), torch.zeros(4, dtype=torch.long), 0.1, torch.zeros(3, dtype=torch.long), "batch"),
        (torch.full((4, 3), float("nan")), torch.zeros(4, dtype=torch.long), 0.1, None, "NaN"),
    ],
)
def test_bad_input(pos, obj, radius, batch, match) -> None:
    with pytest.raises(ValueError, match=match):
        collision_edges(pos, obj, radius, batch)


def test_points_billions_of_radii_apart_still_match_brute_force() -> None:
    # clusters 1e7 m apart with r = 0.05 (a diverged rollout looks like this): the dense cell
    # grid would need ~1e26 keys; renumbering occupied cells keeps the search exact
    g = torch.Generator().manual_seed(3)
    centres = torch.tensor([[0.0, 0.0, 0.0], [1e7, -1e7, 3e6], [1e7, -1e7, 3e6 + 0.03]], dtype=torch.float64)
    pos = (centres.repeat_interleave(20, 0) + 0.04 * torch.rand(60, 3, generator=g, dtype=torch.float64))
    obj = torch.arange(3).repeat_interleave(20)
    got = collision_edges(pos, obj, 0.05)
    assert got.size(1) > 0
    assert torch.equal(got, brute_force(pos, obj, 0.05))
