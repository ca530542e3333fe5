import io

import pytest
import torch
from torch_geometric.data import Batch
from toy_scene import toy_scene, toy_window

from hrn_pyg.data.graph import COLLISION, replicate
from hrn_pyg.nn.hrn import HRN, STATE_DIM, HRNConfig
from hrn_pyg.nn.mlp import dropout_mask
from hrn_pyg.nn.normalizer import fit_normalizer
from hrn_pyg.sim.step import build_inputs

SMALL = dict(hidden=16, depth=2, effect_dim=8)


def _model(seed=0, **kw):
    torch.manual_seed(seed)
    model = HRN(HRNConfig(**{**SMALL, **kw}))
    fit_normalizer([toy_window(4)], model.normalizer)
    return model


def test_config_validation_and_roundtrip():
    with pytest.raises(ValueError, match="dropout_modules"):
        HRNConfig(dropout_modules=("force", "gravity"))
    with pytest.raises(ValueError, match="dropout_rate"):
        HRNConfig(dropout_rate=1.0)
    with pytest.raises(ValueError, match="hidden"):
        HRNConfig(hidden=0)
    c = HRNConfig(dropout_modules=["force"], dropout_rate=0.1)
    assert HRNConfig.from_dict(c.to_dict()) == c


def test_output_shape_and_static_zero():
    model = _model()
    g = toy_scene(force=True)
    out = model(build_inputs(model, g))
    assert out.shape == (19, 3)
    assert build_inputs(model, g).state.shape == (19, STATE_DIM)
    assert torch.equal(out[g["particle"].is_static], torch.zeros(3, 3))
    assert torch.isfinite(out).all()


def _count_calls(module):
    calls = []
    module.register_forward_hook(lambda *a: calls.append(1))
    return calls


@pytest.mark.parametrize("scene", [dict(separate=True), dict(force=False)])
def test_idle_modules_skipped_and_equal_to_running_them(scene):
    skip, run = _model(skip_idle_modules=True), _model(skip_idle_modules=False)
    run.load_state_dict(skip.state_dict())
    g = toy_scene(**scene)
    if scene.get("separate"):
        assert g[COLLISION].edge_index.size(1) == 0
    force_calls, coll_calls = _count_calls(skip.force), _count_calls(skip.collision)
    out_skip = skip(build_inputs(skip, g))
    out_run = run(build_inputs(run, g))
    assert torch.equal(out_skip, out_run)
    assert force_calls == []  # the toy scene has no force unless asked
    assert (coll_calls == []) == bool(scene.get("separate"))


def test_active_modules_do_contribute():
    model = _model()
    g = toy_scene(force=True)
    with_force = model(build_inputs(model, g))
    without = model(build_inputs(model, g, torch.zeros(19, 3)))
    assert not torch.allclose(with_force, without)


def test_rate_zero_masks_equal_deterministic_and_masks_matter():
    model = _model(dropout_modules=("force", "collision"))
    g = toy_scene(force=True)
    inputs = build_inputs(model, g)
    plain = model(inputs)
    assert torch.equal(model(inputs, model.sample_masks(1, rate=0.0)), plain)
    masks = model.sample_masks(1, rate=0.5, generator=torch.Generator().manual_seed(0))
    assert set(masks) == {"force", "collision"} and masks["force"].shape == (1, 16)
    assert not torch.allclose(model(inputs, masks), plain)
    with pytest.raises(ValueError, match="history"):
        model(inputs, {"history": dropout_mask(1, 16, 0.1)})


def test_seeded_determinism_and_checkpoint_roundtrip():
    g = toy_scene(force=True)
    a, b = _model(seed=3), _model(seed=3)
    out = a(build_inputs(a, g))
    assert torch.equal(out, b(build_inputs(b, g)))
    assert not torch.equal(out, _model(seed=4)(build_inputs(a, g)))
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    assert "normalizer.velocity_std" in a.state_dict() and bool(a.state_dict()["normalizer.fitted"])
    c = HRN(a.config)
    c.load_state_dict(torch.load(io.BytesIO(buf.getvalue()), weights_only=True))
    assert torch.equal(c(build_inputs(c, g)), out)


