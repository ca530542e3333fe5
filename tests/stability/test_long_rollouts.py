"""Long rollouts: finite, bounded, and (for a trained model) nothing sinking through the ground.

What is asserted where, and why:

* A randomly initialised network is not a physical model: fed its own predictions it is an
  unstable map (on pybullet scenes its positions grow about 100-fold every 50 steps and overflow
  float32 before step 400), so "finite after 1000 steps" is not a property of untrained weights
  and is not asserted for them. What the package itself must keep stable over 1000 steps is the
  rollout machinery (decoding, the sum down the tree, integration, derived ancestors, collision
  search as the scene moves): that is tested with a network whose output layer is zero, which
  makes the model an exact ballistic integrator of the fitted mean accelerations, so every
  position has a closed form.
* No sinking through the ground is a property of a *trained* model (the decoder does not clamp
  positions: a clamp would hide errors and is not physical for soft bodies, whose pybullet nodes
  may sit slightly in the contact margin). It is checked on the shipped checkpoints
  (``hrn_pyg/checkpoints``), with a stated depth of one voxel pitch (5 cm); the shipped models
  that still fail it over 1000 steps are marked as strict expected failures below.
"""

from __future__ import annotations

import pytest
import torch
from stability_helpers import SLOW, fitted_model, slow, trained_checkpoint
from toy_scene import toy_scene

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import COLLISION, NODE
from hrn_pyg.data.scene_file import SCENES
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.ensemble import episode_state
from hrn_pyg.sim.rollout import rollout, unroll

#: how far (m) a leaf may go below the ground plane z = 0 in a trained model's long rollout:
#: one voxel pitch of the datasets (0.05 m); pybullet's own contact margin is 6 mm
SINK_DEPTH = 0.05
#: no leaf of a trained model's rollout may move further than this (m) from where it started
TRAINED_BOUND = 50.0
LONG_STEPS = 1000


def ballistic(model: HRN) -> HRN:
    """Zero the last layer of the next-state MLP: the output is 0, so every node's local
    velocity changes by the fitted mean each step (a constant acceleration)."""
    with torch.no_grad():
        model.state.psi.output_layer.weight.zero_()
        model.state.psi.output_layer.bias.zero_()
    return model


def closed_form(model: HRN, graph, steps: int) -> torch.Tensor:
    r"""``[steps, N, 3]`` positions of the ballistic model: a leaf accelerates by
    :math:`a = \mu_{root} + (\mathrm{depth} - 1)\,\mu_{loc}` + its own :math:`\mu_{loc}`."""
    store = graph[NODE]
    norm = model.normalizer
    depth = store.depth.to(store.pos.dtype)[:, None]
    mu_root, mu_loc = norm.root_mean.to(store.pos.dtype), norm.local_mean.to(store.pos.dtype)
    accel = torch.where(store.is_root[:, None], mu_root, mu_root + depth * mu_loc)
    accel = torch.where(store.is_static[:, None], torch.zeros_like(accel), accel)
    v0 = torch.where(store.is_static[:, None], torch.zeros_like(store.pos), store.pos - store.prev_pos)
    k = torch.arange(1, steps + 1, dtype=store.pos.dtype)[:, None, None]
    x = store.pos + k * v0 + k * (k + 1) / 2 * accel
    from hrn_pyg.data.graph import leaf_to_ancestor_mean

    return leaf_to_ancestor_mean(x, graph)


def _double(graph):
    graph = graph.clone()
    for key in ("pos", "prev_pos", "prev_prev_pos", "mass", "stiffness", "material", "force"):
        graph[NODE][key] = graph[NODE][key].double()
    return graph


def test_ballistic_rollout_of_the_toy_scene_is_exact():
    steps = LONG_STEPS if SLOW else 300
    model = ballistic(fitted_model(dtype=torch.float64))
    g = _double(toy_scene())
    with torch.no_grad():
        traj = rollout(model, g, steps, sleep=None)
    assert torch.isfinite(traj).all()
    torch.testing.assert_close(traj, closed_form(model, g, steps), rtol=1e-9, atol=1e-9)
    s = g[NODE]
    fixed = s.is_static & s.is_leaf  # static leaves never move, bit for bit
    assert torch.equal(traj[:, fixed], s.pos[fixed].expand(steps, -1, -1))


def test_random_network_stays_finite_for_a_short_horizon():
    """The honest claim for untrained weights: finite over 100 steps (not over 1000)."""
    model = fitted_model()
    with torch.no_grad():
        traj = rollout(model, toy_scene(), 100, sleep=None)
    assert torch.isfinite(traj).all()


def _scene_state(scene: str, seed: int = 9):
    episode = simulate_episode(scene, seed, steps=5)
    return episode, episode_state(episode, start=2, steps=3)


@slow
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_thousand_step_ballistic_rollout_of_every_scene(scene):
    _, window = _scene_state(scene)
    torch.manual_seed(0)
    model = HRN(HRNConfig(hidden=32, effect_dim=32))
    fit_normalizer([window], model.normalizer)
    model = ballistic(model.double().eval())
    g = _double(window)
    with torch.no_grad():
        traj = rollout(model, g, LONG_STEPS, sleep=None)
    assert torch.isfinite(traj).all()
    expected = closed_form(model, g, LONG_STEPS)
    torch.testing.assert_close(traj, expected, rtol=1e-7, atol=1e-6)


