"""Hard cases that must stay finite: degenerate objects, extreme mass ratios and scales,
dropout extremes, float32 / float64, fast impacts and long gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from stability_helpers import fitted_model
from toy_scene import DT, GRAVITY, toy_scene, toy_window

from hrn_pyg.data.graph import (
    COLLISION,
    NODE,
    build_structure,
    leaf_to_ancestor_mean,
    set_state,
)
from hrn_pyg.data.hierarchy import build_hierarchy
from hrn_pyg.data.voxelise import box_mesh, lattice_tetrahedra, voxelise
from hrn_pyg.losses import full_shape_loss
from hrn_pyg.nn.hrn import HRN, MODULE_NAMES, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import rollout, unroll
from hrn_pyg.train import TrainConfig, window_loss

#: steps of the short rollouts of this file
STEPS = 15


def _scene(objects: list[np.ndarray], masses: list[float], radius: float = 0.08, speed=None,
           leaf_weights: list[np.ndarray] | None = None):
    """Graph of rigid objects given by their leaf positions, falling (or moving at ``speed``
    m/step per object). Object ``i`` weighs ``masses[i]``, shared equally by its leaves or in
    proportion to ``leaf_weights[i]``."""
    leaves = np.concatenate(objects)
    leaf_object = np.concatenate([np.full(len(o), i) for i, o in enumerate(objects)])
    if leaf_weights is None:
        leaf_weights = [np.ones(len(o)) for o in objects]
    mass = np.concatenate([m * w / w.sum() for w, m in zip(leaf_weights, masses)])
    parent = build_hierarchy(leaves, mass, leaf_object)
    n_obj = len(objects)
    structure = build_structure(torch.as_tensor(parent), torch.as_tensor(mass, dtype=torch.float32),
                                torch.as_tensor(leaf_object), torch.zeros(n_obj, dtype=torch.long), torch.ones(n_obj))
    x = torch.as_tensor(leaves, dtype=torch.float32)
    if speed is None:
        v = torch.zeros(n_obj, 3) + torch.tensor([0.0, 0.0, -GRAVITY * DT * DT])
    else:
        v = torch.as_tensor(np.asarray(speed), dtype=torch.float32)
    v_leaf = v[torch.as_tensor(leaf_object)]
    return set_state(structure, x - 2 * v_leaf, x - v_leaf, x, radius=radius)


def _assert_finite_rollout(model, graph, steps=STEPS, bound=1e3):
    with torch.no_grad():
        traj = rollout(model, graph, steps, sleep=None)
    assert torch.isfinite(traj).all()
    assert traj.abs().max() < bound
    return traj


def _grads_finite(model, graph, steps=5):
    model.zero_grad()
    results = unroll(model, graph, steps, sleep=None)
    loss = sum(r.pos.pow(2).mean() for r in results)
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_single_voxel_object_next_to_a_cube():
    cube = voxelise(box_mesh(0.1), 0.05) + [0, 0, 0.3]
    single = np.array([[0.1, 0.0, 0.3]])  # one leaf, within the collision radius of the cube
    g = _scene([cube, single], [1.0, 0.1])
    assert g[COLLISION].edge_index.size(1) > 0
    model = fitted_model()
    traj = _assert_finite_rollout(model, g)
    # the one-leaf object's root is its leaf
    torch.testing.assert_close(traj[:, g[NODE].num_nodes - 1], traj[:, len(cube)])
    _grads_finite(model, g)


def test_flat_and_very_thin_meshes():
    sheet = voxelise(box_mesh((0.2, 0.2, 1e-4)), 0.05)
    assert np.ptp(sheet[:, 2]) < 1e-3  # one layer of leaves
    g = _scene([sheet + [0, 0, 0.2], voxelise(box_mesh(0.1), 0.05) + [0, 0, 0.3]], [0.2, 1.0])
    model = fitted_model()
    _assert_finite_rollout(model, g)
    _grads_finite(model, g)
    # a soft body needs a volume: a flat lattice is refused with a clear error, not a NaN later
    with pytest.raises(ValueError, match="points"):
        lattice_tetrahedra(sheet, 0.05)


def test_coincident_particles_have_finite_gradients():
    a = np.array([[0.0, 0.0, 0.3], [0.05, 0.0, 0.3], [0.05, 0.0, 0.3]])  # two leaves of one object coincide
    b = np.array([[0.05, 0.0, 0.3], [0.1, 0.0, 0.3]])  # and one of another object sits on them
    g = _scene([a, b], [1.0, 1.0])
    edges = g[COLLISION].edge_index
    offset = g[NODE].pos[edges[0]] - g[NODE].pos[edges[1]]
    assert (offset.norm(dim=-1) == 0).any()  # a zero-length collision edge
    model = fitted_model()
    _assert_finite_rollout(model, g)
    _grads_finite(model, g)
    # the shape loss at coincident points: distance 0 in prediction and truth
    pred = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], requires_grad=True)
    loss = full_shape_loss(pred, pred.detach().clone(), torch.zeros(3, dtype=torch.long))
    loss.backward()
    assert torch.isfinite(pred.grad).all()


def test_mass_ratio_of_a_thousand():
    """A 100 kg cube next to a 0.1 kg one. The heavy cube's leaves are not equally heavy: its
    three x-layers (at x = -0.05, 0, +0.05 about its centre) weigh 1 : 1 : 10, so its root sits
    at x = (-0.05 * 1 + 0 * 1 + 0.05 * 10) / 12 = 0.0375, not at the plain mean 0."""
    cube = voxelise(box_mesh(0.1), 0.05)  # 27 leaves, 3 x-layers of 9
    layer_weight = np.select([cube[:, 0] < -0.01, cube[:, 0] > 0.01], [1.0, 10.0], 1.0)
    heavy, light = cube + [0, 0, 0.3], cube + [0.13, 0, 0.3]
    g = _scene([heavy, light], [100.0, 0.1], leaf_weights=[layer_weight, np.ones(len(cube))])
    store = g[NODE]
    roots = store.is_root.nonzero().flatten()
    assert store.object[roots].tolist() == [0, 1]
    torch.testing.assert_close(store.mass[roots, 0], torch.tensor([100.0, 0.1]))
    torch.testing.assert_close(store.pos[roots], torch.tensor([[0.0375, 0.0, 0.3], [0.13, 0.0, 0.3]]))

    model = fitted_model()
    traj = _assert_finite_rollout(model, g).double().numpy()  # [steps, N, 3]
    leaf_mass = store.mass[:, 0].double().numpy()[: 2 * len(cube)]
    for obj, root in enumerate(roots.tolist()):
        leaves = slice(obj * len(cube), (obj + 1) * len(cube))  # leaves are in input order
        expected = np.einsum("l,tld->td", leaf_mass[leaves], traj[:, leaves]) / leaf_mass[leaves].sum()
        np.testing.assert_allclose(traj[:, root], expected, rtol=0, atol=1e-5)
    # the weighting matters: the heavy root is not the plain mean of its leaves
    assert np.abs(traj[:, roots[0]] - traj[:, : len(cube)].mean(1)).max() > 0.03
    _grads_finite(model, g)


def _scaled(graph, s: float):
    graph = graph.clone()
    for key in ("pos", "prev_pos", "prev_prev_pos", "pos_seq"):
        if key in graph[NODE]:
            graph[NODE][key] = graph[NODE][key] * s
    return graph


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1e3])
def test_scale_equivariance_at_very_small_and_large_scales(scale):
    """A model fitted on a scene scaled by s predicts s times what it predicts unscaled.

    Broke at s = 1e-5 and below before the normaliser's "never varies" test was made relative
    (an absolute 1e-8 floor forced micrometre-scale spreads to 1 m/step)."""
    trajs = []
    for s in (1.0, scale):
        torch.manual_seed(0)
        model = HRN(HRNConfig(hidden=16, effect_dim=16, collision_radius=0.08 * s))
        fit_normalizer([_scaled(toy_window(6, seed=q), s) for q in range(3)], model.normalizer)
        model = model.double().eval()
        g = _scaled(toy_scene(), s)
        for key in ("pos", "prev_pos", "prev_prev_pos", "mass", "stiffness", "material", "force"):
            g[NODE][key] = g[NODE][key].double()
        with torch.no_grad():
            trajs.append(rollout(model, g, STEPS, sleep=None) / s)
    assert torch.isfinite(trajs[1]).all()
    torch.testing.assert_close(trajs[1], trajs[0], rtol=1e-5, atol=1e-5 * float(trajs[0].abs().max()))


def test_dropout_zero_is_deterministic_and_point_nine_stays_finite():
    model = fitted_model(dropout_modules=MODULE_NAMES)
    g = toy_scene(force=True)
    forces = torch.zeros(STEPS, 14, 3)
    with torch.no_grad():
        reference = rollout(model, g, STEPS, sleep=None)[:, g[NODE].is_leaf]
    zero = sample(model, g, 3, STEPS, 0.0, sleep=None)
    torch.testing.assert_close(zero, reference.expand(3, -1, -1, -1), rtol=0, atol=0)
    high = sample(model, g, 4, STEPS, 0.9, forces=forces, generator=torch.Generator().manual_seed(0), sleep=None)
    assert torch.isfinite(high).all() and high.abs().max() < 1e3
    assert not torch.equal(high[0], high[1])  # the masks did differ


def test_float32_matches_float64():
    m32 = fitted_model()
    m64 = fitted_model(dtype=torch.float64)
    g32 = toy_scene(force=True)
    g64 = g32.clone()
    for key in ("pos", "prev_pos", "prev_prev_pos", "mass", "stiffness", "material", "force"):
        g64[NODE][key] = g64[NODE][key].double()
    with torch.no_grad():
        a, b = rollout(m32, g32, STEPS, sleep=None), rollout(m64, g64, STEPS, sleep=None)
    assert a.dtype == torch.float32 and b.dtype == torch.float64
    assert torch.isfinite(a).all()
    torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-5)


def test_gradients_finite_through_a_fifteen_step_unroll():
    model = fitted_model()
    model.train()
    window = toy_window(15)
    loss, parts = window_loss(model, window, 15, TrainConfig(shape_loss="full"))
    assert torch.isfinite(loss)
    loss.backward()
    grads = {n: p.grad for n, p in model.named_parameters() if p.grad is not None}
    assert all(torch.isfinite(g).all() for g in grads.values())
    assert any(g.abs().sum() > 0 for g in grads.values())


def _min_distance_between_objects(graph) -> float:
    """Smallest distance between leaves of different objects at the graph's current state."""
    store = graph[NODE]
    leaf = store.is_leaf
    pos, obj = store.pos[leaf], store.object[leaf]
    dist = torch.cdist(pos, pos)
    return float(dist[obj[:, None] != obj[None, :]].min())