def test_batched_copies_equal_each_alone():
    model = _model()
    g1, g2 = toy_scene(seed=0, force=True), toy_scene(seed=1)
    batch = Batch.from_data_list([g1, g2])
    out = model(build_inputs(model, batch))
    torch.testing.assert_close(out[:19], model(build_inputs(model, g1)))
    torch.testing.assert_close(out[19:], model(build_inputs(model, g2)))
    # one mask row per copy: dropping copy 1's units leaves copy 0 untouched
    masks = {"force": torch.stack([torch.ones(16), torch.zeros(16)]), "collision": torch.ones(2, 16)}
    torch.testing.assert_close(model(build_inputs(model, batch), masks)[:19], out[:19])
    assert "HRN(hidden=16" in repr(model)


def test_one_mask_per_copy_shared_by_its_nodes_and_edges():
    model = _model(dropout_modules=("force", "collision"))
    g = replicate(toy_scene(force=True), 2)
    inputs = build_inputs(model, g)
    gen = torch.Generator().manual_seed(0)
    row = model.sample_masks(1, rate=0.5, generator=gen)
    same = {k: v.expand(2, -1) for k, v in row.items()}
    out = model(inputs, same)
    # identical copies under the same mask row: identical predictions
    torch.testing.assert_close(out[:19], out[19:])
    torch.testing.assert_close(out[:19], model(build_inputs(model, toy_scene(force=True)), row))
    # independent rows per copy: the copies now differ
    masks = model.sample_masks(2, rate=0.5, generator=gen)
    assert not torch.equal(masks["force"][0], masks["force"][1])
    out2 = model(inputs, masks)
    assert not torch.allclose(out2[:19], out2[19:])


@pytest.mark.parametrize("equivariant", [False, True])
def test_with_collision_force_a_push_reaches_the_other_body_in_the_same_step(equivariant):
    """Objects are separate trees: in one pass only the collision module links them, so a push on
    one object changes the other's next step only when the collision module reads the force."""
    g = toy_scene()
    store = g["particle"]
    first = store.object == 0
    assert g[COLLISION].edge_index.size(1) > 0
    force = torch.zeros(store.num_nodes, 3)
    force[first & store.is_leaf.bool()] = torch.tensor([1.0, 0.5, 0.0])
    others = ~first & ~store.is_static.bool()
    for reads, reaches in ((False, False), (True, True)):
        model = _model(collision_force=reads, equivariant=equivariant, vector_channels=4).eval()
        if equivariant:
            from hrn_pyg.nn.normalizer import isotropic_horizontal
            isotropic_horizontal(model.normalizer)
            torch.nn.init.normal_(model.state.vector.weight, std=0.5)
        with torch.no_grad():
            still = model(build_inputs(model, g, torch.zeros_like(force)))
            pushed = model(build_inputs(model, g, force))
        changed = (pushed - still)[others].abs().max()
        assert (changed > 1e-6) == reaches, (reads, float(changed))
    config = HRNConfig(collision_force=True)
    assert HRNConfig.from_dict(config.to_dict()) == config and "collision_force=True" in repr(HRN(config))


def test_a_saved_config_with_a_removed_field_loads_at_its_old_default_only():
    """A checkpoint's config from before ``material_heads`` went holds it as False and still
    builds the same network; True describes a network this release does not build: one line."""
    from hrn_pyg.nn.networks import config_from_dict

    saved = {**HRNConfig(hidden=16).to_dict(), "material_heads": False}
    assert config_from_dict(saved) == HRNConfig(hidden=16)
    with pytest.raises(ValueError, match="material_heads, which hrn_pyg no longer builds"):
        config_from_dict({**saved, "material_heads": True})
