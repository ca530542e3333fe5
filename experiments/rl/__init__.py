"""The RL experiments of docs/rl.md: sweeps over modes and seeds, their statistics, summaries
and figures, the scripted planners and their thresholds, the planner cloned into a PPO actor,
and the partial-hit share. Each script runs as ``python -m experiments.rl.<name>``
(:mod:`experiments.rl.sweep`, :mod:`experiments.rl.summary`, :mod:`experiments.rl.clone`)."""
