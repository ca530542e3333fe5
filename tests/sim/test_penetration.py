"""Cloth leaves inside other objects (:mod:`hrn_pyg.sim.penetration`) on scenes made by hand: a
sheet above a box, on it, pushed through it; a soft body that moves and squashes; the same counts
for a scene shifted or turned; shapes and bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from hrn_pyg.data.kinds import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.sim.penetration import (
    cloth_inside,
    cloth_inside_counts,
    episode_solids,
    inside_summary,
    lattice_cells,
    object_solids,
)

PITCH = 0.1


def block(n: tuple[int, int, int], centre=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """Leaves of an ``n`` box of lattice points ``PITCH`` apart around ``centre``."""
    axes = [(torch.arange(k, dtype=torch.float64) - (k - 1) / 2) * PITCH for k in n]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return grid + torch.tensor(centre, dtype=torch.float64)


def sheet(height: float, spacing: float = 0.08, n: int = 5) -> torch.Tensor:
    """A flat ``n x n`` sheet of leaves ``spacing`` apart around the z axis at ``height``."""
    ticks = (torch.arange(n, dtype=torch.float64) - (n - 1) / 2) * spacing
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    return torch.stack([x.flatten(), y.flatten(), torch.full((n * n,), height, dtype=torch.float64)], dim=1)


def scene(box: torch.Tensor, cloth: torch.Tensor, material: int = RIGID):
    """Leaves of one box (object 0) and one cloth (object 1), and their solids."""
    rest = torch.cat([box, cloth])
    obj = torch.cat([torch.zeros(len(box), dtype=torch.long), torch.ones(len(cloth), dtype=torch.long)])
    return rest, object_solids(rest, obj, torch.tensor([material, CLOTH]), PITCH)


# a 3x3x3 box whose leaves span z 0.05..0.25 (its voxels 0..0.3, its solid 0.05..0.25)
BOX = block((3, 3, 3), (0.0, 0.0, 0.15))


def test_a_box_is_eight_cells_of_six_tetrahedra_and_the_sheet_is_its_cloth():
    _, solids = scene(BOX, sheet(0.5))
    assert solids.tets.shape == (8 * 6, 4) and (solids.tet_object == 0).all()
    assert solids.cloth.tolist() == list(range(27, 27 + 25)) and solids.cloth_leaves == 25
    assert lattice_cells(BOX.numpy(), PITCH).shape == (8, 8)


@pytest.mark.parametrize("height, inside", [
    (0.5, 0),      # above the box
    (0.31, 0),     # just above its surface (z = 0.3)
    (0.27, 0),     # between the surface and the top leaves' centres: resting contact, not inside
    (0.24, 9),     # below the top leaves' centres: the 3x3 leaves over the box (|x|, |y| <= 0.08)
    (0.15, 9),     # through the middle
    (0.06, 9),
    (0.04, 0),     # below its bottom leaves' centres
])
def test_a_sheet_through_a_box_counts_the_leaves_inside_its_solid(height, inside):
    rest, solids = scene(BOX, sheet(0.5))
    frame = torch.cat([BOX, sheet(height)])
    assert int(cloth_inside_counts(frame, solids)) == inside
    flags = cloth_inside(frame, solids)
    assert flags.shape == (25,)
    if inside:
        xy = sheet(height)[flags, :2]
        assert xy.abs().max() <= 0.1


def test_a_rollout_counts_each_step_and_a_shift_or_turn_of_the_scene_changes_nothing():
    heights = [0.5, 0.3, 0.2, 0.1, 0.0, -0.1]
    rest, solids = scene(BOX, sheet(heights[0]))
    traj = torch.stack([torch.cat([BOX, sheet(h)]) for h in heights])  # [T, L, 3]
    counts = cloth_inside_counts(traj, solids)
    assert counts.tolist() == [0, 0, 9, 9, 0, 0] and cloth_inside(traj, solids).shape == (6, 25)

    shift = torch.tensor([3.7, -12.25, 0.0], dtype=torch.float64)  # along the ground
    shifted = object_solids(rest + shift, solids_objects(rest), torch.tensor([RIGID, CLOTH]), PITCH)
    assert torch.equal(cloth_inside_counts(traj + shift, shifted), counts)

    turn = rotation(torch.tensor([0.3, -0.8, 0.5]), 1.1)  # the box's lattice turned in space
    turned = object_solids(rest @ turn.T, solids_objects(rest), torch.tensor([RIGID, CLOTH]), PITCH)
    assert torch.equal(cloth_inside_counts(traj @ turn.T, turned), counts)


def solids_objects(rest: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.zeros(27, dtype=torch.long), torch.ones(len(rest) - 27, dtype=torch.long)])


def rotation(axis: torch.Tensor, angle: float) -> torch.Tensor:
    """Rodrigues' rotation matrix, float64."""
    k = (axis / axis.norm()).double()
    cross = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def test_a_soft_body_that_moves_and_squashes_carries_its_solid_along():
    cloth_leaf = torch.tensor([[0.0, 0.0, 0.15]], dtype=torch.float64)
    rest, solids = scene(BOX, cloth_leaf, material=SOFT)
    assert int(cloth_inside_counts(torch.cat([BOX, cloth_leaf]), solids)) == 1
    moved = BOX + torch.tensor([0.6, 0.0, 0.0], dtype=torch.float64)
    assert int(cloth_inside_counts(torch.cat([moved, cloth_leaf]), solids)) == 0  # the body left it
    squashed = moved.clone()
    squashed[:, 2] = 0.05 + (squashed[:, 2] - 0.05) * 0.3  # flattened to z 0.05..0.11
    for z, inside in ((0.15, 0), (0.09, 1)):
        leaf = torch.tensor([[0.6, 0.0, z]], dtype=torch.float64)
        assert int(cloth_inside_counts(torch.cat([squashed, leaf]), solids)) == inside


