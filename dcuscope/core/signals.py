"""Ctrl-C or SIGTERM while a long-running command is still starting up, or already finishing.

Until a command's main loop has its own handlers in place, Python turns SIGINT into a
KeyboardInterrupt wherever the interpreter happens to be. Inside PyGObject's type registration
(our elements registering) that aborts the whole process with an assertion; elsewhere it prints
a traceback and skips the clean stop. ``hold()`` makes the first SIGINT or SIGTERM a note instead;
the main loop, once its handlers are installed, asks ``held()`` and stops at once if one came.
A second SIGINT while held ends the process at once (exit 130), so a start that hangs (an
unreachable camera, say) can still be ended from the keyboard. SIGTERM never aborts, here as in
the main loops: it asks for the clean stop, which a second one only repeats (a service manager
that loses patience sends SIGKILL). ``finishing()`` does the same after the main loop, while the
command writes what is left.
"""

from __future__ import annotations

import os
import signal

HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)

_received: int | None = None
_holding = False
_finishing = False


def hold() -> None:
    """From now until the main loop takes over, remember the first SIGINT/SIGTERM."""
    global _received, _holding, _finishing
    _received, _holding, _finishing = None, True, False
    for signum in HELD_SIGNALS:
        signal.signal(signum, _note)


def held() -> int | None:
    """The signal that came while held (``signal.SIGINT`` ...), or None."""
    return _received


def finishing() -> None:
    """The main loop is over (its stop is done) and the command writes what is left, the trace's
    last events: from now on SIGTERM is only said (the stop it asks for is under way), Ctrl-C
    ends the process at once. GLib, whose handlers the main loop used, left both signals fatal.
    Only in a process that called :func:`hold`: a library user keeps its own handlers."""
    global _finishing
    if not _holding:
        return
    _finishing = True
    for signum in HELD_SIGNALS:
        signal.signal(signum, _note)


def _note(signum: int, _frame) -> None:
    global _received
    name = signal.Signals(signum).name
    when = "while finishing" if _finishing else "while starting"
    if _received is not None or _finishing:
        if signum == signal.SIGINT:
            _tell(f"{name} {'again ' if not _finishing else ''}{when}: aborted")
            os._exit(128 + signum)
        _tell(f"{name} {when}: already stopping (Ctrl-C to abort)")
        return
    _received = signum
    again = "again " if signum == signal.SIGINT else ""
    _tell(f"{name} {when}: stopping as soon as started (Ctrl-C {again}to abort)")


def _tell(text: str) -> None:
    # os.write, not print: a handler may run in the middle of another write to sys.stderr;
    # and a closed stderr must not turn the signal into an exception after all
    try:
        os.write(2, f"\ndcuscope: {text}\n".encode())
    except OSError:
        pass
