"""hrn_pyg: stochastic Hierarchical Relation Networks in PyTorch Geometric.

The names most users need are here: the model (:class:`HRN`, :class:`HRNConfig`), the one
rollout loop (:func:`rollout`, which also names the module ``hrn_pyg/rollout.py``), and the
Monte Carlo dropout sampler (:func:`sample`).
"""

from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.rollout import rollout  # the function shadows the module name on purpose
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sleep_config import SleepConfig

__version__ = "0.1.0"

__all__ = ["HRN", "HRNConfig", "SleepConfig", "rollout", "sample", "__version__"]
