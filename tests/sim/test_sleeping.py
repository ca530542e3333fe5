"""Objects at rest sleep (hrn_pyg/sleeping.py): the rule, the sub-graph step, bit-exact holding.

Most cases use a toy dynamics: the real HRN (so every module runs and hooks see real passes)
with a zero output layer and zero target means, plus a response ``gain * force``: an object
keeps its velocity (no gravity) unless pushed. The toy scene (tests/toy_scene.py) has a soft
cube (object 0, leaves 0-7, root 16), a rigid square (object 1, leaves 8-11, root 17) and a
static body (object 2, leaves 12-13, root 18); ``separate=True`` puts the square 1 m away.
"""

from __future__ import annotations

import math

import pytest
import torch
from stability.stability_helpers import fitted_model, trained_checkpoint
from toy_scene import LEAF_OBJECT, leaf_rest_positions, structure, toy_scene

from hrn_pyg.data.graph import COLLISION, NODE, replicate, set_state
from hrn_pyg.nn.hrn import HRN, HRNInputs
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.sim.sleeping import (
    SleepConfig,
    freeze,
    initial_state,
    objects,
    subgraph,
    update,
)
from hrn_pyg.sim.step import build_inputs, decode, run_network

CUBE, SQUARE = 0, 1
N = 19


class ToyHRN(HRN):
    """The HRN's full pass, output ``0 + gain * normalised force``; records what it is given."""

    gain: float = 0.0

    def forward(self, inputs: HRNInputs, masks=None):
        self.seen_nodes.append(inputs.state.size(0))
        self.seen_batch.append(inputs.batch.clone())
        return super().forward(inputs, masks) + self.gain * inputs.force


def toy_model(gain: float = 0.0, **config) -> ToyHRN:
    base = fitted_model(**config)
    model = ToyHRN(base.config)
    model.load_state_dict(base.state_dict())
    with torch.no_grad():
        model.state.psi.output_layer.weight.zero_()
        model.state.psi.output_layer.bias.zero_()
        model.normalizer.local_mean.zero_()
        model.normalizer.root_mean.zero_()
    model.gain, model.seen_nodes, model.seen_batch = gain, [], []
    return model.eval()


def scene(velocity: dict[int, tuple[float, float, float]] | None = None, separate: bool = True):
    """The toy scene with each listed object moving at a constant velocity (m per step)."""
    x = leaf_rest_positions(separate)
    v = torch.zeros_like(x)
    for obj, vel in (velocity or {}).items():
        v[LEAF_OBJECT == obj] = torch.tensor(vel)
    return set_state(structure(), x - 2 * v, x - v, x, radius=0.08)


def nodes_of(graph, obj: int):
    return graph[NODE].object == obj


def full_search_edges(graph):
    """The collision edges of a graph's ``pos`` searched over all leaves (as ``set_state`` does)."""
    s = graph[NODE]
    return set_state(graph, s.prev_prev_pos, s.prev_pos, s.pos, radius=0.08)[COLLISION].edge_index


def asleep_of(step, graph, obj: int) -> bool:
    flags = step.asleep[nodes_of(graph, obj)]
    assert bool((flags == flags[0]).all()), "an object sleeps as a whole"
    return bool(flags[0])


# (1) sleeping off ------------------------------------------------------------------------------

@pytest.mark.parametrize("config", [{}, {"rigid_fit": True, "ground_contact": True, "rest_offsets": True}])
def test_sleep_off_is_bit_identical_to_plain_rollout(config):
    model = fitted_model(dropout_modules=("force", "collision", "state"), **config)
    graph = replicate(toy_scene(force=True), 2)
    forces = torch.randn(6, graph[NODE].num_nodes, 3, generator=torch.Generator().manual_seed(0))

    def run(**kw):
        gen = torch.Generator().manual_seed(1)
        masks_fn = lambda t, g: model.sample_masks(2, rate=0.3, generator=gen)  # noqa: E731
        with torch.no_grad():
            return unroll(model, graph, 6, forces, masks_fn, **kw)

    ref = run(sleep=None)
    assert all(s.asleep is None for s in ref)
    ref_pos = torch.stack([s.pos for s in ref])
    for kw in ({"sleep": None}, {"sleep": SleepConfig(enabled=False)},
               # on, but nothing still for `patience` steps: every step is the plain step
               {"sleep": SleepConfig(patience=100)}):
        out = run(**kw)
        assert torch.equal(torch.stack([s.pos for s in out]), ref_pos), kw
        assert all(torch.equal(a.velocity, b.velocity) for a, b in zip(out, ref))
        assert all(torch.equal(a.graph[COLLISION].edge_index, b.graph[COLLISION].edge_index) for a, b in zip(out, ref))
    with torch.no_grad():
        assert torch.equal(rollout(model, graph, 3, forces, sleep=SleepConfig(enabled=False)),
                           rollout(model, graph, 3, forces, sleep=None))


