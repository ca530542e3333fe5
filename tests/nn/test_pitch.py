"""A pitch-aware HRN (HRNConfig.pitch_aware): the pitch column, the inputs read relative to the
pitch, one batch of two pitches answering as the two scenes alone, and the symmetries kept."""

import pytest
import torch
from toy_scene import structure, toy_window, trajectory
from torch_geometric.data import Batch

from hrn_pyg.data.graph import COLLISION, NODE, node_pitch, set_pitch, set_state
from hrn_pyg.nn.hrn import GROUND_CONTACT_DIM, HRN, STATE_DIM, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.nn.pitch import PITCH_DIM, collision_radius_of
from hrn_pyg.sim.step import build_inputs, step

SMALL = dict(hidden=16, depth=2, effect_dim=8)
#: the toy scene's leaves are 0.1 m apart: at this pitch it is the scene "as made"
TOY_PITCH = 0.05


def _windows(pitch: float = TOY_PITCH):
    windows = [toy_window(4, seed=s) for s in range(3)]
    return [set_pitch(w, pitch) for w in windows]


def _model(seed: int = 0, **kw) -> HRN:
    torch.manual_seed(seed)
    config = HRNConfig(**{**SMALL, "pitch_aware": True, **kw})
    model = HRN(config)
    fit_normalizer(_windows(), model.normalizer, reference_pitch=config.reference_pitch)
    return model.eval()


def _scene(model: HRN, pitch: float, scale: float = 1.0, shift=(0.0, 0.0, 0.0), flip=(1.0, 1.0, 1.0),
           force: bool = True):
    """The toy scene made at ``pitch``: its leaves ``scale`` times as far apart (lattice steps
    stay lattice steps), moved by ``shift`` and reflected by ``flip``, a push on leaf 0."""
    leaves = trajectory(2, 0) * scale * torch.tensor(flip) + torch.tensor(shift)
    push = torch.zeros(14, 3)
    if force:
        push[0] = torch.tensor([0.5, 0.2, 2.0]) * torch.tensor(flip)
    graph = set_pitch(structure(), pitch)
    return set_state(graph, leaves[0], leaves[1], leaves[2], radius=collision_radius_of(model.config, graph),
                     force=push)


