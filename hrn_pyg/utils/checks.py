"""Checks of input at the package's boundaries, each written once.

Every function raises :class:`ValueError` with a message that names the bad argument.
"""

from __future__ import annotations

import torch
from torch import Tensor


def non_finite_error(name: str) -> ValueError:
    """The error of a tensor ``name`` that holds NaN or infinite values."""
    return ValueError(f"{name} contains NaN or infinite values")


def check_finite(name: str, value: Tensor) -> None:
    """Raise unless every entry of ``value`` is finite (one host read on a GPU)."""
    if not bool(torch.isfinite(value).all()):
        raise non_finite_error(name)


def check_rate(rate: float, name: str = "rate") -> None:
    """Raise unless ``rate`` is a dropout rate, ``0 <= rate < 1``."""
    if isinstance(rate, bool) or not 0.0 <= float(rate) < 1.0:
        raise ValueError(f"{name} must be in [0, 1), got {rate!r}")


def check_count(value: int, name: str) -> None:
    """Raise unless ``value`` is an integer >= 1 (a number of samples, steps, copies)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
