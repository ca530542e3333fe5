"""Monte Carlo graph-convolutional dropout sampling: hrn_pyg.sampling.sample."""

from __future__ import annotations

import copy
import os

import pytest
import torch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.graph import NODE
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sampling.sample import make_masks_fn, sample
from hrn_pyg.sim.rollout import rollout

STEPS = 4
LEAVES = 14
#: a force large enough that the force module's dropout visibly changes the trajectory
PUSH = torch.tensor([20.0, 0.0, 40.0])


@pytest.fixture(scope="module")
def model() -> HRN:
    torch.manual_seed(0)
    m = HRN(HRNConfig(hidden=16, effect_dim=16, depth=2))
    fit_normalizer([toy_window(4, seed) for seed in range(3)], m.normalizer)
    return m.eval()


def scene_and_forces():
    graph = toy_scene(force=True)
    forces = torch.zeros(STEPS, graph[NODE].num_nodes, 3)
    forces[:, 0] = PUSH
    return graph, forces


def deterministic(model: HRN, graph, forces) -> torch.Tensor:
    with torch.no_grad():
        return rollout(model, graph, STEPS, forces)[:, :LEAVES]


def test_output_shape_is_k_steps_leaves(model):
    graph, forces = scene_and_forces()
    out = sample(model, graph, 3, STEPS, 0.2, forces=forces, generator=torch.Generator().manual_seed(0))
    assert out.shape == (3, STEPS, LEAVES, 3)
    assert torch.isfinite(out).all()


def test_rate_zero_equals_deterministic_exactly(model):
    graph, forces = scene_and_forces()
    out = sample(model, graph, 5, STEPS, 0.0, forces=forces)
    det = deterministic(model, graph, forces)
    for b in range(5):
        assert torch.equal(out[b], det)


def test_leaf_forces_equal_node_forces(model):
    graph, forces = scene_and_forces()
    gen = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    a = sample(model, graph, 2, STEPS, 0.3, forces=forces, generator=gen())
    b = sample(model, graph, 2, STEPS, 0.3, forces=forces[:, :LEAVES], generator=gen())
    assert torch.equal(a, b)


def test_seeded_sampling_repeats_and_seeds_differ(model):
    graph, forces = scene_and_forces()
    a = sample(model, graph, 4, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(7))
    b = sample(model, graph, 4, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(7))
    c = sample(model, graph, 4, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def recorded_masks(model: HRN, k: int, rate: float, seed: int) -> list[dict[str, torch.Tensor]]:
    """The masks ``sample`` draws with this seed: one ``make_masks_fn`` call per step, in order."""
    fn = make_masks_fn(model, k, rate, torch.Generator().manual_seed(seed))
    return [dict(fn(t, None)) for t in range(STEPS)]


def test_masks_differ_across_trajectories_and_steps(model):
    masks = recorded_masks(model, 4, 0.5, seed=1)
    assert set(masks[0]) == {"force", "collision"}
    for step in masks:
        for table in step.values():
            assert table.shape == (4, model.config.hidden)
            assert len({tuple(row.tolist()) for row in table}) == 4  # one distinct mask per copy
    for name in ("force", "collision"):
        assert not torch.equal(masks[0][name], masks[1][name])  # fresh masks every step


def test_each_copy_equals_a_single_run_with_its_own_mask(model):
    """The batched copy b equals a one-copy rollout fed row b of each step's mask table: the mask
    is indexed by the copy's batch id and shared by all of its nodes and edges."""
    graph, forces = scene_and_forces()
    k, rate, seed = 3, 0.4, 11
    batched = sample(model, graph, k, STEPS, rate, forces=forces, generator=torch.Generator().manual_seed(seed))
    masks = recorded_masks(model, k, rate, seed)
    det = deterministic(model, graph, forces)
    for b in range(k):
        def one_copy(t, g, b=b):
            return {name: table[b : b + 1] for name, table in masks[t].items()}

        with torch.no_grad():
            single = rollout(model, graph, STEPS, forces, one_copy)[:, :LEAVES]
        torch.testing.assert_close(batched[b], single, rtol=0, atol=1e-7)
        assert (batched[b] - det).abs().max() > 1e-5  # the mask did change this trajectory
    assert (batched[0] - batched[1]).abs().max() > 1e-5


def test_mask_rows_follow_the_batch_id(model):
    """What the masked MLPs receive: every row of copy b is given index b (one mask per copy)."""
    graph, forces = scene_and_forces()
    seen = []
    hook = model.force.phi.register_forward_pre_hook(lambda mod, args: seen.append(args))
    try:
        sample(model, graph, 3, 1, 0.3, forces=forces, generator=torch.Generator().manual_seed(0))
    finally:
        hook.remove()
    x, mask, index = seen[0]
    assert mask.shape == (3, model.config.hidden)
    assert index.tolist() == [0, 1, 2]  # leaf 0 of each copy carries the force


def test_modules_subset_masks_only_those(model):
    graph, forces = scene_and_forces()
    fn = make_masks_fn(model, 2, 0.3, torch.Generator().manual_seed(0), modules=("force",))
    assert set(fn(0, graph)) == {"force"}
    with pytest.raises(ValueError, match="history"):
        sample(model, graph, 2, STEPS, 0.3, modules=("history",))


def test_window_fields_are_not_copied_and_input_untouched(model):
    window = toy_window(STEPS)
    before = {key: value.clone() for key, value in window[NODE].items() if torch.is_tensor(value)}
    out = sample(model, window, 2, STEPS, 0.3, generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, STEPS, LEAVES, 3)
    assert "pos_seq" in window[NODE] and "force_seq" in window[NODE]
    for key, value in before.items():
        assert torch.equal(window[NODE][key], value)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"k": 0}, "k must"),
        ({"k": 2.0}, "k must"),
        ({"steps": 0}, "steps must"),
        ({"rate": 1.0}, "rate must"),
        ({"rate": -0.1}, "rate must"),
        ({"forces": torch.zeros(STEPS, 5, 3)}, "forces must"),
        ({"forces": torch.zeros(STEPS - 1, 19, 3)}, "forces must"),
    ],
)
def test_bad_arguments_raise(model, kwargs, match):
    graph, _ = scene_and_forces()
    args = {"k": 2, "steps": STEPS, "rate": 0.3} | kwargs
    with pytest.raises(ValueError, match=match):
        sample(model, graph, **args)


