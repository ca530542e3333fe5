"""``HRNConfig.corotated_rest``: the rest shape of a soft body is turned onto its current leaves,
rigid and static rows keep the recorded rest shape, the network then reads a turned body as
undeformed, a rollout's cached constants hold only where nothing turns, and the option needs
rest offsets."""

import math

import pytest
import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, RIGID, SOFT, leaf_to_ancestor_mean
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim.rollout import iterate
from hrn_pyg.sim.step import corotated_rest_positions, hierarchy_constants, step

SOFT_LEAVES = slice(0, 8)  # the toy scene's soft cube


def _model(**kw) -> HRN:
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=16, depth=2, effect_dim=8, rigid_fit=True, rest_offsets=True, **kw))
    fit_normalizer([toy_window(4, seed=s) for s in range(3)], model.normalizer)
    return model.eval()


def _turn() -> torch.Tensor:
    """A rotation by 50 degrees about z after 30 degrees about x."""
    a, b = math.radians(50.0), math.radians(30.0)
    rz = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(b), -math.sin(b)], [0.0, math.sin(b), math.cos(b)]])
    return rz @ rx


def _with_rest(graph, soft_rest: torch.Tensor):
    """``graph`` with a recorded rest shape: the soft cube's leaves at ``soft_rest`` ``[8, 3]``, the
    other leaves where they are now (ancestors derived)."""
    rest = graph[NODE].pos.clone()
    rest[SOFT_LEAVES] = soft_rest
    graph[NODE].rest_pos = leaf_to_ancestor_mean(rest, graph)
    return graph


def _turned_away(graph) -> torch.Tensor:
    """The soft cube's current leaves turned back by :func:`_turn` and moved 0.2 m aside: a rest
    shape that differs from the current one by a rigid motion only."""
    soft = graph[NODE].pos[SOFT_LEAVES]
    centre = soft.mean(dim=0)
    return (soft - centre) @ _turn() + centre + torch.tensor([0.2, -0.1, 0.05])


def test_a_turned_soft_rest_shape_is_turned_onto_the_current_leaves():
    graph = toy_scene()
    graph = _with_rest(graph, _turned_away(graph))
    store = graph[NODE]
    turned = corotated_rest_positions(graph, store.rest_pos, store.pos)
    # the toy cube's leaves weigh the same: the fit maps the rest cube exactly onto the current one
    assert torch.allclose(turned[SOFT_LEAVES], store.pos[SOFT_LEAVES], atol=1e-5)
    others = torch.ones(store.num_nodes, dtype=torch.bool)
    others[SOFT_LEAVES] = False
    others &= store.is_leaf
    assert torch.equal(turned[others], store.rest_pos[others])  # rigid and static leaves: as recorded
    assert torch.equal(turned, leaf_to_ancestor_mean(turned, graph))  # ancestors derived from the leaves
    assert not torch.allclose(store.rest_pos[SOFT_LEAVES], store.pos[SOFT_LEAVES], atol=1e-2)


def test_the_network_reads_a_turned_rest_shape_as_the_current_one():
    """With the option, a soft body whose rest shape is its current shape turned and moved steps
    as if its rest shape were its current shape; without it, the two differ."""
    base = toy_scene()
    turned = _with_rest(toy_scene(), _turned_away(base))
    same = _with_rest(toy_scene(), base[NODE].pos[SOFT_LEAVES].clone())
    plain = _model()
    corotated = with_applied_options(plain, corotated_rest=True)
    assert corotated.config.corotated_rest and not plain.config.corotated_rest
    with torch.no_grad():
        assert torch.allclose(step(corotated, turned).pos, step(corotated, same).pos, atol=1e-6)
        assert torch.equal(step(corotated, same).pos, step(plain, same).pos)  # nothing to turn: unchanged
        assert not torch.allclose(step(plain, turned).pos, step(plain, same).pos, atol=1e-6)


def test_the_rest_offsets_are_cached_only_when_nothing_turns():
    """A scene with a moving soft body gets no cached rest offsets (they change every step), so a
    rollout equals stepping by hand; a scene of rigid and static bodies keeps them cached."""
    model = with_applied_options(_model(), corotated_rest=True)
    graph = toy_scene()
    graph = _with_rest(graph, _turned_away(graph))
    assert hierarchy_constants(model, graph).rest_offset is None
    rigid = toy_scene()
    material = rigid[NODE].material.clone()
    material[:, RIGID] += material[:, SOFT]  # the soft cube becomes rigid
    material[:, SOFT] = 0.0
    rigid[NODE].material = material
    rigid = _with_rest(rigid, _turned_away(rigid))
    assert hierarchy_constants(model, rigid).rest_offset is not None

    with torch.no_grad():
        rolled = [s.pos for s in iterate(model, graph, 3, None, None, sleep=None)]
        by_hand, state = [], graph
        for _ in range(3):
            result = step(model, state)
            by_hand.append(result.pos)
            state = result.graph
    for a, b in zip(rolled, by_hand):
        assert torch.allclose(a, b, atol=1e-6)


def test_a_rigid_only_graph_runs_no_fit_and_steps_as_without_the_option(monkeypatch):
    """A graph without moving soft or cloth leaves (a rigid scene, or the sub-graph of a sleeping
    step) turns nothing: the step runs no fit and equals the step without the option."""
    from hrn_pyg.sim import step as step_module

    rigid = toy_scene()
    material = rigid[NODE].material.clone()
    material[:, RIGID] += material[:, SOFT]
    material[:, SOFT] = 0.0
    rigid[NODE].material = material
    rigid = _with_rest(rigid, _turned_away(rigid))
    plain = _model()
    corotated = with_applied_options(plain, corotated_rest=True)

    def no_fit(*args, **kwargs):
        raise AssertionError("a rigid-only graph ran the co-rotation fit")

    monkeypatch.setattr(step_module, "corotated_rest_positions", no_fit)
    with torch.no_grad():
        assert torch.equal(step(corotated, rigid).pos, step(plain, rigid).pos)


def test_corotated_rest_needs_rest_offsets():
    with pytest.raises(ValueError, match="corotated_rest"):
        HRNConfig(corotated_rest=True)
    HRNConfig(corotated_rest=True, rest_offsets=True)  # fine
