import pytest
import torch
from torch_geometric.data import Batch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.graph import COLLISION, NODE, set_state
from hrn_pyg.losses import full_shape_loss, local_velocity_loss, shape_groups
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.nn.state import to_local_velocity
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.sim.step import build_inputs, decode, run_network, step, target_output


def _model(seed=0, hidden=16, **kw):
    torch.manual_seed(seed)
    model = HRN(HRNConfig(hidden=hidden, depth=2, effect_dim=hidden, **kw))
    fit_normalizer([toy_window(6, seed=s) for s in range(3)], model.normalizer)
    return model


def test_rollout_shapes_static_and_derived_ancestors():
    model = _model()
    g = toy_scene(force=True)
    traj = rollout(model, g, 5)
    assert traj.shape == (5, 19, 3)
    s = g[NODE]
    assert torch.equal(traj[:, s.is_static], s.pos[s.is_static].expand(5, -1, -1))
    # ancestors are the mass-weighted means of their leaves
    soft_root = (traj[:, :8] * 0.1).sum(1) / 0.8
    torch.testing.assert_close(traj[:, 16], soft_root)


def test_step_stages_compose_and_decode_inverts_target():
    model = _model()
    g = toy_scene(force=True)
    out = run_network(model, build_inputs(model, g))
    pos, local, velocity, _ = decode(model, g, out)
    result = step(model, g)
    assert torch.equal(result.pos, pos) and torch.equal(result.local_velocity, local)
    torch.testing.assert_close(result.pos[:14], g[NODE].pos[:14] + velocity[:14])
    nxt = result.graph[NODE]
    assert torch.equal(nxt.prev_pos, g[NODE].pos) and torch.equal(nxt.pos, pos)


def test_decode_inverts_target_output():
    model = _model()
    window = toy_window(1)
    true_next = window[NODE].pos_seq[:, 3]
    target = target_output(model, window, true_next)
    pos, _, velocity, _ = decode(model, window, target)
    torch.testing.assert_close(pos, true_next, atol=1e-6, rtol=0)
    torch.testing.assert_close(velocity, true_next - window[NODE].pos, atol=1e-6, rtol=0)


def test_collision_edges_recomputed_each_step():
    model = _model()
    g = toy_scene(separate=True)
    assert g[COLLISION].edge_index.size(1) == 0
    assert step(model, g).graph[COLLISION].edge_index.size(1) == 0
    # the same motion with the square next to the cube, given without collision edges:
    # unroll recomputes them on the initial graph and after every step
    back = torch.zeros(19, 3)
    back[8:12, 0] = -1.0
    s = g[NODE]
    near = set_state(g, (s.prev_prev_pos + back)[:14], (s.prev_pos + back)[:14], (s.pos + back)[:14], radius=None)
    assert near[COLLISION].edge_index.size(1) == 0
    calls = []
    model.collision.register_forward_hook(lambda *a: calls.append(1))
    steps = unroll(model, near, 2)
    assert len(calls) == 2
    assert all(st.graph[COLLISION].edge_index.size(1) > 0 for st in steps)


def test_gradients_finite_through_six_step_unroll():
    model = _model()
    window = toy_window(6)
    steps = unroll(model, window, 6)
    leaf, group = shape_groups(window)
    loss = sum(
        full_shape_loss(st.pos[leaf], window[NODE].pos_seq[leaf, t + 3], group) for t, st in enumerate(steps)
    )
    loss = loss + sum(st.pos.pow(2).mean() for st in steps)
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_horizontal_translation_moves_prediction():
    model = _model()
    g = toy_scene(force=True)
    shift = torch.tensor([0.7, -1.3, 0.0])
    s = g[NODE]
    moved = set_state(g, s.prev_prev_pos[:14] + shift, s.prev_pos[:14] + shift, s.pos[:14] + shift,
                      radius=0.08, force=s.force[:14])
    a, b = rollout(model, g, 3), rollout(model, moved, 3)
    torch.testing.assert_close(b, a + shift, atol=1e-5, rtol=0)
    # a vertical shift changes the height above the ground, so the prediction is not just shifted
    up = torch.tensor([0.0, 0.0, 0.5])
    lifted = set_state(g, s.prev_prev_pos[:14] + up, s.prev_pos[:14] + up, s.pos[:14] + up,
                       radius=0.08, force=s.force[:14])
    assert not torch.allclose(rollout(model, lifted, 3) - up, a, atol=1e-6)


