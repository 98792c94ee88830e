"""Progress and messages for a terminal or pipe that may go away under a running pipeline.

Python ignores SIGPIPE, so a write to a closed stderr (``dcuscope run ... 2>&1 | head``, an ssh
session that dropped) raises BrokenPipeError. Raised inside a GLib callback, that silently
removed the callback: the run's ticker (--duration, the end-of-stream deadline) and its SIGTERM
handler died with it and the run never stopped. A Console drops its output instead, once its
stream is gone, and the run goes on to a clean end.
"""

from __future__ import annotations

from typing import TextIO


class Console:
    def __init__(self, stream: TextIO):
        self.stream: TextIO | None = stream
        self.tty = _isatty(stream)

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> None:
        """Write and flush ``text``; nothing, from the first failed write on."""
        if self.stream is None:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # ValueError: the stream was closed
            self.stream = None

    def flush(self) -> None:
        """Writes flush already (TextIO compatibility)."""


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (OSError, ValueError):
        return False
