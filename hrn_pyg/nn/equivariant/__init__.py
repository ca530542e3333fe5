"""The modules of the horizontally equivariant HRN (``HRNConfig(equivariant=True)``): those of
:mod:`hrn_pyg.nn` rebuilt so their MLPs read only invariants of turns about z and vertical
mirrors and their horizontal outputs are weighted sums of the scene's vectors
(:mod:`hrn_pyg.nn.equivariant.features`): one pass is exactly equivariant."""

from hrn_pyg.nn.equivariant.collision import CollisionModule
from hrn_pyg.nn.equivariant.force import ForceModule
from hrn_pyg.nn.equivariant.history import HistoryModule
from hrn_pyg.nn.equivariant.propagation import PropagationModule
from hrn_pyg.nn.equivariant.state import NextStateModule

__all__ = ["CollisionModule", "ForceModule", "HistoryModule", "PropagationModule", "NextStateModule"]
