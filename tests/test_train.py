import csv
import json
import os
import subprocess
import sys

import pytest
import torch

from hrn_pyg.cli import main
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.train import TrainConfig, load_model, train

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


def test_data_parallel_under_torchrun(tiny_episodes, tmp_path):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "-m", "hrn_pyg.cli", "train",
           "--preset", "hrn", "--data", str(tiny_episodes), "--out", str(out), "--steps", "3", "--batch-size", "1",
           "--model-hidden", "16", "--model-depth", "1", "--model-effect-dim", "16", "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((out / "config.json").read_text())["world_size"] == 2
    assert len(_losses(out)) == 3
    load_model(out / "model.pt")
