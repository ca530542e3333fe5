"""Helpers of the stability suite (a module of its own: ``conftest`` is a name every test folder
has, so importing from it is ambiguous when several folders run together)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from toy_scene import toy_window

from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.nn.normalizer import fit_normalizer

#: the long cases run only when this environment variable is "1"
SLOW = os.environ.get("HRN_SLOW") == "1"
slow = pytest.mark.skipif(not SLOW, reason="long stability case: set HRN_SLOW=1 (make test-slow)")

REPO = Path(__file__).resolve().parents[2]


def fitted_model(seed: int = 0, hidden: int = 16, dtype: torch.dtype = torch.float32, **config) -> HRN:
    """A randomly initialised HRN whose normaliser is fitted on toy windows."""
    torch.manual_seed(seed)
    model = HRN(HRNConfig(hidden=hidden, depth=2, effect_dim=hidden, **config))
    fit_normalizer([toy_window(6, seed=s) for s in range(3)], model.normalizer)
    return model.to(dtype).eval()


def trained_checkpoint(scene: str) -> Path | None:
    """The shipped checkpoint of ``scene`` (Table 1 "ours" first, then the scene's default)."""
    for path in (REPO / "hrn_pyg" / "checkpoints" / f"{scene}_ours.pt",
                 REPO / "hrn_pyg" / "checkpoints" / f"{scene}.pt"):
        if path.is_file():
            return path
    return None
