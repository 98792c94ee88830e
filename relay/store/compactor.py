"""The relay's compaction thread (``--compact-after SECONDS``, 0: none): what
:mod:`relay.store.compaction` says, every COMPACT_EVERY_S, on a store connection of its own.

The writer thread's commits never wait for it but for the short transaction that swaps a range
of batches for its segment (the read and the encoding happen outside it). A store that fails is
tried again at the next pass, said once when it starts failing and once when it works again.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from relay.errors import RelayError
from relay.store.base import Database
from relay.store.compaction import Compacted, compact
from relay.store.engines import open_database

COMPACT_EVERY_S = 30.0
"""How often the due batches are looked for (more often with a short ``--compact-after``); also
once at the start (a relay restarted compacts what waited meanwhile)."""
MIN_EVERY_S = 0.5

log = logging.getLogger(__name__)


class Compactor:
    """Compacts the store's due batches in a thread until stopped; :meth:`view` for /api/health."""

    def __init__(self, db: str | Path, after_s: float, name: str = "", every_s: float = COMPACT_EVERY_S) -> None:
        self.db, self.after_s, self.name = db, after_s, name
        self.every_s = min(every_s, max(after_s / 2, MIN_EVERY_S))
        """Twice as often as batches come due, at most every COMPACT_EVERY_S."""
        self.done = Compacted()
        self.passes = 0
        self.last_pass_s = 0.0
        self.failing: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dcuscope-relay-compact", daemon=True)
        self._database: Database | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop after the range being moved (its transaction is short)."""
        self._stop.set()
        self._thread.join(30)

    def view(self) -> dict:
        return {"after_s": self.after_s, "passes": self.passes, "last_pass_s": round(self.last_pass_s, 3),
                **self.done.to_dict(), "failing": self.failing}

    def _run(self) -> None:
        try:
            self.run_pass()
            while not self._stop.wait(self.every_s):
                self.run_pass()
        finally:
            if self._database is not None:
                self._database.close()

    def run_pass(self) -> Compacted:
        """One pass: every due batch compacted (now, whatever the timer)."""
        started = time.monotonic()
        try:
            if self._database is None:
                self._database = open_database(self.db, name=self.name)  # the relay's: one relay in /api/health
            done = compact(self._database, time.time_ns() - int(self.after_s * 1e9), stop=self._stop.is_set)
            self._database.give_back_space()
        except RelayError as exc:  # the store failed (StoreUnavailable is one): next pass, on a new connection
            if self.failing is None:
                log.warning("compaction fails, tried again every %g s: %s", self.every_s, exc)
            self.failing = str(exc)
            if self._database is not None:
                try:
                    self._database.close()
                except Exception:  # noqa: BLE001 - a connection already broken
                    pass
                self._database = None
            return Compacted()
        if self.failing is not None:
            log.warning("compaction works again")
            self.failing = None
        self.passes += 1
        self.last_pass_s = time.monotonic() - started
        self.done.add(done)
        if done.segments:
            log.debug("compacted %d batches (%d events) into %d segments: %.1f -> %.2f MB in %.2f s", done.batches,
                      done.events, done.segments, done.bytes_before / 1e6, done.bytes_after / 1e6, self.last_pass_s)
        return done
