"""What a scene needs simulated (hrn_pyg/effects.py): the plan, and that skipping is exact."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from stability.stability_helpers import fitted_model
from torch_geometric.data import HeteroData
from toy_scene import toy_scene

from hrn_pyg.data.effects import SceneEffects, can_collide, plan_effects
from hrn_pyg.data.graph import COLLISION, NODE, build_structure, replicate, set_state
from hrn_pyg.data.scene_file import SCENES, scene_effects
from hrn_pyg.nn.hrn import HRN, StepOptions
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.sim.step import build_inputs, run_network, step

N = 19  # nodes of the toy scene
STEPS = 6


def lone_body() -> HeteroData:
    """One soft body of 4 leaves under one root, at rest above the ground."""
    x = torch.tensor([[0.0, 0.0, 0.3], [0.05, 0.0, 0.3], [0.0, 0.05, 0.3], [0.0, 0.0, 0.35]])
    g = build_structure(torch.tensor([4, 4, 4, 4, -1]), torch.full((4,), 0.1), torch.zeros(4, dtype=torch.long),
                        torch.tensor([1]), torch.tensor([0.5]))
    return set_state(g, x, x, x, radius=0.08)


def pushes(at: tuple[int, ...]) -> torch.Tensor:
    forces = torch.zeros(STEPS, N, 3)
    for t in at:
        forces[t, 0] = torch.tensor([1.0, 0.0, 0.0])
    return forces


def test_plan_reads_the_force_of_every_step_once():
    g = toy_scene()
    assert plan_effects(g, STEPS, None).force_active == (False,) * STEPS
    plan = plan_effects(g, STEPS, pushes((1, 4)))
    assert plan.force_active == (False, True, False, False, True, False)
    assert plan.collisions  # three objects, two of them movable


def test_a_declaration_the_data_contradict_is_an_error():
    with pytest.raises(ValueError, match="declares no external forces.*step 4"):
        plan_effects(toy_scene(), STEPS, pushes((4,)), SceneEffects(forces=False))
    with pytest.raises(ValueError, match="SceneEffects.collisions must be True, False or None"):
        SceneEffects(collisions="yes")


def test_who_can_collide():
    assert can_collide(toy_scene())
    assert not can_collide(lone_body())
    assert not can_collide(replicate(lone_body(), 3))  # copies never collide with each other
    static_pair = build_structure(torch.tensor([4, 4, 5, 5, -1, -1]), torch.ones(4), torch.tensor([0, 0, 1, 1]),
                                  torch.tensor([3, 3]), torch.tensor([1.0, 1.0]))
    assert not can_collide(static_pair)  # neither can move
    assert plan_effects(toy_scene(), 2, None, SceneEffects(collisions=False)).collisions is False


@pytest.mark.parametrize("rigid_fit", [False, True])
def test_planned_rollout_equals_the_step_that_checks_for_itself(rigid_fit):
    """The fast path (plan made once) and the slow one (the network asks each step) agree bit
    for bit, with forces on some steps only."""
    model = fitted_model(rigid_fit=rigid_fit)
    g, forces = toy_scene(), pushes((1, 2))
    with torch.no_grad():
        fast = rollout(model, g, STEPS, forces, sleep=None)
        slow = []  # the same first graph as unroll's, then steps that decide nothing in advance
        graph = set_state(g, g[NODE].prev_prev_pos, g[NODE].prev_pos, g[NODE].pos, radius=model.config.collision_radius)
        for t in range(STEPS):
            result = step(model, graph, forces[t])
            slow.append(result.pos)
            graph = result.graph
    assert torch.equal(fast, torch.stack(slow))


def test_a_skipped_module_changes_nothing():
    """Not running the force module on a zero force, or the collision module on no edge, gives
    what running them gives (so a plan can skip them)."""
    model = fitted_model()
    eager = HRN(replace(model.config, skip_idle_modules=False))  # runs every module, always
    eager.load_state_dict(model.state_dict())
    g = toy_scene(separate=True)  # no collision edge
    assert g[COLLISION].edge_index.size(1) == 0
    with torch.no_grad():
        runs = run_network(model, build_inputs(model, g, torch.zeros(N, 3), StepOptions(force_active=True)))
        skips = run_network(model, build_inputs(model, g, torch.zeros(N, 3), StepOptions(force_active=False)))
        everything = run_network(eager.eval(), build_inputs(eager, g, torch.zeros(N, 3)))
    torch.testing.assert_close(runs, skips, rtol=0, atol=1e-6)
    torch.testing.assert_close(everything, skips, rtol=0, atol=1e-6)


def test_the_plan_is_obeyed_not_second_guessed():
    """``StepOptions(force_active=False)`` means the network does not look at the force (no host read)."""
    model = fitted_model()
    g = toy_scene()
    push = pushes((0,))[0]
    with torch.no_grad():
        told_off = run_network(model, build_inputs(model, g, push, StepOptions(force_active=False)))
        no_force = run_network(model, build_inputs(model, g, torch.zeros(N, 3)))
        checked = run_network(model, build_inputs(model, g, push))
    assert torch.equal(told_off, no_force)
    assert not torch.allclose(checked, no_force)


def test_a_scene_without_collisions_gets_no_search():
    model = fitted_model()
    g = replicate(lone_body(), 2)
    with torch.no_grad():
        steps = unroll(model, g, 3, sleep=None)
        declared = unroll(model, g, 3, sleep=None, effects=SceneEffects(collisions=True))
    assert all(s.graph[COLLISION].edge_index.size(1) == 0 for s in steps)
    assert all(torch.equal(a.pos, b.pos) for a, b in zip(steps, declared))


def test_every_scene_declares_its_effects():
    assert set(SCENES) >= {"soft_bounce", "cube_collision", "wedge", "multi_material", "cube_push", "tower"}
    for name in SCENES:
        assert isinstance(scene_effects(name), SceneEffects)
    assert scene_effects("soft_bounce") == SceneEffects(forces=True, collisions=False)
    assert scene_effects("wedge").forces is False and scene_effects("multi_material").forces is False
    with pytest.raises(ValueError, match="nope"):
        scene_effects("nope")
