"""``HRNConfig.energy_limit`` (:mod:`hrn_pyg.sim.energy`): a step that creates energy is scaled
back to the balance, only on the objects that gained; a step that loses energy, or gains no more
than its pushes' work, is left as it is; a rigid object stays rigid; copies of a batch are held
to their own balance; and a rollout with the rule never rises above its start."""

from __future__ import annotations

import torch
from toy_scene import DT, GRAVITY, toy_model, toy_scene
from torch_geometric.data import Batch

from hrn_pyg.checkpoints import with_applied_options
from hrn_pyg.data.graph import NODE, leaf_to_ancestor_mean
from hrn_pyg.sim.energy import energy_balance, limit_energy, scene_energy
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.step import Prediction, object_of

SOFT_LEAVES, RIGID_LEAVES = slice(0, 8), slice(8, 12)


def prediction_moving(graph, moves: torch.Tensor) -> Prediction:
    """A prediction whose leaves move by ``moves`` ``[N, 3]`` from the graph's ``pos``."""
    store = graph[NODE]
    pos = leaf_to_ancestor_mean(store.pos + torch.where(store.is_leaf.unsqueeze(-1), moves, 0.0), graph)
    velocity = pos - store.pos
    return Prediction(pos, velocity.clone(), velocity)


def total(graph, prediction, force=None) -> tuple[float, float, float]:
    balance = energy_balance(graph, prediction, force)
    return float(balance.now.sum()), float(balance.next.sum()), float(balance.work.sum())


def test_a_step_that_creates_energy_is_scaled_back_on_the_gainers_only():
    graph = toy_scene()
    n = graph[NODE].num_nodes
    moves = torch.zeros(n, 3)
    moves[SOFT_LEAVES] = torch.tensor([0.0, 0.0, 0.05])  # the soft cube jumps 5 cm up
    moves[RIGID_LEAVES] = torch.tensor([0.0, 0.0, -0.01])  # the rigid square falls on
    prediction = prediction_moving(graph, moves)
    before, after, _ = total(graph, prediction)
    assert after > before + 0.01  # the prediction creates energy
    limited = limit_energy(graph, prediction, object_of(graph))
    _, limited_energy, _ = total(graph, limited)
    assert limited_energy <= before + 1e-9
    assert torch.equal(limited.pos[RIGID_LEAVES], prediction.pos[RIGID_LEAVES])  # it lost energy: untouched
    step = limited.pos[SOFT_LEAVES] - graph[NODE].pos[SOFT_LEAVES]
    fraction = step[:, 2] / 0.05
    assert torch.allclose(fraction, fraction[0].expand(8), atol=1e-5) and 0 < float(fraction[0]) < 1
    assert torch.allclose(limited.velocity[SOFT_LEAVES], step)


def test_a_step_that_loses_energy_is_returned_as_it_is():
    graph = toy_scene()
    moves = torch.zeros(graph[NODE].num_nodes, 3)
    moves[:12] = torch.tensor([0.0, 0.0, -0.01])
    prediction = prediction_moving(graph, moves)
    assert limit_energy(graph, prediction, object_of(graph)) is prediction


def test_the_work_of_a_push_pays_for_a_gain():
    graph = toy_scene(separate=True)
    store = graph[NODE]
    n = store.num_nodes
    moves = (store.pos - store.prev_pos) + torch.tensor([0.0, 0.0, -GRAVITY * DT**2])  # both fall on
    moves[SOFT_LEAVES] += torch.tensor([0.06, 0.0, 0.0])  # and the soft cube is pushed sideways
    prediction = prediction_moving(graph, moves)
    before, after, _ = total(graph, prediction)
    gain = after - before
    assert gain > 0
    step = float(prediction.pos[0, 0] - store.pos[0, 0])
    force = torch.zeros(n, 3)
    force[SOFT_LEAVES, 0] = 1.5 * gain / (8 * step)  # the push does 1.5 times the gain in work
    assert limit_energy(graph, prediction, object_of(graph), force) is prediction
    force[SOFT_LEAVES, 0] = 0.5 * gain / (8 * step)  # half of it: scaled back to before + work
    limited = limit_energy(graph, prediction, object_of(graph), force)
    _, limited_energy, _ = total(graph, limited)
    work = float((force * (limited.pos - graph[NODE].pos)).sum())
    assert limited_energy <= before + work + 1e-9
    assert not torch.equal(limited.pos, prediction.pos)