def test_sleeping_is_the_default_of_rollout_and_sample():
    """``rollout`` and ``sample`` let objects at rest sleep unless given ``sleep=None``."""
    from hrn_pyg.sampling.sample import sample
    from hrn_pyg.sim.sleeping import DEFAULT_SLEEP

    model = toy_model()
    graph = scene({CUBE: (5e-4, 0.0, 0.0)})  # creeps below the threshold: falls asleep
    steps = DEFAULT_SLEEP.patience + 5
    with torch.no_grad():
        default = rollout(model, graph, steps)
        explicit = rollout(model, graph, steps, sleep=SleepConfig())
        awake = rollout(model, graph, steps, sleep=None)
        sampled = sample(model, graph, 2, steps, 0.0)
        sampled_awake = sample(model, graph, 2, steps, 0.0, sleep=None)
    assert torch.equal(default, explicit)
    cube = nodes_of(graph, CUBE)
    assert torch.equal(default[-1, cube], default[-2, cube])  # held still
    assert not torch.equal(awake[-1, cube], awake[-2, cube])  # the network alone keeps creeping
    leaves = graph[NODE].is_leaf
    assert torch.equal(sampled, default[:, leaves].expand(2, -1, -1, -1))
    assert torch.equal(sampled_awake, awake[:, leaves].expand(2, -1, -1, -1))


# (2) a resting object falls asleep and holds still ---------------------------------------------

def test_creeping_object_falls_asleep_after_patience_steps_and_holds_exactly_still():
    patience = 5
    model = toy_model()
    graph = scene({CUBE: (5e-4, 0.0, 0.0)})  # creeps below the threshold (2e-3 m per step)
    cube = nodes_of(graph, CUBE)
    with torch.no_grad():
        steps = unroll(model, graph, 30, sleep=SleepConfig(patience=patience, start_from_history=False))
        free = rollout(model, graph, 30, sleep=None)
    pos = torch.stack([s.pos for s in steps])
    # still for `patience` observed steps: the initial velocity and patience - 1 predicted ones
    for t in range(patience - 1):
        assert not asleep_of(steps[t], graph, CUBE)
        assert not torch.equal(pos[t, cube], (pos[t - 1] if t else graph[NODE].pos)[cube])
    for t in range(patience - 1, 30):
        assert asleep_of(steps[t], graph, CUBE) and asleep_of(steps[t], graph, SQUARE)
        assert torch.equal(pos[t], pos[patience - 2]), t  # bit for bit, every node
        nxt = steps[t].graph[NODE]
        assert torch.equal(nxt.prev_pos, nxt.pos) and torch.equal(nxt.prev_prev_pos, nxt.pos)
    assert asleep_of(steps[0], graph, 2)  # the static body is always asleep
    # without sleeping the cube creeps on
    assert float((free[-1, cube] - free[patience - 2, cube]).abs().max()) > 0.005


def test_a_scene_wholly_asleep_keeps_its_contacts_without_a_search(monkeypatch):
    from hrn_pyg.sim import sleeping

    model = toy_model()
    graph = scene(separate=False)  # at rest, the square touching the cube
    with torch.no_grad():
        first = unroll(model, graph, 1)[0]  # asleep from the start (the history shows rest)
    assert bool(first.asleep.all())
    assert first.graph[COLLISION].edge_index.size(1) > 0
    assert torch.equal(first.graph[COLLISION].edge_index, full_search_edges(first.graph))

    def no_search(*args, **kwargs):
        raise AssertionError("searched although every leaf is held")

    monkeypatch.setattr(sleeping, "collision_edges", no_search)
    with torch.no_grad():
        steps = unroll(model, first.graph, 3)
    for st in steps:
        assert bool(st.asleep.all())
        assert torch.equal(st.graph[COLLISION].edge_index, first.graph[COLLISION].edge_index)
        assert torch.equal(st.pos, first.pos)


