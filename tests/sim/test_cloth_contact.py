"""``HRNConfig.cloth_clearance`` (:mod:`hrn_pyg.sim.cloth_contact`): the surface normals of a
lattice at rest, a cloth leaf inside a box moved out along the face it entered (turned with the
box), leaves outside, beside a convex edge or held by sleeping kept where they are, and a
rollout with the rule: no leaf ends inside, the rule off is the plain rollout bit for bit, and
the count of :mod:`hrn_pyg.sim.penetration` agrees."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from toy_scene import toy_model, toy_window

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, set_pitch, set_state
from hrn_pyg.data.kinds import CLOTH, RIGID, SOFT, STATIC
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.sim.cloth_contact import (ENTRY_MARGIN, RIGID_DEPTH, RIGID_RUN, SHIFT_LIMIT, STRETCH_LIMIT,
                                      cloth_contact, surface_normals)
from hrn_pyg.sim.penetration import cloth_inside_counts, object_solids
from hrn_pyg.sim.rollout import rollout

PITCH = 0.1
BOX_SIDE = 4  # leaves a side: 64 leaves, 0..0.3 m from the box's corner leaf


def lattice(n: int, origin=(0.0, 0.0, 0.0)) -> torch.Tensor:
    ticks = torch.arange(n, dtype=torch.float32) * PITCH
    grid = torch.stack(torch.meshgrid(ticks, ticks, ticks, indexing="ij"), dim=-1).reshape(-1, 3)
    return grid + torch.tensor(origin)


def turn(degrees: float) -> torch.Tensor:
    """A turn by ``degrees`` about z after half as much about x."""
    a, b = math.radians(degrees), math.radians(degrees / 2)
    about_z = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    about_x = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(b), -math.sin(b)], [0.0, math.sin(b), math.cos(b)]])
    return about_z @ about_x


def box_and_cloth(cloth: torch.Tensor, box_pose: torch.Tensor | None = None, material: int = RIGID,
                  far_cube: bool = False):
    """A box of 4x4x4 leaves at rest with its corner leaf at the origin (object 0, rigid unless
    told) and a cloth of the given leaves (object 1), the box placed by ``box_pose`` (a rotation
    about its centre); with ``far_cube`` a rigid cube of 2x2x2 leaves 3 m away (object 2, out of
    everyone's reach). The graph at rest, its pitch set, collision edges at radius 1.6 pitches."""
    box = lattice(BOX_SIDE)
    n_box, n_cloth = len(box), len(cloth)
    far = lattice(2, (3.0, 0.0, 0.0)) if far_cube else torch.zeros(0, 3)
    n = n_box + n_cloth + len(far)
    parent = torch.tensor([n] * n_box + [n + 1] * n_cloth + [n + 2] * len(far) + [-1] * (3 if far_cube else 2))
    mass = torch.cat([torch.full((n_box,), 0.1), torch.full((n_cloth,), 0.01), torch.full((len(far),), 0.1)])
    obj = torch.cat([torch.zeros(n_box, dtype=torch.long), torch.ones(n_cloth, dtype=torch.long),
                     torch.full((len(far),), 2, dtype=torch.long)])
    rest = torch.cat([box, cloth, far])
    materials = [material, CLOTH] + ([RIGID] if far_cube else [])
    graph = build_structure(parent, mass, obj, torch.tensor(materials), torch.tensor([1.0, 0.5, 1.0][:len(materials)]),
                            rest_pos=rest, pitch=PITCH)
    now = rest.clone()
    if box_pose is not None:
        centre = box.mean(dim=0)
        now[:n_box] = (box - centre) @ box_pose.T + centre
    graph = set_state(graph, now, now, now, radius=1.6 * PITCH)
    return graph, n_box


def test_surface_normals_point_out_of_a_lattice_and_vanish_inside():
    box = lattice(3).numpy()  # 27 leaves: the centre one is interior
    normals = surface_normals(box, PITCH)
    centre = 13
    assert np.allclose(normals[centre], 0.0)
    face = int(np.flatnonzero(np.all(np.isclose(box, [0.1, 0.1, 0.2]), axis=1))[0])  # top face's centre
    assert np.allclose(normals[face], [0.0, 0.0, 1.0], atol=1e-9)
    corner = int(np.flatnonzero(np.all(np.isclose(box, [0.0, 0.0, 0.0]), axis=1))[0])
    assert np.allclose(normals[corner], -np.ones(3) / math.sqrt(3.0), atol=1e-9)
    rotation = turn(35.0).double().numpy()
    assert np.allclose(surface_normals(box @ rotation.T, PITCH), normals @ rotation.T, atol=1e-9)
    slab = lattice(3).numpy()[:9]  # one leaf thick (x = 0): its middle leaf has no side to face
    assert np.allclose(surface_normals(slab, PITCH)[4], 0.0)


def test_a_cloth_leaf_inside_is_moved_out_along_the_face_it_entered():
    top = PITCH * (BOX_SIDE - 1)  # the top leaves' height
    cloth = torch.tensor([[0.15, 0.15, top + 0.5], [0.25, 0.15, top + 0.5]])
    graph, n_box = box_and_cloth(cloth)
    contact = cloth_contact(graph, clearance=0.2)
    pos = graph[NODE].pos.clone()
    pos[n_box] = torch.tensor([0.15, 0.15, top - 0.03])  # 3 cm under the top face's plane
    pos[n_box + 1] = torch.tensor([0.15, 0.25, top + 0.04])  # above it: left alone
    graph = set_state(graph, pos, pos, pos, radius=1.6 * PITCH)
    moved = contact.project(graph, pos)
    assert torch.allclose(moved[n_box], torch.tensor([0.15, 0.15, top + 0.2 * PITCH]), atol=1e-6)
    assert torch.equal(moved[n_box + 1], pos[n_box + 1]) and torch.equal(moved[:n_box], pos[:n_box])
    parents = graph[NODE].is_root
    assert not torch.equal(moved[parents], pos[parents])  # the cloth's root re-derived from its leaves
    held = torch.ones(graph[NODE].num_nodes, dtype=torch.bool)
    held[n_box] = False
    assert contact.project(graph, pos, movable=held) is pos  # a leaf held still stays


def test_the_normals_turn_with_the_box():
    rotation = turn(40.0)
    graph, n_box = box_and_cloth(torch.tensor([[0.15, 0.15, 0.9], [0.0, 0.0, 1.2]]), box_pose=rotation)
    contact = cloth_contact(graph, clearance=0.1)
    store = graph[NODE]
    centre = store.pos[:n_box].mean(dim=0)
    up = rotation @ torch.tensor([0.0, 0.0, 1.0])
    top_centre = centre + 0.15 * up  # the turned top face's middle, at its leaves' plane
    pos = store.pos.clone()
    pos[n_box] = top_centre - 0.02 * up
    graph = set_state(graph, pos, pos, pos, radius=1.6 * PITCH)
    moved = contact.project(graph, pos)
    assert torch.allclose(moved[n_box], top_centre + 0.1 * PITCH * up, atol=1e-5)


def test_a_leaf_beside_a_convex_edge_is_not_pushed():
    """Outside the box beside its side face, below the top plane and behind the top edge's
    diagonal plane: in front of the side face's plane, so not inside."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_cloth(torch.tensor([[0.33, 0.15, top - 0.02], [0.15, 0.15, 1.0]]))
    contact = cloth_contact(graph, clearance=0.0)
    pos = graph[NODE].pos
    assert contact.project(graph, pos) is pos


def test_nothing_to_do_gives_no_contact_and_bad_settings_are_refused():
    graph, _ = box_and_cloth(torch.tensor([[0.1, 0.1, 1.0]]))
    assert cloth_contact(graph, 0.1) is not None
    toy = toy_window(2)  # soft, rigid and static: no cloth
    assert cloth_contact(set_pitch(toy, 0.05), 0.1) is None
    with pytest.raises(ValueError, match="clearance"):
        cloth_contact(graph, -0.1)
    with pytest.raises(ValueError, match="cloth_clearance"):
        HRNConfig(cloth_clearance=1.5)


def _model() -> HRN:
    return toy_model(collision_radius=1.6 * PITCH, rest_offsets=True)


def test_a_stop_is_a_motion_and_a_push_out_a_correction_of_place():
    """A cloth leaf falling from 2 cm over the box's top to 3 cm into it is stopped where it
    enters (its velocity: that shorter move) and then pushed out to the clearance, which moves
    its :math:`x_t` too (the returned ``prev_pos``), so the push gives it no speed; the same with
    an :math:`x_t` a ground lift moved (``prev_pos`` given), where nodes nothing moved keep it."""
    from hrn_pyg.sim.step import Prediction

    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_cloth(torch.tensor([[0.15, 0.15, top + 0.5], [0.25, 0.15, top + 0.5]]))
    now = graph[NODE].pos.clone()
    now[n_box] = torch.tensor([0.15, 0.15, top + 0.02])  # 2 cm over the top leaves, falling
    graph = set_state(graph, now, now, now, radius=1.6 * PITCH)
    now = graph[NODE].pos
    pos = now.clone()
    pos[n_box] = torch.tensor([0.15, 0.15, top - 0.03])  # the step put it 3 cm into the box
    since = now + torch.tensor([0.0, 0.0, 0.01])  # as if a lift had moved every x_t up 1 cm
    contact = cloth_contact(graph, clearance=0.2)
    plain = contact(graph, Prediction(pos, pos - now, pos - now))
    lifted = contact(graph, Prediction(pos, pos - since, pos - since, since))
    torch.testing.assert_close(lifted.pos, plain.pos)
    assert float(plain.pos[n_box, 2]) == pytest.approx(top + 0.2 * PITCH, abs=1e-6)  # pushed out
    stopped = float(now[n_box, 2]) - 0.05 * (0.4 - ENTRY_MARGIN)  # where it enters, less the margin
    assert float(plain.velocity[n_box, 2]) == pytest.approx(stopped - float(now[n_box, 2]), abs=1e-5)
    assert float(lifted.velocity[n_box, 2]) == pytest.approx(stopped - float(since[n_box, 2]), abs=1e-5)
    for result, start in ((plain, now), (lifted, since)):
        torch.testing.assert_close(result.pos - result.prev_pos, result.velocity)  # x_t moved with the push
        still = (result.pos == pos).all(-1) & graph[NODE].is_leaf
        assert torch.equal(result.prev_pos[still], start[still])


@pytest.mark.parametrize("sleep", [None, "default"])
def test_a_rollout_with_the_rule_keeps_the_falling_cloth_out_and_off_is_unchanged(sleep):
    """A sheet falling onto a static box, 2 cm a step from 3 cm above its top leaves, stepped by
    an untrained network: without the rule its leaves end steps inside the box (by
    :mod:`hrn_pyg.sim.penetration`'s count); with it, every leaf over the top face ends every
    step at least the clearance above the top leaves' plane, and the count falls to none. The
    rule at 0 is the plain rollout, bit for bit."""
    top = PITCH * (BOX_SIDE - 1)
    ticks = torch.arange(5, dtype=torch.float32) * 0.075
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    sheet = torch.stack([x.flatten(), y.flatten(), torch.full((25,), top + 0.03)], dim=1)
    graph, n_box = box_and_cloth(sheet, material=STATIC)
    store = graph[NODE]
    fall = torch.tensor([0.0, 0.0, 0.02]) * (torch.arange(store.num_nodes) >= n_box).unsqueeze(-1)
    graph = set_state(graph, store.pos + 2 * fall, store.pos + fall, store.pos, radius=1.6 * PITCH)
    plain = _model()
    kept = with_applied_options(plain, cloth_clearance=0.1)
    off = with_applied_options(plain, cloth_clearance=0.0)
    kw = {} if sleep == "default" else {"sleep": None}
    with torch.no_grad():
        free = rollout(plain, graph, 8, **kw)
        held = rollout(kept, graph, 8, **kw)
        assert torch.equal(rollout(off, graph, 8, **kw), free)
    leaves = store.is_leaf.nonzero().flatten()
    solids = object_solids(store.rest_pos[leaves], torch.cat([torch.zeros(n_box), torch.ones(25)]).long(),
                           torch.tensor([STATIC, CLOTH]), PITCH)
    assert int(cloth_inside_counts(free[:, leaves], solids).sum()) > 0  # the untrained network lets it in
    assert int(cloth_inside_counts(held[:, leaves], solids).sum()) == 0
    assert torch.isfinite(held).all() and torch.equal(held[:, :n_box], free[:, :n_box])  # the box as it was
    xy = held[:, n_box:n_box + 25, :2]
    over_box = ((xy > 0.02) & (xy < top - 0.02)).all(-1)  # over the top face, off its edges
    assert int(over_box.sum()) > 25
    assert bool((held[:, n_box:n_box + 25, 2][over_box] >= top + 0.1 * PITCH - 1e-5).all())


def test_objects_asleep_elsewhere_change_nothing_for_the_rule():
    """With a rigid cube asleep out of reach, the sleeping rollout runs the held step (the cube
    held, the rest on a sub-graph) and applies the rule there: the sheet and box move as in the
    rollout with every object awake, and the cube stays where it was."""
    top = PITCH * (BOX_SIDE - 1)
    ticks = torch.arange(5, dtype=torch.float32) * 0.075
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    sheet = torch.stack([x.flatten(), y.flatten(), torch.full((25,), top + 0.03)], dim=1)
    graph, n_box = box_and_cloth(sheet, material=STATIC, far_cube=True)
    store = graph[NODE]
    moving = ((torch.arange(store.num_nodes) >= n_box) & (torch.arange(store.num_nodes) < n_box + 25)).unsqueeze(-1)
    fall = torch.tensor([0.0, 0.0, 0.02]) * moving
    graph = set_state(graph, store.pos + 2 * fall, store.pos + fall, store.pos, radius=1.6 * PITCH)
    kept = with_applied_options(_model(), cloth_clearance=0.1)
    with torch.no_grad():
        awake = rollout(kept, graph, 6, sleep=None)
        asleep = rollout(kept, graph, 6)
    sheet_rows = slice(n_box, n_box + 25)
    assert torch.allclose(asleep[:, sheet_rows], awake[:, sheet_rows], atol=1e-5)
    assert not torch.allclose(awake[:, sheet_rows], rollout(_model(), graph, 6, sleep=None)[:, sheet_rows], atol=1e-3)
    far = slice(n_box + 25, n_box + 33)
    assert torch.equal(asleep[:, far], store.pos[far].expand(6, -1, -1))


def test_fixed_shape_steps_run_the_rule_after_the_network_where_it_acts():
    """The rule's sizes depend on the step's contacts: fixed-shape steps run it after their
    network, on the collision edges of the candidate list, and give the plain rollout's positions,
    on a scene with a cloth sunk 2 cm into a solid (which the rule moves out) and on one with no cloth."""
    from hrn_pyg.sim.fixed_shape import fixed_shape_rollout

    top = PITCH * (BOX_SIDE - 1)
    ticks = torch.arange(3, dtype=torch.float32) * 0.075
    x, y = torch.meshgrid(ticks, ticks, indexing="ij")
    sheet = torch.stack([x.flatten(), y.flatten(), torch.full((9,), top - 0.02)], dim=1)
    graph, _ = box_and_cloth(sheet)
    kept = with_applied_options(_model(), cloth_clearance=0.1)
    no_cloth = toy_window(steps=4)
    with torch.no_grad():
        for scene in (graph, no_cloth):
            assert torch.equal(fixed_shape_rollout(kept, scene, 3).pos, rollout(kept, scene, 3, sleep=None))
        assert not torch.equal(rollout(kept, graph, 3, sleep=None), rollout(_model(), graph, 3, sleep=None))


def box_and_small_cube(material: int, offset, box_material: int = STATIC, side: int = BOX_SIDE) -> tuple:
    """The 4x4x4 box of :func:`box_and_cloth` (``side`` leaves a side), static unless
    ``box_material`` says (object 0), and a 2x2x2 cube of ``material`` (object 1) whose corner
    leaf sits at ``offset``: the graph at rest, its pitch set."""
    box, small = lattice(side), lattice(2, offset)
    n_box = len(box)
    n = n_box + len(small)
    parent = torch.tensor([n] * n_box + [n + 1] * len(small) + [-1, -1])
    mass = torch.full((n,), 0.1)
    obj = torch.tensor([0] * n_box + [1] * len(small))
    rest = torch.cat([box, small])
    graph = build_structure(parent, mass, obj, torch.tensor([box_material, material]), torch.tensor([1.0, 0.5]),
                            rest_pos=rest, pitch=PITCH)
    return set_state(graph, rest, rest, rest, radius=1.6 * PITCH), n_box


@pytest.mark.parametrize("material", [RIGID, SOFT])
def test_solid_clearance_keeps_soft_and_rigid_leaves_out_and_moves_a_rigid_body_whole(material):
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(material, (0.1, 0.1, top + 0.2))
    assert cloth_contact(graph, clearance=0.3) is None  # no cloth, no solid clearance: nothing to do
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    pos[n_box:n_box + 8] -= torch.tensor([0.0, 0.0, 0.2 + 0.03])  # its lower leaves 3 cm under the top plane
    pos[n_box + 2] += torch.tensor([0.0, 0.0, 0.01])  # one of them only 2 cm under
    graph = set_state(graph, pos, pos, pos, radius=1.6 * PITCH)
    moved = contact.project(graph, pos)
    small = moved[n_box:n_box + 8] - pos[n_box:n_box + 8]
    lower = pos[n_box:n_box + 8, 2] < top
    assert torch.equal(moved[:n_box], pos[:n_box])  # a static box never moves
    assert bool((moved[n_box:n_box + 8][lower, 2] >= top + 0.2 * PITCH - 1e-6).all())  # every lower leaf out
    if material == RIGID:  # one move for all, the longest push: 3 cm + the clearance
        assert torch.allclose(small, torch.tensor([0.0, 0.0, 0.03 + 0.2 * PITCH]).expand(8, 3), atol=1e-6)
    else:  # each leaf by its own push; the upper ones stay
        assert torch.allclose(small[~lower], torch.zeros(int((~lower).sum()), 3))
        assert float(small[2, 2]) == pytest.approx(0.02 + 0.2 * PITCH, abs=1e-6)


def leaves_inside(graph, pos: torch.Tensor, of: int) -> int:
    """How many leaves of object ``of`` lie in another object's solid at ``pos``."""
    store = graph[NODE]
    leaf = torch.nonzero(store.is_leaf).flatten()
    material = store.material.argmax(dim=1)
    objects = store.object[leaf]
    kinds = torch.zeros(int(objects.max()) + 1, dtype=torch.long).index_put_((objects,), material[leaf])
    solids = object_solids(store.rest_pos[leaf], objects, kinds, PITCH)
    x = pos[leaf].double()
    corners = x[solids.tets]
    edges = corners[:, 1:] - corners[:, :1]
    solid = torch.linalg.det(edges).abs() > 1e-9  # a flattened tetrahedron holds nothing
    corners, edges, owner = corners[solid], edges[solid], solids.tet_object[solid]
    b = torch.linalg.solve(edges.transpose(1, 2)[None], (x[:, None] - corners[None, :, 0]).unsqueeze(-1)).squeeze(-1)
    inside = (torch.cat([1 - b.sum(-1, keepdim=True), b], -1) >= -1e-6).all(-1)
    inside &= objects[:, None] != owner[None]
    return int(inside.any(dim=1)[objects == of].sum())


@pytest.mark.parametrize("material", [RIGID, SOFT])
def test_a_fast_step_into_a_solid_is_stopped_where_it_enters(material):
    """x_t: the small cube far above the box (no collision edge); x_{t+1}: the cube moved whole
    into the box's middle, every leaf inside its solid. The step is stopped where the cube enters:
    no leaf is left inside, a rigid cube moves as one, and no leaf ends below the box's top."""
    graph, n_box = box_and_small_cube(material, (0.05, 0.05, 1.0))
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    pos[n_box:n_box + 8] += torch.tensor([0.10, 0.10, 0.15 - 1.0])
    assert graph[COLLISION].edge_index.numel() == 0
    assert leaves_inside(graph, pos, of=1) == 8
    moved = contact.project(graph, pos)
    assert leaves_inside(graph, moved, of=1) == 0
    assert torch.equal(moved[:n_box], pos[:n_box])  # a static box never moves
    top = PITCH * (BOX_SIDE - 1)
    assert float(moved[n_box:n_box + 8, 2].min()) >= top - 1e-6
    shift = moved[n_box:n_box + 8] - pos[n_box:n_box + 8]
    if material == RIGID:  # one move for all leaves
        assert torch.allclose(shift, shift[:1].expand(8, 3), atol=1e-6) and float(shift[0].norm()) > 0


def test_two_soft_bodies_sunk_into_each_other_are_parted():
    """A soft 2x2x2 cube sunk 1.2 pitches into the top of a soft 4x4x4 box, at rest (so the
    surface planes reach only its upper leaves): within three steps of no motion no leaf of
    either body is in the other's solid (the smaller cube moves whole by at most
    :data:`SHIFT_LIMIT` pitches a step); the box's bottom layer stays where it was, and no leaf
    moves more than three pitches in all."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(SOFT, (0.1, 0.1, top - 0.12))
    graph[NODE].material[:n_box] = torch.nn.functional.one_hot(torch.tensor(SOFT), 4).to(graph[NODE].material)
    graph[NODE].is_static[:n_box] = False
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    assert leaves_inside(graph, pos, of=1) == 8
    moved = pos
    for _ in range(3):
        before = moved
        moved = contact.project(set_state(graph, before, before, before, radius=1.6 * PITCH), before)
    assert leaves_inside(graph, moved, of=1) == 0 and leaves_inside(graph, moved, of=0) == 0
    bottom = pos[:n_box, 2] < 0.5 * PITCH
    assert torch.equal(moved[:n_box][bottom], pos[:n_box][bottom])
    assert float((moved - pos).norm(dim=1).max()) < 3 * PITCH


def test_a_soft_body_gives_way_to_a_static_object_inside_it():
    """A static 2x2x2 cube sunk half a pitch into the top of a soft 4x4x4 box: the cube cannot
    move, so the box's tetrahedra move off its leaves in one step; its bottom layer stays. (A
    cube sunk 0.8 pitch is not freed in one step: the stretch limit pulls part of it back.)"""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(SOFT, (0.1, 0.1, top - 0.05))
    store = graph[NODE]
    store.material[:n_box] = torch.nn.functional.one_hot(torch.tensor(SOFT), 4).to(store.material)
    store.is_static[:n_box] = False
    store.material[n_box:n_box + 8] = torch.nn.functional.one_hot(torch.tensor(STATIC), 4).to(store.material)
    store.is_static[n_box:n_box + 8] = True
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = store.pos.clone()
    assert leaves_inside(graph, pos, of=1) == 4
    moved = contact.project(graph, pos)
    assert leaves_inside(graph, moved, of=1) == 0
    assert torch.equal(moved[n_box:n_box + 8], pos[n_box:n_box + 8])
    bottom = pos[:n_box, 2] < 0.5 * PITCH
    assert torch.equal(moved[:n_box][bottom], pos[:n_box][bottom])


def test_a_soft_body_is_stretched_no_further_than_the_limit():
    """One leaf of a soft cube, far from anything, pulled two pitches out (edges 3x their rest
    length): afterwards no lattice edge is longer than STRETCH_LIMIT times its rest length (an
    edge squashed to nothing gives no NaN), the cube's centre of mass stays, and a cube that is
    not stretched is returned as it was."""
    graph, n_box = box_and_small_cube(SOFT, (1.0, 1.0, 1.0))
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    assert contact.project(graph, pos) is pos
    pos[n_box] += torch.tensor([-0.2, 0.0, 0.0])
    pos[n_box + 7] = pos[n_box + 6]  # an edge of length 0 (leaves 6 and 7 are neighbours)
    moved = contact.project(graph, pos)
    assert bool(torch.isfinite(moved).all())
    i, j = contact.edges.T
    stretch = (moved[i] - moved[j]).norm(dim=1) / (contact.rest[i] - contact.rest[j]).norm(dim=1)
    assert float(stretch.max()) <= STRETCH_LIMIT + 1e-5
    cube = slice(n_box, n_box + 8)
    assert torch.allclose(moved[cube].mean(0), pos[cube].mean(0), atol=1e-6)
    assert torch.equal(moved[:n_box], pos[:n_box])


@pytest.mark.parametrize("material", [RIGID, SOFT])
def test_the_energy_limit_keeps_a_push_out_of_a_solid(material):
    """A cube at rest sunk 0.3 pitch into a static box, a step that predicts no motion: the rules
    with the energy limit and the solid clearance end the step with no leaf inside. The push out
    raises the cube, so an energy limit applied after it would take the push back; it comes
    first, on the network's prediction alone."""
    from hrn_pyg.sim.rules import StepRules
    from hrn_pyg.sim.step import Prediction, object_of

    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(material, (0.1, 0.1, top - 0.03))
    pos = graph[NODE].pos
    assert leaves_inside(graph, pos, of=1) == 4
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    rules = StepRules(contact, energy=True, objects=object_of(graph))
    still = torch.zeros_like(pos)
    after = rules(graph, Prediction(pos.clone(), still, still))
    assert leaves_inside(graph, after.pos, of=1) == 0
    assert torch.equal(after.pos[:n_box], pos[:n_box])


def test_a_rigid_body_deep_in_another_climbs_out_a_limited_step_at_a_time():
    """A rigid cube sunk 1.2 pitches into a static box, at rest: it moves whole, each push (the
    planes', the solid's) at most :data:`SHIFT_LIMIT` pitches long (a longer jump reads as a
    burst of speed), and is out within four steps."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(RIGID, (0.1, 0.1, top - 0.12))
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    moved = graph[NODE].pos.clone()
    assert leaves_inside(graph, moved, of=1) > 0
    steps = []
    for _ in range(4):
        before = moved
        moved = contact.project(set_state(graph, before, before, before, radius=1.6 * PITCH), before)
        shift = moved[n_box:n_box + 8] - before[n_box:n_box + 8]
        torch.testing.assert_close(shift, shift[:1].expand(8, 3))  # whole
        steps.append(float(shift[0].norm()))
    assert max(steps) <= 2 * SHIFT_LIMIT * PITCH + 1e-6 and max(steps) > SHIFT_LIMIT * PITCH
    assert leaves_inside(graph, moved, of=1) == 0


def test_a_turning_rigid_body_stopped_where_it_enters_stays_rigid():
    """x_t: the small rigid cube far above the box; x_{t+1}: turned by 60 degrees and moved into
    the box. Cut short by one fraction of its step, its leaves would lie on chords of their arcs;
    stopped, it is fitted rigid again: every distance between two of its leaves is as at rest."""
    graph, n_box = box_and_small_cube(RIGID, (0.05, 0.05, 1.0))
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    cube = pos[n_box:n_box + 8]
    centre = cube.mean(0)
    pos[n_box:n_box + 8] = (cube - centre) @ turn(60.0).T + centre + torch.tensor([0.10, 0.10, 0.15 - 1.0])
    moved = contact.project(graph, pos)
    assert leaves_inside(graph, moved, of=1) == 0 and not torch.equal(moved, pos)
    torch.testing.assert_close(torch.cdist(moved[n_box:n_box + 8], moved[n_box:n_box + 8]),
                               torch.cdist(cube, cube), atol=1e-5, rtol=0.0)


@pytest.mark.parametrize("box", [RIGID, STATIC])
def test_two_rigid_bodies_may_overlap_a_little(box):
    """x_t: the small rigid cube just above the box; x_{t+1}: its lower leaves 0.3 pitch under the
    box's top plane. Into a rigid box that is within :data:`RIGID_DEPTH` (the collision is left to
    the network: nothing moves); a static box is not a rigid body, and the step is stopped."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(RIGID, (0.1, 0.1, top + 0.05), box_material=box)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    pos[n_box:n_box + 8] -= torch.tensor([0.0, 0.0, 0.05 + 0.3 * PITCH])
    assert 0.3 < RIGID_DEPTH and leaves_inside(graph, pos, of=1) == 4
    moved = contact.project(graph, pos)
    if box == RIGID:
        assert moved is pos
    else:
        assert leaves_inside(graph, moved, of=1) == 0