@pytest.mark.parametrize("field", ["pos", "prev_pos", "prev_prev_pos"])
def test_nan_in_state_names_the_field(model, field):
    graph, _ = scene_and_forces()
    graph[NODE][field] = graph[NODE][field].clone()
    graph[NODE][field][3, 1] = float("nan")
    with pytest.raises(ValueError, match=f"'{field}'"):
        sample(model, graph, 2, STEPS, 0.3)


def test_missing_state_and_batches_are_rejected(model):
    graph, _ = scene_and_forces()
    del graph[NODE]["prev_prev_pos"]
    with pytest.raises(ValueError, match="prev_prev_pos"):
        sample(model, graph, 2, STEPS, 0.3)
    from hrn_pyg.data.graph import replicate

    with pytest.raises(ValueError, match="one scene"):
        sample(model, replicate(toy_scene(), 2), 2, STEPS, 0.3)


def test_explicit_cpu_device_and_a_caller_graph_left_in_place(model):
    """``sample`` runs where the model is (here ``torch.device("cpu")``, named explicitly),
    leaves the caller's graph where it was, and matches the implicit-device run."""
    graph, forces = scene_and_forces()
    on_cpu = model.to(torch.device("cpu"))
    out = sample(on_cpu, graph, 2, STEPS, 0.3, forces=forces,
                 generator=torch.Generator(device=torch.device("cpu")).manual_seed(4))
    assert out.device == torch.device("cpu") and graph[NODE].pos.device == torch.device("cpu")
    again = sample(model, graph, 2, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(4))
    assert torch.equal(out, again)


def test_masks_from_a_generator_on_another_device_are_moved_to_the_model():
    """A CPU generator driving a model elsewhere (the meta device stands in for CUDA) draws on
    the CPU, the numbers a CPU model gets, and hands the masks over on the model's device."""
    from hrn_pyg.sampling.sample import draw_masks

    cpu_model = HRN(HRNConfig(hidden=8, effect_dim=8, depth=2))
    elsewhere = HRN(HRNConfig(hidden=8, effect_dim=8, depth=2)).to("meta")
    moved = draw_masks(elsewhere, 3, 0.4, torch.Generator().manual_seed(2))
    expected = cpu_model.sample_masks(3, 0.4, torch.Generator().manual_seed(2))
    assert moved.keys() == expected.keys()
    for name, mask in moved.items():
        assert mask.device.type == "meta" and mask.shape == expected[name].shape
    gen = torch.Generator().manual_seed(2)
    masks = make_masks_fn(elsewhere, 3, 0.4, gen)(0, None)
    assert all(m.device.type == "meta" for m in masks.values())
    assert torch.equal(gen.get_state(), _after(expected, seed=2))


def _after(masks: dict, seed: int) -> torch.Tensor:
    """State of a CPU generator after drawing tables the size of ``masks``, in order."""
    gen = torch.Generator().manual_seed(seed)
    for table in masks.values():
        torch.rand(table.shape, generator=gen)
    return gen.get_state()


@pytest.mark.skipif(os.environ.get("HRN_SLOW") != "1", reason="compiles the network (tens of seconds): HRN_SLOW=1")
def test_compiled_network_samples_the_same_futures():
    torch.manual_seed(0)
    eager = HRN(HRNConfig(hidden=16, effect_dim=16, depth=2))
    fit_normalizer([toy_window(4, seed) for seed in range(3)], eager.normalizer)
    eager.eval()
    compiled = copy.deepcopy(eager)
    compiled.compile()
    graph, forces = scene_and_forces()
    runs = [sample(m, graph, 3, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(2))
            for m in (eager, compiled)]
    assert torch.allclose(runs[0], runs[1], atol=1e-5)
    assert not torch.equal(runs[0][0], runs[0][1])  # the copies do differ: masks reached the network


def test_fixed_shape_steps_sample_the_same_futures(model):
    """``fixed_shape=`` (no host read inside a step) gives the futures of ``sleep=None`` with the
    same generator seed, and refuses to run with sleeping on."""
    from hrn_pyg.sim.fixed_shape import FixedShapeConfig

    graph, forces = scene_and_forces()

    def draw(**kwargs):
        return sample(model, graph, 3, STEPS, 0.3, forces=forces, generator=torch.Generator().manual_seed(4),
                      sleep=None, **kwargs)

    assert torch.equal(draw(fixed_shape=FixedShapeConfig(check_every=2)), draw())
    with pytest.raises(ValueError, match="pass sleep=None"):
        sample(model, graph, 3, STEPS, 0.3, forces=forces, fixed_shape=FixedShapeConfig())
