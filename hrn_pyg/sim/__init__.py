"""Simulation with a trained HRN: the one learned step and everything that repeats it.

* :mod:`hrn_pyg.sim.step`: the step's three stages (inputs, network, decode) and the next graph;
* :mod:`hrn_pyg.sim.rollout`: the loop that feeds the model its own predictions;
* :mod:`hrn_pyg.sim.sleeping`: objects at rest held still and not run;
* :mod:`hrn_pyg.sim.fixed_shape`: the same rollout with no host read inside a step's network
  (CUDA graphs, ``torch.compile``), the rules that read the contacts after it.
"""