def _tower_at_rest():
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.sampling.ensemble import episode_state

    graph = episode_state(simulate_episode("tower", 9, steps=3), start=2)
    del graph[NODE].pos_seq, graph[NODE].force_seq
    return graph


@pytest.mark.skipif(trained_checkpoint("tower") is None, reason="no shipped tower checkpoint")
def test_resting_tower_sleeps_holds_exactly_still_and_wakes_when_hit():
    from hrn_pyg.checkpoints import load_model

    model = load_model(trained_checkpoint("tower"))
    graph = _tower_at_rest()  # pybullet's tower (objects 0-2) and ball (3) after two steps
    s = graph[NODE]
    ball, base = s.is_leaf & (s.object == 3), s.is_leaf & (s.object == 0)
    tower = s.object < 3
    aim = s.pos[base].mean(0) - s.pos[ball].mean(0)
    aim[2] = 0.0
    forces = torch.zeros(50, s.num_nodes, 3)
    forces[15:25, ball] = 0.3 * aim / aim.norm()  # 8 N on the ball towards the tower, steps 15-24
    with torch.no_grad():
        steps = unroll(model, graph, 50, forces, sleep=SleepConfig())
    asleep = torch.stack([st.asleep[s.is_root] for st in steps])  # [50, 4]
    first = int(torch.nonzero(asleep.all(1)).min())
    assert first <= SleepConfig().patience  # the resting scene falls asleep whole
    assert bool(asleep[first:15].all()) and not bool(asleep[15, 3])  # the push wakes the ball
    # the first graph with a collision edge from the ball into the tower
    hit = next(t for t in range(15, 50)
               if bool((ball[steps[t].graph[COLLISION].edge_index[0]]
                        & tower[steps[t].graph[COLLISION].edge_index[1]]).any()))
    pos = torch.stack([st.pos for st in steps])
    assert torch.equal(pos[first:hit + 1, tower], pos[first, tower].expand(hit + 1 - first, -1, -1))
    assert bool(asleep[hit, :3].all()) and not bool(asleep[hit + 1, :3].any())  # the hit wakes the tower
    # collision edges searched only around awake leaves are the full search's, every step
    assert all(torch.equal(st.graph[COLLISION].edge_index, full_search_edges(st.graph)) for st in steps)
    assert float((pos[-1, base] - pos[hit, base]).norm(dim=-1).max()) > 0.01  # and it moves


# (3) a force wakes a sleeping object ------------------------------------------------------------

def test_force_wakes_a_sleeping_object_and_it_moves():
    model = toy_model(gain=0.5)
    graph = scene()
    forces = torch.zeros(20, N, 3)
    forces[10, 0] = torch.tensor([0.0, 0.0, 2.0])  # a push on cube leaf 0 at step 10 only
    with torch.no_grad():
        steps = unroll(model, graph, 20, forces, sleep=SleepConfig(patience=5, start_from_history=False))
    pos = torch.stack([s.pos for s in steps])
    cube, square = nodes_of(graph, CUBE), nodes_of(graph, SQUARE)
    assert all(asleep_of(steps[t], graph, CUBE) for t in range(4, 10))
    assert not asleep_of(steps[10], graph, CUBE)  # woken in the step of the force, and run in it
    assert float((pos[10, 0] - pos[9, 0]).norm()) > 1e-4
    assert not torch.equal(pos[-1, cube], pos[9, cube])
    # the square is not touched: asleep throughout, bit for bit
    assert all(asleep_of(steps[t], graph, SQUARE) for t in range(4, 20))
    assert torch.equal(pos[4:, square], pos[3, square].expand(16, -1, -1))


# (4) an awake object moving into a sleeping one wakes it ----------------------------------------

def test_moving_object_wakes_a_sleeping_one_on_contact():
    model = toy_model()
    graph = scene({SQUARE: (-0.04, 0.0, 0.0)})  # the square flies at the resting cube
    cube_leaf, square_leaf = nodes_of(graph, CUBE) & graph[NODE].is_leaf, nodes_of(graph, SQUARE)
    with torch.no_grad():
        steps = unroll(model, graph, 40, sleep=SleepConfig(patience=5, start_from_history=False))
    graphs = [graph] + [s.graph for s in steps]  # graphs[t]: the input of step t

    def contact(g) -> bool:
        src, dst = g[COLLISION].edge_index
        return bool((square_leaf[src] & cube_leaf[dst]).any())

    t_contact = next(t for t in range(40) if contact(graphs[t]))
    assert t_contact > 5
    assert all(asleep_of(steps[t], graph, CUBE) for t in range(4, t_contact))
    assert not asleep_of(steps[t_contact], graph, CUBE)
    assert all(not asleep_of(s, graph, SQUARE) for s in steps)  # it never stops
    assert all(torch.equal(g[COLLISION].edge_index, full_search_edges(g)) for g in graphs)