def test_impact_at_ten_times_the_training_speed():
    """Two cubes flying at each other at 10x the fastest push of cube_collision (2.5 m/s).

    At that speed a cube moves further in one step than the collision radius, so the start is
    chosen to make them meet: their facing layers of leaves coincide after ``meet`` steps of
    constant velocity. The rollout must see collision edges there (not fly through without
    contact) and stay finite and bounded."""
    meet = 2
    speed = 10 * 2.5 * DT  # m per model step
    cube = voxelise(box_mesh(0.1), 0.05)  # leaves from -0.05 to 0.05 about the centre
    centre = 0.05 + meet * speed
    left, right = cube + [-centre, 0, 0.05], cube + [centre, 0, 0.05]
    g = _scene([left, right], [1.0, 1.0], speed=[[speed, 0, 0], [-speed, 0, 0]])
    model = fitted_model()
    radius = model.config.collision_radius
    assert speed > radius  # one step jumps further than a collision reaches
    assert _min_distance_between_objects(g) > radius and g[COLLISION].edge_index.size(1) == 0  # no contact yet

    with torch.no_grad():
        steps = unroll(model, g, 30, sleep=None)
    traj = torch.stack([s.pos for s in steps])
    assert torch.isfinite(traj).all() and traj.abs().max() < 1e3

    at_meet = steps[meet - 1].graph  # Step.graph holds the state after the step and its collisions
    assert _min_distance_between_objects(at_meet) < radius
    edges = at_meet[COLLISION].edge_index
    assert edges.size(1) > 0
    objects = at_meet[NODE].object
    assert bool((objects[edges[0]] != objects[edges[1]]).all())  # edges join the two cubes
    _grads_finite(model, g, steps=5)


