"""The relay's compaction (``--compact-after SECONDS``, 0: none): what :mod:`dcuscope.relay.store.compaction`
says, every COMPACT_EVERY_S, in a process of its own beside the relay. A run's rollups come with
it: the first within :func:`rollups_within_s` of its start (90 s by default), then at every pass.

A process, not a thread: decoding batches, pairing their frames for the rollups and encoding
segments cost about a microsecond of CPU an event, which in the relay's process would compete with
its event loop for Python's one lock. Beside it, the relay's own CPU per event is what it was, and
compaction runs on another core. The relay's commits never wait for it but for the short
transaction that swaps a range of batches for its segment.

:class:`Compactor` (in the relay) starts ``python -m dcuscope.relay.store.compactor``, hands it its settings
on stdin (the store's URL may hold a password: not on a command line) and keeps stdin open: the
child stops when it closes, so a relay killed outright takes its compactor with it. The child
prints one JSON line of its totals after each pass, which :meth:`Compactor.view` shows in
``/api/health``; it logs to the relay's stderr. SIGTERM stops it after the range being moved.

For tests only, ``DCUSCOPE_TEST_LIVE_WAIT_S`` in the relay's environment replaces LIVE_WAIT_S: with a
short ``--compact-after`` it has a live run's rollups come in seconds, not in a minute and a half.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import Database
from dcuscope.relay.store.compaction import LIVE_WAIT_S, Compacted, compact
from dcuscope.relay.store.engines import open_database

COMPACT_EVERY_S = 30.0
"""How often the due batches are looked for (more often with a short ``--compact-after``); also
once as the process starts, ``--compact-after`` after the relay did (a relay restarted compacts
what waited meanwhile)."""
MIN_EVERY_S = 0.5
STOP_S = 30.0
"""How long a stopping relay waits for its compactor to finish the range it is moving."""
TEST_LIVE_WAIT_ENV = "DCUSCOPE_TEST_LIVE_WAIT_S"

log = logging.getLogger(__name__)


def pass_every_s(after_s: float) -> float:
    """How often a relay compacting ``after_s`` after storing looks: twice as often as batches come
    due, at most every COMPACT_EVERY_S."""
    return min(COMPACT_EVERY_S, max(after_s / 2, MIN_EVERY_S))


def live_wait_s() -> float:
    """LIVE_WAIT_S, unless a test set TEST_LIVE_WAIT_ENV."""
    return float(os.environ.get(TEST_LIVE_WAIT_ENV, LIVE_WAIT_S))


def rollups_within_s(after_s: float, live_wait: float = LIVE_WAIT_S) -> float:
    """How long after a run's start its first rollups are written, at most (the compaction process
    starts ``after_s`` after the relay, a run's first batch comes due ``after_s`` after it was stored
    and, the run going on, is compacted at the first pass once it waited ``live_wait``): 90 s with
    the default ``--compact-after``, and then as often as the relay compacts it."""
    return max(after_s, live_wait) + pass_every_s(after_s)


class Compactor:
    """The compaction process of a relay: started, watched and stopped; :meth:`view` for /api/health."""

    def __init__(self, db: str | Path, after_s: float, name: str = "") -> None:
        self.db, self.after_s, self.name = db, after_s, name
        self.every_s = pass_every_s(after_s)
        self.live_wait_s = live_wait_s()
        self.last: dict = {}
        self.proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._timer: threading.Timer | None = None
        self._lock = threading.Lock()
        self._stopped = False

    def start(self) -> None:
        """Start the process once batches can be due (``after_s`` from now): a relay that lives less
        long costs no process (the CPU of starting one: about half a second)."""
        self._timer = threading.Timer(self.after_s, self._spawn)
        self._timer.daemon = True
        self._timer.start()

    def _spawn(self) -> None:
        with self._lock:
            if self._stopped:
                return
            self.proc = subprocess.Popen([sys.executable, "-m", "dcuscope.relay.store.compactor"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True)
        self.proc.stdin.write(json.dumps({"db": str(self.db), "after_s": self.after_s, "every_s": self.every_s,
                                          "live_wait_s": self.live_wait_s, "name": self.name}) + "\n")
        self.proc.stdin.flush()
        self._reader = threading.Thread(target=self._read, name="dcuscope-relay-compact", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                self.last = json.loads(line)
            except ValueError:
                continue
        code = self.proc.wait()
        if code not in (0, -signal.SIGTERM):
            log.warning("the compaction process exited with status %d: batches are no longer compacted until the "
                        "relay restarts (`dcuscope db compact` compacts them meanwhile)", code)

    def stop(self) -> None:
        with self._lock:
            self._stopped = True
            if self._timer is not None:
                self._timer.cancel()
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(STOP_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)

    def view(self) -> dict:
        running = self.proc is not None and self.proc.poll() is None
        return {"after_s": self.after_s, "every_s": self.every_s,
                "rollups_within_s": rollups_within_s(self.after_s, self.live_wait_s),
                "pid": self.proc.pid if self.proc else None,
                "running": running, "passes": 0, **Compacted().to_dict(), **self.last}


class Passes:
    """The child's loop: a pass now, then every ``every_s`` until ``stop`` is set."""

    def __init__(self, db: str, after_s: float, every_s: float, name: str, stop: threading.Event,
                 live_wait: float = LIVE_WAIT_S) -> None:
        self.db, self.after_s, self.every_s, self.name, self.stop = db, after_s, every_s, name, stop
        self.live_wait = live_wait
        self.done = Compacted()
        self.passes = 0
        self.failing: str | None = None
        self._database: Database | None = None

    def run(self) -> None:
        try:
            self.run_pass()
            while not self.stop.wait(self.every_s):
                self.run_pass()
        finally:
            if self._database is not None:
                self._database.close()

    def run_pass(self) -> None:
        started, cpu = time.monotonic(), time.process_time()
        try:
            if self._database is None:
                self._database = open_database(self.db, name=self.name)  # the relay's: one relay in /api/health
            now = time.time_ns()
            done = compact(self._database, now - int(self.after_s * 1e9), stop=self.stop.is_set,
                           waited_ns=now - int(self.live_wait * 1e9))
            self._database.give_back_space()
        except RelayError as exc:  # the store failed (StoreUnavailable is one): next pass, on a new connection
            if self.failing is None:
                log.warning("compaction fails, tried again every %g s: %s", self.every_s, exc)
            self.failing = str(exc)
            self._forget()
            self._say(started, cpu)
            return
        if self.failing is not None:
            log.warning("compaction works again")
            self.failing = None
        self.passes += 1
        self.done.add(done)
        self._say(started, cpu)

    def _forget(self) -> None:
        if self._database is not None:
            try:
                self._database.close()
            except Exception:  # noqa: BLE001 - a connection already broken
                pass
            self._database = None

    def _say(self, started: float, cpu: float) -> None:
        print(json.dumps({"passes": self.passes, **self.done.to_dict(), "failing": self.failing,
                          "last_pass_s": round(time.monotonic() - started, 3),
                          "cpu_s": round(time.process_time(), 3)}), flush=True)


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = json.loads(sys.stdin.readline() or "{}")
    if not settings.get("db"):
        print("dcuscope.relay.store.compactor: started by the relay (its settings come on stdin)", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())

    def parent_gone() -> None:  # stdin closes when the relay ends, however it ends
        sys.stdin.read()
        stop.set()

    threading.Thread(target=parent_gone, daemon=True).start()
    Passes(settings["db"], float(settings["after_s"]), float(settings["every_s"]), settings.get("name", ""), stop,
           float(settings.get("live_wait_s", LIVE_WAIT_S))).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