# (5) asleep objects do not enter the network ------------------------------------------------------

def test_asleep_objects_are_not_run_through_the_network():
    patience = 5
    model = toy_model()
    with torch.no_grad():
        unroll(model, scene({SQUARE: (0.03, 0.0, 0.0)}), 12, sleep=SleepConfig(patience=patience, start_from_history=False))
    # all 19 nodes until the cube (and only the cube) sleeps, then the square's 4 leaves + root
    assert model.seen_nodes == [N] * (patience - 1) + [5] * (12 - patience + 1)
    model.seen_nodes.clear()
    with torch.no_grad():
        steps = unroll(model, scene(), 12, sleep=SleepConfig(patience=patience, start_from_history=False))
    assert model.seen_nodes == [N] * (patience - 1)  # a scene at rest costs no network pass
    assert all(bool(s.asleep.all()) for s in steps[patience - 1:])


def test_a_lift_that_is_not_a_motion_is_carried_by_the_sleeping_step():
    """The square falls into the ground beside the resting (asleep) cube, with the ground lift
    not a motion (``ground_lift_velocity=False``): each sleeping step keeps the network's
    velocity in the next graph (x_{t+1} - x_t of the square's leaves is its constant fall) and
    gives the plain rollout's positions; the asleep cube holds bit for bit."""
    model = toy_model(ground_projection=True, ground_lift_velocity=False)
    graph = scene({SQUARE: (0.0, 0.0, -0.06)})
    square = nodes_of(graph, SQUARE) & graph[NODE].is_leaf
    with torch.no_grad():
        slept = unroll(model, graph, 6, sleep=SleepConfig(patience=2))
        plain = unroll(model, graph, 6, sleep=None)
    assert all(asleep_of(s, graph, CUBE) and not asleep_of(s, graph, SQUARE) for s in slept)
    last = slept[-1].graph[NODE]
    assert last.pos[square, 2].min() == 0.0 and graph[NODE].pos[square, 2].min() - 6 * 0.06 < 0.0  # lifted
    torch.testing.assert_close(last.pos[square] - last.prev_pos[square],
                               torch.tensor([0.0, 0.0, -0.06]).expand(int(square.sum()), 3))
    for a, b in zip(slept, plain, strict=True):
        torch.testing.assert_close(a.pos, b.pos)
        torch.testing.assert_close(a.graph[NODE].prev_pos, b.graph[NODE].prev_pos)
    cube = nodes_of(graph, CUBE)
    assert torch.equal(last.pos[cube], graph[NODE].pos[cube])


def test_a_start_at_rest_begins_asleep_by_default():
    """``start_from_history`` (the default): objects still over both steps of the start's
    history begin asleep, as the RL environment's do, so a scene at rest costs no network pass
    from the first step; a moving object starts awake and sleeps only after its patience."""
    model = toy_model()
    with torch.no_grad():
        steps = unroll(model, scene(), 8)
    assert model.seen_nodes == [] and all(bool(s.asleep.all()) for s in steps)
    model.seen_nodes.clear()
    graph = scene({SQUARE: (0.03, 0.0, 0.0)})
    with torch.no_grad():
        steps = unroll(model, graph, 8, sleep=SleepConfig(patience=5))
    assert model.seen_nodes == [5] * 8  # the sliding square (4 leaves + root) from the first step
    assert all(asleep_of(s, graph, CUBE) and not asleep_of(s, graph, SQUARE) for s in steps)
    assert torch.equal(steps[-1].pos[nodes_of(graph, CUBE)], graph[NODE].pos[nodes_of(graph, CUBE)])