def test_one_leaf_objects_get_a_physical_local_scale():
    """Every object a single voxel (cube_collision at pitch 0.1): the local velocity of a leaf in
    its root's frame is always 0. Its scale used to fall back to 1 m/step, so a barely trained
    model flew apart within 15 steps (the cell grid of the collision search then overflowed);
    it now takes the root's scale."""
    windows = []
    for seed in range(3):
        x = torch.tensor([[0.0, 0.0, 0.05], [0.4, 0.0, 0.05]]) + 0.01 * seed
        v = torch.tensor([[0.02, 0.01, 0.0], [-0.03, -0.02, 0.0]]) * (1 + seed)
        traj = torch.stack([x + t * v + torch.tensor([0, 0, -0.001 * t * t]) for t in range(6)])
        g = _scene([traj[2, :1].numpy(), traj[2, 1:].numpy()], [1.0, 1.0])
        n = g[NODE].num_nodes
        seq = torch.zeros(6, n, 3)
        seq[:, :2] = traj
        g[NODE].pos_seq = leaf_to_ancestor_mean(seq, g).transpose(0, 1).contiguous()
        g[NODE].force_seq = torch.zeros(n, 3, 3)
        windows.append(g)
    norm = fit_normalizer(windows)
    assert torch.equal(norm.local_std, norm.root_std)
    assert norm.root_std.max() < 0.01  # m/step: the data's scale, not 1
