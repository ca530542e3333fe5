"""``hrn-pyg demo --device``: passed on to every step (a tiny stand-in checkpoint, so only the
sampling step runs; the others are skipped with a note)."""

from __future__ import annotations

import json

import pytest
import torch

import hrn_pyg.demo
from hrn_pyg.cli import main
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.train import TrainConfig, model_payload
from hrn_pyg.utils.checkpoint import save_checkpoint


@pytest.fixture
def tiny_checkpoints(tmp_path, monkeypatch):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    torch.manual_seed(0)
    save_checkpoint(folder / "wedge.pt", model_payload(HRN(HRNConfig(hidden=8, effect_dim=8)), TrainConfig(), 0))
    monkeypatch.setattr(hrn_pyg.demo, "checkpoint_dir", lambda: folder)
    return folder


def test_demo_on_cpu_passes_the_device_on(tiny_checkpoints, tmp_path, monkeypatch):
    """The default device is made ``meta`` here: a demo that ignored ``--device cpu`` (and passed
    on, or let its steps take, the default) would sample there and fail."""
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("meta"))
    calls = []
    run_command = hrn_pyg.demo.run_command

    def shorter(name, module, argv):  # the demo's own sub-commands, cut to 2 steps to keep the test fast
        calls.append([name, *argv])
        return run_command(name, module, [("2" if prev == "--horizon" else a) for prev, a in zip([None, *argv], argv)])

    monkeypatch.setattr(hrn_pyg.demo, "run_command", shorter)
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--k", "2", "--device", "cpu"]) == 0
    assert [c[0] for c in calls] == ["sample"] and calls[0][-2:] == ["--device", "cpu"]
    assert json.loads((out / "samples" / "wedge" / "samples.json").read_text())["device"] == "cpu"
    assert "skipped Table 1" in (out / "README.md").read_text()


class _Stop(Exception):
    """Ends the demo at its first sub-command."""


def test_demo_passes_on_a_device_other_than_the_default(tiny_checkpoints, tmp_path, monkeypatch):
    """``--device cuda:0`` on a machine made to have no default CUDA device reaches the sampling
    step as asked."""
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("cpu"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    calls = []

    def record(name, module, argv):
        calls.append([name, *argv])
        raise _Stop

    monkeypatch.setattr(hrn_pyg.demo, "run_command", record)
    with pytest.raises(_Stop):
        main(["demo", "--out", str(tmp_path / "demo"), "--k", "2", "--device", "cuda:0"])
    assert [c[0] for c in calls] == ["sample"] and calls[0][-2:] == ["--device", "cuda:0"]


def test_demo_unknown_device_is_a_one_line_error(tiny_checkpoints, tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--device", "nonsense"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("hrn-pyg demo: error:") and "\n" not in err and "nonsense" in err
    assert not out.exists()
