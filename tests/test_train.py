import csv
import dataclasses
import json
import math
import os
import subprocess
import sys

import pytest
import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.cli import main
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.train import TrainConfig, draw_windows, parse_data_weights, train, window_draw_weights

SMALL = HRNConfig(hidden=16, depth=1, effect_dim=16)


def _config(data, out, preset="ours", **kw):
    base = dict(data=str(data), out=str(out), steps=6, batch_size=2, checkpoint_every=2, eval_every=3, warmup=2)
    base.update(kw)
    return TrainConfig.for_preset(preset, **base)


def _losses(out):
    with open(out / "metrics.csv") as fh:
        return [(int(r["step"]), float(r["loss"])) for r in csv.DictReader(fh)]


def test_presets_set_loss_and_schedule():
    hrn, ours = TrainConfig.for_preset("hrn"), TrainConfig.for_preset("ours")
    assert (hrn.shape_loss, hrn.seq_end) == ("group", 1)
    assert (ours.shape_loss, ours.seq_start, ours.seq_end) == ("full", 1, 6)
    with pytest.raises(ValueError, match="preset"):
        TrainConfig(preset="big")
    with pytest.raises(ValueError, match="lr"):
        TrainConfig.for_preset("ours", lr=-1.0)
    with pytest.raises(ValueError, match=r"threads must be >= 0 \(0: torch's default\), got -1"):
        TrainConfig.for_preset("ours", threads=-1)


def test_seeded_runs_are_identical(tiny_episodes, tmp_path):
    train(_config(tiny_episodes, tmp_path / "a", seq_end=3), SMALL, progress=False)
    train(_config(tiny_episodes, tmp_path / "b", seq_end=3), SMALL, progress=False)
    assert _losses(tmp_path / "a") == _losses(tmp_path / "b")
    assert len(_losses(tmp_path / "a")) == 6


def test_resume_gives_the_same_next_losses(tiny_episodes, tmp_path):
    cfg_full = _config(tiny_episodes, tmp_path / "full", seq_end=3, train_dropout=0.1)
    train(cfg_full, SMALL, progress=False)
    cfg_part = _config(tiny_episodes, tmp_path / "part", seq_end=3, train_dropout=0.1)
    train(cfg_part, SMALL, progress=False, stop_after=3)
    assert not (tmp_path / "part" / "model.pt").exists()
    assert torch.load(tmp_path / "part" / "last.pt", weights_only=True)["step"] == 3
    train(cfg_part, SMALL, progress=False, resume=True)
    full, part = _losses(tmp_path / "full"), _losses(tmp_path / "part")
    assert [s for s, _ in part] == list(range(6))
    for (s1, l1), (s2, l2) in zip(full, part):
        assert s1 == s2 and l1 == pytest.approx(l2, rel=1e-5), f"step {s1}"
    model = load_model(tmp_path / "part" / "model.pt")
    assert model.normalizer.fitted


def test_a_weight_average_is_the_kept_model_and_resumes_to_the_same_average(tiny_episodes, tmp_path):
    """ema_decay: model.pt and the snapshots hold the average of the weights (not the last
    weights, which last.pt keeps beside it), and a run stopped and resumed ends with the same
    average as one run straight through."""
    kw = dict(seq_end=3, ema_decay=0.6, snapshot_every=3)
    train(_config(tiny_episodes, tmp_path / "full", **kw), SMALL, progress=False)
    train(_config(tiny_episodes, tmp_path / "part", **kw), SMALL, progress=False, stop_after=3)
    train(_config(tiny_episodes, tmp_path / "part", **kw), SMALL, progress=False, resume=True)
    full, part = (torch.load(tmp_path / run / "model.pt", weights_only=True)["model"] for run in ("full", "part"))
    for name, value in full.items():
        assert torch.allclose(value, part[name], rtol=0, atol=1e-6), name
    last = torch.load(tmp_path / "full" / "last.pt", weights_only=True)
    params = last["weight_average"]
    assert params and all(torch.equal(full[name], value) for name, value in params.items())
    assert any(not torch.equal(last["model"][name], value) for name, value in params.items())
    assert all(torch.equal(last["model"][name], full[name]) for name in full if name not in params)  # buffers: the model's
    snap = torch.load(tmp_path / "full" / "snapshots" / "step_00006.pt", weights_only=True)["model"]
    assert all(torch.equal(snap[name], full[name]) for name in full)
    with pytest.raises(ValueError, match="ema_decay must be in"):
        _config(tiny_episodes, tmp_path / "bad", ema_decay=1.0)


