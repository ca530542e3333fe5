r"""A trained model's weights as the start of a larger one: a pitch-aware model from a plain one
(:func:`widen_to_pitch_aware`), or a collision module that reads the force
(:func:`with_collision_force`).

A pitch-aware HRN reads one more state column, :math:`\log_2(p / p_{ref})`. Every module takes
its state vectors as the first blocks of its input, so only each MLP's first layer grows, with
one zero column after each of its :math:`k` state blocks:

.. math::
    W_1 = [W^{(1)} \,|\, \dots \,|\, W^{(k)} \,|\, W^{rest}]
    \;\mapsto\;
    [W^{(1)} \,|\, 0 \,|\, \dots \,|\, W^{(k)} \,|\, 0 \,|\, W^{rest}]

At the reference pitch the widened model predicts what the plain one does, bit for bit.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from hrn_pyg.nn.hrn import HRN
from hrn_pyg.nn.mlp import MLP


def widen_state_blocks(weight: Tensor, blocks: int, old_state: int, new_state: int) -> Tensor:
    """``weight [H, in]`` whose first ``blocks`` column blocks of ``old_state`` are state vectors,
    each padded with zero columns to ``new_state``: ``[H, in + blocks * (new_state - old_state)]``."""
    if new_state < old_state or blocks < 0 or blocks * old_state > weight.size(1):
        raise ValueError(f"cannot widen {blocks} state blocks of {old_state} to {new_state} in a weight "
                         f"of {weight.size(1)} columns")
    pad = weight.new_zeros(weight.size(0), new_state - old_state)
    parts = []
    for i in range(blocks):
        parts += [weight[:, i * old_state:(i + 1) * old_state], pad]
    parts.append(weight[:, blocks * old_state:])
    return torch.cat(parts, dim=1)


def widen_to_pitch_aware(model: HRN, **changes: Any) -> HRN:
    """A pitch-aware :class:`HRN` holding ``model``'s weights (zero on the pitch column); ``changes``:
    other config fields that keep every layer's size. In ``model``'s training mode."""
    config = _grown_config(model, "widen_to_pitch_aware", "pitch_aware", "is pitch-aware already", changes)
    wide = HRN(config)
    old_state, new_state = model.config.state_dim, config.state_dim
    weights = dict(model.state_dict())
    for name, module in wide.named_modules():
        if not isinstance(module, MLP):
            continue
        before = model.get_submodule(name)
        grown = module.in_dim - before.in_dim
        if grown % (new_state - old_state):
            raise ValueError(f"widen_to_pitch_aware: {name} grew by {grown} columns, not whole state columns")
        key = f"{name}.hidden_layers.0.weight"
        weights[key] = widen_state_blocks(weights[key], grown // (new_state - old_state), old_state, new_state)
    wide.load_state_dict(weights)  # strict: any other size that changed is an error here
    return wide.train(model.training)


def _grown_config(model: HRN, caller: str, option: str, already: str, changes: dict[str, Any]) -> Any:
    """``model``'s config with ``option`` switched on and ``changes`` applied; ValueError naming
    ``caller`` unless ``model`` is an HRN without the option."""
    if not isinstance(model, HRN):
        raise ValueError(f"{caller}: an HRN is needed, got {type(model).__name__}")
    if getattr(model.config, option):
        raise ValueError(f"{caller}: the model {already}")
    return dataclasses.replace(model.config, **{**changes, option: True})


def with_collision_force(model: HRN, **changes: Any) -> HRN:
    """An :class:`HRN` with ``HRNConfig.collision_force`` holding ``model``'s weights and zero weights
    on the force (the collision MLP's first layer, and the equivariant readout's rows of the force
    vectors), so it predicts what ``model`` does. ``changes`` as in :func:`widen_to_pitch_aware`."""
    config = _grown_config(model, "with_collision_force", "collision_force", "reads the force already", changes)
    grown = HRN(config)
    old, new = model.collision, grown.collision
    weights = dict(model.state_dict())
    key = "collision.phi.hidden_layers.0.weight"
    first = widen_state_blocks(weights[key], 2, old.node_dim, new.node_dim)
    extra_edge = new.phi.in_dim - 2 * new.node_dim - (old.phi.in_dim - 2 * old.node_dim)
    weights[key] = torch.cat([first, first.new_zeros(first.size(0), extra_edge)], dim=1)
    if config.equivariant:
        for name in ("collision.vector.weight", "collision.vector.bias"):
            value = weights[name]
            rows = (new.basis - old.basis) * new.channels
            weights[name] = torch.cat([value, value.new_zeros(rows, *value.shape[1:])], dim=0)
    grown.load_state_dict(weights)  # strict: any other size that changed is an error here
    return grown.train(model.training)
