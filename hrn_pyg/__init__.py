"""hrn_pyg: stochastic Hierarchical Relation Networks in PyTorch Geometric.

The names most users need are here: the model (:class:`HRN`, :class:`HRNConfig`), loading a
checkpoint (:func:`load_model`), a scene's start state in one call (:func:`scene`), the
deterministic rollout (:func:`rollout`) and the Monte Carlo dropout sampler (:func:`sample`), both
giving leaf positions without gradients (:mod:`hrn_pyg.sampling.start`), and objects at rest
(:class:`SleepConfig`). Each is imported on first use (PEP 562), so ``import hrn_pyg``
and the command line's first checks do not load torch. This module is the top of the package:
no module of the package imports it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hrn_pyg.version import __version__

if TYPE_CHECKING:
    from hrn_pyg.checkpoints import load_model
    from hrn_pyg.nn.hrn import HRN, HRNConfig
    from hrn_pyg.sampling.sample import sample
    from hrn_pyg.sampling.start import rollout, scene
    from hrn_pyg.sim.sleeping import SleepConfig

#: public name -> the module it comes from
LAZY: dict[str, str] = {
    "HRN": "hrn_pyg.nn.hrn",
    "HRNConfig": "hrn_pyg.nn.hrn",
    "SleepConfig": "hrn_pyg.sim.sleeping",
    "load_model": "hrn_pyg.checkpoints",
    "rollout": "hrn_pyg.sampling.start",
    "sample": "hrn_pyg.sampling.sample",
    "scene": "hrn_pyg.sampling.start",
}

__all__ = ["HRN", "HRNConfig", "SleepConfig", "load_model", "rollout", "sample", "scene", "__version__"]


def __getattr__(name: str) -> Any:
    """The public name ``name``, imported from its module on first use and kept here."""
    if name not in LAZY:
        raise AttributeError(f"module 'hrn_pyg' has no attribute {name!r}")
    value = getattr(importlib.import_module(LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
