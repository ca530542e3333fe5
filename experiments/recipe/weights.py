r"""The weights a recipe publishes: a weighted mean of checkpoints' weights written as one
checkpoint (:func:`write_average`), and a checkpoint with applied options (:func:`write_applied`).

Stages of one network trained from each other stay close in weight space, so their mean is a
model too. With weights :math:`w_i > 0`, :math:`\sum_i w_i = 1`, every learned parameter is

.. math::
    \theta_j = \sum_{i=1}^{n} w_i \, \theta^{(i)}_j ,

summed in the order given; everything else (buffers, config, step, domain) is the last one's.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from typing import Any

import torch

from hrn_pyg.checkpoints import load_model, model_path, with_applied_options
from hrn_pyg.utils.checkpoint import load_checkpoint, save_checkpoint

#: how far the weights' sum may be from one
WEIGHT_SUM_TOLERANCE = 1e-6


def check_average_weights(weights: Sequence[float], count: int) -> tuple[float, ...]:
    """``weights`` as floats, or a ``ValueError`` saying what is wrong: one per checkpoint
    (``count``), at least two, each finite and > 0, summing to one."""
    if count < 2:
        raise ValueError(f"average: needs at least two checkpoints, got {count}")
    if len(weights) != count:
        raise ValueError(f"average: {len(weights)} weights for {count} checkpoints")
    values = tuple(float(w) for w in weights)
    if not all(math.isfinite(w) and w > 0 for w in values):
        raise ValueError(f"average: weights must be finite numbers > 0, got {list(values)}")
    if abs(sum(values) - 1.0) > WEIGHT_SUM_TOLERANCE:
        raise ValueError(f"average: weights must sum to 1, got {sum(values):g}")
    return values


def average_state(states: Sequence[dict[str, torch.Tensor]], weights: Sequence[float],
                  parameters: set[str]) -> dict[str, torch.Tensor]:
    """The last state dict with each entry named in ``parameters`` replaced by the weighted mean
    of that entry over ``states`` (in their order). Raises ``ValueError`` when the states do not
    hold the same entries of the same shapes, or a parameter is not floating point."""
    last = states[-1]
    for i, state in enumerate(states[:-1]):
        if set(state) != set(last):
            names = sorted(set(state) ^ set(last))
            raise ValueError(f"average: checkpoint {i} and the last one hold different tensors ({names[:3]} ...)")
        shapes = [k for k in last if state[k].shape != last[k].shape]
        if shapes:
            raise ValueError(f"average: checkpoint {i} and the last one differ in the shape of {shapes[0]!r}")
    averaged = dict(last)
    for name in parameters:
        if not last[name].is_floating_point():
            raise ValueError(f"average: parameter {name!r} is not floating point")
        total = weights[0] * states[0][name]
        for weight, state in zip(weights[1:], states[1:], strict=True):
            total = total + weight * state[name]
        averaged[name] = total
    return averaged


def write_average(sources: Sequence[str | os.PathLike], weights: Sequence[float],
                  target: str | os.PathLike) -> None:
    """Write (atomically) to ``target`` the checkpoint whose parameters are the ``weights``-mean
    of those of the model checkpoints ``sources`` (paths or shipped names), everything else the
    last source's. Every problem (bad weights, checkpoints of different networks, a file that
    is not a model) is a ``ValueError`` (:class:`~hrn_pyg.utils.checkpoint.CheckpointError` for
    a file) raised before anything is written."""
    values = check_average_weights(weights, len(sources))
    paths = [model_path(s) for s in sources]
    model = load_model(paths[-1])  # also checks that the last file is a model this package builds
    parameters = {name for name, _ in model.named_parameters()}
    checkpoints = [load_checkpoint(p) for p in paths]
    state = average_state([c["model"] for c in checkpoints], values, parameters)
    payload = {key: value for key, value in checkpoints[-1].items() if key != "format"}
    payload["model"] = state
    save_checkpoint(target, payload)


def write_applied(source: str | os.PathLike, options: dict[str, Any], target: str | os.PathLike) -> None:
    """Write ``source`` (a path or shipped name) to ``target`` atomically with the
    :data:`~hrn_pyg.checkpoints.APPLIED_OPTIONS` ``options`` set; ValueError for another option or a
    refused value, before anything is written."""
    path = model_path(source)
    changed = with_applied_options(load_model(path), **options)  # checks the options and their values
    payload = {key: value for key, value in load_checkpoint(path).items() if key != "format"}
    config = json.loads(payload["config"])
    config["model"] = changed.config.to_dict()
    payload["config"] = json.dumps(config)
    save_checkpoint(target, payload)