def test_subgraph_keeps_awake_objects_and_their_collision_sources():
    model = fitted_model(rigid_fit=True, ground_contact=True)
    graph = toy_scene(force=False)  # the square touches the cube
    s = graph[NODE]
    asleep = nodes_of(graph, CUBE) | s.is_static  # the cube sleeps: only the square is awake
    prev_pos, prev_prev_pos = freeze(graph, asleep)  # the cube's velocities zero
    assert torch.equal(prev_pos[~asleep], s.prev_pos[~asleep]) and torch.equal(prev_pos[asleep], s.pos[asleep])
    sub, index, awake_rows = subgraph(graph, asleep, prev_pos, prev_prev_pos)
    src, dst = graph[COLLISION].edge_index
    sources = torch.unique(src[nodes_of(graph, SQUARE)[dst] & asleep[src]])
    assert sources.numel() > 0 and bool(s.is_leaf[sources].all())
    assert torch.equal(index, torch.cat([torch.nonzero(~asleep).flatten(), sources]))
    assert torch.equal(awake_rows, ~asleep[index])
    part = sub[NODE]
    assert torch.equal(part.is_static, asleep[index]) and torch.equal(part.object, s.object[index])
    assert bool(awake_rows[sub[COLLISION].edge_index[1]].all())  # only effects on awake leaves
    # the awake square sees what it sees in the whole graph with the cube held still
    frozen = set_state(graph, prev_prev_pos, prev_pos, s.pos, radius=0.08)
    with torch.no_grad():
        full = decode(model, frozen, run_network(model, build_inputs(model, frozen)))[0]
        part_pos = decode(model, sub, run_network(model, build_inputs(model, sub)))[0]
    torch.testing.assert_close(part_pos[awake_rows], full[index[awake_rows]], atol=1e-6, rtol=1e-5)


# (6) batched copies sleep independently --------------------------------------------------------

def test_batched_copies_sleep_independently_and_keep_their_batch_ids():
    model = toy_model(gain=0.5, dropout_modules=("force", "state"))
    graph = replicate(scene(), 3)
    n = graph[NODE].num_nodes
    forces = torch.zeros(12, n, 3)
    forces[8, N + 0] = torch.tensor([0.0, 0.0, 2.0])  # copy 1's cube, step 8
    seen_graphs = []

    def masks_fn(t, g):
        seen_graphs.append(g[NODE].num_nodes)
        return {name: torch.ones(3, model.config.hidden) for name in model.config.dropout_modules}

    with torch.no_grad():
        steps = unroll(model, graph, 12, forces, masks_fn, sleep=SleepConfig(patience=5, start_from_history=False))
    assert seen_graphs == [n] * 12  # masks_fn always sees the whole graph
    batch, root = graph[NODE].batch, graph[NODE].is_root
    asleep = torch.stack([s.asleep[root] for s in steps]).view(12, 3, 3)  # [step, copy, object]
    assert bool(asleep[4:8].all()) and not bool(asleep[8, 1, CUBE])
    assert bool(asleep[8:, 0].all()) and bool(asleep[8:, 2].all()) and bool(asleep[8:, 1, SQUARE].all())
    # no pass while all sleep (steps 4-7), then one for copy 1's cube (8 leaves, 2 groups, a
    # root), with its own batch id (a [3, H] mask table is looked up by it)
    assert model.seen_nodes == [n] * 4 + [11] * 4
    assert all(bool((b == 1).all()) for b in model.seen_batch[4:])
    # each copy moves as it does alone
    pos = torch.stack([s.pos for s in steps])
    single = toy_model(gain=0.5)
    with torch.no_grad():
        alone = rollout(single, scene(), 12, forces[:, N:2 * N], sleep=SleepConfig(patience=5, start_from_history=False))
    assert torch.equal(pos[:, batch == 1], alone)
    assert torch.equal(pos[:, batch == 0], pos[:, batch == 2])


# (7) configuration -----------------------------------------------------------------------------

@pytest.mark.parametrize("kw, match", [
    ({"threshold": 0.0}, "threshold must be a finite number > 0"),
    ({"threshold": -1e-3}, "threshold must be a finite number > 0"),
    ({"threshold": math.nan}, "threshold must be a finite number > 0"),
    ({"threshold": math.inf}, "threshold must be a finite number > 0"),
    ({"threshold": "0.002"}, "threshold must be a finite number > 0"),
    ({"patience": 0}, "patience must be an integer >= 1"),
    ({"patience": 2.5}, "patience must be an integer >= 1"),
    ({"patience": True}, "patience must be an integer >= 1"),
    ({"enabled": "yes"}, "enabled must be a bool"),
])
def test_bad_config_values_raise(kw, match):
    with pytest.raises(ValueError, match=f"SleepConfig.{match}"):
        SleepConfig(**kw)


