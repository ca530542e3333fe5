"""Files: atomic writing (a reader never sees half a file, a killed writer leaves none behind), the
lock of a folder that several processes write, a file's SHA-256, and silencing C-level prints."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import math
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

#: permissions of every file written here (what a plain ``open`` gives under a 022 umask)
FILE_MODE = 0o644
#: the lock file of a folder written by several processes (:class:`FolderLock`)
LOCK_NAME = ".lock"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same folder, so ``os.replace`` is atomic), renamed onto
    ``path`` on success and removed on any exception (``KeyboardInterrupt`` included)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix + ".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, FILE_MODE)  # mkstemp makes 0600; outputs are meant to be shared
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], Any]) -> None:
    """Call ``write(fileobj)`` on a temporary binary file and move it onto ``path``."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


class FolderLock:
    """This process as one writer of a folder, among others that may write it at the same time.

    Two POSIX record locks (``fcntl.lockf``) on the folder's :data:`LOCK_NAME`: byte 1 shared by
    every writer while it writes, byte 0 exclusive for a short read-check-write (:meth:`exclusive`).
    :attr:`alone`: this writer took byte 1 exclusively at the start, so temporaries a killed writer
    left may be removed (:func:`remove_temporaries`). The kernel drops both when the process ends.
    """

    def __init__(self, folder: str | os.PathLike) -> None:
        self.path = Path(folder) / LOCK_NAME
        self._fd: int | None = None
        self.alone = False

    def __enter__(self) -> FolderLock:
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, FILE_MODE)
        try:
            fcntl.lockf(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, 1)
            self.alone = True
        except OSError:
            self.alone = False
            fcntl.lockf(self._fd, fcntl.LOCK_SH, 1, 1)
        return self

    def shared(self) -> None:
        """Let other writers in (after this one has tidied the folder, when :attr:`alone`)."""
        fcntl.lockf(self._fd, fcntl.LOCK_SH, 1, 1)

    @contextlib.contextmanager
    def exclusive(self) -> Iterator[None]:
        """The block runs while no other writer of the folder runs its own (waits for it)."""
        fcntl.lockf(self._fd, fcntl.LOCK_EX, 1, 0)
        try:
            yield
        finally:
            fcntl.lockf(self._fd, fcntl.LOCK_UN, 1, 0)

    def __exit__(self, *exc: object) -> None:
        os.close(self._fd)  # releases both locks
        self._fd = None


def remove_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporaries :func:`atomic_path` left in ``folder`` when its writer was killed
    (``.<name>.<random>.tmp``); the removed paths. Call it only when no writer of the folder is
    running (:attr:`FolderLock.alone`)."""
    removed = []
    for path in Path(folder).glob(".*.tmp"):
        if path.is_file():
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None, in nested dicts and lists (strict
    JSON has no Infinity): a null count or bound then means "never reached"."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def silenced(*streams: IO[str]) -> Iterator[None]:
    """Send what C code writes to the file descriptors of ``streams`` (default: stdout) to
    ``/dev/null`` inside the block (pybullet prints a banner on import and counts from
    ``loadSoftBody`` and ``vhacd``); a stream without a real descriptor is left as it is."""
    fds = []
    for stream in streams or (sys.stdout,):
        try:
            fds.append(stream.fileno())
            stream.flush()
        except (AttributeError, OSError, ValueError):  # captured streams without a real fd
            pass
    saved = [os.dup(fd) for fd in fds]
    try:
        with open(os.devnull, "w") as devnull:
            for fd in fds:
                os.dup2(devnull.fileno(), fd)
        yield
    finally:
        for fd, copy in zip(fds, saved):
            os.dup2(copy, fd)
            os.close(copy)


def quiet_stdout() -> contextlib.AbstractContextManager[None]:
    """:func:`silenced` stdout."""
    return silenced(sys.stdout)


def import_pybullet():
    """pybullet, imported without the build-time banner its C code prints on import."""
    with silenced(sys.stdout, sys.stderr):
        import pybullet
    return pybullet
