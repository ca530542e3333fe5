""":mod:`hrn_pyg.sim.rules`: the rules after the network are made once and applied by every path;
a copy whose prediction is not finite is held while the others go on, and ``sample`` returns the
finite futures with one warning line."""

from __future__ import annotations

import importlib

import pytest
import torch
from toy_scene import toy_model, toy_scene

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, replicate
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import iterate, rollout
from hrn_pyg.sim.rules import StepRules, step_rules
from hrn_pyg.sim.step import Prediction, object_of, predict

#: the module (``hrn_pyg.sampling.sample`` the name is its function, re-exported)
sample_module = importlib.import_module("hrn_pyg.sampling.sample")


def test_a_model_without_rules_gets_none_and_one_with_them_gets_each():
    graph = toy_scene()
    assert step_rules(toy_model(), graph) is None
    rules = step_rules(with_applied_options(toy_model(), energy_limit=True), graph)
    assert isinstance(rules, StepRules) and rules.energy and rules.cloth is None
    held = step_rules(toy_model(), graph, hold_failed=True)
    assert held is not None and held.hold_failed and not held.energy


def test_a_non_finite_copy_is_held_and_the_others_go_on():
    model = toy_model()
    one = toy_scene()
    graph = replicate(one, 3)
    n = one[NODE].num_nodes
    with torch.no_grad():
        prediction = predict(model, graph)
    broken = prediction.pos.clone()
    broken[n + 2] = float("nan")  # copy 1 blows up
    rules = step_rules(model, graph, hold_failed=True)
    held = rules(graph, Prediction(broken, prediction.local_velocity, prediction.velocity))
    assert torch.equal(held.pos[n:2 * n], graph[NODE].pos[n:2 * n])  # held where it was
    assert torch.equal(held.velocity[n:2 * n], torch.zeros(n, 3))
    assert torch.equal(held.pos[:n], prediction.pos[:n]) and torch.equal(held.pos[2 * n:], prediction.pos[2 * n:])
    assert rules.failed_copies(3).tolist() == [False, True, False]


def test_without_holding_a_blow_up_is_an_error_of_the_step():
    model = toy_model()
    graph = toy_scene()
    with torch.no_grad():
        model.normalizer.root_std.fill_(float("inf"))
        with pytest.raises(ValueError, match="NaN or infinite"):
            rollout(model, graph, 2, sleep=None)


@pytest.mark.parametrize("path", ["plain", "fixed shape", "fixed shape, contact rules after"])
def test_sample_returns_the_finite_futures_and_says_how_many_failed(monkeypatch, path):
    """Future 2 of 4 gets a NaN mask at step 3: it is NaN from step 4 on, the others are those
    of the same draw without the poisoned mask, and one RuntimeWarning says so; the same on
    the fixed-shape steps (their network holding the failed copy on the device), also with a
    rule that reads the contacts run after it."""
    from hrn_pyg.data.graph import set_pitch
    from hrn_pyg.sim.fixed_shape import FixedShapeConfig

    model = toy_model(dropout_modules=("collision",))
    graph = set_pitch(toy_scene(), 0.1)
    if path.endswith("after"):
        model = with_applied_options(model, solid_clearance=0.3)
    fixed = None if path == "plain" else FixedShapeConfig()
    original = sample_module.draw_masks
    calls = []

    def poisoned(model, k, rate, generator=None):
        masks = original(model, k, rate, generator)
        calls.append(len(calls))
        if len(calls) == 4:
            masks = {name: m.clone() for name, m in masks.items()}
            masks["collision"][2] = float("nan")
        return masks

    monkeypatch.setattr(sample_module, "draw_masks", poisoned)
    with pytest.warns(RuntimeWarning, match=r"1 of 4 sampled futures failed \(not finite from step 4\)"):
        futures = sample(model, graph, k=4, steps=6, rate=0.3, generator=torch.Generator().manual_seed(1), sleep=None,
                         fixed_shape=fixed)
    monkeypatch.setattr(sample_module, "draw_masks", original)
    clean = sample(model, graph, k=4, steps=6, rate=0.3, generator=torch.Generator().manual_seed(1), sleep=None)
    assert bool(torch.isnan(futures[2, 3:]).all()) and bool(torch.isfinite(futures[2, :3]).all())
    keep = [0, 1, 3]
    assert torch.allclose(futures[keep], clean[keep], atol=1e-6)


def test_every_step_of_a_rollout_reports_the_failed_copies_when_holding():
    model = toy_model()
    graph = replicate(toy_scene(), 2)
    with torch.no_grad():
        steps = list(iterate(model, graph, 3, sleep=None, hold_failed=True))
    assert all(s.failed is not None and not bool(s.failed.any()) for s in steps)
    with torch.no_grad():
        plain = list(iterate(model, graph, 3, sleep=None))
    assert all(s.failed is None for s in plain)
    assert all(torch.equal(a.pos, b.pos) for a, b in zip(steps, plain))


def test_the_objects_the_rules_hold_are_the_graphs():
    graph = replicate(toy_scene(), 2)
    rules = step_rules(toy_model(), graph, hold_failed=True)
    group, count = object_of(graph)
    assert torch.equal(rules.objects[0], group) and rules.objects[1] == count == 6