#: Shipped models that do NOT pass the 1000-step check (measured when they were last retrained).
#: Strict: a model that starts passing turns the xfail into a failure, so this list has to be
#: kept true. tower, cube_push and soft_bounce left it when they were retrained on 150-step
#: episodes with the rigid fit / rest-shape offsets (before: drifted away, sank 14 cm and 8.6 cm);
#: multi_material left it with its unroll-16 rest stage (2026-11-27): its cloth settles 4.0-5.4 cm
#: into the ground on the validation starts (before 5.9-11 cm), above the 5 cm bound on this start.
LONG_ROLLOUT_FAILURES: dict[str, str] = {}


@slow
@pytest.mark.parametrize("scene", [
    pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=LONG_ROLLOUT_FAILURES[s]))
    if s in LONG_ROLLOUT_FAILURES else s
    for s in sorted(SCENES)
])
def test_thousand_steps_of_a_trained_model_stay_above_the_ground(scene):
    path = trained_checkpoint(scene)
    if path is None:
        pytest.skip(f"no trained checkpoint for {scene} on disk")
    model = load_model(path)
    episode, window = _scene_state(scene)
    g = window.clone()
    del g[NODE].pos_seq, g[NODE].force_seq
    with torch.no_grad():
        traj = rollout(model, g, LONG_STEPS, sleep=None)
    leaves = g[NODE].is_leaf
    assert torch.isfinite(traj).all()
    assert (traj[:, leaves] - g[NODE].pos[leaves]).abs().max() < TRAINED_BOUND
    assert traj[:, leaves, 2].min() > -SINK_DEPTH


def _cross_object_leaf_edges(graph) -> int:
    """Collision edges of ``graph`` that join leaves of two different objects."""
    store = graph[NODE]
    src, dst = graph[COLLISION].edge_index
    joins = store.is_leaf[src] & store.is_leaf[dst] & (store.object[src] != store.object[dst])
    return int(joins.sum())


def _min_leaf_distance(pos, store, a: int, b: int) -> float:
    leaf = store.is_leaf
    return float(torch.cdist(pos[leaf & (store.object == a)], pos[leaf & (store.object == b)]).min())


@slow
def test_trained_model_survives_an_impact_at_ten_times_the_training_speed():
    """Both cubes of cube_collision flying at each other at 10x the fastest scripted push (2.5 m/s).

    At that speed a cube moves ~10 collision radii per step and the trained model slows a lone
    cube down on its own, so the start is placed from the model's own contact-free flight: a
    run with cube 1 moved sideways out of reach gives where each cube is after ``meet`` steps,
    and cube 1 is then shifted along the line of approach so that its leaves come within half a
    collision radius of cube 0's exactly there. The rollout must see collision edges between the
    two cubes at that step (not fly through without contact), the contact must change both
    cubes' velocity against the contact-free flight (each is slowed in its direction of travel),
    and the 100 steps must stay finite and bounded."""
    path = trained_checkpoint("cube_collision")
    if path is None:
        pytest.skip("no trained cube_collision checkpoint on disk")
    model = load_model(path)
    radius = model.config.collision_radius
    episode, window = _scene_state("cube_collision")
    g = window.clone()
    del g[NODE].pos_seq, g[NODE].force_seq
    store = g[NODE]
    assert sorted(torch.unique(store.object).tolist()) == [0, 1]
    centre = store.pos[store.is_root]
    direction = centre[1] - centre[0]
    direction[2] = 0
    direction = direction / direction.norm()  # from cube 0 towards cube 1
    sideways = torch.stack([-direction[1], direction[0], torch.zeros(())])
    speed = 10 * 2.5 * float(episode["dt"])  # m per model step
    assert speed > 5 * radius  # one step jumps far further than a collision reaches
    v = torch.where((store.object == 0)[:, None], direction * speed, -direction * speed)
    cube1 = (store.object == 1)[:, None].to(store.pos.dtype)

    def start(offset_of_cube1):
        h = g.clone()
        pos = store.pos + cube1 * offset_of_cube1
        h[NODE].pos, h[NODE].prev_pos, h[NODE].prev_prev_pos = pos, pos - v, pos - 2 * v
        return h

    meet = 2  # the step after which the cubes touch (Step.graph of step index meet - 1)
    away = 3.0 * sideways  # cube 1 this far sideways never comes within reach of cube 0
    with torch.no_grad():
        free = unroll(model, start(away), meet + 1, sleep=None)
    assert all(_cross_object_leaf_edges(s.graph) == 0 for s in free)
    pos = free[meet - 1].pos.clone()
    pos[store.object == 1] -= away
    # the largest shift along the line of approach that brings the cubes within radius / 2
    shifts = torch.arange(4.0, -4.0, -1e-3)
    shift = next(float(a) for a in shifts
                 if _min_leaf_distance(pos + cube1 * (a * direction), store, 0, 1) <= radius / 2)
    g = start(shift * direction)
    assert _min_leaf_distance(g[NODE].pos, store, 0, 1) > 2 * speed  # far apart at the start

    with torch.no_grad():
        steps = unroll(model, g, 100, sleep=None)
    traj = torch.stack([s.pos for s in steps])
    assert torch.isfinite(traj).all()
    assert (traj - g[NODE].pos).abs().max() < TRAINED_BOUND

    # no contact before the meeting step, contact (edges between the cubes' leaves) at it
    assert [_cross_object_leaf_edges(s.graph) for s in steps[: meet - 1]] == [0] * (meet - 1)
    assert _min_leaf_distance(steps[meet - 1].pos, store, 0, 1) < radius
    assert _cross_object_leaf_edges(steps[meet - 1].graph) > 0

    # before the impact both cubes fly exactly as without the other one; the step after the
    # contact slows each of them along its direction of travel, by more than 0.05 m/step
    roots = store.is_root
    for k in range(meet):
        torch.testing.assert_close(steps[k].velocity[roots], free[k].velocity[roots], rtol=1e-4, atol=1e-5)
    along = (steps[meet].velocity[roots] - free[meet].velocity[roots]) @ direction  # [cube 0, cube 1]
    assert float(along[0]) < -0.05, f"cube 0 velocity change at impact {float(along[0]):.4f} m/step"
    assert float(along[1]) > 0.05, f"cube 1 velocity change at impact {float(along[1]):.4f} m/step"


