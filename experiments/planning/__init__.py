"""Closed-loop planning through the learned model, judged in pybullet: the sweep over scores,
scenes and planner seeds (:mod:`experiments.planning.sweep`) and its summary
(:mod:`experiments.planning.summary`)."""
