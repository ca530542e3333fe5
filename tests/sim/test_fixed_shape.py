"""The fixed-shape rollout (hrn_pyg.sim.fixed_shape) gives the plain rollout's positions."""

from __future__ import annotations

import pytest
import torch
from stability.stability_helpers import fitted_model
from toy_scene import toy_scene

from hrn_pyg.data.effects import SceneEffects
from hrn_pyg.data.graph import NODE, replicate, set_pitch
from hrn_pyg.nn.hrn import StepOptions
from hrn_pyg.sampling.sample import make_masks_fn
from hrn_pyg.sim import fixed_shape
from hrn_pyg.sim.fixed_shape import FixedShapeConfig, fixed_shape_rollout
from hrn_pyg.sim.rollout import rollout

STEPS = 12


def pushes(n: int, at: tuple[int, ...]) -> torch.Tensor:
    forces = torch.zeros(STEPS, n, 3)
    for t in at:
        forces[t, 0] = torch.tensor([0.5, 0.0, 2.0])
    return forces


def plain(model, graph, forces=None, masks_fn=None, effects=None) -> torch.Tensor:
    with torch.no_grad():
        return rollout(model, graph, STEPS, forces, masks_fn, sleep=None, effects=effects)


@pytest.mark.parametrize("rigid_fit", [False, True])
@pytest.mark.parametrize("config", [FixedShapeConfig(), FixedShapeConfig(skin=0.05, check_every=3),
                                    FixedShapeConfig(skin=2.0, check_every=1)])
def test_equals_the_plain_rollout_bit_for_bit(rigid_fit, config):
    """Forces on some steps, collisions between the soft and the rigid body: the same positions,
    whatever the skin and the look-ahead."""
    model = fitted_model(rigid_fit=rigid_fit)
    graph = toy_scene()
    forces = pushes(graph[NODE].num_nodes, (2, 3))
    result = fixed_shape_rollout(model, graph, STEPS, forces, config=config)
    assert torch.equal(result.pos, plain(model, graph, forces))
    assert result.searches >= 1 and 1 <= result.host_reads <= STEPS


def test_sampled_copies_get_each_step_s_masks_once():
    """K copies with dropout: the masks of every step are drawn once (a rerun step keeps them),
    so the same generator seed gives the plain sampler's futures."""
    model = fitted_model(dropout_modules=("force", "collision"))
    k = 3
    graph = replicate(toy_scene(), k)
    forces = pushes(graph[NODE].num_nodes, (1,))
    calls = []
    masks = make_masks_fn(model, k, 0.2, torch.Generator().manual_seed(5))

    def counted(t, g):
        calls.append(t)
        return masks(t, g)

    result = fixed_shape_rollout(model, graph, STEPS, forces, counted)
    assert calls == list(range(STEPS))
    expected = plain(model, graph, forces, make_masks_fn(model, k, 0.2, torch.Generator().manual_seed(5)))
    assert torch.equal(result.pos, expected)


def test_a_stale_list_is_caught_and_the_steps_rerun(monkeypatch):
    """With the look-ahead forced long and a thin skin, lists go stale inside a run of steps: those
    steps are thrown away and rerun after a new search, and the positions do not change."""
    monkeypatch.setattr(fixed_shape, "_steps_within", lambda limit, moved, speed, most: most)
    model = fitted_model()
    graph = replicate(toy_scene(), 2)

    def masks(seed):
        return make_masks_fn(model, 2, 0.3, torch.Generator().manual_seed(seed))

    result = fixed_shape_rollout(model, graph, STEPS, masks_fn=masks(1), config=FixedShapeConfig(skin=0.02, check_every=6))
    assert result.repeated_steps > 0
    assert torch.equal(result.pos, plain(model, graph, masks_fn=masks(1)))


