"""Which side of the wedge's ridge a ball ends on: the seed paper's Figure 1 as numbers.

A ball dropped within millimetres of a wedge's ridge rolls off to one side or the other; the
physics' own answer is a probability (the share of a perturbed-start pybullet ensemble that
ends at ``x < 0``), and a stochastic model's answer is the share of its samples that do. These
helpers turn positions into that share and compare two sets of per-episode shares.

- :func:`ball_centres`: the ball's mass-weighted centre in each trajectory.
- :func:`share_below`: the fraction of trajectories whose ball ends at ``x < ridge``.
- :func:`brier_score`, :func:`split_difference`: mean squared / absolute difference of
  per-episode probabilities.
- :func:`ridge_config`: the scene settings a ``hrn-pyg generate`` folder was made with.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from benchmarks.common import object_centres

#: the wedge scene's ball is object 0; the ridge runs along y at x = 0
BALL, RIDGE_X = 0, 0.0


def ball_centres(positions: Tensor, leaf_object, leaf_mass) -> Tensor:
    """Mass-weighted centre of the ball's leaves.

    **Shapes:** positions ``(*, L, 3)``, leaf_object / leaf_mass ``(L,)``; returns ``(*, 3)``.
    """
    return object_centres(positions, torch.as_tensor(np.asarray(leaf_object)),
                          torch.as_tensor(np.asarray(leaf_mass)))[..., BALL, :]


def share_below(ball_x: Tensor, ridge: float = RIDGE_X) -> float:
    """Fraction of trajectories whose ball centre ends at ``x < ridge``; ``ball_x`` ``(K,)``."""
    ball_x = torch.as_tensor(ball_x)
    if ball_x.dim() != 1 or ball_x.numel() == 0:
        raise ValueError(f"ball_x must be [K>=1], got {tuple(ball_x.shape)}")
    if not bool(torch.isfinite(ball_x).all()):
        raise ValueError("ball_x contains NaN or infinite values")
    return float((ball_x < ridge).double().mean())


def _probabilities(p, q) -> tuple[np.ndarray, np.ndarray]:
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    if p.shape != q.shape or p.ndim != 1 or p.size == 0:
        raise ValueError(f"need two equal-length lists of per-episode probabilities, got {p.shape} and {q.shape}")
    if ((p < 0) | (p > 1) | (q < 0) | (q > 1)).any() or not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise ValueError("probabilities must lie in [0, 1]")
    return p, q


def brier_score(p_model, p_truth) -> float:
    r"""Mean over episodes of :math:`(p_{model} - p_{truth})^2`: 0 for a model whose shares are
    the physics'; a constant 1/2 scores :math:`\overline{(1/2 - p)^2}`."""
    p, q = _probabilities(p_model, p_truth)
    return float(np.mean((p - q) ** 2))


def split_difference(p_model, p_truth) -> float:
    r"""Mean over episodes of :math:`|p_{model} - p_{truth}|`."""
    p, q = _probabilities(p_model, p_truth)
    return float(np.mean(np.abs(p - q)))


def ridge_config(folder: str | Path):
    """The wedge scene with the settings recorded in a generated folder's ``meta.json``."""
    from hrn_pyg.data.scene_file import builtin_scene

    meta_path = Path(folder) / "meta.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"no {meta_path}: pass a folder written by `hrn-pyg generate --scene wedge`")
    meta = json.loads(meta_path.read_text())
    if meta.get("scene", "wedge") != "wedge":
        raise ValueError(f"{folder} holds {meta.get('scene')!r} episodes, not wedge")
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in (meta.get("config") or {}).items()}
    return builtin_scene("wedge", **fields)
