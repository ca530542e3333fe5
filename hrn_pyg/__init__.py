"""hrn_pyg: stochastic Hierarchical Relation Networks in PyTorch Geometric.

The names most users need are here: the model (:class:`HRN`, :class:`HRNConfig`), loading a
checkpoint (:func:`load_model`), the deterministic rollout (:func:`rollout`, from
:mod:`hrn_pyg.sim.rollout`), objects at rest (:class:`SleepConfig`) and the Monte Carlo
dropout sampler (:func:`sample`). This module is the top of the package: no module of the
package imports it.
"""

from hrn_pyg.checkpoints import load_model
from hrn_pyg.nn.hrn import HRN, HRNConfig
from hrn_pyg.sampling.sample import sample
from hrn_pyg.sim.rollout import rollout
from hrn_pyg.sim.sleeping import SleepConfig
from hrn_pyg.version import __version__


__all__ = ["HRN", "HRNConfig", "SleepConfig", "load_model", "rollout", "sample", "__version__"]
