"""Choosing the torch device for a command (``--device``).

``default_device()`` is CUDA when it is usable, else the CPU; ``resolve_device(name)`` turns a
user's ``--device`` string into a :class:`torch.device`, refusing strings torch does not parse
and CUDA requests on a machine without CUDA, each with a one-line :class:`ValueError`.
"""

from __future__ import annotations

import torch

__all__ = ["default_device", "resolve_device"]


def default_device() -> torch.device:
    """``cuda`` if ``torch.cuda.is_available()``, otherwise ``cpu``."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def resolve_device(name: str | None) -> torch.device:
    """The device named by ``name`` (``None`` or ``""`` gives :func:`default_device`).

    Accepts anything :class:`torch.device` parses (``"cpu"``, ``"cuda"``, ``"cuda:1"``, ...).

    Raises:
        ValueError: ``name`` is not a device string torch knows; CUDA is asked for but
            ``torch.cuda.is_available()`` is False; or a CUDA index past the visible devices.
    """
    if name is None or not str(name).strip():
        return default_device()
    text = str(name).strip()
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError, TypeError):
        raise ValueError(f"unknown device {text!r}; expected e.g. 'cpu', 'cuda' or 'cuda:0'") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("cuda requested but torch.cuda.is_available() is False")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {text!r} requested but only {torch.cuda.device_count()} "
                             "CUDA device(s) are visible")
    return device
