"""Choosing the torch device for a command (``--device``): :func:`default_device` (CUDA when
usable, else the CPU) and :func:`resolve_device`."""

from __future__ import annotations

import torch

__all__ = ["DEVICE_TYPES", "default_device", "resolve_device"]

#: the kinds of device the package runs on (``meta`` has no data, ``mps`` and the others are untested)
DEVICE_TYPES = ("cpu", "cuda")


def default_device() -> torch.device:
    """``cuda`` if ``torch.cuda.is_available()``, otherwise ``cpu``."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(name: str | None) -> torch.device:
    """The device named by ``name`` (``None`` or ``""``: :func:`default_device`), one of
    :data:`DEVICE_TYPES` as :class:`torch.device` parses it (``"cpu"``, ``"cuda"``, ``"cuda:1"``).
    ValueError for another string, or CUDA (or a CUDA index) the machine does not have."""
    if name is None or not str(name).strip():
        return default_device()
    text = str(name).strip()
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"unknown device {text!r}; expected e.g. 'cpu', 'cuda' or 'cuda:0'") from None
    if device.type not in DEVICE_TYPES:
        raise ValueError(f"device {text!r}: the package runs on {' or '.join(DEVICE_TYPES)} devices only")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("cuda requested but torch.cuda.is_available() is False")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {text!r} requested but only {torch.cuda.device_count()} "
                             "CUDA device(s) are visible")
    return device
