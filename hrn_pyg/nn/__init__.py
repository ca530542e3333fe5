"""The HRN's operators (Fig. 2), one per file, and the model that composes them."""

from hrn_pyg.nn.collision import CollisionModule
from hrn_pyg.nn.force import ForceModule
from hrn_pyg.nn.history import HistoryModule
from hrn_pyg.nn.hrn import HRN, HRNConfig, HRNInputs
from hrn_pyg.nn.mlp import MLP, MLPConfig, dropout_mask
from hrn_pyg.nn.normalizer import Normalizer, fit_normalizer
from hrn_pyg.nn.propagation import PropagationModule
from hrn_pyg.nn.state import NextStateModule, to_global_velocity, to_local_velocity

__all__ = [
    "CollisionModule",
    "ForceModule",
    "HistoryModule",
    "HRN",
    "HRNConfig",
    "HRNInputs",
    "MLP",
    "MLPConfig",
    "dropout_mask",
    "Normalizer",
    "fit_normalizer",
    "PropagationModule",
    "NextStateModule",
    "to_global_velocity",
    "to_local_velocity",
]