def test_a_scene_without_collisions_never_searches():
    model = fitted_model()
    graph = toy_scene(separate=True)
    result = fixed_shape_rollout(model, graph, STEPS, effects=SceneEffects(collisions=False))
    assert result.searches == 0 and result.repeated_steps == 0
    assert result.host_reads == -(-STEPS // FixedShapeConfig().check_every)  # one read per look-ahead
    assert torch.equal(result.pos, plain(model, graph, effects=SceneEffects(collisions=False)))


def test_a_diverging_model_is_stopped_as_the_plain_rollout_stops_it():
    model = fitted_model()
    with torch.no_grad():
        model.state.psi.output_layer.bias.fill_(float("inf"))
    with pytest.raises(ValueError, match="advance: pos contains NaN or infinite values"):
        plain(model, toy_scene())
    with pytest.raises(ValueError, match="advance: pos contains NaN or infinite values"):
        fixed_shape_rollout(model, toy_scene(), STEPS)


def test_bad_input():
    model = fitted_model()
    with pytest.raises(ValueError, match="skin must be > 0"):
        FixedShapeConfig(skin=0.0)
    with pytest.raises(ValueError, match="check_every must be >= 1"):
        FixedShapeConfig(check_every=0)
    with pytest.raises(ValueError, match="cuda_graph needs the graph on a CUDA device"):
        fixed_shape_rollout(model, toy_scene(), STEPS, config=FixedShapeConfig(cuda_graph=True))
    with pytest.raises(ValueError, match="steps must be >= 1"):
        fixed_shape_rollout(model, toy_scene(), 0)


@pytest.mark.parametrize("scene", ["tower", "cube_push"])
def test_shipped_model_on_a_pybullet_state(scene):
    """The shipped model of a scene with many contacts (tower: hundreds of candidate pairs) or
    pushes (cube_push: the dense force path), from a pybullet state: the same positions."""
    from stability.stability_helpers import trained_checkpoint

    from hrn_pyg.checkpoints import load_model
    from hrn_pyg.data.episodes import simulate_episode
    from hrn_pyg.sampling.ensemble import episode_state

    model = load_model(trained_checkpoint(scene)).eval()
    graph = episode_state(simulate_episode(scene, 3, steps=2 + STEPS), start=2)
    forces = graph[NODE].force_seq.transpose(0, 1).contiguous()
    result = fixed_shape_rollout(model, graph, STEPS, forces)
    assert torch.equal(result.pos, plain(model, graph, forces))


def _fixed_step_args(model, graph, masks: bool, device: str):
    """The fixed-shape step of ``model`` on ``graph`` and its tensor arguments, built on the CPU
    (the candidate search and the object count read the host) and then moved to ``device``."""
    from hrn_pyg.data.candidates import build_candidates
    from hrn_pyg.sim.step import object_of

    store = graph[NODE]
    radius = float(model.config.collision_radius)
    candidates = build_candidates(graph, store.pos, radius, 0.5 * radius)
    objects = object_of(graph) if model.config.rigid_fit else None
    names = tuple(sorted(model.config.dropout_modules)) if masks else ()
    mask_rows = model.mask_rows(1)
    mask_values = tuple(torch.ones(mask_rows, model.config.hidden) for _ in names)
    force = pushes(store.num_nodes, (0,))[0]
    args = (store.pos, store.prev_pos, store.prev_prev_pos, force, mask_values,
            candidates.edge_index, candidates.valid, candidates.reference)
    to = (lambda t: tuple(x.to(device) for x in t) if isinstance(t, tuple) else t.to(device))
    graph, model = graph.to(device), model.to(device)
    if objects is not None:
        objects = (objects[0].to(device), objects[1])
    options = StepOptions(force_active=True, objects=objects)
    step_fn = fixed_shape.make_step(model, graph, options, radius, 0.5 * radius, names)
    return step_fn, tuple(to(a) for a in args)


MODEL_OPTIONS = [
    dict(),
    dict(rigid_fit=True),
    dict(rest_offsets=True, ground_contact=True),
    dict(rigid_fit=True, ground_projection=True, rigid_ground_depth=0.5),
    dict(rigid_fit=True, ground_projection=True, rigid_ground_speed=0.1, ground_lift_velocity=False),
    dict(mirror_average=True),
    dict(mirror_average=True, mirror_planes="xy", rigid_fit=True),
    dict(skip_idle_modules=False),
    dict(equivariant=True, vector_channels=4),
    dict(equivariant=True, vector_channels=4, rigid_fit=True, rest_offsets=True, skip_idle_modules=False),
]


@pytest.mark.parametrize("options", MODEL_OPTIONS, ids=lambda o: ",".join(o) or "default")
@pytest.mark.parametrize("masks", [False, True], ids=["deterministic", "masked"])
def test_the_fixed_shape_step_never_reads_the_host(options, masks):
    """On the ``meta`` device every read of a value raises, so a step that runs there to the end
    asks the device nothing: for every model option, with and without dropout masks."""
    model = fitted_model(dropout_modules=("force", "collision"), **options)
    graph = set_pitch(toy_scene(), 0.1)  # read by the rigid ground depth
    step_fn, args = _fixed_step_args(model, graph, masks, "meta")
    next_pos, since, report = step_fn(*args)
    assert next_pos.device.type == "meta" and next_pos.shape == since.shape == graph[NODE].pos.shape
    assert report.shape == (3,)


def test_the_meta_check_catches_a_host_read(monkeypatch):
    """The check above is not vacuous: a host read inside the step raises on ``meta``."""
    from hrn_pyg.sim import step as step_module

    real = step_module.decode

    def reading_decode(model, graph, out, objects=None):
        bool(out.abs().sum() > 0)  # a host read
        return real(model, graph, out, objects)

    monkeypatch.setattr(step_module, "decode", reading_decode)
    step_fn, args = _fixed_step_args(fitted_model(), toy_scene(), False, "meta")
    with pytest.raises((NotImplementedError, RuntimeError)):
        step_fn(*args)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("options", MODEL_OPTIONS, ids=lambda o: ",".join(o) or "default")
def test_on_cuda_the_step_never_syncs_and_a_cuda_graph_rollout_equals_the_plain_one(options):
    """With ``set_sync_debug_mode("error")`` any synchronising call inside the step raises; the
    CUDA-graph rollout then gives the plain rollout's positions (run by benchmarks/device/check.sh)."""
    model = fitted_model(dropout_modules=("force", "collision"), **options)
    graph = set_pitch(toy_scene(), 0.1)  # read by the rigid ground depth
    step_fn, args = _fixed_step_args(model, graph, True, "cuda")
    step_fn(*args)  # warm-up: lazy initialisation may sync once
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        step_fn(*args)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    model, graph = model.cuda(), graph.to("cuda")
    forces = pushes(graph[NODE].num_nodes, (2, 3)).cuda()
    recorded = fixed_shape_rollout(model, graph, STEPS, forces, config=FixedShapeConfig(cuda_graph=True))
    assert torch.allclose(recorded.pos, plain(model, graph, forces), atol=1e-6, rtol=0)


def test_pruned_rigid_leaf_siblings_equal_the_plain_rollout_bit_for_bit():
    """A model without the rigid leaves' within-sibling edges: the rollout selects them once
    (``HierarchyConstants.within_siblings``), the fixed-shape steps read the same edges."""
    from hrn_pyg.checkpoints import with_applied_options

    model = with_applied_options(fitted_model(rigid_fit=True), rigid_leaf_siblings=False)
    graph = toy_scene()
    forces = pushes(graph[NODE].num_nodes, (2, 3))
    result = fixed_shape_rollout(model, graph, STEPS, forces)
    assert torch.equal(result.pos, plain(model, graph, forces))


@pytest.mark.parametrize("lift_velocity", [True, False], ids=["lift_is_motion", "lift_moves_x_t"])
def test_the_ground_projection_with_a_rigid_depth_equals_the_plain_rollout_bit_for_bit(lift_velocity):
    """The rigid square started 30 cm into the ground and lifted back to half a pitch under it
    each step (the node pitch read on the step's own device): the plain rollout's positions,
    whether the lift counts as motion or carries ``x_t`` with it."""
    from hrn_pyg.data.graph import leaf_to_ancestor_mean

    model = fitted_model(rigid_fit=True, ground_projection=True, rigid_ground_depth=0.5,
                         ground_lift_velocity=lift_velocity)
    graph = set_pitch(toy_scene(), 0.1)
    store = graph[NODE]
    for name in ("pos", "prev_pos", "prev_prev_pos"):
        value = store[name].clone()
        value[8:12, 2] -= 0.3
        store[name] = leaf_to_ancestor_mean(value, graph)
    result = fixed_shape_rollout(model, graph, STEPS)
    expected = plain(model, graph)
    assert torch.equal(result.pos, expected)
    assert expected[-1, 8:12, 2].min() >= -0.05 - 1e-6


def test_the_equivariant_network_equals_the_plain_rollout_bit_for_bit():
    """The fixed-shape step of the equivariant network (a random horizontal readout, so that it
    moves sideways): the plain rollout's positions."""
    model = fitted_model(rigid_fit=True, rest_offsets=True, equivariant=True, vector_channels=4)
    torch.nn.init.normal_(model.state.vector.weight, std=0.3)
    graph = toy_scene()
    forces = pushes(graph[NODE].num_nodes, (2, 3))
    result = fixed_shape_rollout(model, graph, STEPS, forces)
    expected = plain(model, graph, forces)
    assert torch.equal(result.pos, expected)
    assert (expected[-1, :, :2] - graph[NODE].pos[:, :2]).abs().max() > 0


def test_compiled_steps_equal_the_plain_rollout_to_rounding():
    """``compile=True``: each kind of step compiled once (here with and without a push, and
    the numpy polar rotation swapped for the torch one under the compiler); the positions are
    the plain rollout's up to float32 rounding, and a second rollout reuses the compiled steps."""
    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    forces = pushes(graph[NODE].num_nodes, (2,))
    expected = plain(model, graph, forces)
    sim = fixed_shape.FixedShapeSimulator(model, graph, FixedShapeConfig(compile=True))
    with torch.no_grad():
        first = sim.rollout(STEPS, forces)
        kinds = len(sim._steps)
        again = sim.rollout(STEPS, forces)
    torch.testing.assert_close(first.pos, expected, rtol=0, atol=1e-5)
    assert torch.equal(again.pos, first.pos) and len(sim._steps) == kinds == 2


def test_own_code_is_the_same_function_on_a_code_object_of_its_own():
    scale = 3.0

    def triple(x):
        return scale * x

    copy = fixed_shape.own_code(triple)
    assert copy.__code__ is not triple.__code__ and copy(torch.ones(2)).tolist() == [3.0, 3.0]


def test_compiled_steps_keep_guards_on_their_inputs_and_follow_a_changing_candidate_count():
    """The compiled steps drop the guards on the model and the static graph
    (:func:`~hrn_pyg.sim.fixed_shape.step_input_guards`) but keep those on their arguments: with
    frequent searches the candidate list changes length from step to step, and every step
    still gives the plain rollout's positions."""
    from types import SimpleNamespace as Guard

    kept = fixed_shape.step_input_guards([
        Guard(guard_type="TENSOR_MATCH", name="pos"), Guard(guard_type="TENSOR_MATCH", name="masks[0]"),
        Guard(guard_type="TENSOR_MATCH", name="edge_index"), Guard(guard_type="GRAD_MODE", name=""),
        Guard(guard_type="SHAPE_ENV", name=""), Guard(guard_type="TENSOR_MATCH", name="model._modules['ws']"),
        Guard(guard_type="NOT_PRESENT_IN_GENERIC_DICT", name="___stack0._node_store_dict['particle']"),
        Guard(guard_type="CLOSURE_MATCH", name="G['__import_hrn_pyg']"),
    ])
    assert kept == [True, True, True, True, True, False, False, False]

    model = fitted_model(rigid_fit=True)
    graph = toy_scene()
    forces = pushes(graph[NODE].num_nodes, (2, 6))
    expected = plain(model, graph, forces)
    sim = fixed_shape.FixedShapeSimulator(model, graph, FixedShapeConfig(compile=True, skin=0.05, check_every=1))
    with torch.no_grad():
        sim.rollout(STEPS, forces)
        counts = []
        for key, step in list(sim._steps.items()):
            def recording(*args, step=step):
                counts.append(args[5].size(1))
                return step(*args)
            sim._steps[key] = recording
        again = sim.rollout(STEPS, forces)
    assert len(set(counts)) > 1, counts
    torch.testing.assert_close(again.pos, expected, rtol=0, atol=1e-5)


def _solid_clearance_model():
    """The toy model with the solid clearance (a rule that reads the step's contacts) and the
    energy limit, on the toy scene at a pitch of 0.1 m, where the clearance moves leaves."""
    from hrn_pyg.checkpoints import with_applied_options

    model = fitted_model(rigid_fit=True)
    graph = set_pitch(toy_scene(), 0.1)
    kept = with_applied_options(model, solid_clearance=0.3, energy_limit=True)
    assert not torch.equal(plain(kept, graph), plain(with_applied_options(model, energy_limit=True), graph))
    return kept, graph


@pytest.mark.parametrize("config", [FixedShapeConfig(), FixedShapeConfig(skin=0.05, check_every=1),
                                    FixedShapeConfig(skin=2.0, check_every=3)])
def test_rules_that_read_the_contacts_run_after_the_fixed_shape_part_bit_for_bit(config):
    """A model whose clearance moves leaves: the split step (network fixed-shape, every rule after
    it on the collision edges from the candidate list) gives the plain rollout's positions,
    whatever the skin and the look-ahead (a stale list's steps run again with the rules)."""
    kept, graph = _solid_clearance_model()
    result = fixed_shape_rollout(kept, graph, STEPS, config=config)
    assert torch.equal(result.pos, plain(kept, graph))


def test_rules_that_read_the_contacts_run_after_a_compiled_network():
    kept, graph = _solid_clearance_model()
    sim = fixed_shape.FixedShapeSimulator(kept, graph, FixedShapeConfig(compile=True))
    assert sim.host_rules is not None and sim.rules is None
    with torch.no_grad():
        result = sim.rollout(STEPS)
    torch.testing.assert_close(result.pos, plain(kept, graph), rtol=0, atol=1e-5)


def test_a_cuda_graph_refuses_rules_that_read_the_contacts_in_one_line():
    kept, graph = _solid_clearance_model()
    with pytest.raises(ValueError, match=r"read the step's contacts \(solid_clearance=0\.3\).*compile=True"):
        fixed_shape_rollout(kept, graph, STEPS, config=FixedShapeConfig(cuda_graph=True))


def test_holding_failed_copies_changes_nothing_while_every_copy_is_finite():
    """``hold_failed``: the same positions, and every copy's failure step is ``steps`` (never);
    without it there is no record."""
    model = fitted_model(rigid_fit=True)
    graph = replicate(toy_scene(), 2)
    held = fixed_shape_rollout(model, graph, STEPS, hold_failed=True)
    plain_result = fixed_shape_rollout(model, graph, STEPS)
    assert torch.equal(held.pos, plain_result.pos) and plain_result.failed_at is None
    assert held.failed_at.tolist() == [STEPS, STEPS]


def test_a_diverging_copy_is_held_on_the_device_and_its_step_recorded():
    """The network's output made infinite on one copy's rows from the fourth step: that copy is
    held where it was (zero velocity) and recorded as failed at step 3; the other copy moves as
    it does alone."""
    from hrn_pyg.sim import step as step_module

    model = fitted_model(rigid_fit=True)
    one = toy_scene()
    n = one[NODE].num_nodes
    graph = replicate(one, 2)
    calls = []
    original = step_module.predict

    def breaking(model, graph, *args, **kwargs):
        prediction = original(model, graph, *args, **kwargs)
        calls.append(1)
        if len(calls) >= 4:
            pos = prediction.pos.clone()
            pos[n] = float("inf")
            prediction = prediction._replace(pos=pos)
        return prediction

    fixed_shape.predict = breaking
    try:
        result = fixed_shape_rollout(model, graph, STEPS, config=FixedShapeConfig(check_every=1), hold_failed=True)
    finally:
        fixed_shape.predict = original
    assert result.failed_at.tolist() == [STEPS, 3]
    assert bool(torch.isfinite(result.pos).all())
    assert torch.equal(result.pos[3:, n:], result.pos[2, n:].expand(STEPS - 3, -1, -1))
    alone = fixed_shape_rollout(model, one, STEPS).pos
    assert torch.equal(result.pos[:, :n], alone)
