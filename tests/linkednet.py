"""Two DCUs on a real network for tests: a sender namespace and a receiver namespace joined by one
veth pair. Links slower and lossier than a veth are made with :mod:`tests.delayline` (this
machine's kernel has no netem). Addresses are private to the namespaces (10.79.0.0/24);
:meth:`LinkedNet.close` ends the processes and removes the namespaces, the pair with them,
whatever happened.
"""

from __future__ import annotations

import os
import random
import subprocess
from pathlib import Path

from tests.ptpnet import end_processes, netns_permitted, pair_namespaces

__all__ = ["LinkedNet", "netns_permitted", "SENDER_ADDR", "RECEIVER_ADDR"]

SENDER_ADDR, RECEIVER_ADDR = "10.79.0.1", "10.79.0.2"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


class LinkedNet:
    """Namespaces ``sender`` (SENDER_ADDR) and ``receiver`` (RECEIVER_ADDR), one veth pair between."""

    def __init__(self, tmp: Path) -> None:
        tag = f"ln{os.getpid() % 100000:05d}{random.randrange(16 ** 3):03x}"
        self.sender, self.receiver, self.tmp, self.tag = f"{tag}-s", f"{tag}-r", tmp, tag
        self._procs: list[subprocess.Popen] = []

    def __enter__(self) -> LinkedNet:
        try:
            pair_namespaces((self.sender, f"{self.tag}s", SENDER_ADDR), (self.receiver, f"{self.tag}r", RECEIVER_ADDR))
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def prefix(self, ns: str) -> list[str]:
        return ["ip", "netns", "exec", ns]

    def spawn(self, ns: str, argv: list[str], log: str, env: dict | None = None) -> subprocess.Popen:
        """``argv`` in namespace ``ns``, its output to ``tmp/LOG.log``; ended by :meth:`close` if still running."""
        with open(self.tmp / f"{log}.log", "wb") as out:
            proc = subprocess.Popen([*self.prefix(ns), *argv], stdout=out, stderr=subprocess.STDOUT, env=env,
                                    cwd=self.tmp, start_new_session=True)
        self._procs.append(proc)
        return proc

    def log(self, name: str) -> str:
        path = self.tmp / f"{name}.log"
        return path.read_text(errors="replace")[-3000:] if path.exists() else ""

    def close(self) -> None:
        end_processes(self._procs)
        for ns in (self.sender, self.receiver):
            _ip("netns", "del", ns, check=False)
