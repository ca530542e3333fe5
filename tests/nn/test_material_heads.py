"""``HRNConfig.material_heads``: one next-state head per material. Started from a one-head model
every head is a copy and the rollout is unchanged, bit for bit; each row meets its material's
head (sparse and dense paths agree, a scene of one material runs one head); a fine-tuning step
from a one-head checkpoint makes the heads differ."""

import pytest
import torch
from toy_scene import toy_model, toy_scene

from hrn_pyg.checkpoints import load_model
from hrn_pyg.data.graph import NODE
from hrn_pyg.nn.hrn import MATERIAL_COLUMNS
from hrn_pyg.nn.state import NextStateModule
from hrn_pyg.nn.widen import with_material_heads
from hrn_pyg.sim.rollout import rollout


def test_a_model_with_copied_heads_rolls_out_as_the_one_headtoy_model():
    plain = toy_model()
    heads = with_material_heads(plain).eval()
    assert heads.config.material_heads and len(heads.state.heads) == 3
    for head in heads.state.heads:
        for a, b in zip(head.parameters(), plain.state.psi.parameters()):
            assert torch.equal(a, b)
    graph = toy_scene()  # soft, rigid and static: three materials
    with torch.no_grad():
        assert torch.equal(rollout(heads, graph, 5, sleep=None), rollout(plain, graph, 5, sleep=None))
    with pytest.raises(ValueError, match="already"):
        with_material_heads(heads)


def test_each_row_meets_its_materials_head_and_dense_equals_sparse():
    torch.manual_seed(1)
    module = NextStateModule(12, 4, material_columns=(2, 6)).eval()
    state = torch.randn(9, 12)
    material = torch.tensor([0, 1, 2, 3, 0, 2, 1, 1, 3])
    state[:, 2:6] = torch.nn.functional.one_hot(material, 4).float()
    effect = torch.randn(9, 4)
    static = material == 3
    with torch.no_grad():
        sparse = module(state, effect, static)
        dense = module(state, effect, static, dense=True)
        x = torch.cat([state, effect], dim=-1)
        by_hand = torch.stack([module.heads[min(int(m), 2)](x[i:i + 1])[0] for i, m in enumerate(material)])
    assert torch.allclose(sparse, dense, atol=1e-6)
    assert torch.allclose(sparse[~static], by_hand[~static], atol=1e-6)
    assert torch.equal(sparse[static], torch.zeros(int(static.sum()), 3))
    one = torch.zeros(9, dtype=torch.long)  # every row rigid: the rigid head alone, on all rows
    state[:, 2:6] = torch.nn.functional.one_hot(one, 4).float()
    with torch.no_grad():
        assert torch.equal(module(state, effect), module.heads[0](torch.cat([state, effect], dim=-1)))


def test_the_material_columns_are_the_states_one_hot_code():
    graph = toy_scene()
    from hrn_pyg.sim.step import build_inputs

    state = build_inputs(toy_model(), graph).state
    start, stop = MATERIAL_COLUMNS
    assert torch.equal(state[:, start:stop], graph[NODE].material.to(state.dtype))


def test_train_init_from_a_one_head_checkpoint_grows_and_trains_the_heads(tmp_path):
    from hrn_pyg.cli import main

    data, out = tmp_path / "mm", tmp_path / "run"
    assert main(["generate", "--scene", "multi_material", "--episodes", "2", "--episode-steps", "10",
                 "--out", str(data), "--no-progress"]) == 0
    start = load_model("multi_material")
    assert main(["train", "--preset", "ours", "--data", str(data), "--out", str(out), "--init-from", "multi_material",
                 "--model-material-heads", "true", "--train-steps", "2", "--batch-size", "2", "--seq-end", "1",
                 "--warmup", "1", "--threads", "1", "--no-progress"]) == 0
    trained = load_model(out / "model.pt")
    assert trained.config.material_heads and not start.config.material_heads
    first = [head.hidden_layers[0].weight for head in trained.state.heads]
    assert not torch.equal(first[0], first[2])  # rigid and cloth rows trained their own heads