def test_training_lowers_the_loss(tiny_episodes, tmp_path):
    cfg = _config(tiny_episodes, tmp_path / "fit", preset="hrn", steps=60, lr=3e-3, batch_size=4,
                  checkpoint_every=100, eval_every=100)
    train(cfg, SMALL, progress=False)
    losses = [l for _, l in _losses(tmp_path / "fit")]
    assert sum(losses[-10:]) / 10 < 0.5 * sum(losses[:10]) / 10
    assert (tmp_path / "fit" / "loss.png").stat().st_size > 1000
    saved = json.loads((tmp_path / "fit" / "config.json").read_text())
    assert saved["train"]["preset"] == "hrn"


def test_cli_errors_are_one_line(tiny_episodes, tmp_path, capsys):
    assert main(["train", "--preset", "ours", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
    assert main(["train", "--preset", "ours", "--data", str(tiny_episodes), "--out", str(tmp_path / "o"),
                 "--lr", "-1"]) == 2
    assert "lr" in capsys.readouterr().err
    assert main(["train", "--preset", "ours", "--data", str(tiny_episodes), "--out", str(tmp_path / "o2"),
                 "--resume"]) == 2
    capsys.readouterr()
    assert main(["train", "--preset", "ours", "--data", str(tiny_episodes), "--out", str(tmp_path / "o3"),
                 "--data-weights", "elsewhere=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'elsewhere' is not a folder" in err[0]


#: Run under torchrun: ``hrn-pyg train`` with the rest of argv, recording on every rank the
#: windows it drew and its gradients before and after the all-reduce, then saving them with the
#: rank's final weights to ``<argv[1]>/rank<R>.pt`` (train.py writes rank 0's model only).
RANK_RECORDER = """
import os
import sys

import torch

import hrn_pyg.train.loader as loader
import hrn_pyg.train.loop as loop
from hrn_pyg.cli import main

seen = {"windows": [], "before": [], "after": [], "model": None}
draw_windows, average_gradients = loader.draw_windows, loop.average_gradients


def flat_gradients(model):
    return torch.cat([torch.zeros_like(p).flatten() if p.grad is None else p.grad.detach().flatten().clone()
                      for p in model.parameters()])


def recording_draw(*args, **kwargs):
    ids = draw_windows(*args, **kwargs)
    seen["windows"].append(list(ids))
    return ids


def recording_average(model):
    seen["model"] = model
    seen["before"].append(flat_gradients(model))
    average_gradients(model)
    seen["after"].append(flat_gradients(model))


loader.draw_windows = recording_draw  # where the loader draws each step's windows
loop.average_gradients = recording_average  # where the loop averages the ranks' gradients
code = main(sys.argv[2:])
torch.save({"windows": seen["windows"], "before": torch.stack(seen["before"]), "after": torch.stack(seen["after"]),
            "weights": seen["model"].state_dict()}, os.path.join(sys.argv[1], f"rank{os.environ['RANK']}.pt"))
sys.exit(code)
"""


def test_data_parallel_under_torchrun(tiny_episodes, tmp_path):
    out, ranks = tmp_path / "ddp", tmp_path / "ranks"
    ranks.mkdir()
    script = tmp_path / "record_ranks.py"
    script.write_text(RANK_RECORDER)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", str(script), str(ranks), "train",
           "--preset", "hrn", "--data", str(tiny_episodes), "--out", str(out), "--train-steps", "3", "--batch-size", "1",
           "--model-hidden", "16", "--model-depth", "1", "--model-effect-dim", "16", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((out / "config.json").read_text())["world_size"] == 2
    assert len(_losses(out)) == 3

    rank0, rank1 = (torch.load(ranks / f"rank{r}.pt", weights_only=True) for r in (0, 1))
    # the ranks drew their own windows (by chance the same one at some steps); where the windows
    # differed, so did the ranks' own gradients, and unsynced weights would have parted there ...
    assert len(rank0["windows"]) == len(rank1["windows"]) == 3
    same_windows = [w0 == w1 for w0, w1 in zip(rank0["windows"], rank1["windows"])]
    assert not all(same_windows)
    same_gradients = [torch.equal(g0, g1) for g0, g1 in zip(rank0["before"], rank1["before"])]
    assert same_gradients == same_windows
    # ... and the all-reduce gave both their mean, so they took the same steps
    torch.testing.assert_close(rank0["after"], (rank0["before"] + rank1["before"]) / 2)
    assert torch.equal(rank0["after"], rank1["after"])
    assert rank0["weights"].keys() == rank1["weights"].keys()
    for key, value in rank0["weights"].items():
        assert torch.equal(value, rank1["weights"][key]), key
    # rank 0's weights are the ones written to model.pt
    saved = load_model(out / "model.pt").state_dict()
    for key, value in rank0["weights"].items():
        assert torch.equal(value, saved[key]), key


def test_time_limit_stops_like_an_interruption(tiny_episodes, tmp_path):
    out = tmp_path / "run"
    train(_config(tiny_episodes, out, steps=50, time_limit=1e-5), SMALL, progress=False)
    stopped = torch.load(out / "last.pt", weights_only=True)["step"]
    assert 1 <= stopped < 50 and not (out / "model.pt").exists()
    train(_config(tiny_episodes, out, steps=50), SMALL, resume=True, progress=False)
    assert [s for s, _ in _losses(out)] == list(range(50)) and (out / "model.pt").exists()


def test_stop_at_keeps_an_early_point_of_the_longer_schedule(tiny_episodes, tmp_path):
    """``stop_at``: the run ends after that many steps of the ``steps``-long schedule, and its
    model.pt equals the full run's model at that step (same losses, same learning rates)."""
    full, early = tmp_path / "full", tmp_path / "early"
    train(_config(tiny_episodes, full, steps=6, snapshot_every=3), SMALL, progress=False)
    train(_config(tiny_episodes, early, steps=6, stop_at=3), SMALL, progress=False)
    assert _losses(early) == _losses(full)[:3]
    lrs = [[float(r["lr"]) for r in csv.DictReader(open(out / "metrics.csv"))] for out in (full, early)]
    assert lrs[1] == lrs[0][:3] and lrs[0][2] != lrs[0][5]
    kept = load_model(early / "model.pt").state_dict()
    at_three = load_model(full / "snapshots" / "step_00003.pt").state_dict()
    assert kept.keys() == at_three.keys() and all(torch.equal(kept[k], at_three[k]) for k in kept)
    assert torch.load(early / "model.pt", weights_only=True)["step"] == 3
    rows = list(csv.DictReader(open(early / "metrics.csv")))
    assert rows[-1]["val_loss"] != ""  # the kept step is scored on validation; here eval_every=3 would
    # score it anyway, so a stop off the evaluation grid is checked too
    off_grid = tmp_path / "off_grid"
    train(_config(tiny_episodes, off_grid, steps=6, stop_at=2, eval_every=5), SMALL, progress=False)
    assert list(csv.DictReader(open(off_grid / "metrics.csv")))[-1]["val_loss"] != ""
    with pytest.raises(ValueError, match="stop_at must be between 0"):
        TrainConfig(steps=10, stop_at=11)


def test_input_noise_is_a_random_walk_rigid_per_object_and_zero_on_static():
    from toy_scene import toy_window

    from hrn_pyg.data.graph import NODE
    from hrn_pyg.train import input_noise

    window = toy_window(3)
    store = window[NODE]
    noise = input_noise(window, 0.01, torch.Generator().manual_seed(0))  # [N, 3 inputs, 3]
    assert noise.shape == (store.num_nodes, 3, 3)
    rigid = torch.arange(8, 12)  # the toy scene's rigid square: one shift for all its leaves
    assert torch.equal(noise[rigid], noise[rigid[:1]].expand(4, 3, 3))
    assert not torch.equal(noise[0], noise[1])  # soft leaves move independently
    assert torch.equal(noise[12:14], torch.zeros(2, 3, 3))  # static leaves never move
    many = torch.stack([input_noise(window, 0.01, torch.Generator().manual_seed(s))[:8] for s in range(400)])
    # the noise of x_t has the requested standard deviation, x_{t-2}'s a third of its variance
    assert many[:, :, 2].std().item() == pytest.approx(0.01, rel=0.1)
    assert many[:, :, 0].std().item() == pytest.approx(0.01 / 3 ** 0.5, rel=0.1)


def test_boolean_model_options_parse_false(tiny_episodes, tmp_path):
    out = tmp_path / "run"
    args = ["train", "--preset", "ours", "--data", str(tiny_episodes), "--out", str(out), "--train-steps", "2",
            "--batch-size", "2", "--model-hidden", "8", "--model-effect-dim", "8", "--no-progress",
            "--model-rigid-fit", "false", "--model-ground-contact", "true"]
    assert main(args) == 0
    model = load_model(out / "model.pt")
    assert model.config.rigid_fit is False and model.config.ground_contact is True
    with pytest.raises(SystemExit):
        main([*args[:-1], "maybe"])


def test_symmetry_augmentation_is_seeded_and_leaves_no_horizontal_mean(tiny_episodes, tmp_path):
    plain = _config(tiny_episodes, tmp_path / "plain", seq_end=2)
    turned = _config(tiny_episodes, tmp_path / "a", seq_end=2, augment_symmetry=True)
    train(plain, SMALL, progress=False)
    train(turned, SMALL, progress=False)
    train(_config(tiny_episodes, tmp_path / "b", seq_end=2, augment_symmetry=True), SMALL, progress=False)
    assert _losses(tmp_path / "a") == _losses(tmp_path / "b")
    assert _losses(tmp_path / "a") != _losses(tmp_path / "plain")  # the windows were really mapped
    norm, base = load_model(tmp_path / "a" / "model.pt").normalizer, load_model(tmp_path / "plain" / "model.pt").normalizer
    for name in ("velocity_mean", "root_mean", "local_mean"):
        assert torch.equal(getattr(norm, name)[:2], torch.zeros(2)), name
        assert getattr(norm, name)[2] == getattr(base, name)[2]  # vertical statistics unchanged
    assert not torch.equal(base.root_mean[:2], torch.zeros(2))


def test_an_equivariant_network_trains_with_an_isotropic_normaliser_and_resumes(tiny_episodes, tmp_path):
    """Without augmentation too, an equivariant model's normaliser is made isotropic (else its
    inputs and decoding would have a horizontal direction); it trains, saves, loads and
    resumes like any HRN, and a fine-tuning from it keeps its settings."""
    config = dataclasses.replace(SMALL, equivariant=True, vector_channels=3)
    train(_config(tiny_episodes, tmp_path / "eq", seq_end=2), config, progress=False, stop_after=3)
    train(_config(tiny_episodes, tmp_path / "eq", seq_end=2), config, progress=False, resume=True)
    model = load_model(tmp_path / "eq" / "model.pt")
    assert model.config.equivariant and model.config.vector_channels == 3
    norm = model.normalizer
    for mean, std in (("velocity_mean", "velocity_std"), ("root_mean", "root_std"), ("local_mean", "local_std")):
        assert torch.equal(getattr(norm, mean)[:2], torch.zeros(2)), mean
        assert getattr(norm, std)[0] == getattr(norm, std)[1], std
    assert norm.force_std[0] == norm.force_std[1]
    losses = [l for _, l in _losses(tmp_path / "eq")]
    assert len(losses) == 6 and all(math.isfinite(l) for l in losses)
    start = str(tmp_path / "eq" / "model.pt")
    train(_config(tiny_episodes, tmp_path / "tuned", steps=1, init_from=start), SMALL, progress=False)
    assert load_model(tmp_path / "tuned" / "model.pt").config == model.config  # the checkpoint's settings hold
    with pytest.raises(ValueError, match="differ from it: vector_channels"):
        train(_config(tiny_episodes, tmp_path / "clash", steps=1, init_from=start),
              dataclasses.replace(SMALL, vector_channels=5), progress=False)


def _untrained_model_and_batch(tiny_episodes):
    """A seeded small HRN with its normaliser fitted, and every one-step training window of the
    tiny episodes in one batch (the loss-term tests recompute their parts from these by hand)."""
    from torch_geometric.data import Batch

    from hrn_pyg.data.dataset import EpisodeWindows
    from hrn_pyg.nn.hrn import HRN
    from hrn_pyg.nn.normalizer import fit_normalizer

    windows = EpisodeWindows(str(tiny_episodes), "train", horizon=1)
    torch.manual_seed(0)
    model = HRN(SMALL)
    fit_normalizer((windows[i] for i in range(16)), model.normalizer)
    return model, Batch.from_data_list([windows[i] for i in range(len(windows))])


def test_rest_term_is_the_absolute_error_of_the_resting_roots(tiny_episodes):
    """``w_rest``: the logged ``rest`` part of a one-step loss, recomputed by hand from the step,
    and the total grows by exactly ``w_rest`` times it; bad settings are refused."""
    from hrn_pyg.data.graph import NODE, set_state
    from hrn_pyg.sim.step import step as model_step
    from hrn_pyg.train import window_loss

    model, batch = _untrained_model_and_batch(tiny_episodes)
    store = batch[NODE]
    seq = store.pos_seq
    true_v = seq[:, 3] - seq[:, 2]
    threshold = float(true_v[store.is_root & ~store.is_static].norm(dim=-1).median())  # half the roots rest
    plain, _ = window_loss(model, batch, 1, TrainConfig(data="unused", out="unused"))
    config = TrainConfig(data="unused", out="unused", w_rest=2.0, rest_threshold=threshold)
    total, parts = window_loss(model, batch, 1, config)
    graph = set_state(batch, seq[:, 0], seq[:, 1], seq[:, 2], radius=model.config.collision_radius)
    pred_v = model_step(model, graph, store.force_seq[:, 0], None).pos - seq[:, 2]
    resting = store.is_root & ~store.is_static & (true_v.norm(dim=-1) < threshold)
    assert 0 < int(resting.sum()) < int((store.is_root & ~store.is_static).sum())
    by_hand = ((pred_v - true_v) / model.normalizer.velocity_std)[resting].abs().mean()
    assert parts["rest"] == pytest.approx(by_hand.item(), rel=1e-5)
    assert total.item() == pytest.approx(plain.item() + 2.0 * by_hand.item(), rel=1e-5)
    with pytest.raises(ValueError, match="w_rest must be a finite number >= 0"):
        TrainConfig(w_rest=-1.0)
    with pytest.raises(ValueError, match="rest_threshold must be a finite number > 0"):
        TrainConfig(rest_threshold=0.0)


def test_rest_rollout_starts_resting_scenes_from_the_models_own_rollout(tiny_episodes, tmp_path):
    """``rest_rollout``: a window at rest gets the last three frames of the model's own R-step
    rollout as its inputs and the last of them as every target (its graph rolled alone equals the
    whole batch rolled, by hand below); a moving window keeps its frames;
    the draw of R is the generator's; a short run trains with it; bad settings are refused."""
    from hrn_pyg.data.graph import NODE, set_state
    from hrn_pyg.sim.rollout import iterate
    from hrn_pyg.train import held_rest_sequence, resting_windows, window_loss

    model, batch = _untrained_model_and_batch(tiny_episodes)
    store = batch[NODE]
    seq = store.pos_seq.clone()
    window0 = store.batch == 0
    seq[window0] = seq[window0, :1].expand(-1, seq.size(1), -1)  # window 0 still: its first frame throughout
    store.pos_seq = seq
    resting = resting_windows(batch, 1, 1e-3)
    leaf = store.is_leaf & ~store.is_static
    moved = (seq[:, :4] - seq[:, :1]).norm(dim=-1).amax(dim=1)
    for b in range(len(resting)):  # by hand: every moving leaf of the window within 1 mm of its start
        assert bool(resting[b]) == bool((moved[leaf & (store.batch == b)] < 1e-3).all())
    assert bool(resting[0]) and not bool(resting.all())
    held_rows = resting[store.batch]  # the rows of every window at rest

    held = held_rest_sequence(model, batch, 1, 5, 1e-3, torch.Generator().manual_seed(3))
    steps = int(torch.randint(1, 6, (1,), generator=torch.Generator().manual_seed(3)))
    graph = set_state(batch, seq[:, 0], seq[:, 1], seq[:, 2], radius=model.config.collision_radius)
    frames = [seq[:, 2]] + [r.pos for r in iterate(model, graph, steps, None, None, sleep=None)]
    frames = ([seq[:, 0], seq[:, 1]] + frames)[-3:]
    assert torch.equal(held[~held_rows], seq[~held_rows])
    for t in range(3):
        assert torch.allclose(held[held_rows, t], frames[t][held_rows], atol=1e-6)
    assert torch.equal(held[held_rows, 3:], held[held_rows, 2:3].expand(-1, seq.size(1) - 3, -1))
    moved = (held[held_rows, 2] - seq[held_rows, 2]).norm(dim=-1)
    assert float(moved.max()) > 0  # the untrained model does not hold still: the inputs changed

    config = TrainConfig(data="unused", out="unused", w_rest=1.0, rest_rollout=5)
    loss, parts = window_loss(model, batch, 1, config, noise_generator=torch.Generator().manual_seed(3))
    assert torch.isfinite(loss) and parts["rest"] > 0
    still = seq[:, :1].expand(-1, seq.size(1), -1).clone()
    store.pos_seq = still  # every window at rest: none keeps its frames
    assert bool(resting_windows(batch, 1, 1e-3).all())
    assert not torch.equal(held_rest_sequence(model, batch, 1, 5, 1e-3, torch.Generator().manual_seed(3)), still)

    out = tmp_path / "rest_rollout"
    train(_config(tiny_episodes, out, steps=2, rest_rollout=3, w_rest=1.0), SMALL)
    assert (out / "model.pt").exists()
    with pytest.raises(ValueError, match="rest_rollout must be >= 0"):
        TrainConfig(rest_rollout=-1)
    with pytest.raises(ValueError, match="rest_rollout"):
        TrainConfig.for_preset("gns", rest_rollout=4)


def test_rest_rollout_length_draws_uniform_or_log_uniform():
    """``rest_rollout_length``: uniform is ``randint(1, R_max)`` of the generator; log keeps to
    1..R_max, is seeded, and draws as often under 16 as from 16 to 256 (the law
    ``ln((k+1)/k) / ln(R_max+1)``), with a mean far below uniform's; bad settings are refused."""
    from hrn_pyg.train import rest_rollout_length

    g = torch.Generator().manual_seed(5)
    same = int(torch.randint(1, 33, (1,), generator=torch.Generator().manual_seed(5)))
    assert rest_rollout_length(32, "uniform", g) == same
    draws = torch.tensor([rest_rollout_length(255, "log", g) for _ in range(4000)])
    assert int(draws.min()) >= 1 and int(draws.max()) <= 255
    below = float((draws < 16).double().mean())  # law: ln 16 / ln 256 = 0.5
    assert abs(below - 0.5) < 0.04
    assert float((draws == 1).double().mean()) == pytest.approx(math.log(2) / math.log(256), abs=0.03)
    assert 30 < float(draws.double().mean()) < 70  # law: about 45; uniform's would be 128
    again = [rest_rollout_length(255, "log", torch.Generator().manual_seed(9)) for _ in range(2)]
    assert again[0] == again[1]
    assert rest_rollout_length(1, "log", g) == 1
    with pytest.raises(ValueError, match="draw must be one of"):
        rest_rollout_length(8, "normal", g)
    with pytest.raises(ValueError, match="max_steps"):
        rest_rollout_length(0, "log", g)
    with pytest.raises(ValueError, match="rest_rollout_draw"):
        TrainConfig(rest_rollout=8, rest_rollout_draw="normal")


def test_init_from_starts_at_the_checkpoint_and_keeps_its_settings(tiny_episodes, tmp_path):
    train(_config(tiny_episodes, tmp_path / "base", steps=4), SMALL, progress=False)
    base = tmp_path / "base" / "model.pt"
    # zero steps of learning: lr tiny and one step, so the weights must match the checkpoint's
    tuned = _config(tiny_episodes, tmp_path / "tuned", steps=1, lr=1e-30, init_from=str(base))
    train(tuned, HRNConfig(), progress=False)  # default options: the checkpoint's settings hold
    before, after = load_model(base), load_model(tmp_path / "tuned" / "model.pt")
    assert after.config == before.config and after.config.hidden == 16
    recorded = json.loads((tmp_path / "tuned" / "config.json").read_text())
    assert recorded["model"] == before.config.to_dict() and recorded["train"]["init_from"] == str(base)
    for (name, a), b in zip(before.state_dict().items(), after.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-12), name
    # a fresh network of the same settings differs: the start really came from the checkpoint
    fresh = _config(tiny_episodes, tmp_path / "fresh", steps=1, lr=1e-30, seed=5)
    train(fresh, SMALL, progress=False)
    weights = load_model(tmp_path / "fresh" / "model.pt").state_dict()
    assert any(not torch.allclose(a, weights[k]) for k, a in before.state_dict().items() if a.is_floating_point())
    with pytest.raises(ValueError, match="hidden"):
        train(_config(tiny_episodes, tmp_path / "clash", steps=1, init_from=str(base)),
              HRNConfig(hidden=32), progress=False)


def _base_and_fine_tuned(tiny_episodes, tmp_path, model_config: HRNConfig):
    """A two-step run of SMALL and a one-step fine-tuning of it at a vanishing rate under
    ``model_config``: both models, as loaded."""
    train(_config(tiny_episodes, tmp_path / "base", steps=2), SMALL, progress=False)
    base = tmp_path / "base" / "model.pt"
    tuned = _config(tiny_episodes, tmp_path / "tuned", steps=1, lr=1e-30, init_from=str(base))
    train(tuned, model_config, progress=False)
    return load_model(base), load_model(tmp_path / "tuned" / "model.pt")


def test_init_from_may_switch_on_the_mirror_average(tiny_episodes, tmp_path):
    """mirror_average changes how the weights are applied, not which weights there are: a
    fine-tuning may set it, and its first step starts from the checkpoint's weights."""
    before, after = _base_and_fine_tuned(tiny_episodes, tmp_path, HRNConfig(mirror_average=True))
    assert after.config.mirror_average and not before.config.mirror_average
    assert dataclasses.replace(after.config, mirror_average=False) == before.config
    for (name, a), b in zip(before.state_dict().items(), after.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-12), name


def test_an_option_given_on_purpose_holds_even_at_its_default(tiny_episodes, tmp_path):
    """A checkpoint trained with ground_projection_rigid off, fine-tuned with it set to true (its
    default): set on purpose, it holds; not named, the checkpoint's setting holds."""
    import argparse

    from hrn_pyg.train import add_arguments, given_model_options

    train(_config(tiny_episodes, tmp_path / "base", steps=2), HRNConfig(**{**SMALL.to_dict(), "ground_projection": True,
                                                                          "ground_projection_rigid": False}),
          progress=False)
    base = tmp_path / "base" / "model.pt"
    for given, expected in ((("ground_projection_rigid",), True), ((), False)):
        out = tmp_path / f"tuned_{expected}"
        train(_config(tiny_episodes, out, steps=1, lr=1e-30, init_from=str(base)), HRNConfig(),
              progress=False, given_model_options=given)
        assert load_model(out / "model.pt").config.ground_projection_rigid is expected
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--preset", "ours", "--data", "d", "--out", "o",
                              "--model-ground-projection-rigid", "true", "--dropout-modules", "force"])
    assert given_model_options(args) == {"ground_projection_rigid", "dropout_modules"}


def test_a_fine_tuning_command_line_builds_its_config_over_the_checkpoints(tiny_episodes, tmp_path):
    """``--init-from M --model-corotated-rest true``: corotated_rest needs rest_offsets, which M
    has and the command line does not name, so the command line's config is M's with the named
    options over it (a config of the named options alone would be refused); an option that
    changes the weights still clashes with M by name, and without --init-from the defaults hold."""
    import argparse

    from hrn_pyg.train import add_arguments, config_from_args

    train(_config(tiny_episodes, tmp_path / "base", steps=2), HRNConfig(**{**SMALL.to_dict(), "rest_offsets": True}),
          progress=False)
    base = tmp_path / "base" / "model.pt"
    parser = argparse.ArgumentParser()
    add_arguments(parser)

    def parsed(*extra: str):
        return config_from_args(parser.parse_args(["--preset", "ours", "--data", str(tiny_episodes),
                                                   "--out", str(tmp_path / "tuned"), *extra]))

    config, model_config = parsed("--init-from", str(base), "--model-corotated-rest", "true")
    assert model_config == dataclasses.replace(load_model(base).config, corotated_rest=True)
    train(dataclasses.replace(config, steps=1, lr=1e-30), model_config, progress=False,
          given_model_options=("corotated_rest",))
    assert load_model(tmp_path / "tuned" / "model.pt").config.corotated_rest
    with pytest.raises(ValueError, match="rest_offsets"):
        parsed("--model-corotated-rest", "true")
    _, wider = parsed("--init-from", str(base), "--model-hidden", "32")
    with pytest.raises(ValueError, match="hidden"):
        train(_config(tiny_episodes, tmp_path / "clash", steps=1, init_from=str(base)), wider, progress=False)


def test_init_from_may_make_the_collision_module_read_the_force(tiny_episodes, tmp_path):
    """collision_force from a checkpoint without it: the new weights start at zero, every other
    weight at the checkpoint's, and the run's model reads the force from then on."""
    before, after = _base_and_fine_tuned(tiny_episodes, tmp_path, HRNConfig(collision_force=True))
    assert after.config.collision_force and not before.config.collision_force
    assert dataclasses.replace(after.config, collision_force=False) == before.config
    key = "collision.phi.hidden_layers.0.weight"
    old, new = before.state_dict(), after.state_dict()
    state = before.collision.node_dim
    assert new[key].shape[1] == old[key].shape[1] + 6
    force_columns = [state, state + 1, state + 2, 2 * state + 3, 2 * state + 4, 2 * state + 5]
    assert new[key][:, force_columns].abs().max() < 1e-20
    for name, value in old.items():
        if name != key:
            assert torch.allclose(value, new[name], atol=1e-12), name


def test_with_applied_options_keeps_the_weights_and_refuses_other_settings(tiny_episodes, tmp_path):
    """The xy mirror average applied to trained weights: same weights and normaliser, the new
    planes in the config, the mode kept; a setting that changes which weights there are is
    refused by name."""
    from hrn_pyg.checkpoints import with_applied_options

    train(_config(tiny_episodes, tmp_path / "base", steps=2), SMALL, progress=False)
    model = load_model(tmp_path / "base" / "model.pt")
    averaged = with_applied_options(model, mirror_average=True, mirror_planes="xy")
    assert averaged.config.mirror_group == ((), (0,), (1,), (0, 1)) and not averaged.training
    for (name, a), b in zip(model.state_dict().items(), averaged.state_dict().values()):
        assert torch.equal(a, b), name
    with pytest.raises(ValueError, match=r"not \['hidden'\]"):
        with_applied_options(model, hidden=32)


def test_snapshots_keep_the_model_every_n_steps(tiny_episodes, tmp_path):
    out = tmp_path / "snap"
    train(_config(tiny_episodes, out, seq_end=2, snapshot_every=3), SMALL, progress=False)
    kept = sorted(p.name for p in (out / "snapshots").iterdir())
    assert kept == ["step_00003.pt", "step_00006.pt"]
    last = load_model(out / "snapshots" / "step_00006.pt")
    final = load_model(out / "model.pt")
    for a, b in zip(last.state_dict().values(), final.state_dict().values()):
        assert torch.equal(a, b)
    assert torch.load(out / "snapshots" / "step_00003.pt", weights_only=True)["step"] == 3
    with pytest.raises(ValueError, match="snapshot_every"):
        TrainConfig.for_preset("ours", snapshot_every=-1)


def test_data_weights_parse_by_folder_name_and_refuse_bad_pairs():
    folders = ["data/a", "more/b", "c"]
    assert parse_data_weights("", folders) == [1.0, 1.0, 1.0]
    assert parse_data_weights("b=3, c=0.5", folders) == [1.0, 3.0, 0.5]
    for text, words in [("z=2", "is not a folder"), ("a=2,a=3", "twice"), ("a=0", "> 0"), ("a=inf", "> 0"),
                        ("a=x", "number"), ("a", "name=weight"), ("=2", "name=weight")]:
        with pytest.raises(ValueError, match=words):
            parse_data_weights(text, folders)
    with pytest.raises(ValueError, match="more than one folder"):
        parse_data_weights("a=2", ["x/a", "y/a"])
    with pytest.raises(ValueError, match="data_weights"):  # refused when the config is made
        TrainConfig(data="data/a", data_weights="b=2")


def test_data_weights_draw_a_folder_in_proportion_and_uniform_draws_stay_as_they_were(tiny_episodes, tmp_path):
    import shutil

    from hrn_pyg.data.dataset import EpisodeWindows, split_of_seed

    seeds = sorted(int(p.stem.removeprefix("episode_")) for p in tiny_episodes.glob("episode_*.npz"))
    train_seeds = [s for s in seeds if split_of_seed(s) == "train"]
    small, large = tmp_path / "small", tmp_path / "large"
    for folder, seeds in ((small, train_seeds[:1]), (large, train_seeds[1:])):
        folder.mkdir()
        for s in seeds:
            shutil.copy(tiny_episodes / f"episode_{s:06d}.npz", folder / f"episode_{s:06d}.npz")
    folders = [str(large), str(small)]
    windows = EpisodeWindows(folders, "train", horizon=1)
    from_small = torch.as_tensor([windows.paths[e].parent == small for e in windows.window_episodes])
    share = float(from_small.double().mean())  # uniform draws: the small folder's share of windows

    assert window_draw_weights(windows, folders, [1.0, 1.0]) is None
    n = len(windows)
    assert draw_windows(n, 8, 0, 3, 0) == draw_windows(n, 8, 0, 3, 0, None)  # runs without weights unchanged

    weight = 4.0
    cumulative = window_draw_weights(windows, folders, [1.0, weight])
    drawn = torch.as_tensor([i for step in range(500) for i in draw_windows(n, 8, 0, step, 0, cumulative)])
    assert int(drawn.min()) >= 0 and int(drawn.max()) < n
    expected = weight * share / (weight * share + 1 - share)
    observed = float(from_small[drawn].double().mean())
    assert abs(observed - expected) < 0.03, (observed, expected, share)  # 4000 draws: 3 sigma < 0.025
    assert draw_windows(n, 8, 0, 7, 0, cumulative) == draw_windows(n, 8, 0, 7, 0, cumulative)  # seeded


def test_rigid_bodies_under_the_rigid_fit_leave_the_shape_gradient_as_it_was(monkeypatch):
    """The full shape loss skips the pairs of rigid bodies when the model fits rigid motions
    (their distances are the input's): every parameter's gradient is the one of the loss that
    computes them, and the logged shape part is lower by their constant error."""
    import hrn_pyg.train.loss as train_module
    from hrn_pyg.losses import full_shape_loss
    from hrn_pyg.train import window_loss
    from toy_scene import toy_model, toy_window

    model = toy_model().train()
    window = toy_window(3, seed=1)
    config = TrainConfig(data="unused", out="unused", input_noise=0.01)

    def gradients(loss_fn):
        monkeypatch.setattr(train_module, "full_shape_loss", loss_fn)
        model.zero_grad()
        total, parts = window_loss(model, window, 3, config, noise_generator=torch.Generator().manual_seed(0))
        total.backward()
        return [p.grad.clone() for p in model.parameters() if p.grad is not None], parts

    skipping, parts = gradients(full_shape_loss)
    computing, parts_all = gradients(lambda *args, fixed=None: full_shape_loss(*args[:5]))
    for a, b in zip(skipping, computing):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
    assert parts["shape"] < parts_all["shape"]  # the noisy input's rigid distances are off the truth
    assert any(g.abs().sum() > 0 for g in skipping)


def test_train_help_is_in_groups_and_removed_options_warn_and_are_ignored(capsys):
    """``--help`` lists the options under data, model, loss, schedule and run; an option of an
    earlier release that no recipe used warns in one line and changes nothing."""
    import argparse

    from hrn_pyg.train import add_arguments, config_from_args

    parser = argparse.ArgumentParser(prog="hrn-pyg train")
    add_arguments(parser)
    titles = {g.title: {a.dest for a in g._group_actions} for g in parser._action_groups}
    assert {"data", "model", "loss", "schedule", "run"} <= set(titles)
    assert {"data", "batch_size"} <= titles["data"] and {"lr", "steps", "seq_end"} <= titles["schedule"]
    assert {"w_rest", "shape_loss"} <= titles["loss"] and "model_hidden" in titles["model"]
    assert {"out", "device", "seed"} <= titles["run"]
    args = parser.parse_args(["--preset", "ours", "--data", "data/x", "--w-contact", "2", "--rest-leaves"])
    err = capsys.readouterr().err
    assert "--w-contact was removed" in err and "--rest-leaves was removed" in err
    config, _ = config_from_args(args)
    assert config == TrainConfig.for_preset("ours", data="data/x", out=os.path.join("runs", "train", "x_ours"))
