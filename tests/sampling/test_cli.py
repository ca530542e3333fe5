"""``hrn-pyg sample`` end to end on a random-init checkpoint (pipeline check, not a result)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from hrn_pyg.checkpoints import resolve_model
from hrn_pyg.cli import main
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.train import TrainConfig, model_payload
from hrn_pyg.utils.checkpoint import save_checkpoint


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "wedge.pt"
    save_checkpoint(path, model_payload(HRN(HRNConfig(hidden=16, effect_dim=16)), TrainConfig(), 0))
    return path


def test_sample_writes_png_gif_and_arrays(checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["sample", "--scene", "wedge", "--k", "3", "--rate", "0.3", "--episode-seed", "5", "--horizon", "3",
                 "--model", str(checkpoint), "--out", str(out)])
    assert code == 0
    assert (out / "samples.png").stat().st_size > 0
    assert (out / "samples.gif").stat().st_size > 0
    with np.load(out / "samples.npz", allow_pickle=False) as npz:
        assert npz["samples"].shape[:2] == (3, 3)
        assert npz["truth"].shape[0] == 4
        assert npz["samples"].shape[2:] == npz["truth"].shape[1:]
    meta = json.loads((out / "samples.json").read_text())
    assert meta["k"] == 3 and meta["seed"] == 5
    plausible = meta["plausibility"]  # one report per future, pybullet's beside them, and its line
    assert len(plausible["futures"]) == 3 and plausible["truth"]["first_non_finite"] == 0
    assert plausible["line"].startswith("plausibility of 3 futures: ")
    assert plausible["line"] in capsys.readouterr().out


def test_missing_default_checkpoint_names_path_and_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="no_such_scene.pt.*hrn-pyg train"):
        resolve_model("no_such_scene", None)
    code = main(["sample", "--scene", "wedge", "--model", str(tmp_path / "missing.pt")])
    assert code == 2


def test_bad_rate_is_a_clean_error(checkpoint, capsys):
    assert main(["sample", "--scene", "wedge", "--rate", "1.5", "--model", str(checkpoint)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("hrn-pyg sample: error:") and "rate" in err and "1.5" in err, err


def _spy_on_model_loading(monkeypatch) -> list[torch.device]:
    """The device of the model ``hrn-pyg sample`` loads, one entry per load."""
    import hrn_pyg.sampling.cli as sample_cli

    devices, load = [], sample_cli.load_model

    def spy(*args, **kwargs):
        model = load(*args, **kwargs)
        devices.append(next(model.parameters()).device)
        return model

    monkeypatch.setattr(sample_cli, "load_model", spy)
    return devices


def test_device_cpu_runs_and_is_recorded(checkpoint, tmp_path, monkeypatch):
    """The default device is made ``meta`` here, so a command that ignored ``--device cpu`` (and
    took the default) would put its model there and fail; it must run on the CPU."""
    import hrn_pyg.sampling.cli as sample_cli
    import hrn_pyg.utils.device

    monkeypatch.setattr(hrn_pyg.utils.device, "default_device", lambda: torch.device("meta"))
    devices = _spy_on_model_loading(monkeypatch)
    drawn, sample = [], sample_cli.sample

    def spy_sample(model, graph, *args, generator=None, **kwargs):
        drawn.append((next(model.parameters()).device, generator.device))
        return sample(model, graph, *args, generator=generator, **kwargs)

    monkeypatch.setattr(sample_cli, "sample", spy_sample)
    out = tmp_path / "out"
    code = main(["sample", "--scene", "wedge", "--k", "2", "--episode-seed", "5", "--horizon", "2",
                 "--model", str(checkpoint), "--out", str(out), "--device", "cpu"])
    assert code == 0
    cpu = torch.device("cpu")
    assert devices == [cpu] and drawn == [(cpu, cpu)]
    assert json.loads((out / "samples.json").read_text())["device"] == "cpu"


def test_device_meta_is_refused_before_a_model_is_loaded(checkpoint, tmp_path, monkeypatch, capsys):
    """``--device meta`` (a device with no data, which the package does not run on): one line,
    no model loaded, nothing written."""
    devices = _spy_on_model_loading(monkeypatch)
    out = tmp_path / "out"
    assert main(["sample", "--scene", "wedge", "--k", "2", "--episode-seed", "5", "--horizon", "2",
                 "--model", str(checkpoint), "--out", str(out), "--device", "meta"]) == 2
    assert "runs on cpu or cuda devices only" in capsys.readouterr().err
    assert devices == [] and not out.exists()


def test_unknown_device_is_a_one_line_error(checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["sample", "--scene", "wedge", "--model", str(checkpoint), "--out", str(out),
                 "--device", "nonsense"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "nonsense" in err and err.startswith("hrn-pyg sample: error:")
    assert not out.exists()


def test_fixed_shape_flag_samples_the_no_sleep_futures(checkpoint, tmp_path, capsys):
    def run(*flags):
        out = tmp_path / "_".join(flags)
        assert main(["sample", "--scene", "wedge", "--k", "2", "--rate", "0.3", "--episode-seed", "5", "--horizon", "3",
                     "--model", str(checkpoint), "--out", str(out), *flags]) == 0
        with np.load(out / "samples.npz", allow_pickle=False) as npz:
            return npz["samples"], json.loads((out / "samples.json").read_text())

    fixed, meta = run("--fixed-shape")
    plain, _ = run("--no-sleep")
    assert np.array_equal(fixed, plain)
    assert meta["sleep"] is None and meta["fixed_shape"]["cuda_graph"] is False
    assert main(["sample", "--scene", "wedge", "--cuda-graph", "--model", str(checkpoint)]) == 2
    assert "--cuda-graph needs --fixed-shape" in capsys.readouterr().err
