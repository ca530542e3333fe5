"""``hrn-pyg train`` records the domain of its datasets in the checkpoints it writes, and the
recipe's manifest keeps a shipped model's domain while its file is unchanged."""

from __future__ import annotations

import argparse

import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.checkpoints.domain import dataset_domain
from hrn_pyg.nn.hrn import HRNConfig
from hrn_pyg.recipe.manifest import read_json, update_manifest
from hrn_pyg.train import TrainConfig, train


def test_a_trained_checkpoint_records_its_datasets_domain(tiny_episodes, tmp_path):
    config = TrainConfig.for_preset("ours", data=str(tiny_episodes), out=str(tmp_path / "run"), steps=2,
                                    batch_size=2, seq_end=2, checkpoint_every=2, eval_every=2, warmup=1)
    train(config, HRNConfig(hidden=8, depth=1, effect_dim=8), progress=False)
    assert "domain" in torch.load(tmp_path / "run" / "model.pt", weights_only=True)
    model = load_model(tmp_path / "run" / "model.pt")
    assert model.domain.to_dict() == dataset_domain(tiny_episodes).to_dict()
    assert model.domain.pitches == (0.05,) and model.domain.materials == ("rigid",) and model.domain.objects == (2, 2)
    assert model.checkpoint_name == str(tmp_path / "run" / "model.pt")


def test_the_manifest_keeps_a_domain_while_the_file_is_the_same(tmp_path):
    path = tmp_path / "manifest.json"
    update_manifest(path, "m", {"sha256": "a", "domain": {"pitches": [0.05]}})
    update_manifest(path, "m", {"sha256": "a", "steps": 2})
    assert read_json(path)["checkpoints"]["m"]["domain"] == {"pitches": [0.05]}
    update_manifest(path, "m", {"sha256": "b", "steps": 2})  # another file: its domain is unknown
    assert "domain" not in read_json(path)["checkpoints"]["m"]


def test_checkpoints_go_under_the_working_directory_by_default():
    from hrn_pyg.recipe.cli import add_arguments, config_from_args
    from hrn_pyg.recipe.runner import RunConfig

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    config = config_from_args(parser.parse_args([]))
    assert str(config.checkpoints_dir) == "checkpoints" == str(RunConfig().checkpoints_dir)
    assert not config.checkpoints_dir.is_absolute()
