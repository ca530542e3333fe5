r"""Scores of a set of sampled futures against a ground-truth ensemble.

``K`` samples :math:`X_1..X_K` and ``M`` members :math:`y_1..y_M`, each in
:math:`\mathbb{R}^D` (``D`` = 3 for one point, ``3L`` for a flattened scene); dimensions between
the first and the last are kept (a score per index). Euclidean, metres; ``K = 1`` is a
deterministic model. Computed and returned on the samples' device.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hrn_pyg.data.graph import object_centres as graph_object_centres
from hrn_pyg.data.graph import object_span

#: the two sides of the wedge's ridge, in the order :func:`side_fractions` returns them
SIDES = ("below", "above")


def _pair(samples: Tensor, truth: Tensor, name: str = "truth") -> tuple[Tensor, Tensor]:
    samples = torch.as_tensor(samples)
    truth = torch.as_tensor(truth, device=samples.device)  # e.g. a numpy ensemble against device samples
    if samples.dim() < 2 or samples.shape[0] < 1:
        raise ValueError(f"samples must be [K>=1, ..., D], got {tuple(samples.shape)}")
    if truth.shape[1:] != samples.shape[1:] or truth.shape[0] < 1:
        raise ValueError(f"{name} must be [M>=1, {', '.join(map(str, samples.shape[1:]))}], got {tuple(truth.shape)}")
    dtype = torch.promote_types(torch.promote_types(samples.dtype, truth.dtype), torch.float32)
    return samples.to(dtype), truth.to(dtype)


def energy_score(samples: Tensor, truth: Tensor) -> Tensor:
    r"""Energy score of the samples, averaged over the ground-truth members (lower is better).

    .. math::
        \mathrm{ES} = \frac{1}{M} \sum_{m=1}^{M} \frac{1}{K} \sum_{k=1}^{K} \lVert X_k - y_m \rVert
        \; - \; \frac{1}{2K^2} \sum_{k=1}^{K} \sum_{k'=1}^{K} \lVert X_k - X_{k'} \rVert

    A proper scoring rule; ``K = 1`` gives the plain error :math:`\lVert X_1 - y \rVert`.

    **Shapes:** samples ``(K, *, D)``, truth ``(M, *, D)``; returns ``(*)``.
    """
    samples, truth = _pair(samples, truth)
    to_truth = (samples.unsqueeze(1) - truth.unsqueeze(0)).norm(dim=-1).mean(dim=(0, 1))
    spread = (samples.unsqueeze(1) - samples.unsqueeze(0)).norm(dim=-1).mean(dim=(0, 1))
    return to_truth - 0.5 * spread


def best_of_k_error(samples: Tensor, truth: Tensor) -> Tensor:
    r"""Mean particle distance of the closest sample, averaged over the ground-truth members.

    .. math::
        \mathrm{BoK} = \frac{1}{M} \sum_{m=1}^{M} \min_{k} \frac{1}{L} \sum_{l=1}^{L}
            \lVert X_{k,l} - y_{m,l} \rVert

    **Shapes:** samples ``(K, *, L, 3)``, truth ``(M, *, L, 3)``; returns ``(*)``.
    """
    samples, truth = _pair(samples, truth)
    if samples.dim() < 3 or samples.shape[-1] != 3:
        raise ValueError(f"samples must be [K, ..., L, 3], got {tuple(samples.shape)}")
    error = (samples.unsqueeze(1) - truth.unsqueeze(0)).norm(dim=-1).mean(dim=-1)  # [K, M, *]
    return error.min(dim=0).values.mean(dim=0)


def coverage(samples: Tensor, truth: Tensor, per: str = "coordinate") -> Tensor:
    r"""Fraction of the ground truth inside the samples' per-coordinate range
    :math:`[\ell_d, u_d] = [\min_k X_{k,d}, \max_k X_{k,d}]`: ``per="coordinate"``
    :math:`\frac{1}{MD} \sum_{m,d} \mathbb{1}[\ell_d \le y_{m,d} \le u_d]`, ``per="member"``
    :math:`\frac{1}{M} \sum_m \prod_d \mathbb{1}[\ell_d \le y_{m,d} \le u_d]`.

    **Shapes:** samples ``(K, *, D)``, truth ``(M, *, D)``; returns ``(*)``.
    """
    if per not in ("coordinate", "member"):
        raise ValueError(f"per must be 'coordinate' or 'member', got {per!r}")
    samples, truth = _pair(samples, truth)
    low, high = samples.min(dim=0).values, samples.max(dim=0).values
    inside = (truth >= low) & (truth <= high)  # [M, *, D]
    if per == "member":
        return inside.all(dim=-1).to(samples.dtype).mean(dim=0)
    return inside.to(samples.dtype).mean(dim=(0, -1))


def object_centres(positions: Tensor, leaf_object: Tensor, leaf_mass: Tensor) -> Tensor:
    r"""Mass-weighted centre of each object's leaves: the position of its hierarchy root.

    .. math:: r_o = \sum_{l \in o} m_l x_l \Big/ \sum_{l \in o} m_l

    **Shapes:** positions ``(*, L, 3)``, leaf_object ``(L,)`` in ``0..O-1``, leaf_mass ``(L,)``;
    returns ``(*, O, 3)``.
    """
    positions = torch.as_tensor(positions)
    leaf_object = torch.as_tensor(leaf_object, device=positions.device).long()
    leaf_mass = torch.as_tensor(leaf_mass, device=positions.device).to(positions.dtype)
    if positions.dim() < 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must be [..., L, 3], got {tuple(positions.shape)}")
    n_leaves = positions.shape[-2]
    if leaf_object.shape != (n_leaves,) or leaf_mass.shape != (n_leaves,):
        raise ValueError(f"leaf_object and leaf_mass must be [{n_leaves}], got {tuple(leaf_object.shape)}, {tuple(leaf_mass.shape)}")
    if bool((leaf_mass <= 0).any()) or bool((leaf_object < 0).any()):
        raise ValueError("leaf_mass must be > 0 and leaf_object >= 0")
    return graph_object_centres(positions, leaf_object, object_span(leaf_object), leaf_mass)


def root_spread(centres: Tensor) -> Tensor:
    r"""Spread of each object's root over the samples (Fig. 10/11), the RMS distance from their mean:

    .. math:: \sigma_{t,o} = \Bigl(\frac{1}{K} \sum_k \lVert r_{k,t,o} - \bar r_{t,o} \rVert^2\Bigr)^{1/2},
        \qquad \bar r_{t,o} = \frac{1}{K} \sum_k r_{k,t,o}

    **Shapes:** centres ``(K, *, 3)`` (e.g. ``(K, T, O, 3)``); returns ``(*)``.
    """
    centres = torch.as_tensor(centres)
    if centres.dim() < 2 or centres.shape[-1] != 3 or centres.shape[0] < 1:
        raise ValueError(f"centres must be [K>=1, ..., 3], got {tuple(centres.shape)}")
    centres = centres.to(torch.promote_types(centres.dtype, torch.float32))
    deviation = centres - centres.mean(dim=0, keepdim=True)
    return deviation.pow(2).sum(dim=-1).mean(dim=0).sqrt()


def side_fractions(coordinate: Tensor, ridge: float = 0.0) -> Tensor:
    r"""Fraction of trajectories ending on each side (:data:`SIDES`) of the ridge at ``r``:
    :math:`\bigl(\frac{1}{K}\#\{c_k < r\},\ \frac{1}{K}\#\{c_k \ge r\}\bigr)` of the ball's final
    ``coordinate``.

    **Shapes:** coordinate ``(K,)``; returns ``(2,)``.
    """
    coordinate = torch.as_tensor(coordinate)
    if coordinate.dim() != 1 or coordinate.numel() < 1:
        raise ValueError(f"coordinate must be [K>=1], got {tuple(coordinate.shape)}")
    if not bool(torch.isfinite(coordinate).all()):
        raise ValueError("coordinate contains NaN or infinite values")
    below = (coordinate < ridge).to(torch.float64).mean()
    return torch.stack([below, 1.0 - below])
