"""The GNS baseline: its operator, its inputs, and that the package's step, rollout, sampling,
sleeping, training and loading run it unchanged."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hrn_pyg import rollout, sample
from hrn_pyg.checkpoints import load_model, with_applied_options
from hrn_pyg.cli import main
from hrn_pyg.data.graph import NODE, set_state
from hrn_pyg.nn.gns import EDGE_INPUTS, GNS, NODE_NUMBERS, GNSConfig, radius_graph
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.nn.networks import config_from_dict, network_from_dict
from hrn_pyg.sim.sleeping import SleepConfig
from hrn_pyg.sim.step import build_inputs, decode, predict, target_output
from hrn_pyg.train import TrainConfig, train

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from toy_scene import toy_scene, trajectory  # noqa: E402

TINY = GNSConfig(latent=8, hidden=8, depth=1, message_passing_steps=2, material_embedding=4)
#: the toy soft cube's leaves are 0.1 apart: a radius above that connects them within the object
WIDE = GNSConfig(latent=8, hidden=8, depth=1, message_passing_steps=2, material_embedding=4, collision_radius=0.15)


def _model(config: GNSConfig = TINY, seed: int = 0) -> GNS:
    torch.manual_seed(seed)
    model = GNS(config).eval()
    with torch.no_grad():  # a plausible normalisation: velocities of cm per step, accelerations of mm
        model.normalizer.velocity_std.fill_(0.01)
        model.acceleration_std.fill_(1e-3)
    return model


def _shifted(graph, shift: torch.Tensor):
    store = graph[NODE]
    return set_state(graph, store.prev_prev_pos + shift, store.prev_pos + shift, store.pos + shift, radius=0.08)


def test_message_passing_shapes():
    model, graph = _model(WIDE), toy_scene()
    inputs = build_inputs(model, graph)
    assert inputs.state.shape == (19, model.config.state_dim)
    leaves = torch.arange(14)
    nodes = model.node_features(inputs, leaves)
    assert nodes.shape == (14, NODE_NUMBERS + WIDE.material_embedding)
    pos = graph[NODE].pos[:14]
    edges = radius_graph(pos, WIDE.collision_radius)
    assert edges.shape[0] == 2 and edges.shape[1] > 0
    assert model.edge_features(pos, edges).shape == (edges.shape[1], EDGE_INPUTS)
    acc = model.network(nodes, model.edge_features(pos, edges), edges, torch.zeros(14, dtype=torch.long), {})
    assert acc.shape == (14, 3)
    out = model(inputs)
    assert out.shape == (19, 3)
    assert torch.equal(out[14:], torch.zeros(5, 3))  # ancestors: no output
    assert "M=2" in repr(model)


def test_radius_graph_connects_every_close_pair_within_and_between_objects():
    pos = toy_scene()[NODE].pos[:14]
    edges = radius_graph(pos, 0.15)
    found = set(map(tuple, edges.t().tolist()))
    d = torch.cdist(pos, pos)
    expected = {(j, i) for i in range(14) for j in range(14) if i != j and d[i, j] < 0.15}
    assert found == expected
    obj = torch.tensor([0] * 8 + [1] * 4 + [2] * 2)
    src, dst = edges
    assert bool((obj[src] == obj[dst]).any()) and bool((obj[src] != obj[dst]).any())


def test_edge_feature_by_hand():
    model = _model()
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.03, 0.0, 0.04]])
    edges = radius_graph(pos, 0.08)
    assert edges.tolist() == [[1, 0], [0, 1]]
    # edge 1 -> 0: (x_1 - x_0) / R = (0.375, 0, 0.5), |.| / R = 0.05 / 0.08 = 0.625
    feature = model.edge_features(pos, edges)[0]
    assert torch.allclose(feature, torch.tensor([0.375, 0.0, 0.5, 0.625]), atol=1e-6)


def test_inputs_and_prediction_are_translation_invariant():
    model, graph = _model(WIDE), toy_scene()
    base = build_inputs(model, graph)
    leaves = torch.arange(14)
    # tolerances: float32 positions of a shifted scene round differently, by about 1e-7 m, which
    # is 1e-5 of the 0.01 m/step velocity scale
    for shift in (torch.tensor([0.7, -0.3, 0.0]), torch.tensor([-2.0, 5.0, 0.0])):
        moved = _shifted(graph, shift)
        other = build_inputs(model, moved)
        assert torch.allclose(model.node_features(other, leaves), model.node_features(base, leaves), atol=1e-3)
        pos, pos_moved = graph[NODE].pos[:14], moved[NODE].pos[:14]
        e, e_moved = radius_graph(pos, 0.15), radius_graph(pos_moved, 0.15)
        assert torch.equal(e, e_moved)
        assert torch.allclose(model.edge_features(pos_moved, e), model.edge_features(pos, e), atol=1e-4)
        assert torch.allclose(model(other), model(base), atol=1e-3)
    # lifted by 1 m: the static body leaves the ground, the movable objects (clear of the ground
    # by more than R, and not connected to the static body) predict the same accelerations
    lifted = build_inputs(model, _shifted(graph, torch.tensor([0.0, 0.0, 1.0])))
    assert torch.allclose(model(lifted)[:12], model(base)[:12], atol=1e-5)


def test_decode_is_semi_implicit_euler_and_target_output_inverts_it():
    model, graph = _model(), toy_scene()
    store = graph[NODE]
    next_leaves = trajectory(3)[3]
    nxt = set_state(graph, store.prev_pos, store.pos, next_leaves, radius=None)[NODE].pos
    out = target_output(model, graph, nxt)
    assert torch.equal(out[14:], torch.zeros(5, 3))
    pos, local, velocity, _ = decode(model, graph, out)
    assert torch.allclose(pos[:12], nxt[:12], atol=1e-6)
    assert torch.equal(pos[12:14], store.pos[12:14])  # static leaves stay
    assert torch.allclose(velocity[:12], nxt[:12] - store.pos[:12], atol=1e-6)
    root = 16  # the soft cube's root: the mass-weighted mean velocity of its leaves
    assert torch.allclose(velocity[root], velocity[:8].mean(0), atol=1e-6)
    assert local.shape == (19, 3)


def test_rollout_sample_and_sleeping_run_it_unchanged():
    model, graph = _model(), toy_scene()
    with torch.no_grad():
        path = rollout(model, graph, 4, sleep=None)
        assert path.shape == (4, 14, 3) and bool(torch.isfinite(path).all())  # the leaves
        futures = sample(model, graph, k=3, steps=3, rate=0.2, generator=torch.Generator().manual_seed(1), sleep=None)
        assert futures.shape[0] == 3 and bool(torch.isfinite(futures).all())
        assert not torch.equal(futures[0], futures[1])  # each copy its own processor mask
        same = sample(model, graph, k=2, steps=3, rate=0.0, sleep=None)
        assert torch.allclose(same[0], path[:3], atol=1e-6)  # one convention: the leaves
        # the rigid square at rest, out of reach of the falling cube: with sleeping it is held
        # still (its objects asleep) while the cube's steps are those of the plain rollout
        far = toy_scene(separate=True)
        store = far[NODE]
        rest = store.pos.clone()
        prev = torch.where(torch.arange(19)[:, None].ge(8) & torch.arange(19)[:, None].lt(12), rest, store.prev_pos)
        prev2 = torch.where(torch.arange(19)[:, None].ge(8) & torch.arange(19)[:, None].lt(12), rest,
                            store.prev_prev_pos)
        far = set_state(far, prev2[:14], prev[:14], rest[:14], radius=0.08)
        asleep = rollout(model, far, 3, sleep=SleepConfig())
        awake = rollout(model, far, 3, sleep=None)
    assert torch.equal(asleep[:, 8:12], far[NODE].pos[8:12].expand(3, 4, 3))
    assert not torch.equal(awake[:, 8:12], asleep[:, 8:12])
    assert torch.allclose(asleep[:, :8], awake[:, :8], atol=1e-6)


def test_dropout_masks_follow_the_hrn_api():
    model, graph = _model(), toy_scene()
    masks = model.sample_masks(1, 0.3, torch.Generator().manual_seed(0))
    assert set(masks) == {"processor"} and masks["processor"].shape == (1, TINY.hidden)
    assert model.mask_rows(5) == 5
    inputs = build_inputs(model, graph)
    with torch.no_grad():
        plain = model(inputs)
        assert torch.equal(model(inputs, model.sample_masks(1, 0.0)), plain)
        assert not torch.equal(model(inputs, masks), plain)
    with pytest.raises(ValueError, match="dropout_modules"):
        model(inputs, {"force": masks["processor"]})


def test_rigid_fit_applies_to_a_trained_gns():
    model, graph = _model(), toy_scene()
    fitted = with_applied_options(model, rigid_fit=True)
    assert isinstance(fitted, GNS) and fitted.config.rigid_fit and not model.config.rigid_fit
    with torch.no_grad():
        pos = predict(fitted, graph).pos
    square, now = pos[8:12], graph[NODE].pos[8:12]
    assert torch.allclose(torch.cdist(square, square), torch.cdist(now, now), atol=1e-5)  # rigid
    with pytest.raises(ValueError, match="rigid_fit"):
        with_applied_options(model, mirror_average=True)


def test_network_field_picks_the_model():
    assert isinstance(config_from_dict(HRNConfig().to_dict()), HRNConfig)
    assert "network" not in HRNConfig().to_dict()  # HRN checkpoints are written as they were
    d = TINY.to_dict()
    assert d["network"] == "gns" and config_from_dict(d) == TINY
    assert isinstance(network_from_dict(d), GNS)
    with pytest.raises(ValueError, match="network"):
        config_from_dict({**d, "network": "mystery"})


def _losses(out: Path) -> list[tuple[int, float]]:
    with open(out / "metrics.csv") as fh:
        return [(int(r["step"]), float(r["loss"])) for r in csv.DictReader(fh)]


def test_train_preset_gns_resumes_and_round_trips(tiny_episodes, tmp_path):
    base = dict(data=str(tiny_episodes), steps=4, batch_size=2, checkpoint_every=2, eval_every=2, warmup=1,
                input_noise_ratio=0.0)
    full = TrainConfig.for_preset("gns", out=str(tmp_path / "full"), **base)
    assert (full.seq_end, full.lr) == (1, 1e-4)
    train(full, TINY, progress=False)
    part = TrainConfig.for_preset("gns", out=str(tmp_path / "part"), **base)
    train(part, TINY, progress=False, stop_after=2)
    train(part, TINY, progress=False, resume=True)
    assert [s for s, _ in _losses(tmp_path / "part")] == [0, 1, 2, 3]
    for (s1, l1), (s2, l2) in zip(_losses(tmp_path / "full"), _losses(tmp_path / "part")):
        assert l1 == pytest.approx(l2, rel=1e-5), f"step {s1}"
    model = load_model(tmp_path / "part" / "model.pt")
    assert isinstance(model, GNS) and model.config == TINY and model.normalizer.fitted
    assert float(model.acceleration_std.min()) > 0
    saved = torch.load(tmp_path / "part" / "model.pt", weights_only=True)["model"]
    assert all(torch.equal(model.state_dict()[k], v) for k, v in saved.items())
    graph = toy_scene()
    with torch.no_grad():
        assert torch.equal(predict(model, graph).pos, predict(load_model(tmp_path / "full" / "model.pt"), graph).pos)


def test_gns_noise_is_resolved_from_the_velocity_scale(tiny_episodes, tmp_path):
    config = TrainConfig.for_preset("gns", data=str(tiny_episodes), out=str(tmp_path / "n"), steps=1, batch_size=1,
                                    checkpoint_every=1, eval_every=1, warmup=1)
    train(config, TINY, progress=False)
    saved = json.loads((tmp_path / "n" / "config.json").read_text())
    velocity_std = load_model(tmp_path / "n" / "model.pt").normalizer.velocity_std.mean()
    assert saved["train"]["input_noise"] == pytest.approx(config.input_noise_ratio * float(velocity_std), rel=1e-5)
    assert saved["model"]["network"] == "gns"
    with pytest.raises(ValueError, match="gns preset"):
        TrainConfig.for_preset("gns", seq_end=4)


BLOCKED = """
import sys
for name in ("pybullet", "pybullet_data", "trimesh", "torchrl", "tensordict"):
    sys.modules[name] = None  # importing any of them now fails
from hrn_pyg.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_cli_trains_gns_without_the_simulator_or_torchrl(tiny_episodes, tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["train", "--preset", "gns", "--data", str(tiny_episodes), "--out", str(out), "--train-steps", "1",
            "--batch-size", "1", "--threads", "1", "--device", "cpu", "--no-progress", "--model-latent", "8",
            "--model-hidden", "8", "--model-message-passing-steps", "1"]
    done = subprocess.run([sys.executable, "-c", BLOCKED, *args], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / "model.pt").is_file()
    assert main([*args, "--model-rest-offsets", "true"]) == 2
    assert "not an option of the GNS" in capsys.readouterr().err
