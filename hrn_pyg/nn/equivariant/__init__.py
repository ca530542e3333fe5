"""The modules of the horizontally equivariant HRN (``HRNConfig(equivariant=True)``): the force,
collision, history, propagation and next-state modules of :mod:`hrn_pyg.nn`, rebuilt so that
their MLPs read only what no turn about the vertical axis or mirror in a vertical plane changes,
and their horizontal outputs are weighted sums of the scene's own horizontal vectors
(:mod:`hrn_pyg.nn.equivariant.features`). One pass of the network is then exactly equivariant,
with no average over transforms."""

from hrn_pyg.nn.equivariant.collision import CollisionModule
from hrn_pyg.nn.equivariant.force import ForceModule
from hrn_pyg.nn.equivariant.history import HistoryModule
from hrn_pyg.nn.equivariant.propagation import PropagationModule
from hrn_pyg.nn.equivariant.state import NextStateModule

__all__ = ["CollisionModule", "ForceModule", "HistoryModule", "PropagationModule", "NextStateModule"]
