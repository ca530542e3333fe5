"""A polite stop for long loops: SIGINT / SIGTERM become a flag checked between units of work.

Inside :class:`StopRequest` the first signal only sets :attr:`StopRequest.requested`, so the
loop can finish its unit, write its checkpoint and stop; a second one interrupts at once.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

#: the signals turned into a request (SIGTERM is what `kill` and a session's end send)
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """Context manager: ``with StopRequest() as stop: ... if stop.requested: save; break``; outside
    the main thread it does nothing."""

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
