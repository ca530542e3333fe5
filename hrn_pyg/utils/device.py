"""Choosing the torch device for a command (``--device``).

``default_device()`` is CUDA when it is usable, else the CPU; ``resolve_device(name)`` turns a
user's ``--device`` string into a :class:`torch.device`, refusing strings torch does not parse
and CUDA requests on a machine without CUDA, each with a one-line :class:`ValueError`.
"""

from __future__ import annotations

import torch

__all__ = ["DEVICE_TYPES", "default_device", "resolve_device"]

#: the kinds of device the package runs on (``meta`` has no data, ``mps`` and the others are untested)
DEVICE_TYPES = ("cpu", "cuda")


def default_device() -> torch.device:
    """``cuda`` if ``torch.cuda.is_available()``, otherwise ``cpu``."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(name: str | None) -> torch.device:
    """The device named by ``name`` (``None`` or ``""`` gives :func:`default_device`).

    Accepts what :class:`torch.device` parses of the :data:`DEVICE_TYPES` (``"cpu"``, ``"cuda"``, ``"cuda:1"``).

    Raises:
        ValueError: ``name`` is not a device string torch knows, or names a device type not in
            :data:`DEVICE_TYPES`; CUDA is asked for but
            ``torch.cuda.is_available()`` is False; or a CUDA index past the visible devices.
    """
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
