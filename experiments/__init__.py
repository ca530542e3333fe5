"""Experiments beside the ``hrn_pyg`` package: the scripts that produced the docs' results.

Not part of the wheel (``setup.cfg`` packages ``hrn_pyg*`` only); they import the library and
nothing in the library imports them. Run from the checkout's root, e.g.
``python -m experiments.rl.sweep --help``.
"""
