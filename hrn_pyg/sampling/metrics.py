r"""Scores of a set of sampled futures against a ground-truth ensemble.

``K`` samples :math:`X_1..X_K` and ``M`` members :math:`y_1..y_M`, each in
:math:`\mathbb{R}^D` (``D`` = 3 for one point, ``3L`` for a flattened scene); dimensions between
the first and the last are kept (a score per index). Euclidean, metres; ``K = 1`` is a
deterministic model. Computed and returned on the samples' device.
"""

from __future__ import annotations

import torch
from torch import Tensor


def paired(samples: Tensor, truth: Tensor, name: str = "truth") -> tuple[Tensor, Tensor]:
    """``samples`` ``(K, *, D)`` and ``truth`` ``(M, *, D)`` checked and in one float dtype, on the
    samples' device."""
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
    samples, truth = paired(samples, truth)
    to_truth = (samples.unsqueeze(1) - truth.unsqueeze(0)).norm(dim=-1).mean(dim=(0, 1))
    spread = (samples.unsqueeze(1) - samples.unsqueeze(0)).norm(dim=-1).mean(dim=(0, 1))
    return to_truth - 0.5 * spread


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
