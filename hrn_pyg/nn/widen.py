r"""A trained model's weights as the start of a larger one: a pitch-aware model from a plain
one (:func:`widen_to_pitch_aware`), or one whose collision module reads the force from one whose
does not (:func:`with_collision_force`).

**Pitch-aware.** A pitch-aware HRN (``HRNConfig.pitch_aware``, :mod:`hrn_pyg.nn.pitch`) reads one more state
column than the plain model it may start from: :math:`\log_2(p / p_{ref})`, appended to the
state vector :math:`s_i` of every particle. Every learned module takes its state vectors as the
first blocks of its input (force :math:`[s_i, f_i]`, collision :math:`[s_i, s_j, \dots]`,
history :math:`[s_i(t), s_i(t-1)]`, propagation :math:`[s_i, s_j, \dots]`, state
:math:`[s_i, e_i]`), so only the first layer of each MLP grows: with :math:`k` state blocks of
:math:`S` columns,

.. math::
    W_1 = [W^{(1)} \,|\, \dots \,|\, W^{(k)} \,|\, W^{rest}]
    \;\mapsto\;
    [W^{(1)} \,|\, 0 \,|\, \dots \,|\, W^{(k)} \,|\, 0 \,|\, W^{rest}],

one zero column after each state block. Everything else is copied. At the reference pitch the
new column is 0, the radius and the geometric scale are those of the plain model, and the
widened model predicts what the plain one does, bit for bit; training then learns what the new
column is for.
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
    """A pitch-aware :class:`HRN` holding ``model``'s weights (zero on the pitch column).

    ``changes``: other fields of the new config (e.g. ``mirror_average=False``); they must keep
    every layer's size. The result is in ``model``'s training mode.
    """
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
    """An :class:`HRN` with ``HRNConfig.collision_force`` holding ``model``'s weights, the
    collision module's weights on the force zero, so it predicts what ``model`` does (up to the
    rounding of longer sums) until training moves them.

    The collision MLP's first layer gains zero columns after each end's state block (the force,
    or with ``equivariant`` the force's horizontal length and vertical part) and, equivariant, at
    the end (the force's dot products with the edge's offset); the equivariant vector readout
    gains zero rows for the two force vectors of its weighted sum. ``changes``: other fields of
    the new config that keep every other layer's size. The result is in ``model``'s training mode.
    """
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
