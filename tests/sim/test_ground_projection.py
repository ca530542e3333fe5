"""``HRNConfig.ground_projection``: no moving leaf ends under the ground; a rigid object is
lifted whole, a deformable leaf alone, static rows and leaves above the ground untouched; off,
or with nothing under the ground, the step is the same bit for bit. ``rigid_ground_depth``: a
rigid object's leaves may lie that many pitches under the plane before it is lifted."""

import dataclasses

import pytest
import torch
from toy_scene import toy_model, toy_scene

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, set_pitch
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sim.step import ground_projected_positions, leaf_to_ancestor_mean, predict, step

SOFT, RIGID, STATIC = slice(0, 8), slice(8, 12), slice(12, 14)


def _sunk(graph):
    """The toy scene's leaves with the rigid square 11 cm under the ground at its lowest leaf, soft
    leaf 0 at z = -0.02 and a static leaf at z = -0.1."""
    pos = graph[NODE].pos.clone()
    pos[RIGID, 2] -= 0.35
    pos[0, 2] = -0.02
    pos[12, 2] = -0.1
    return leaf_to_ancestor_mean(pos, graph)


def test_a_rigid_object_is_lifted_whole_and_a_soft_leaf_alone():
    graph = toy_scene()
    pos = _sunk(graph)
    out = ground_projected_positions(graph, pos)
    lift = -pos[RIGID, 2].min()
    torch.testing.assert_close(out[RIGID], pos[RIGID] + torch.tensor([0.0, 0.0, 1.0]) * lift)
    assert out[RIGID, 2].min() == 0.0
    assert torch.equal(torch.cdist(out[RIGID], out[RIGID]), torch.cdist(pos[RIGID], pos[RIGID]))
    assert out[0, 2] == 0.0 and torch.equal(out[0, :2], pos[0, :2])
    assert torch.equal(out[1:8], pos[1:8])               # the soft leaves above the ground
    assert torch.equal(out[STATIC], pos[STATIC])         # static rows stay, even under the ground
    assert torch.equal(out[14:], pos[14:])               # ancestors are left to re-derive


def test_without_rigid_objects_only_the_deformable_leaves_are_lifted():
    graph = toy_scene()
    pos = _sunk(graph)
    out = ground_projected_positions(graph, pos, rigid=False)
    assert torch.equal(out[RIGID], pos[RIGID])           # the sunk rigid square stays where it is
    assert out[0, 2] == 0.0 and torch.equal(out[0, :2], pos[0, :2])
    assert torch.equal(out[1:8], pos[1:8]) and torch.equal(out[STATIC], pos[STATIC])


def test_a_rigid_object_may_lie_a_given_depth_under_the_plane():
    """With ``rigid_depth`` 0.5 at pitch 0.1 a rigid object sunk 11 cm comes back to 5 cm under the
    plane (lifted whole), one 4 cm under it stays bit for bit; soft leaves still go to the plane."""
    graph = set_pitch(toy_scene(), 0.1)
    pos = _sunk(graph)
    out = ground_projected_positions(graph, pos, rigid_depth=0.5)
    lift = -pos[RIGID, 2].min() - 0.05
    torch.testing.assert_close(out[RIGID], pos[RIGID] + torch.tensor([0.0, 0.0, 1.0]) * lift)
    torch.testing.assert_close(out[RIGID, 2].min(), torch.tensor(-0.05))
    assert out[0, 2] == 0.0 and torch.equal(out[1:8], pos[1:8]) and torch.equal(out[STATIC], pos[STATIC])
    shallow = pos.clone()
    shallow[RIGID, 2] += -0.04 - pos[RIGID, 2].min()  # lowest rigid leaf 4 cm under the plane
    assert torch.equal(ground_projected_positions(graph, shallow, rigid_depth=0.5)[RIGID], shallow[RIGID])
    assert ground_projected_positions(graph, shallow)[RIGID, 2].min() == 0.0  # depth 0: onto the plane
    assert torch.equal(ground_projected_positions(graph, pos, rigid=False, rigid_depth=0.5)[RIGID], pos[RIGID])
    with pytest.raises(ValueError, match="pitch"):
        ground_projected_positions(toy_scene(), pos, rigid_depth=0.5)  # a graph without a pitch