def test_seeded_determinism_and_rate_zero_masks():
    g = toy_scene(force=True)
    a, b = _model(seed=5, dropout_modules=("force", "collision")), _model(seed=5)
    ref = rollout(a, g, 4)
    assert torch.equal(ref, rollout(b, g, 4))
    zero = rollout(a, g, 4, masks_fn=lambda t, graph: a.sample_masks(1, rate=0.0))
    assert torch.equal(zero, ref)
    gen = torch.Generator().manual_seed(0)
    noisy = rollout(a, g, 4, masks_fn=lambda t, graph: a.sample_masks(1, rate=0.5, generator=gen))
    assert not torch.allclose(noisy, ref)


def test_batched_copies_equal_each_alone():
    model = _model()
    g1, g2 = toy_scene(seed=0, force=True), toy_scene(seed=1)
    batch = Batch.from_data_list([g1, g2])
    traj = rollout(model, batch, 4)
    torch.testing.assert_close(traj[:, :19], rollout(model, g1, 4), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(traj[:, 19:], rollout(model, g2, 4), atol=1e-5, rtol=1e-5)


def test_forces_argument_checked_and_used():
    model = _model()
    g = toy_scene()
    push = torch.zeros(3, 19, 3)
    push[1, 0] = torch.tensor([0.0, 0.0, 3.0])
    free, pushed = rollout(model, g, 3), rollout(model, g, 3, forces=push)
    assert torch.equal(free[0], pushed[0])  # forces[1] acts on the second predicted step
    assert not torch.allclose(free[1], pushed[1])
    with pytest.raises(ValueError, match="forces"):
        rollout(model, toy_scene(), 3, forces=torch.zeros(2, 19, 3))
    with pytest.raises(ValueError, match="steps"):
        rollout(model, toy_scene(), 0)


def test_tiny_model_overfits_one_batch():
    model = _model(seed=0, hidden=32)
    batch = Batch.from_data_list([toy_window(2, seed=s) for s in range(2)])
    s = batch[NODE]
    c2p = batch["particle", "child_to_parent", "particle"].edge_index
    true_local = to_local_velocity(s.pos_seq[:, 3] - s.pos_seq[:, 2], c2p)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(150):
        opt.zero_grad()
        result = step(model, batch)
        loss = local_velocity_loss(result.local_velocity, true_local, s.is_root, s.is_static, model.normalizer)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_unroll_equals_checked_steps_with_objects_found_each_step():
    # unroll finds the objects once and skips the per-step input checks: same numbers as
    # stepping by hand, where every step checks its inputs and finds the objects again
    model = _model(rigid_fit=True).eval()
    g = toy_scene(force=True)
    with torch.no_grad():
        fast = rollout(model, g, 4, sleep=None)
        graph = set_state(g, g[NODE].prev_prev_pos, g[NODE].prev_pos, g[NODE].pos, radius=model.config.collision_radius)
        slow = []
        for _ in range(4):
            result = step(model, graph, torch.zeros_like(graph[NODE].pos))
            slow.append(result.pos)
            graph = result.graph
    assert torch.equal(fast, torch.stack(slow))


def test_unroll_rejects_a_non_finite_start_once():
    model = _model()
    g = toy_scene(force=True)
    g[NODE].prev_pos = g[NODE].prev_pos.clone()
    g[NODE].prev_pos[0, 1] = float("nan")
    with pytest.raises(ValueError, match=r"prev_pos contains NaN or infinite values"):
        rollout(model, g, 2, sleep=None)


def test_iterate_checks_its_arguments_when_called_not_when_stepped():
    from stability.stability_helpers import fitted_model

    from hrn_pyg.sim.rollout import iterate

    model, graph = fitted_model(), toy_scene()
    with pytest.raises(ValueError, match="steps must be >= 1"):
        iterate(model, graph, 0)  # nothing taken from the iterator
    bad = torch.full((3, graph["particle"].num_nodes, 3), float("nan"))
    with pytest.raises(ValueError, match="forces contains NaN"):
        iterate(model, graph, 3, bad)
    steps = iterate(model, graph, 3)
    assert len(list(steps)) == 3