@pytest.mark.parametrize("box", [RIGID, STATIC])
def test_a_rigid_step_that_cuts_a_rigid_corner_and_ends_outside_is_left_alone(box):
    """x_t: the small rigid cube beside the box's top edge; x_{t+1}: moved up and across, so that
    the straight steps of its lower leaves cut through the box's corner (0.17 pitch inside it,
    under :data:`RIGID_RUN`) and end above it, as pybullet's own steps do at an impact. Past a
    rigid box nothing is stopped; a static box is not a rigid body, and the step is stopped."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(RIGID, (top + 0.02, 0.1, top - 0.04), box_material=box)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    start = graph[NODE].pos
    pos = start.clone()
    pos[n_box:n_box + 8] += torch.tensor([-0.06, 0.0, 0.08])
    assert leaves_inside(graph, start, of=1) == 0 and leaves_inside(graph, pos, of=1) == 0
    assert leaves_inside(graph, (start + pos) / 2, of=1) == 2  # halfway, the lower leaves are in the box
    assert (0.1 / 6) / PITCH < RIGID_RUN  # the test's own set-up: the cut is short
    stopped, _ = contact.stop_and_push(graph, pos)
    cube = slice(n_box, n_box + 8)
    if box == RIGID:
        assert stopped is pos
    else:
        moved, asked = (stopped[cube] - start[cube]).norm(dim=-1), (pos[cube] - start[cube]).norm(dim=-1)
        assert float(moved.max()) < 0.6 * float(asked.max())


def test_a_rigid_step_through_a_thin_rigid_part_is_stopped():
    """x_t: the small rigid cube above a rigid plate two leaves (one pitch) thick; x_{t+1}: 0.35 m
    lower, wholly under the plate's bottom: no leaf ends inside it, but each runs a pitch through
    it (more than :data:`RIGID_RUN`), so the cube is stopped where it enters."""
    plate = lattice(4, (0.0, 0.0, 0.5))
    plate = plate[plate[:, 2] <= 0.6 + 1e-6]
    small = lattice(2, (0.1, 0.1, 0.65))
    n_plate = len(plate)
    n = n_plate + len(small)
    parent = torch.tensor([n] * n_plate + [n + 1] * len(small) + [-1, -1])
    graph = build_structure(parent, torch.full((n,), 0.1), torch.tensor([0] * n_plate + [1] * len(small)),
                            torch.tensor([RIGID, RIGID]), torch.tensor([1.0, 0.5]),
                            rest_pos=torch.cat([plate, small]), pitch=PITCH)
    rest = graph[NODE].rest_pos
    graph = set_state(graph, rest, rest, rest, radius=1.6 * PITCH)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    start = graph[NODE].pos
    pos = start.clone()
    pos[n_plate:n_plate + 8] -= torch.tensor([0.0, 0.0, 0.25 + 0.1])
    assert leaves_inside(graph, pos, of=1) == 0 and 1.0 > RIGID_RUN and float(pos[n_plate:n_plate + 8, 2].max()) < 0.5
    stopped, _ = contact.stop_and_push(graph, pos)
    assert float(stopped[n_plate:n_plate + 8, 2].min()) > 0.6  # above the plate's top still


@pytest.mark.parametrize("step", [(0.0, 0.0, -0.01), (0.01, 0.0, -0.01), (0.0, 0.0, 0.01)])
def test_a_rigid_body_sinking_into_another_is_stopped_and_keeps_its_slide(step):
    """x_t: the small rigid cube with its lower leaves a pitch into the middle of a 6x6x6 rigid
    box's top (deeper than :data:`RIGID_DEPTH`, so the entry stop does not see them; pushed out
    upwards); x_{t+1}: 0.1 pitch further down, straight or sliding along x too. The step down is
    taken back (the cube's height stays within 0.01 pitch of x_t's) and at least 90 % of the slide
    is kept; moving up instead, nothing is stopped. Then the pushes move it up, out."""
    side = 6
    top = PITCH * (side - 1)
    graph, n_box = box_and_small_cube(RIGID, (0.2, 0.2, top - 0.10), box_material=RIGID, side=side)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    start = graph[NODE].pos.clone()
    pos = start.clone()
    pos[n_box:n_box + 8] += torch.tensor(step)
    assert 0.2 + RIGID_DEPTH < 0.9 + 0.2  # the test's own set-up: both ways deeper than RIGID_DEPTH
    stopped, projected = contact.stop_and_push(graph, pos)
    cube = slice(n_box, n_box + 8)
    if step[2] < 0:
        moved = stopped[cube] - start[cube]
        # each push out points at its leaf's anchor, so after a slide it leans back a little
        assert bool((moved[:, 2].abs() < 0.01 * PITCH).all())
        assert bool((moved[:, 0] >= 0.9 * step[0]).all()) and bool((moved[:, 0] <= step[0] + 1e-6).all())
        assert bool((moved[:, 1].abs() < 1e-6).all()) and torch.equal(stopped[:n_box], pos[:n_box])
    else:
        assert stopped is pos
    assert float(projected[cube, 2].min()) > float(stopped[cube, 2].min())


def test_a_rigid_body_whose_slide_takes_it_deeper_is_held():
    """x_t: the small rigid cube on the corner edge of the rigid box, its lower leaves 0.8 pitch
    into the top; x_{t+1}: 0.1 pitch down and 0.2 pitch along x, further into the box. Without
    its step down it would still lie deeper in the box than at x_t, so it is held at x_t."""
    top = PITCH * (BOX_SIDE - 1)
    graph, n_box = box_and_small_cube(RIGID, (0.0, 0.0, top - 0.08), box_material=RIGID)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    start = graph[NODE].pos.clone()
    pos = start.clone()
    pos[n_box:n_box + 8] += torch.tensor([0.02, 0.0, -0.01])
    stopped, _ = contact.stop_and_push(graph, pos)
    assert torch.equal(stopped[n_box:n_box + 8], start[n_box:n_box + 8])
    assert torch.equal(stopped[:n_box], pos[:n_box])


def test_a_leaf_inside_one_object_is_still_stopped_where_it_enters_another():
    """x_t: a soft cube with its lower leaves 0.3 pitch into the top of a static box; x_{t+1}: moved
    a metre sideways into a second static box. The leaves inside the first box are left to the
    pushes there, but their step into the second is still stopped where it enters."""
    first, second = lattice(BOX_SIDE), lattice(BOX_SIDE, (1.0, 0.0, 0.0))
    top = PITCH * (BOX_SIDE - 1)
    small = lattice(2, (0.15, 0.1, top - 0.03))
    n_box = len(first)
    n = 2 * n_box + len(small)
    parent = torch.tensor([n] * n_box + [n + 1] * n_box + [n + 2] * len(small) + [-1, -1, -1])
    obj = torch.tensor([0] * n_box + [1] * n_box + [2] * len(small))
    rest = torch.cat([first, second, small])
    graph = build_structure(parent, torch.full((n,), 0.1), obj, torch.tensor([STATIC, STATIC, SOFT]),
                            torch.tensor([1.0, 1.0, 0.5]), rest_pos=rest, pitch=PITCH)
    graph = set_state(graph, rest, rest, rest, radius=1.6 * PITCH)
    contact = cloth_contact(graph, clearance=0.0, solid_clearance=0.2, project_cloth=False)
    pos = graph[NODE].pos.clone()
    cube = slice(2 * n_box, n)
    pos[cube] += torch.tensor([1.0, 0.0, 0.0])
    assert leaves_inside(graph, graph[NODE].pos, of=2) == 4 and leaves_inside(graph, pos, of=2) == 4
    stopped, _ = contact.stop_and_push(graph, pos)
    lower = graph[NODE].pos[cube, 2] < top
    assert bool((stopped[cube][lower, 0] <= 1.0).all())  # cut short before the second box's face (x = 1 m)
