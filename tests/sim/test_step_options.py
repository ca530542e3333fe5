"""The step's options (hrn_pyg.nn.hrn.StepOptions) travel as one object down to the network pass.

A recording ``HRN._pass`` sees the options every pass was given. The first test sets every
field to a value other than its default, so a field added to :class:`StepOptions` fails it
until the test gives that field a value too, and then checks that the new field travels.
"""

from __future__ import annotations

import dataclasses
import warnings

import pytest
import torch
from stability.stability_helpers import fitted_model
from toy_scene import toy_scene

from hrn_pyg.data.effects import plan_effects
from hrn_pyg.data.graph import COLLISION, NODE
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.sim import step as step_module
from hrn_pyg.sim.fixed_shape import fixed_shape_rollout
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.sleeping import objects as sleeping_objects
from hrn_pyg.sim.sleeping import predict_held
from hrn_pyg.sim.step import build_inputs, hierarchy_constants, object_of, predict, step

STEPS = 6
N = 19
CUBE = 0


@pytest.fixture
def passes(monkeypatch):
    """``[(options, inputs)]`` of every network pass, in order."""
    seen = []
    original = HRN._pass

    def recording(self, inputs, masks):
        seen.append((inputs.options, inputs))
        return original(self, inputs, masks)

    monkeypatch.setattr(HRN, "_pass", recording)
    return seen


def unchanged_prediction(graph, prediction, force, movable):
    """Rules that move nothing."""
    return prediction


def every_option_set(graph) -> StepOptions:
    """Options of ``graph`` with every field away from its default (none changes the physics
    of this step except ``collisions``, which only drops the next graph's collision edges)."""
    options = StepOptions(
        force_active=True,
        check=False,
        objects=object_of(graph),
        collision_weight=torch.ones(graph[COLLISION].edge_index.size(1)),
        fixed_shape=True,
        collisions=False,
        hierarchy=hierarchy_constants(fitted_model(), graph),
        rules=unchanged_prediction,
    )
    default = StepOptions()
    unset = [f.name for f in dataclasses.fields(StepOptions) if getattr(options, f.name) is getattr(default, f.name)]
    assert not unset, f"give these StepOptions fields a value other than the default here: {unset}"
    return options


def test_the_rules_move_the_step_before_the_graph_advances():
    """``rules`` get the graph at t, the prediction and the step's force (no ``movable`` in a
    plain step); what they return is the step's result and the next graph's state."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    calls = []
    lift = torch.tensor([0.0, 0.0, 0.01])

    def lifted(g, prediction, force, movable):
        calls.append((g, movable))
        assert force.shape == g[NODE].pos.shape
        return prediction._replace(pos=prediction.pos + lift, velocity=prediction.velocity + lift)

    with torch.no_grad():
        plain = step(model, graph)
        moved = step(model, graph, options=StepOptions(rules=lifted))
    assert len(calls) == 1 and calls[0][0] is graph and calls[0][1] is None
    assert torch.allclose(moved.pos, plain.pos + lift) and torch.equal(moved.graph[NODE].pos, moved.pos)
    assert torch.allclose(moved.velocity, plain.velocity + lift)


@pytest.mark.parametrize("config", [dict(rigid_fit=True), dict(mirror_average=True, mirror_planes="xy")])
def test_every_option_reaches_the_network_pass(passes, config):
    """``step`` -> ``predict`` -> ``build_inputs`` -> ``HRNInputs`` -> every pass of the mirror
    average: the very object the caller made."""
    model = fitted_model(**config)
    graph = toy_scene(force=True)
    options = every_option_set(graph)
    with torch.no_grad():
        step(model, graph, None, None, options)
    assert len(passes) == len(model.config.mirror_group)
    assert all(seen is options for seen, _ in passes)
    assert passes[0][1].hierarchy is options.hierarchy


def test_the_options_read_outside_the_pass_are_read(monkeypatch):
    """``check`` in build_inputs, ``objects`` in decode, ``collisions`` in the next graph."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    options = every_option_set(graph)
    nan_force = torch.full((N, 3), float("nan"))
    with torch.no_grad():
        with pytest.raises(ValueError, match="force"):
            predict(model, graph, nan_force)
        assert not bool(torch.isfinite(predict(model, graph, nan_force, None, options).pos).all())
        given = []
        decode = step_module.decode
        monkeypatch.setattr(step_module, "decode", lambda m, g, out, objects=None: given.append(objects)
                            or decode(m, g, out, objects))
        result = step(model, graph, None, None, options)
        assert given == [options.objects] and given[0] is options.objects
        assert result.graph[COLLISION].edge_index.size(1) == 0
        assert step(model, graph).graph[COLLISION].edge_index.size(1) > 0