#: the goals of the stability issue: over 1000 steps a rigid object keeps its mean pairwise leaf
#: distance within 1 %, and an object pybullet keeps at rest moves less than one voxel pitch
RIGID_SHAPE_TOLERANCE = 0.01
REST_DRIFT = 0.05
#: step after which every object of a resting start must hold still (the model may settle first)
SETTLE = 200
#: shipped models that keep no rigid shape (trained before the rigid fit existed)
RIGID_SHAPE_FAILURES: dict[str, str] = {}  # every shipped model with a rigid object has the rigid fit
#: scenes at rest at step 2 with no force, and the shipped models that still slide there
#: (soft_bounce left the list with its unroll-16 fine-tuning stage: 4-5 cm -> 1.2-1.7 cm; cube_push
#: with its third stage, the rest term weighted 3: 0.069/0.054/0.028 -> 0.032/0.021/0.031 m on the
#: validation starts, 2026-11-27; tower with its stages 3 and 4, standing towers mixed in and the
#: average over the mirrors x and y: 0.18-0.20 -> 0.013-0.037 m on validation seeds 8-48)
RESTING_SCENES = ("cube_collision", "cube_push", "soft_bounce", "tower")
REST_DRIFT_FAILURES: dict[str, str] = {}


def _xfail_unless(scenes, failures):
    return [pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=failures[s])) if s in failures else s
            for s in scenes]


def _resting_rollout(scene):
    path = trained_checkpoint(scene)
    if path is None:
        pytest.skip(f"no trained checkpoint for {scene} on disk")
    _, window = _scene_state(scene)
    g = window.clone()
    del g[NODE].pos_seq, g[NODE].force_seq
    with torch.no_grad():
        traj = rollout(load_model(path), g, LONG_STEPS, sleep=None)
    store = g[NODE]
    return traj, store, torch.nonzero(store.is_leaf & ~store.is_static).flatten()


def _mean_pairwise(x):
    p = x.shape[-2]
    return (x[..., :, None, :] - x[..., None, :, :]).norm(dim=-1).sum(dim=(-1, -2)) / (p * (p - 1))


@slow
@pytest.mark.parametrize("scene", _xfail_unless(["cube_collision", "cube_push", "tower", "wedge", "multi_material"],
                                                RIGID_SHAPE_FAILURES))
def test_rigid_objects_keep_their_shape_for_a_thousand_steps(scene):
    traj, store, leaves = _resting_rollout(scene)
    rigid = leaves[store.material[leaves, 0].bool()]
    assert rigid.numel() > 0
    for obj in torch.unique(store.object[rigid]).tolist():  # a few objects per scene
        idx = rigid[store.object[rigid] == obj]
        change = _mean_pairwise(traj[-1, idx]) / _mean_pairwise(store.pos[idx]) - 1.0
        assert abs(float(change)) < RIGID_SHAPE_TOLERANCE, f"object {obj}: {100 * float(change):.2f} %"


@slow
@pytest.mark.parametrize("scene", _xfail_unless(RESTING_SCENES, REST_DRIFT_FAILURES))
def test_objects_at_rest_stay_at_rest_for_a_thousand_steps(scene):
    from hrn_pyg.evaluate.rest import object_centroids

    traj, store, leaves = _resting_rollout(scene)
    num_objects = int(store.object.max()) + 1
    centres = object_centroids(traj[SETTLE:, leaves], store.object[leaves], num_objects, store.mass[leaves, 0])
    present = torch.bincount(store.object[leaves], minlength=num_objects) > 0
    drift = (centres - centres[:1]).norm(dim=-1).amax(dim=0)[present]
    assert float(drift.max()) < REST_DRIFT, f"drift {drift.tolist()} m"
