""":mod:`hrn_pyg.sim.rest_friction`: a supported object that has all but stopped is held; one in the
air, one still moving or one just braked is not; copies are judged apart; a rollout of a resting
scene stays put bit for bit."""

from __future__ import annotations

import pytest
import torch

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, build_structure, leaf_to_ancestor_mean, replicate, set_state
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.sim.rest_friction import hold_resting, resting_objects, supported_objects
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.rules import StepRules, step_rules
from hrn_pyg.sim.step import Prediction, object_of

PITCH = 0.05
#: two rigid bars of 2 leaves each: bar 0 lies on the ground, bar 1 floats 1 m up, far from it
LEAVES = torch.tensor([[0.0, 0.0, 0.025], [0.05, 0.0, 0.025], [0.0, 0.0, 1.0], [0.05, 0.0, 1.0]])


def scene(last_step: float = 0.0) -> torch.Tensor:
    parent = torch.tensor([4, 4, 5, 5, -1, -1])
    structure = build_structure(parent, torch.full((4,), 0.5), torch.tensor([0, 0, 1, 1]),
                                torch.tensor([0, 0]), torch.ones(2), pitch=PITCH)
    shift = torch.tensor([last_step, 0.0, 0.0])
    return set_state(structure, LEAVES - 2 * shift, LEAVES - shift, LEAVES, radius=0.08)


def moved(graph, step: float) -> Prediction:
    store = graph[NODE]
    pos = store.pos.clone()
    pos[store.is_leaf] += torch.tensor([step, 0.0, 0.0])
    pos = leaf_to_ancestor_mean(pos, graph)
    velocity = pos - store.pos
    return Prediction(pos, velocity.clone(), velocity)


def test_only_what_touches_the_ground_or_another_object_is_supported():
    graph = scene()
    assert supported_objects(graph, object_of(graph)).tolist() == [True, False]


@pytest.mark.parametrize(("last", "next_", "held"), [
    (1e-5, 1e-5, [True, False]),   # creeping on the ground: held; the same speed in the air: not
    (0.0, 0.004, [False, False]),  # starting to move (0.08 pitch): not held
    (0.004, 1e-5, [False, False]),  # braked hard this step: the last step was long, not held yet
])
def test_a_supported_object_that_has_all_but_stopped_is_held(last, next_, held):
    graph = scene(last)
    objects = object_of(graph)
    out = hold_resting(graph, moved(graph, next_), objects, 0.02)
    assert resting_objects(graph, moved(graph, next_).pos, objects, 0.02).tolist() == held
    store = graph[NODE]
    for o, h in enumerate(held):
        rows = objects[0] == o
        if h:
            assert torch.equal(out.pos[rows], store.pos[rows]) and not out.velocity[rows].any()
        else:
            assert torch.equal(out.pos[rows], moved(graph, next_).pos[rows])


def test_copies_are_judged_apart():
    one = scene(1e-5)
    graph = replicate(one, 2)
    prediction = moved(graph, 1e-5)
    n = one[NODE].num_nodes
    pos = prediction.pos.clone()
    pos[n] += torch.tensor([0.01, 0.0, 0.0])  # copy 1's grounded bar takes a long step
    held = resting_objects(graph, pos, object_of(graph), 0.02)
    group = object_of(graph)[0]
    assert bool(held[group[0]]) and not bool(held[group[n]])


def test_the_rule_is_off_by_default_and_refuses_a_bad_size():
    assert HRNConfig().rest_friction == 0.0
    with pytest.raises(ValueError, match=r"rest_friction must be in \[0, 1\) pitches, got 1.5"):
        HRNConfig(rest_friction=1.5)
    graph = scene()
    with pytest.raises(ValueError, match="rest_friction must be in"):
        StepRules(None, False, object_of(graph), rest_friction=-0.1)


def test_a_model_with_rest_friction_keeps_a_resting_scene_still():
    """The toy model on the ground bar at rest: without the rule the network moves it; with it the
    bar stays bit for bit where it was, 30 steps."""
    from toy_scene import toy_model

    graph = scene()
    model = toy_model(rigid_fit=True)
    free = rollout(model, graph, 30, sleep=None)
    rows = object_of(graph)[0] == 0
    assert (free[-1, rows] - graph[NODE].pos[rows]).abs().max() > 0
    friction = with_applied_options(model, rest_friction=0.5)
    assert step_rules(friction, graph).rest_friction == 0.5
    with torch.no_grad():
        held = rollout(friction, graph, 30, sleep=None)
    assert torch.equal(held[:, rows], graph[NODE].pos[rows].expand(30, -1, -1))


def test_the_fixed_shape_steps_hold_resting_objects_as_the_plain_rollout_does():
    """The fixed-shape path runs the rule after its network: a resting scene is held bit for bit
    as the plain rollout holds it."""
    from toy_scene import toy_model

    from hrn_pyg.sim.fixed_shape import fixed_shape_rollout

    model = with_applied_options(toy_model(), rest_friction=0.5)
    graph = scene(1e-5)
    with torch.no_grad():
        fixed = fixed_shape_rollout(model, graph, 10).pos
        assert torch.equal(fixed, rollout(model, graph, 10, sleep=None))
        assert not torch.equal(fixed, rollout(toy_model(), graph, 10, sleep=None))


def test_a_pushed_object_is_left_to_the_network():
    graph = scene(1e-5)
    objects = object_of(graph)
    force = torch.zeros(graph[NODE].num_nodes, 3)
    assert resting_objects(graph, moved(graph, 1e-5).pos, objects, 0.02, force).tolist() == [True, False]
    force[1] = torch.tensor([0.1, 0.0, 0.0])  # a gentle push on a leaf of the grounded bar
    assert resting_objects(graph, moved(graph, 1e-5).pos, objects, 0.02, force).tolist() == [False, False]


def test_a_push_out_by_the_clearance_is_not_taken_back():
    """Friction judges the step before the clearance: a resting body that the clearance then moves
    out of another (here a stand-in moving everything 0.5 mm, under the 1 mm limit) keeps the move."""
    graph = scene(1e-5)
    objects = object_of(graph)

    def push_out(graph, prediction, movable):
        return moved(graph, 5e-4)

    rules = StepRules(push_out, False, objects, rest_friction=0.02)
    out = rules(graph, moved(graph, 1e-5))
    assert torch.equal(out.pos, moved(graph, 5e-4).pos)