def test_a_rigid_object_moving_faster_than_the_speed_limit_is_not_lifted():
    """``rigid_speed``: the sunk square moved 0.35 m (3.5 pitches of 0.1 m) in the step; a limit
    of 3 pitches leaves it where it is, 4 lifts it as without a limit; soft leaves are lifted
    either way."""
    graph = set_pitch(toy_scene(), 0.1)
    pos = _sunk(graph)
    fast = ground_projected_positions(graph, pos, rigid_depth=0.5, rigid_speed=3.0)
    assert torch.equal(fast[RIGID], pos[RIGID]) and fast[0, 2] == 0.0
    slow = ground_projected_positions(graph, pos, rigid_depth=0.5, rigid_speed=4.0)
    assert torch.equal(slow, ground_projected_positions(graph, pos, rigid_depth=0.5))
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="rigid_ground_speed"):
            HRNConfig(rigid_ground_speed=bad)


def test_a_rigid_object_rises_at_most_the_lift_limit_in_one_step():
    """``rigid_lift``: the square sunk 11 cm at pitch 0.1 rises 2 cm with a limit of 0.2 pitch (its
    shape kept), and as far as without a limit when the limit exceeds its depth; soft leaves go
    onto the plane either way."""
    graph = set_pitch(toy_scene(), 0.1)
    pos = _sunk(graph)
    capped = ground_projected_positions(graph, pos, rigid_lift=0.2)
    torch.testing.assert_close(capped[RIGID], pos[RIGID] + torch.tensor([0.0, 0.0, 0.02]))
    assert capped[0, 2] == 0.0 and torch.equal(capped[STATIC], pos[STATIC])
    assert torch.equal(ground_projected_positions(graph, pos, rigid_lift=1.5), ground_projected_positions(graph, pos))
    for bad in (-0.1, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="rigid_ground_lift"):
            HRNConfig(rigid_ground_lift=bad)
    model = with_applied_options(_model(), ground_projection=True, rigid_ground_lift=0.25)
    assert "rigid_ground_lift=0.25" in repr(model)


def test_the_rigid_ground_depth_is_checked_and_shown():
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="rigid_ground_depth"):
            HRNConfig(rigid_ground_depth=bad)
    model = with_applied_options(_model(), ground_projection=True, rigid_ground_depth=0.5)
    assert "rigid_ground_depth=0.5" in repr(model)
    graph = set_pitch(toy_scene(), 0.1)
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):  # the rigid square falls into the ground
        value = store[name].clone()
        value[RIGID, 2] -= 0.35
        store[name] = leaf_to_ancestor_mean(value, graph)
    with torch.no_grad():
        after = predict(model, graph)
    assert after.pos[RIGID, 2].min() >= -0.05 - 1e-6


def test_nothing_under_the_ground_is_returned_bit_for_bit():
    graph = toy_scene()
    pos = graph[NODE].pos
    assert torch.equal(ground_projected_positions(graph, pos), pos)


def _model(**kw):
    return toy_model(**kw)


def test_the_step_keeps_moving_leaves_above_the_ground_and_derives_velocities():
    plain = _model()
    projected = with_applied_options(plain, ground_projection=True)
    assert projected.config.ground_projection and "ground_projection=True" in repr(projected)
    graph = toy_scene()
    store = graph[NODE]
    low = torch.tensor([0.0, 0.0, -0.35])
    for name in ("pos", "prev_pos", "prev_prev_pos"):  # the rigid square falls into the ground
        value = store[name].clone()
        value[RIGID] += low
        store[name] = leaf_to_ancestor_mean(value, graph)
    with torch.no_grad():
        before = predict(plain, graph)
        after = predict(projected, graph)
    assert before.pos[RIGID, 2].min() < 0
    assert after.pos[:14][~store.is_static[:14], 2].min() >= 0
    lifted = [8, 9, 10, 11, 17]  # the square's leaves and root: the velocity is the whole move
    torch.testing.assert_close(after.velocity[lifted], after.pos[lifted] - store.pos[lifted])
    assert (after.velocity[lifted, 2] > before.velocity[lifted, 2]).all()
    torch.testing.assert_close(after.pos[SOFT], before.pos[SOFT])  # the soft cube is above the ground


