"""A polite stop for long loops: SIGINT / SIGTERM become a flag checked between units of work.

A signal that arrives inside a library call (TorchRL's collector, a PPO minibatch) can be
turned into another exception there, and the work since the last checkpoint is lost. Inside
:class:`StopRequest` the first SIGINT or SIGTERM only sets :attr:`StopRequest.requested`; the
loop checks it after each unit, writes its checkpoint and stops. A second signal interrupts at
once (the previous handlers are back in place), so a stuck loop can still be killed.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

#: the signals turned into a request (SIGTERM is what `kill` and a session's end send)
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Context manager: ``with StopRequest() as stop: ... if stop.requested: save; break``.

    Outside the main thread (where Python cannot install handlers) it does nothing and
    ``requested`` stays False.
    """

    def __init__(self) -> None:
        self.requested = False
        self.signal: int | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.requested, self.signal = True, signum
        self._restore()  # a second signal acts as usual

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for signum in SIGNALS:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        self._restore()