def test_a_rigid_object_scaled_back_stays_rigid():
    graph = toy_scene(separate=True)
    store = graph[NODE]
    centre = store.pos[RIGID_LEAVES].mean(dim=0)
    angle = torch.tensor(0.4)
    turn = torch.tensor([[torch.cos(angle), -torch.sin(angle), 0.0], [torch.sin(angle), torch.cos(angle), 0.0],
                         [0.0, 0.0, 1.0]])
    moves = torch.zeros(store.num_nodes, 3)
    moves[RIGID_LEAVES] = (store.pos[RIGID_LEAVES] - centre) @ turn.T + centre + torch.tensor([0.0, 0.0, 0.08]) \
        - store.pos[RIGID_LEAVES]
    prediction = prediction_moving(graph, moves)
    limited = limit_energy(graph, prediction, object_of(graph))
    assert not torch.equal(limited.pos[RIGID_LEAVES], prediction.pos[RIGID_LEAVES])
    distances = torch.cdist(limited.pos[RIGID_LEAVES], limited.pos[RIGID_LEAVES])
    rest = torch.cdist(store.pos[RIGID_LEAVES], store.pos[RIGID_LEAVES])
    assert torch.allclose(distances, rest, atol=1e-5)


def test_each_copy_of_a_batch_keeps_its_own_balance():
    one = toy_scene()
    graph = Batch.from_data_list([one, one])
    n = one[NODE].num_nodes
    moves = torch.zeros(2 * n, 3)
    moves[SOFT_LEAVES] = torch.tensor([0.0, 0.0, 0.05])  # copy 0 creates energy
    moves[n:n + 8] = torch.tensor([0.0, 0.0, -0.01])  # copy 1 falls
    prediction = prediction_moving(graph, moves)
    limited = limit_energy(graph, prediction, object_of(graph))
    assert torch.equal(limited.pos[n:], prediction.pos[n:])
    assert not torch.equal(limited.pos[:n], prediction.pos[:n])
    alone = limit_energy(one, prediction_moving(one, moves[:n]), object_of(one))
    assert torch.allclose(limited.pos[:n], alone.pos, atol=1e-6)


def test_the_limit_is_differentiable_in_the_positions():
    graph = toy_scene()
    moves = torch.zeros(graph[NODE].num_nodes, 3)
    moves[SOFT_LEAVES] = torch.tensor([0.0, 0.0, 0.05])
    moves.requires_grad_(True)
    limited = limit_energy(graph, prediction_moving(graph, moves), object_of(graph))
    limited.pos.sum().backward()
    assert moves.grad is not None and bool(torch.isfinite(moves.grad).all()) and float(moves.grad.abs().sum()) > 0


def test_scene_energy_of_a_free_fall_does_not_rise():
    t = torch.arange(20, dtype=torch.float64)[:, None, None]
    fall = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64) - torch.tensor([0.0, 0.0, 0.5 * GRAVITY * DT**2]) * t**2
    energy = scene_energy(fall.expand(20, 3, 3), torch.ones(3))
    assert energy.shape == (19,)
    assert bool((energy[1:] <= energy[:-1] + 1e-12).all())


def test_a_rollout_with_the_limit_never_rises_above_its_start():
    """A toy model that pushes every root upward creates energy; with the limit the rollout does not."""
    model = toy_model()
    with torch.no_grad():
        model.normalizer.root_mean.copy_(torch.tensor([0.002, 0.0, 0.004]))  # a lift out of nothing
    graph = toy_scene(separate=True)
    leaves = graph[NODE].is_leaf
    mass = torch.where(graph[NODE].is_static, 0.0, graph[NODE].mass[:, 0])[leaves]
    start = torch.stack([graph[NODE].prev_pos, graph[NODE].pos])[:, leaves]
    with torch.no_grad():
        free = rollout(model, graph, 20, sleep=None)[:, leaves]
        held = rollout(with_applied_options(model, energy_limit=True), graph, 20, sleep=None)[:, leaves]
    e_free = scene_energy(torch.cat([start, free]), mass)
    e_held = scene_energy(torch.cat([start, held]), mass)
    assert float(e_free.max()) > float(e_free[0]) * 1.05  # the network alone gains
    assert float(e_held.max()) <= float(e_held[0]) * (1 + 1e-6)