def test_a_lift_that_is_not_a_motion_carries_x_t_and_the_next_step_reads_the_network_s_velocity():
    """``ground_lift_velocity=False``: the same lifted positions as with the lift counted as
    motion, the network's own velocities, and ``prev_pos`` = x_t moved by the lift, which the
    next graph holds, so x_{t+1} - prev_pos is the predicted velocity; rows not lifted keep x_t
    bit for bit. Off the ground the two settings give the same step."""
    moving = with_applied_options(_model(), ground_projection=True)
    correcting = with_applied_options(moving, ground_lift_velocity=False)
    assert "ground_lift_velocity=False" in repr(correcting) and "ground_lift_velocity" not in repr(moving)
    graph = toy_scene()
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):  # the rigid square falls into the ground
        value = store[name].clone()
        value[RIGID] += torch.tensor([0.0, 0.0, -0.35])
        store[name] = leaf_to_ancestor_mean(value, graph)
    with torch.no_grad():
        plain = predict(_model(), graph)
        counted = predict(moving, graph)
        carried = predict(correcting, graph)
        nxt = step(correcting, graph).graph
    assert counted.prev_pos is None and carried.prev_pos is not None
    torch.testing.assert_close(carried.pos, counted.pos)
    lifted = [8, 9, 10, 11, 17]  # the square's leaves and root
    torch.testing.assert_close(carried.velocity, plain.velocity)
    torch.testing.assert_close(carried.pos[lifted] - carried.prev_pos[lifted], plain.velocity[lifted])
    assert (carried.prev_pos[lifted, 2] > store.pos[lifted, 2]).all()
    still = [i for i in range(store.num_nodes) if i not in lifted]
    assert torch.equal(carried.prev_pos[still], store.pos[still])
    assert torch.equal(nxt[NODE].prev_pos, carried.prev_pos) and torch.equal(nxt[NODE].prev_prev_pos, store.prev_pos)
    above = toy_scene()
    with torch.no_grad():
        assert torch.equal(step(correcting, above).graph[NODE].prev_pos, step(moving, above).graph[NODE].prev_pos)


def test_the_step_without_rigid_objects_leaves_a_sunk_rigid_body_and_lifts_soft_leaves():
    plain = _model()
    projected = with_applied_options(plain, ground_projection=True, ground_projection_rigid=False)
    assert "ground_projection_rigid=False" in repr(projected)
    graph = toy_scene()
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):  # the rigid square and the soft cube in the ground
        value = store[name].clone()
        value[:12, 2] -= 0.35
        store[name] = leaf_to_ancestor_mean(value, graph)
    with torch.no_grad():
        before = predict(plain, graph)
        after = predict(projected, graph)
    assert before.pos[SOFT, 2].min() < 0 and before.pos[RIGID, 2].min() < 0
    torch.testing.assert_close(after.pos[RIGID], before.pos[RIGID])  # left where the network put it
    assert after.pos[SOFT, 2].min() >= 0
    sunk = before.pos[SOFT, 2] < 0
    torch.testing.assert_close(after.pos[SOFT][sunk, 2], torch.zeros(int(sunk.sum())))


def test_off_or_above_the_ground_the_step_is_unchanged():
    plain = _model()
    projected = with_applied_options(plain, ground_projection=True)
    graph = toy_scene()
    with torch.no_grad():
        a, b = step(plain, graph), step(projected, graph)
    assert torch.equal(a.pos, b.pos) and torch.equal(a.velocity, b.velocity)
    assert torch.equal(a.local_velocity, b.local_velocity)
    assert HRNConfig().ground_projection is False
    assert dataclasses.replace(HRNConfig(), ground_projection=True).to_dict()["ground_projection"] is True