def test_defaults_and_update_rule_on_objects():
    config = SleepConfig()
    assert config.enabled and config.threshold == 2e-3 and config.patience == 10
    graph = toy_scene(force=True)  # everything moves; leaf 0 of the cube is pushed
    objs = objects(graph)
    assert objs.count == 3 and objs.static.tolist() == [False, False, True]
    assert torch.equal(objs.of_node[graph[NODE].is_root], torch.arange(3))
    state = initial_state(objs)
    assert state.asleep.tolist() == [False, False, True]
    state = update(config, state, graph, graph[NODE].force, objs)
    assert state.asleep.tolist() == [False, False, True] and state.still.tolist() == [0, 0, 0]


def test_update_wakes_through_contacts_with_moving_objects_only():
    config = SleepConfig(patience=3)
    objs = objects(toy_scene())
    none = torch.zeros(N, 3)

    def state(asleep, still=(0, 0, 0)):
        return initial_state(objs)._replace(asleep=torch.tensor(asleep), still=torch.tensor(still))

    apart = scene()  # at rest; the square is 1 m away
    near = scene(separate=False)  # at rest, the square touching the cube
    assert near[COLLISION].edge_index.size(1) > 0 and apart[COLLISION].edge_index.size(1) == 0
    # an awake but still neighbour does not wake a sleeping object; its counter runs
    out = update(config, state([True, False, True], (0, 1, 0)), near, none, objs)
    assert out.asleep.tolist() == [True, False, True] and out.still.tolist() == [0, 2, 0]
    # ... and falls asleep beside it at `patience`
    out = update(config, state([True, False, True], (0, 2, 0)), near, none, objs)
    assert out.asleep.tolist() == [True, True, True]
    # a moving neighbour wakes it
    moving = scene({SQUARE: (0.01, 0.0, 0.0)}, separate=False)
    out = update(config, state([True, False, True], (0, 5, 0)), moving, none, objs)
    assert out.asleep.tolist() == [False, False, True] and out.still.tolist() == [0, 0, 0]
    # an awake, still object touched by a moving one counts again from zero: when the mover
    # leaves, it does not fall asleep at once wherever it was left (it may have to fall)
    out = update(config, state([False, False, True], (5, 0, 0)), moving, none, objs)
    assert out.asleep.tolist() == [False, False, True] and out.still.tolist() == [0, 0, 0]
    out = update(config, out, apart, none, objs)
    assert out.asleep.tolist() == [False, False, True] and out.still.tolist() == [1, 1, 0]
    # a push on a sleeping object wakes it and, through the contact, its sleeping neighbour
    push = none.clone()
    push[8] = torch.tensor([1.0, 0.0, 0.0])  # a leaf of the square
    out = update(config, state([True, True, True]), near, push, objs)
    assert out.asleep.tolist() == [False, False, True]
    out = update(config, state([True, True, True]), apart, push, objs)  # no contact: the cube sleeps on
    assert out.asleep.tolist() == [True, False, True]


@pytest.mark.parametrize("limit", [None, 0])  # the box test, and the fallback to grid cells
def test_near_awake_holds_every_leaf_within_reach_of_an_awake_one(limit, monkeypatch):
    from hrn_pyg.sim import sleeping

    if limit is not None:
        monkeypatch.setattr(sleeping, "BOX_TEST_LIMIT", limit)
    gen = torch.Generator().manual_seed(0)
    n, radius = 400, 0.08
    pos = torch.rand(n, 3, generator=gen)
    leaf = torch.rand(n, generator=gen) < 0.9
    obj = torch.randint(0, 12, (n,), generator=gen)
    batch = torch.randint(0, 2, (n,), generator=gen)
    awake = leaf & (obj < 2)
    near = sleeping.near_awake(pos, batch, leaf, awake, radius, obj)
    d = torch.cdist(pos, pos)
    reach = ((d < radius) & awake[None, :] & (batch[:, None] == batch[None, :])).any(dim=1) & leaf
    assert bool((near | ~reach).all())  # a superset of what can touch an awake leaf
    assert not bool((near & ~leaf).any())
    assert 0 < int(near.sum()) < int(leaf.sum())  # and not everything
