"""``hrn-pyg train`` records the domain of its datasets in the checkpoints it writes."""

from __future__ import annotations

import torch

from hrn_pyg.checkpoints import load_model
from hrn_pyg.checkpoints.domain import dataset_domain
from hrn_pyg.nn.hrn import HRNConfig
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
