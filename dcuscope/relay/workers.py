"""``dcuscope relay --workers N``: N relay processes on one host, sharing one port and one store.

Each worker is a whole relay (``dcuscope relay`` again, with ``--reuse-port``): the kernel spreads
new connections over them (SO_REUSEPORT), and since any relay may take any node of a shared store
(:mod:`dcuscope.relay.store.postgres`), nothing else is shared between them. Each answers UDP clock
exchanges on a port of its own (the clock port + its index), which it hands its nodes at hello.
This process only starts them, passes SIGINT/SIGTERM on (and SIGHUP: reread the TLS certificate),
and restarts none: a worker that dies leaves its nodes to reconnect to the others.
"""

from __future__ import annotations

import signal
import subprocess
import sys

STOP_TIMEOUT_S = 20


def worker_argv(argv: list[str], index: int, clock_port: int) -> list[str]:
    """A worker's command line: ``python -m dcuscope.relay`` with the relay's own options (``argv``, of
    ``dcuscope relay`` or of ``python -m dcuscope.relay``), without ``--workers``, with its clock port."""
    out, skip = [], False
    for arg in argv[1:] if argv[:1] == ["relay"] else argv:
        if skip:
            skip = False
            continue
        name = arg.split("=", 1)[0]
        if name in ("--workers", "--clock-port"):
            skip = "=" not in arg
            continue
        out.append(arg)
    return [sys.executable, "-m", "dcuscope.relay", *out, "--reuse-port",
            "--clock-port", str(clock_port + index if clock_port else 0)]


def run_workers(argv: list[str], workers: int, clock_port: int) -> int:
    """Run ``workers`` relays until SIGINT/SIGTERM (passed on, as SIGHUP is); the worst exit status."""
    procs = [subprocess.Popen(worker_argv(argv, i, clock_port)) for i in range(workers)]

    def pass_on(signum: int, _frame) -> None:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signum)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, pass_on)
    codes = [p.wait() for p in procs]
    return max(codes, key=abs)
