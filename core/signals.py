"""Ctrl-C or SIGTERM while a long-running command is still starting up.

Until a command's main loop has its own handlers in place, Python turns SIGINT into a
KeyboardInterrupt wherever the interpreter happens to be. Inside PyGObject's type registration
(our elements registering) that aborts the whole process with an assertion; elsewhere it prints
a traceback and skips the clean stop. ``hold()`` makes the first SIGINT or SIGTERM a note instead;
the main loop, once its handlers are installed, asks ``held()`` and stops at once if one came.
A second signal while held ends the process at once (exit 128+signal), so a start that hangs
(an unreachable camera, say) can still be ended from the keyboard.
"""

from __future__ import annotations

import os
import signal

HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_received: int | None = None


def hold() -> None:
    """From now until the main loop takes over, remember the first SIGINT/SIGTERM."""
    global _received
    _received = None
    for signum in HELD_SIGNALS:
        signal.signal(signum, _note)


def held() -> int | None:
    """The signal that came while held (``signal.SIGINT`` ...), or None."""
    return _received


def _note(signum: int, _frame) -> None:
    global _received
    name = signal.Signals(signum).name
    if _received is not None:
        _tell(f"{name} again while starting: aborted")
        os._exit(128 + signum)
    _received = signum
    _tell(f"{name} while starting: stopping as soon as started (again to abort)")


def _tell(text: str) -> None:
    # os.write, not print: a handler may run in the middle of another write to sys.stderr;
    # and a closed stderr must not turn the signal into an exception after all
    try:
        os.write(2, f"\ndcuscope: {text}\n".encode())
    except OSError:
        pass
