"""Each module of hrn_pyg.nn.equivariant: scalar effects invariant and vector effects turned
under turns about z and vertical mirrors; exact zeros where nothing acts; one-line errors."""

import math

import pytest
import torch

from hrn_pyg.nn.equivariant import CollisionModule, ForceModule, HistoryModule, NextStateModule, PropagationModule
from hrn_pyg.nn.mlp import MLPConfig

N, S, D, C = 7, 5, 6, 3
MLP_SHAPE = MLPConfig(hidden=12, depth=2)
EDGES = torch.tensor([[0, 1, 2, 3, 4, 5, 0, 6], [1, 0, 1, 1, 3, 3, 5, 5]])  # node 2, 4 and 6 receive nothing


def _turn(angle: float, mirror: bool) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s], [s, c]]) @ torch.diag(torch.tensor([1.0, -1.0 if mirror else 1.0]))


def _lift(g2: torch.Tensor) -> torch.Tensor:
    g = torch.eye(3)
    g[:2, :2] = g2
    return g


def _inputs(seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=gen)  # noqa: E731
    return dict(state=r(N, S), velocity=r(N, 2), pos=r(N, 3), effect=r(N, D), vectors=r(N, C, 2),
                rest_pos=r(N, 3), force=r(N, 3))


def _randomised(module: torch.nn.Module) -> torch.nn.Module:
    torch.manual_seed(1)
    for p in module.parameters():
        torch.nn.init.normal_(p, std=0.4)
    return module.eval()


MAPS = [(0.7, False), (math.pi / 2, True), (2.5, True)]


@pytest.mark.parametrize("angle,mirror", MAPS)
def test_propagation_is_equivariant(angle, mirror):
    g2 = _turn(angle, mirror)
    g = _lift(g2)
    module = _randomised(PropagationModule(S, D, C, MLP_SHAPE, rest_offsets=True))
    x = _inputs()
    e, v = module(x["state"], x["velocity"], x["effect"], x["vectors"], x["pos"], EDGES, rest_pos=x["rest_pos"])
    e_g, v_g = module(x["state"], x["velocity"] @ g2.T, x["effect"], x["vectors"] @ g2.T, x["pos"] @ g.T, EDGES,
                      rest_pos=x["rest_pos"] @ g.T)
    torch.testing.assert_close(e_g, e, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_g, v @ g2.T, atol=1e-5, rtol=1e-5)
    assert v.abs().max() > 1e-2
    for silent in (2, 4, 6):  # no edge in: an exact zero
        assert torch.equal(e[silent], torch.zeros(D)) and torch.equal(v[silent], torch.zeros(C, 2))


@pytest.mark.parametrize("angle,mirror", MAPS)
def test_collision_is_equivariant_and_a_zero_weight_edge_is_no_edge(angle, mirror):
    g2 = _turn(angle, mirror)
    g = _lift(g2)
    module = _randomised(CollisionModule(S, D, C, MLP_SHAPE))
    x = _inputs(1)
    e, v = module(x["state"], x["velocity"], x["pos"], EDGES)
    e_g, v_g = module(x["state"], x["velocity"] @ g2.T, x["pos"] @ g.T, EDGES)
    torch.testing.assert_close(e_g, e, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_g, v @ g2.T, atol=1e-5, rtol=1e-5)
    weight = torch.tensor([1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0])
    e_w, v_w = module(x["state"], x["velocity"], x["pos"], EDGES, edge_weight=weight)
    kept = EDGES[:, weight.bool()]
    e_k, v_k = module(x["state"], x["velocity"], x["pos"], kept)
    torch.testing.assert_close(e_w, e_k, atol=1e-6, rtol=0)
    torch.testing.assert_close(v_w, v_k, atol=1e-6, rtol=0)


@pytest.mark.parametrize("angle,mirror", MAPS)
def test_collision_reading_the_force_is_equivariant_and_feels_a_push_on_the_other_end(angle, mirror):
    g2 = _turn(angle, mirror)
    g = _lift(g2)
    module = _randomised(CollisionModule(S, D, C, MLP_SHAPE, reads_force=True))
    x = _inputs(2)
    e, v = module(x["state"], x["velocity"], x["pos"], EDGES, force=x["force"])
    e_g, v_g = module(x["state"], x["velocity"] @ g2.T, x["pos"] @ g.T, EDGES, force=x["force"] @ g.T)
    torch.testing.assert_close(e_g, e, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_g, v @ g2.T, atol=1e-5, rtol=1e-5)
    pushed = x["force"].clone()
    pushed[6] += torch.tensor([1.5, -0.5, 0.0])  # node 6 sends to node 5 only (edge 6 -> 5)
    e_p, v_p = module(x["state"], x["velocity"], x["pos"], EDGES, force=pushed)
    moved = (e_p - e).abs().amax(dim=-1) + (v_p - v).abs().flatten(1).amax(dim=-1)
    assert moved[5] > 1e-4 and torch.equal(moved[[0, 1, 2, 3, 4, 6]], torch.zeros(6))
    with pytest.raises(ValueError, match="reads_force needs force"):
        module(x["state"], x["velocity"], x["pos"], EDGES)