def test_the_default_model_reads_no_pitch_and_keeps_its_state_layout():
    """Plain configs keep their state size, and a graph's pitch changes none of their inputs."""
    assert HRNConfig().state_dim == STATE_DIM
    assert HRNConfig(ground_contact=True).state_dim == STATE_DIM + GROUND_CONTACT_DIM
    assert HRNConfig(pitch_aware=True).state_dim == STATE_DIM + PITCH_DIM
    assert HRNConfig(pitch_aware=True, ground_contact=True).state_dim == STATE_DIM + GROUND_CONTACT_DIM + PITCH_DIM
    torch.manual_seed(0)
    plain = HRN(HRNConfig(**SMALL, ground_contact=True, rest_offsets=True)).eval()
    fit_normalizer(_windows(), plain.normalizer)
    leaves = trajectory(2, 0)
    bare = set_state(structure(), leaves[0], leaves[1], leaves[2], radius=0.08)
    tagged = set_state(set_pitch(structure(), 0.025), leaves[0], leaves[1], leaves[2], radius=0.08)
    a, b = build_inputs(plain, bare), build_inputs(plain, tagged)
    for name in ("state", "prev_state", "pos", "rest_pos", "force", "collision"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert collision_radius_of(plain.config, tagged) == plain.config.collision_radius


@pytest.mark.parametrize("pitch, column", [(0.05, 0.0), (0.1, 1.0), (0.025, -1.0), (0.08, 0.6780719)])
def test_the_pitch_column_is_log2_of_the_pitch_over_the_reference(pitch, column):
    model = _model(ground_contact=True)
    state = build_inputs(model, _scene(model, pitch)).state
    assert state.shape[1] == STATE_DIM + GROUND_CONTACT_DIM + PITCH_DIM
    torch.testing.assert_close(state[:, -1], torch.full((state.size(0),), column), atol=1e-6, rtol=0)
    if pitch == 0.05:
        assert bool((state[:, -1] == 0).all())  # exactly 0 at the reference


def test_a_scene_made_at_twice_the_pitch_reads_the_same_geometry():
    """The same lattice at pitch 2p, twice as large: edge offsets, rest offsets and the
    ground-contact column read the same; only velocities and heights (metres) and the pitch
    column differ."""
    model = _model(ground_contact=True, rest_offsets=True)
    fine = _scene(model, 0.05)
    coarse = _scene(model, 0.1, scale=2.0)
    assert torch.equal(fine[COLLISION].edge_index, coarse[COLLISION].edge_index)  # radius 0.08 vs 0.16
    a, b = build_inputs(model, fine), build_inputs(model, coarse)
    torch.testing.assert_close(a.pos, b.pos, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(a.rest_pos, b.rest_pos, atol=1e-6, rtol=1e-6)
    ground = STATE_DIM  # the ground-contact column: z over the graph's own radius
    torch.testing.assert_close(a.state[:, ground], b.state[:, ground], atol=1e-6, rtol=1e-6)
    assert torch.equal(b.state[:, -1], torch.ones(b.state.size(0)))


def test_the_radius_scales_with_the_pitch():
    model = _model()
    for pitch in (0.025, 0.05, 0.08):
        graph = set_pitch(structure(), pitch)
        assert collision_radius_of(model.config, graph) == pytest.approx(1.6 * pitch, rel=1e-12)
    assert collision_radius_of(model.config, set_pitch(structure(), 0.05)) == 0.08  # exactly the plain radius
    with pytest.raises(ValueError, match="pitch"):
        collision_radius_of(model.config, structure())
    mixed = Batch.from_data_list([set_pitch(structure(), 0.05), set_pitch(structure(), 0.08)])
    radii = collision_radius_of(model.config, mixed)
    assert isinstance(radii, torch.Tensor) and radii.tolist() == pytest.approx([0.08, 0.128])
    same = Batch.from_data_list([set_pitch(structure(), 0.08)] * 3)
    assert collision_radius_of(model.config, same) == pytest.approx(0.128)
    assert node_pitch(mixed).tolist() == [0.05] * 19 + [0.08] * 19


@pytest.mark.parametrize("kw", [{}, {"ground_contact": True, "rest_offsets": True, "rigid_fit": True}])
def test_one_batch_of_two_pitches_answers_as_the_two_scenes_alone(kw):
    model = _model(**kw)
    fine, coarse = _scene(model, 0.05), _scene(model, 0.08, scale=1.3)
    batch = Batch.from_data_list([fine, coarse])
    n = fine[NODE].num_nodes
    with torch.no_grad():
        alone = [step(model, fine), step(model, coarse)]
        together = step(model, batch)
    torch.testing.assert_close(together.pos, torch.cat([s.pos for s in alone]), atol=1e-6, rtol=0)
    # the next graphs' collision edges: each graph's own radius
    edges = torch.cat([alone[0].graph[COLLISION].edge_index, alone[1].graph[COLLISION].edge_index + n], dim=1)
    assert torch.equal(together.graph[COLLISION].edge_index, edges)
    assert alone[1].graph[COLLISION].edge_index.size(1) > 0


def test_a_horizontal_shift_changes_nothing():
    model = _model(ground_contact=True, rest_offsets=True)
    with torch.no_grad():
        pos = step(model, _scene(model, 0.07)).pos
        moved = step(model, _scene(model, 0.07, shift=(1.5, -0.75, 0.0))).pos
    torch.testing.assert_close(moved, pos + torch.tensor([1.5, -0.75, 0.0]), atol=2e-6, rtol=0)


@pytest.mark.parametrize("planes, flip", [("x", (-1.0, 1.0, 1.0)), ("xy", (1.0, -1.0, 1.0)), ("d4", (-1.0, -1.0, 1.0))])
def test_the_mirror_average_stays_exact_for_a_pitch_aware_model(planes, flip):
    model = _model(mirror_average=True, mirror_planes=planes, ground_contact=True, rest_offsets=True)
    sign = torch.tensor(flip)
    with torch.no_grad():
        pos = step(model, _scene(model, 0.035)).pos
        pos_m = step(model, _scene(model, 0.035, flip=flip)).pos
    torch.testing.assert_close(pos_m, pos * sign, atol=1e-6, rtol=0)


def test_gradients_reach_every_module_of_a_pitch_aware_model():
    model = _model(ground_contact=True, rest_offsets=True).train()
    batch = Batch.from_data_list([_scene(model, 0.05), _scene(model, 0.08, scale=1.3)])
    pos = batch[NODE].pos.clone().requires_grad_(True)
    batch[NODE].pos = pos
    out = step(model, batch).pos
    out.square().sum().backward()
    assert pos.grad is not None and bool(torch.isfinite(pos.grad).all()) and pos.grad.abs().sum() > 0
    for name in ("force", "collision", "history", "l2a", "ws", "a2d", "state"):
        grads = [p.grad for p in getattr(model, name).parameters()]
        assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads), name
        assert sum(float(g.abs().sum()) for g in grads) > 0, name


def test_the_normaliser_measures_lengths_in_lattice_steps():
    """Windows at pitch p and the same windows twice as large at 2p give one length scale."""
    fine = fit_normalizer(_windows(0.05), reference_pitch=0.05)
    coarse_windows = _windows(0.1)
    for w in coarse_windows:
        w[NODE].pos_seq = w[NODE].pos_seq * 2.0
    coarse = fit_normalizer(coarse_windows, reference_pitch=0.05)
    torch.testing.assert_close(fine.length_scale, coarse.length_scale, atol=0, rtol=1e-6)
    plain = fit_normalizer(coarse_windows)
    torch.testing.assert_close(plain.length_scale, 2.0 * fine.length_scale, atol=0, rtol=1e-6)


def test_a_bad_reference_pitch_is_refused():
    with pytest.raises(ValueError, match="reference_pitch"):
        HRNConfig(pitch_aware=True, reference_pitch=0.0)
