"""Checkpoints: written atomically, read with ``torch.load(weights_only=True)`` only.

A checkpoint is a flat dict of tensors, numbers and strings: the model and optimiser state
dicts, the step, the random-number states needed to continue bit for bit, and the configs as
JSON text. No pickled Python objects, so loading one cannot run code.
"""

from __future__ import annotations

import json
import os
import pickle
import random
import re
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hrn_pyg.utils.files import atomic_write

#: Keys every checkpoint written by hrn_pyg carries.
REQUIRED_KEYS = ("format", "model", "config")
FORMAT = "hrn_pyg.checkpoint.v1"
#: the deepest nesting of lists and objects in a checkpoint's JSON text (a config is three
#: levels deep); deeper text is refused before a parser recurses into it
MAX_JSON_DEPTH = 32
#: the most characters of a checkpoint's JSON text (a config or a domain is a few kB)
MAX_JSON_CHARS = 1_000_000
#: a JSON string, escapes included (brackets inside one do not nest); an unclosed one runs to
#: the end, so that every character is read once
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"?', re.DOTALL)


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> None:
    """Write ``payload`` (plus the format tag) to ``path`` atomically."""
    payload = {"format": FORMAT, **payload}
    atomic_write(path, lambda fh: torch.save(payload, fh))


class CheckpointError(ValueError):
    """A file that is not a usable hrn_pyg checkpoint; the message is one line naming the file."""


def json_depth(text: str) -> int:
    """The deepest nesting of ``[`` and ``{`` in JSON ``text``, brackets inside strings not
    counted; read off the raw characters (a cumulative sum of +1 per opening and -1 per
    closing bracket), so nothing recurses however deep the text is."""
    bare = _JSON_STRING.sub("", text).encode("utf-8", "replace")
    codes = np.frombuffer(bare, dtype=np.uint8)
    steps = np.isin(codes, (ord("["), ord("{"))).astype(np.int64) - np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(steps).max(initial=0))


def check_json_size(text: str, what: str = "JSON") -> None:
    """ValueError naming ``what`` when ``text`` has more than :data:`MAX_JSON_CHARS` characters
    or is nested more than :data:`MAX_JSON_DEPTH` deep (:func:`json_depth`)."""
    if len(text) > MAX_JSON_CHARS:
        raise ValueError(f"{what} is {len(text)} characters of JSON, more than {MAX_JSON_CHARS}")
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise ValueError(f"{what} is JSON nested {depth} deep, more than {MAX_JSON_DEPTH}")


def bounded_json(text: str, what: str = "JSON") -> Any:
    """``json.loads(text)`` after :func:`check_json_size`; a ValueError (a ``JSONDecodeError``
    for text that is not JSON) otherwise."""
    check_json_size(text, what)
    return json.loads(text)


def _unreadable_reason(exc: BaseException) -> str:
    """A short description of why ``torch.load(weights_only=True)`` failed (torch's own
    messages run to a paragraph that suggests ``weights_only=False``, which is not an option)."""
    text = str(exc)
    refused = re.search(r"(?:Unsupported global: GLOBAL|unsupported GLOBAL) ([\w.]+)", text)
    if refused:
        return f"it holds a pickled {refused.group(1)}, which a weights-only load refuses"
    if re.search(r"Unsupported operand \d+", text):  # random bytes, or opcodes torch.save never writes
        return "not a file written by torch.save"
    if "Weights only load failed" in text:
        return "a pickle that a weights-only load refuses"
    if "zip archive" in text or "PytorchStreamReader" in text:
        return "truncated or damaged zip archive"
    if isinstance(exc, EOFError):
        return "the file is empty or cut short"
    if isinstance(exc, pickle.UnpicklingError):
        return "not a file written by torch.save"
    if isinstance(exc, OSError):
        return exc.strerror or type(exc).__name__
    first_line = next((line.strip() for line in text.splitlines() if line.strip()), "")
    return f"{type(exc).__name__}: {first_line[:120]}" if first_line else type(exc).__name__


def _foreign_reason(ckpt: object) -> str | None:
    """Why a loaded object is not an hrn_pyg checkpoint, or None when it is one."""
    if not isinstance(ckpt, dict):
        return f"it holds a {type(ckpt).__name__}, not a dict"
    missing = [k for k in REQUIRED_KEYS if k not in ckpt]
    if missing:
        return "missing keys " + ", ".join(repr(k) for k in missing)
    if ckpt["format"] != FORMAT:
        return f"format {ckpt['format']!r}, expected {FORMAT!r}"
    if not isinstance(ckpt["model"], dict):
        return f"'model' is a {type(ckpt['model']).__name__}, not a state dict"
    for key in ("config", "domain"):  # JSON text, read with bounds before anyone parses it
        if key == "config" or isinstance(ckpt.get(key), str):
            reason = _json_object_reason(ckpt[key], repr(key))
            if reason is not None:
                return reason
    return None


def _json_object_reason(text: object, what: str) -> str | None:
    """Why ``text`` is not a string holding one bounded JSON object (how configs and domains
    are stored), or None when it is one."""
    if not isinstance(text, str):
        return f"{what} is a {type(text).__name__}, not JSON text"
    try:
        check_json_size(text, what)
    except ValueError as exc:
        return str(exc)
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = None
    return None if isinstance(value, dict) else f"{what} is not JSON text of an object"


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint safely and check that it is one of ours: FileNotFoundError for a missing
    file, :class:`CheckpointError` (one line naming the file) for one a weights-only load cannot
    read or that is not an hrn_pyg checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        with warnings.catch_warnings():  # a foreign pickle protocol is reported below, not warned about
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # whatever torch raises becomes the one-line error below
        raise CheckpointError(f"{path} is not a readable checkpoint ({_unreadable_reason(exc)})") from None
    reason = _foreign_reason(ckpt)
    if reason is not None:
        raise CheckpointError(f"{path} is not an hrn_pyg checkpoint ({reason})")
    return ckpt


def rng_state() -> dict[str, Any]:
    """Python, NumPy and torch global generator states in a weights-only-safe form."""
    py_version, py_state, py_gauss = random.getstate()
    np_state = np.random.get_state()
    return {
        "python": torch.tensor(py_state, dtype=torch.int64),
        "python_version": py_version,
        "numpy_keys": torch.from_numpy(np_state[1].astype(np.int64)),
        "numpy_pos": int(np_state[2]),
        "torch": torch.get_rng_state(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`rng_state`."""
    random.setstate((state["python_version"], tuple(int(v) for v in state["python"].tolist()), None))
    keys = state["numpy_keys"].numpy().astype(np.uint32)
    np.random.set_state(("MT19937", keys, int(state["numpy_pos"]), 0, 0.0))
    torch.set_rng_state(state["torch"])
