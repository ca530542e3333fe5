"""A rollout without sleeping finds its hierarchy's constants once (hrn_pyg.sim.step.hierarchy_constants)
and its collision edges from a Verlet list: the same positions, bit for bit, as steps that
recompute everything."""

import pytest
import torch
from stability.stability_helpers import fitted_model
from toy_scene import toy_scene

from hrn_pyg.data.graph import NODE, set_pitch, set_state
from hrn_pyg.nn.hrn import StepOptions
from hrn_pyg.nn.pitch import collision_radius_of
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.step import build_inputs, hierarchy_constants, step

STEPS = 6
CONFIGS = [
    dict(rigid_fit=True, rest_offsets=True, ground_contact=True),
    dict(rigid_fit=True, rest_offsets=True, ground_contact=True, mirror_average=True, mirror_planes="d4"),
    dict(rest_offsets=True, ground_contact=True, pitch_aware=True, reference_pitch=0.05),
]


def _stepped(model, graph, steps):
    """Positions of ``steps`` plain steps, each recomputing everything."""
    graph = set_state(graph, graph[NODE].prev_prev_pos, graph[NODE].prev_pos, graph[NODE].pos,
                      radius=collision_radius_of(model.config, graph))
    out = []
    for _ in range(steps):
        result = step(model, graph, torch.zeros_like(graph[NODE].pos))
        out.append(result.pos)
        graph = result.graph
    return torch.stack(out)


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("rest_shape", [True, False])
def test_a_rollout_with_constants_equals_steps_without(config, rest_shape):
    model = fitted_model(**config)
    graph = set_pitch(toy_scene(), 0.04)
    if rest_shape:
        graph[NODE].rest_pos = 1.02 * graph[NODE].pos  # a rest shape other than the start's
    # without one, the current shape is read as the rest shape: only the degrees are constant
    with torch.no_grad():
        constants = hierarchy_constants(model, graph)
        assert (constants.rest_offset is not None) is rest_shape
        assert torch.equal(rollout(model, graph, STEPS, sleep=None), _stepped(model, graph, STEPS))


def test_constants_of_another_graph_are_refused():
    model = fitted_model(rest_offsets=True)
    constants = hierarchy_constants(model, toy_scene())
    short = constants._replace(degree=tuple(d[:-1] for d in constants.degree))
    with pytest.raises(ValueError, match="another graph"):
        build_inputs(model, toy_scene(), options=StepOptions(hierarchy=short))
