"""A checkpoint's config is checked against fixed limits before any module is built."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hrn_pyg.checkpoints import (MAX_PARAMETERS, check_model_size, checkpoint_path, load_model,
                                 parameter_count)
from hrn_pyg.nn.networks import config_from_dict
from hrn_pyg.utils.checkpoint import CheckpointError


def _with_model_config(tmp_path: Path, **changes) -> Path:
    ckpt = torch.load(checkpoint_path("cube_collision"), weights_only=True)
    config = json.loads(ckpt["config"])
    config["model"].update(changes)
    ckpt["config"] = json.dumps(config)
    path = tmp_path / "changed.pt"
    torch.save(ckpt, path)
    return path


@pytest.mark.parametrize("changes, message", [
    ({"depth": 10**6}, r"config field depth = 1000000; the limit is a whole number up to 16"),
    ({"hidden": 16000}, r"config field hidden = 16000; the limit is a whole number up to 4096"),
    ({"hidden": 2048.5}, r"config field hidden = 2048\.5"),
    ({"hidden": 4096, "depth": 16, "effect_dim": 4096}, r"config describes \d+ parameters, more than the limit"),
])
def test_oversized_config_is_one_line_before_building(tmp_path, changes, message):
    path = _with_model_config(tmp_path, **changes)
    with pytest.raises(CheckpointError, match=message) as info:
        load_model(path)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(path))


def test_a_million_layers_are_refused_in_bounded_memory(tmp_path):
    """Under a 3 GB address-space limit (torch's import alone reserves about 2 GB of it) the
    network of 10^6 layers could not be built; the check refuses it first."""
    path = _with_model_config(tmp_path, depth=10**6)
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))\n"
            "from hrn_pyg.checkpoints import load_model\n"
            f"load_model({str(path)!r})")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 1 and "CheckpointError" in run.stderr and "depth = 1000000" in run.stderr, run.stderr


def test_every_shipped_model_is_well_inside_the_limits():
    for path in sorted(checkpoint_path("x").parent.glob("*.pt")):
        config = json.loads(torch.load(path, weights_only=True)["config"])
        if "model" not in config:  # a policy
            continue
        network = config_from_dict(config["model"])
        check_model_size(network)
        assert parameter_count(network) * 10 < MAX_PARAMETERS, path.name


def test_wrong_shaped_tensor_names_its_key(tmp_path):
    ckpt = torch.load(checkpoint_path("cube_collision"), weights_only=True)
    key = next(iter(ckpt["model"]))
    ckpt["model"] = {**ckpt["model"], key: torch.zeros(3, 3)}
    torch.save(ckpt, tmp_path / "shape.pt")
    with pytest.raises(CheckpointError, match=rf"size mismatch for {key}:") as info:
        load_model(tmp_path / "shape.pt")
    assert "\n" not in str(info.value)
