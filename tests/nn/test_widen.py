"""A plain model widened into a pitch-aware one (hrn_pyg.nn.widen): the same predictions at the
reference pitch, bit for bit; the new column's weights zero; a start training moves them."""

import pytest
import torch

import hrn_pyg
from hrn_pyg.sim.rollout import rollout as rollout_nodes
from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.episodes import simulate_episode
from hrn_pyg.data.graph import set_pitch
from hrn_pyg.nn.mlp import MLP
from hrn_pyg.nn.widen import widen_state_blocks, widen_to_pitch_aware
from hrn_pyg.sampling.ensemble import episode_state


def test_widen_state_blocks_pads_each_state_block_with_zeros():
    weight = torch.arange(2 * 7, dtype=torch.float32).reshape(2, 7)  # two state blocks of 3, then 1
    wide = widen_state_blocks(weight, blocks=2, old_state=3, new_state=4)
    assert wide.shape == (2, 9)
    assert torch.equal(wide[:, [0, 1, 2, 4, 5, 6, 8]], weight)
    assert torch.equal(wide[:, [3, 7]], torch.zeros(2, 2))
    with pytest.raises(ValueError, match="cannot widen"):
        widen_state_blocks(weight, blocks=3, old_state=3, new_state=4)


@pytest.fixture(scope="module")
def drop_start():
    episode = simulate_episode("cube_collision", 9, steps=30)
    return episode_state(episode, start=12, steps=10)


@pytest.mark.parametrize("name", ["shapes_d4", "soft_bounce"])
def test_the_widened_model_predicts_as_the_plain_one_at_the_reference_pitch(drop_start, name):
    torch.set_num_threads(1)
    plain = load_model(name).eval()
    wide = widen_to_pitch_aware(plain).eval()
    assert wide.config.pitch_aware and wide.config.state_dim == plain.config.state_dim + 1
    state = drop_start.clone()
    set_pitch(state, plain.config.reference_pitch)
    with torch.no_grad():
        expected = rollout_nodes(plain, state, 10, sleep=None)
        got = rollout_nodes(wide, state, 10, sleep=None)
    assert torch.equal(got, expected)


def test_only_the_pitch_columns_are_new_and_they_start_at_zero():
    plain = load_model("shapes_d4")
    wide = widen_to_pitch_aware(plain, mirror_average=False)
    assert not wide.config.mirror_average and wide.training == plain.training
    state_dim = plain.config.state_dim
    for name, module in wide.named_modules():
        if isinstance(module, MLP):
            old = plain.get_submodule(name).hidden_layers[0].weight
            new = module.hidden_layers[0].weight
            blocks = (new.size(1) - old.size(1))
            assert blocks >= 1
            pitch_columns = [(i + 1) * (state_dim + 1) - 1 for i in range(blocks)]
            assert torch.equal(new[:, pitch_columns], torch.zeros(new.size(0), blocks))
            kept = [c for c in range(new.size(1)) if c not in pitch_columns]
            assert torch.equal(new[:, kept], old)


def test_a_pitch_aware_or_foreign_model_is_refused():
    wide = widen_to_pitch_aware(load_model("shapes_d4"))
    with pytest.raises(ValueError, match="pitch-aware already"):
        widen_to_pitch_aware(wide)
    with pytest.raises(ValueError, match="pitch-aware already"):
        widen_to_pitch_aware(load_model("shapes"))  # the shipped generalist reads the pitch
    with pytest.raises(ValueError, match="an HRN is needed"):
        widen_to_pitch_aware(load_model("gns_cube_collision"))


def test_train_init_from_a_plain_model_with_pitch_aware_widens_it(tmp_path):
    """``hrn-pyg train --init-from shapes_d4 --model-pitch-aware true --model-mirror-average false``:
    the widened start, one pass, and a step on windows of pitch 0.08 moves the pitch columns."""
    from hrn_pyg.cli import main

    coarse, out = tmp_path / "p008", tmp_path / "run"
    assert main(["generate", "--scene", "cube_collision", "--episodes", "2", "--episode-steps", "12",
                 "--pitch", "0.08", "--out", str(coarse), "--no-progress"]) == 0
    shapes = load_model("shapes_d4")
    assert main(["train", "--preset", "ours", "--data", str(coarse), "--out", str(out), "--init-from", "shapes_d4",
                 "--model-pitch-aware", "true", "--model-mirror-average", "false", "--model-rigid-fit", "true",
                 "--model-rest-offsets", "true", "--model-ground-contact", "true", "--train-steps", "2",
                 "--batch-size", "2", "--seq-end", "1", "--warmup", "1", "--threads", "1", "--no-progress"]) == 0
    trained = load_model(out / "model.pt")
    assert trained.config.pitch_aware and not trained.config.mirror_average
    state_dim = shapes.config.state_dim
    first = trained.history.phi.hidden_layers[0].weight  # [s(t), s(t-1)]: two pitch columns
    assert first.size(1) == shapes.history.phi.hidden_layers[0].weight.size(1) + 2
    assert first[:, state_dim].abs().sum() > 0  # the pitch column learnt from pitch 0.08 windows


@pytest.mark.parametrize("name", ["cube_collision", "equivariant"])
def test_a_model_made_to_read_the_force_in_collisions_predicts_as_before(drop_start, name):
    """The force's new weights start at zero: the same rollout, pushes included, and only the
    collision module's first layer (and the equivariant vector readout) grew."""
    from hrn_pyg.nn.hrn import HRN, HRNConfig
    from hrn_pyg.nn.normalizer import fit_normalizer, isotropic_horizontal
    from hrn_pyg.nn.widen import with_collision_force
    torch.set_num_threads(1)
    if name == "equivariant":
        torch.manual_seed(0)
        model = HRN(HRNConfig(hidden=16, effect_dim=8, vector_channels=3, equivariant=True, rigid_fit=True))
        fit_normalizer([drop_start], model.normalizer)
        isotropic_horizontal(model.normalizer)
        torch.nn.init.normal_(model.state.vector.weight, std=0.3)
        torch.nn.init.normal_(model.collision.vector.weight, std=0.3)
    else:
        model = load_model(name)
    model = model.eval()
    grown = with_collision_force(model).eval()
    assert grown.config.collision_force and not model.config.collision_force
    forces = torch.zeros(10, drop_start["particle"].num_nodes, 3)
    forces[:, :12] = torch.tensor([3.0, -1.0, 0.0])
    with torch.no_grad():
        expected = rollout_nodes(model, drop_start.clone(), 10, forces=forces, sleep=None)
        got = rollout_nodes(grown, drop_start.clone(), 10, forces=forces, sleep=None)
    torch.testing.assert_close(got, expected, atol=1e-6, rtol=0)
    changed = [k for k, v in grown.state_dict().items() if v.shape != model.state_dict()[k].shape]
    assert set(changed) <= {"collision.phi.hidden_layers.0.weight", "collision.vector.weight", "collision.vector.bias"}
    assert "collision.phi.hidden_layers.0.weight" in changed
    with pytest.raises(ValueError, match="reads the force already"):
        with_collision_force(grown)