def test_a_held_step_runs_the_sub_graph_with_the_same_options(passes):
    """The sleeping step's sub-graph gets the caller's options less the whole graph's objects;
    a collision weight of the whole graph's edges cannot come with held rows."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene(force=True)
    store = graph[NODE]
    held = (store.object == CUBE) | store.is_static
    options = dataclasses.replace(every_option_set(graph), collision_weight=None)
    with torch.no_grad():
        predict_held(model, graph, store.force, None, held, options)
        with pytest.raises(ValueError, match="collision_weight"):
            predict_held(model, graph, store.force, None, held, every_option_set(graph))
    (seen, inputs), = passes
    assert inputs.state.size(0) < N  # the sub-graph
    assert seen == dataclasses.replace(options, objects=None, hierarchy=None)


@pytest.mark.parametrize("sleep", [None, "default"])
def test_a_rollout_tells_each_step_its_plan(passes, sleep):
    """``rollout``: every pass is told the plan's force flag of its step and whether collisions
    are searched, that the inputs are checked, and the scene's objects (the sleeping sub-graph
    finds its own)."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    forces = torch.zeros(STEPS, N, 3)
    forces[2, 0] = torch.tensor([0.5, 0.0, 2.0])
    kwargs = {} if sleep == "default" else {"sleep": None}
    with torch.no_grad():
        rollout(model, graph, STEPS, forces, **kwargs)
    plan = plan_effects(graph, STEPS, forces)
    assert len(passes) == STEPS  # toy objects fall: none sleeps, one pass a step
    assert [seen.force_active for seen, _ in passes] == list(plan.force_active)
    whole = object_of(graph) if sleep is None else (lambda o: (o.of_node, o.count))(sleeping_objects(graph))
    for seen, inputs in passes:
        assert seen.check is False and seen.collisions is plan.collisions is True
        assert seen.fixed_shape is False and seen.collision_weight is None
        if inputs.state.size(0) == N:
            assert torch.equal(seen.objects[0], whole[0]) and seen.objects[1] == whole[1]
        else:
            assert seen.objects is None


def test_a_fixed_shape_rollout_tells_each_step_its_candidates(passes):
    """Fixed-shape steps: no check, dense force module, one weight per candidate edge, the
    plan's force flag (never None: no host read) and the scene's objects."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    forces = torch.zeros(STEPS, N, 3)
    forces[2, 0] = torch.tensor([0.5, 0.0, 2.0])
    fixed_shape_rollout(model, graph, STEPS, forces)
    assert len(passes) >= STEPS
    assert {seen.force_active for seen, _ in passes} == {False, True}
    whole = object_of(graph)
    for seen, inputs in passes:
        assert seen.check is False and seen.fixed_shape is True
        assert seen.collision_weight.shape == (inputs.collision.size(1),)
        assert torch.equal(seen.objects[0], whole[0]) and seen.objects[1] == whole[1]


def test_the_old_keywords_still_work_with_a_warning():
    """``step(..., force_active=...)`` and the other options one keyword each: the same step as
    ``options=StepOptions(...)``, with a DeprecationWarning; a keyword that is no option and
    options that are not a StepOptions are TypeErrors."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene(force=True)
    objects = object_of(graph)
    with torch.no_grad():
        with pytest.warns(DeprecationWarning, match="force_active="):
            old = step(model, graph, force_active=True, objects=objects, check=False)
        new = step(model, graph, None, None, StepOptions(force_active=True, objects=objects, check=False))
        assert torch.equal(old.pos, new.pos)
        with pytest.warns(DeprecationWarning, match="fixed_shape="):
            inputs = build_inputs(model, graph, None, fixed_shape=True)
        assert inputs.options == StepOptions(fixed_shape=True)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            predict(model, graph, None, None, StepOptions(check=False))  # no warning without old keywords
        with pytest.raises(TypeError, match="speed"):
            predict(model, graph, speed=2)
        with pytest.raises(TypeError, match="StepOptions"):
            build_inputs(model, graph, None, True)  # the old positional force_active
