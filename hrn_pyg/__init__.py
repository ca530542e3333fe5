"""hrn_pyg: stochastic Hierarchical Relation Networks in PyTorch Geometric."""

__version__ = "0.1.0"