def test_only_other_objects_that_are_not_cloth_have_a_solid():
    block_cloth = block((3, 3, 3))  # a cloth laid out as a block has no solid; nor its own leaves inside
    rest = torch.cat([block_cloth, torch.zeros(1, 3, dtype=torch.float64)])
    solids = object_solids(rest, torch.tensor([0] * 27 + [1]), torch.tensor([CLOTH, CLOTH]), PITCH)
    assert solids.tets.numel() == 0 and solids.cloth_leaves == 28
    assert int(cloth_inside_counts(rest, solids)) == 0
    # a static block is solid; a slab one leaf thick has no full cell and nothing counts inside it
    for material, shape, inside in ((STATIC, (3, 3, 3), 1), (RIGID, (5, 5, 1), 0)):
        body = block(shape)
        rest = torch.cat([body, torch.tensor([[0.01, 0.02, 0.0]], dtype=torch.float64)])
        obj = torch.tensor([0] * len(body) + [1])
        solids = object_solids(rest, obj, torch.tensor([material, CLOTH]), PITCH)
        assert int(cloth_inside_counts(rest, solids)) == inside


def test_shapes_of_one_frame_a_rollout_and_an_empty_one():
    rest, solids = scene(BOX, sheet(0.15))
    assert cloth_inside(rest, solids).shape == (25,) and cloth_inside_counts(rest, solids).shape == ()
    assert cloth_inside(rest[None].expand(4, -1, -1), solids).shape == (4, 25)
    assert cloth_inside(rest[:0][None][:0].reshape(0, len(rest), 3), solids).shape == (0, 25)
    assert cloth_inside_counts(rest.float(), solids) == 9  # float32 positions as well


def test_the_summary_of_a_rollout():
    summary = inside_summary(torch.tensor([0, 0, 3, 1]), cloth_leaves=20)
    assert summary == {"mean": 1.0, "max": 3, "mean_share": 0.05, "steps_with_any": 0.5}
    with pytest.raises(ValueError, match="counts must be"):
        inside_summary(torch.zeros(0, dtype=torch.long), 20)
    with pytest.raises(ValueError, match="cloth_leaves"):
        inside_summary(torch.tensor([1]), 0)


def test_an_episode_gives_its_solids_from_its_first_frame_and_pitch():
    rest, solids = scene(BOX, sheet(0.5))
    episode = {"positions": np.stack([rest.numpy()] * 2), "leaf_object": solids_objects(rest).numpy(),
               "object_material": np.array([RIGID, CLOTH]), "params": json.dumps({"config": {"pitch": PITCH}})}
    from_episode = episode_solids(episode)
    assert torch.equal(from_episode.tets, solids.tets) and torch.equal(from_episode.cloth, solids.cloth)
    with pytest.raises(ValueError, match="no pitch"):
        episode_solids({**episode, "params": json.dumps({})})


def test_bad_input_is_an_error_naming_it():
    rest, solids = scene(BOX, sheet(0.5))
    obj, material = solids_objects(rest), torch.tensor([RIGID, CLOTH])
    with pytest.raises(ValueError, match="positions must be"):
        cloth_inside(rest[:-1], solids)
    with pytest.raises(ValueError, match="positions must be"):
        cloth_inside(rest[None, None], solids)
    bad = rest.clone()
    bad[30, 0] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        cloth_inside(bad, solids)
    with pytest.raises(ValueError, match="rest must be"):
        object_solids(rest[:, :2], obj, material, PITCH)
    with pytest.raises(ValueError, match="leaf_object must be"):
        object_solids(rest, obj[:-1], material, PITCH)
    with pytest.raises(ValueError, match="leaf_object must index"):
        object_solids(rest, obj + 1, material, PITCH)
    with pytest.raises(ValueError, match="object_material must be codes"):
        object_solids(rest, obj, torch.tensor([RIGID, 9]), PITCH)
    for pitch in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="pitch"):
            object_solids(rest, obj, material, pitch)
    off = rest.clone()
    off[0] += 0.03  # a leaf off the box's lattice
    with pytest.raises(ValueError, match="object 0 .rigid.: its rest leaves are not on a lattice"):
        object_solids(off, obj, material, PITCH)