@pytest.mark.parametrize("angle,mirror", MAPS)
def test_force_history_and_state_are_equivariant(angle, mirror):
    g2 = _turn(angle, mirror)
    g = _lift(g2)
    x = _inputs(2)
    force = _randomised(ForceModule(S, D, C, MLP_SHAPE))
    e, v = force(x["state"], x["velocity"], x["force"])
    e_g, v_g = force(x["state"], x["velocity"] @ g2.T, x["force"] @ g.T)
    torch.testing.assert_close(e_g, e, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_g, v @ g2.T, atol=1e-5, rtol=1e-5)
    history = _randomised(HistoryModule(S, D, C, MLP_SHAPE))
    prev = torch.randn(N, 2)
    e, v = history(x["state"], x["state"].flip(0), x["velocity"], prev)
    e_g, v_g = history(x["state"], x["state"].flip(0), x["velocity"] @ g2.T, prev @ g2.T)
    torch.testing.assert_close(e_g, e, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(v_g, v @ g2.T, atol=1e-5, rtol=1e-5)
    state = _randomised(NextStateModule(S, D, C, MLP_SHAPE))
    static = torch.tensor([False] * (N - 1) + [True])
    out = state(x["state"], x["velocity"], x["effect"], x["vectors"], static)
    out_g = state(x["state"], x["velocity"] @ g2.T, x["effect"], x["vectors"] @ g2.T, static)
    torch.testing.assert_close(out_g, out @ g.T, atol=1e-5, rtol=1e-5)
    assert torch.equal(out[-1], torch.zeros(3)) and out[:-1, :2].abs().max() > 1e-2


def test_force_rows_without_a_push_are_exact_zeros_and_dense_equals_sparse():
    module = _randomised(ForceModule(S, D, C, MLP_SHAPE))
    x = _inputs(3)
    force = x["force"].clone()
    force[[1, 4, 5]] = 0.0
    e, v = module(x["state"], x["velocity"], force)
    e_dense, v_dense = module(x["state"], x["velocity"], force, dense=True)
    assert torch.equal(e[[1, 4, 5]], torch.zeros(3, D)) and torch.equal(v[[1, 4, 5]], torch.zeros(3, C, 2))
    torch.testing.assert_close(e_dense, e, atol=1e-6, rtol=0)
    torch.testing.assert_close(v_dense, v, atol=1e-6, rtol=0)


def test_a_dropout_mask_changes_the_vectors_and_needs_the_batch():
    module = _randomised(PropagationModule(S, D, C, MLP_SHAPE))
    x = _inputs(4)
    args = (x["state"], x["velocity"], x["effect"], x["vectors"], x["pos"], EDGES)
    mask = (torch.rand(1, 12, generator=torch.Generator().manual_seed(0)) > 0.5).float() * 2
    _, v = module(*args)
    _, v_masked = module(*args, mask=mask, batch=torch.zeros(N, dtype=torch.long))
    assert (v - v_masked).abs().max() > 1e-3
    with pytest.raises(ValueError, match="batch"):
        module(*args, mask=mask)


def test_gradients_are_finite_when_vectors_vanish():
    """Lengths of zero vectors (a particle at rest, two coinciding leaves) have finite gradients."""
    module = PropagationModule(S, D, C, MLP_SHAPE, rest_offsets=True)
    x = _inputs(5)
    velocity = torch.zeros(N, 2, requires_grad=True)
    pos = torch.zeros(N, 3, requires_grad=True)
    e, v = module(x["state"], velocity, x["effect"], torch.zeros(N, C, 2), pos, EDGES, rest_pos=x["rest_pos"])
    (e.sum() + v.sum()).backward()
    assert torch.isfinite(pos.grad).all() and torch.isfinite(velocity.grad).all()


@pytest.mark.parametrize("build,call,words", [
    (lambda: PropagationModule(S, D, C, MLP_SHAPE), lambda m, x: m(x["state"][:, :2], x["velocity"], x["effect"],
                                                                    x["vectors"], x["pos"], EDGES), "state"),
    (lambda: PropagationModule(S, D, C, MLP_SHAPE), lambda m, x: m(x["state"], x["velocity"], x["effect"],
                                                                    x["vectors"][:, :1], x["pos"], EDGES), "vectors"),
    (lambda: PropagationModule(S, D, C, MLP_SHAPE, rest_offsets=True),
     lambda m, x: m(x["state"], x["velocity"], x["effect"], x["vectors"], x["pos"], EDGES), "rest_pos"),
    (lambda: CollisionModule(S, D, C, MLP_SHAPE), lambda m, x: m(x["state"], x["velocity"], x["pos"], EDGES[:1]),
     "edge_index"),
    (lambda: ForceModule(S, D, C, MLP_SHAPE), lambda m, x: m(x["state"], x["velocity"], x["force"][:, :2]), "force"),
    (lambda: NextStateModule(S, D, C, MLP_SHAPE),
     lambda m, x: m(x["state"], x["velocity"][:, :1], x["effect"], x["vectors"]), "velocity"),
])
def test_bad_shapes_say_which_input(build, call, words):
    with pytest.raises(ValueError, match=words):
        call(build(), _inputs())
