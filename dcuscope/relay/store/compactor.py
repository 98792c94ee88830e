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

**At start** the process starts CATCH_UP_AFTER_S in, not ``--compact-after`` later, when the store holds
batches stored before the relay started (a relay killed outright, SIGKILL or a crash, left them raw):
its first pass compacts, whole, those of the runs not heard from since (:func:`catch_up`), and says so
in the log. The nodes that resume their runs on this relay are back by then, and their runs are left
to the usual passes.

**At stop** (SIGINT, SIGTERM), once its compaction process ended and its writer committed the last
batches, the relay compacts in its own process every batch still raw but those of runs another relay
owns (:func:`roll_up_at_stop`): a stopped relay leaves its runs' rollups whole. It gives up after
STOP_ROLLUP_S, between two ranges, and its last log lines say what it rolled up and how long it took,
or what it left raw (compacted by the next relay as it starts; counted meanwhile by ``dcuscope stats
--since`` and History from the batches). A run whose node is still live when its relay stops has its
last frames in flight cut: they count as incomplete in the rollups.

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
from dcuscope.relay.guard import redact
from dcuscope.relay.store.base import Database
from dcuscope.relay.store.compaction import LIVE_WAIT_S, Compacted, compact
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.unrolled import hhmm

COMPACT_EVERY_S = 30.0
"""How often the due batches are looked for (more often with a short ``--compact-after``); also
once as the process starts, ``--compact-after`` after the relay did (a relay restarted compacts
what waited meanwhile)."""
MIN_EVERY_S = 0.5
STOP_ROLLUP_S = 10.0
"""The longest a stopping relay compacts what its runs hold raw (about a microsecond of CPU an event:
10 s is 10 million events, two minutes of 20 DCUs at the paper's pace; a relay's raw tail is at most
``--compact-after`` plus a pass of its events)."""
CATCH_UP_AFTER_S = 10.0
"""How long a relay that found raw batches of an earlier relay waits before compacting them: its first
seconds are the nodes' (a node reconnects within a few), not a process start's."""
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

    def __init__(self, db: str | Path, after_s: float, name: str = "", owner: str = "") -> None:
        """``owner``: who holds the relay's leases on a shared store (its runs are its own to compact)."""
        self.db, self.after_s, self.name, self.owner = db, after_s, name, owner
        self.every_s = pass_every_s(after_s)
        self.live_wait_s = live_wait_s()
        self.last: dict = {}
        self.proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self.started_ns = 0

    def start(self) -> None:
        """Start the process CATCH_UP_AFTER_S in if an earlier relay left batches raw, else once batches
        can be due (``after_s`` from now): a relay that lives less long costs no process (the CPU of
        starting one: about half a second)."""
        self.started_ns = time.time_ns()
        threading.Thread(target=self._begin, name="dcuscope-relay-compact-start", daemon=True).start()

    def _begin(self) -> None:
        wait_s = min(CATCH_UP_AFTER_S, self.after_s) if self._left_before_start() else self.after_s
        if not self._stopping.wait(wait_s):
            self._spawn()

    def _left_before_start(self) -> bool:
        try:
            database = open_database(self.db, create=False, name=self.name)
        except RelayError:
            return False
        try:
            return database.raw_before(self.started_ns)
        except RelayError:
            return False
        finally:
            database.close()

    def _spawn(self) -> None:
        with self._lock:
            if self._stopping.is_set():
                return
            self.proc = subprocess.Popen([sys.executable, "-m", "dcuscope.relay.store.compactor"], stdin=subprocess.PIPE,
                                         stdout=subprocess.PIPE, text=True)
        self.proc.stdin.write(json.dumps({"db": str(self.db), "after_s": self.after_s, "every_s": self.every_s,
                                          "live_wait_s": self.live_wait_s, "name": self.name, "owner": self.owner,
                                          "left_before_ns": self.started_ns}) + "\n")
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
        """End the compaction process (after the range it is moving); :meth:`roll_up` then."""
        with self._lock:
            self._stopping.set()
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(STOP_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)

    def roll_up(self, bound_s: float = STOP_ROLLUP_S) -> str:
        """:func:`roll_up_at_stop` on this relay's store: call once the relay's writer stopped."""
        return roll_up_at_stop(self.db, self.name, self.owner, bound_s)

    def view(self) -> dict:
        running = self.proc is not None and self.proc.poll() is None
        return {"after_s": self.after_s, "every_s": self.every_s,
                "rollups_within_s": rollups_within_s(self.after_s, self.live_wait_s),
                "pid": self.proc.pid if self.proc else None,
                "running": running, "passes": 0, **Compacted().to_dict(), **self.last}


class Passes:
    """The child's loop: a pass now, then every ``every_s`` until ``stop`` is set."""

    def __init__(self, db: str, after_s: float, every_s: float, name: str, stop: threading.Event,
                 live_wait: float = LIVE_WAIT_S, owner: str = "", left_before_ns: int = 0) -> None:
        """``left_before_ns``: when the relay started (the first pass compacts what was left raw before)."""
        self.db, self.after_s, self.every_s, self.name, self.stop = db, after_s, every_s, name, stop
        self.live_wait, self.owner, self.left_before_ns = live_wait, owner, left_before_ns
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
            if self.left_before_ns:
                done = catch_up(self._database, self.left_before_ns, self.owner, self.stop.is_set)
                self.left_before_ns = 0
                self.done.add(done)
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


def catch_up(database: Database, before_ns: int, owner: str, stop=lambda: False) -> Compacted:
    """Compact, whole, the batches stored before ``before_ns`` of the runs not heard from since (nor
    owned by another relay): what a relay killed outright left raw. Said in the log."""
    started = time.monotonic()
    done = compact(database, before_ns, min_events=sys.maxsize, stop=stop, skip=database.held_elsewhere(owner))
    if done.events:
        log.warning("compaction: rolled up what an earlier relay left raw (it was killed, or stopped without "
                    "compacting): %s in %.2f s", _said(done), time.monotonic() - started)
    return done


def roll_up_at_stop(db: str | Path, name: str, owner: str, bound_s: float = STOP_ROLLUP_S) -> str:
    """Compact every batch still raw of runs no other relay owns, giving up after ``bound_s`` (between
    ranges); what it did, in a line for the relay's last lines."""
    started = time.monotonic()
    try:
        database = open_database(db, create=False, name=name)
    except RelayError as exc:
        return f"nothing rolled up at stop, the store failed: {exc}"
    try:
        skip = database.held_elsewhere(owner)
        done = compact(database, time.time_ns() + 1, min_events=1, stop=lambda: time.monotonic() - started > bound_s,
                       skip=skip)
        runs, batches, events, first, last = database.left_raw(skip)
    except RelayError as exc:
        return f"rolling up at stop failed after {time.monotonic() - started:.1f} s: {exc}; the next relay rolls up the rest"
    finally:
        database.close()
    took = time.monotonic() - started
    head = f"rolled up its runs at stop: {_said(done)} in {took:.2f} s" if done.events else "nothing to roll up at stop"
    if not events:
        return head + (f" (bound {bound_s:g} s); nothing left raw" if done.events else "")
    when = f"stored {hhmm(first)} to {hhmm(last)} UTC"
    gave_up = f"gave up at the {bound_s:g} s bound" if took > bound_s else "not compacted"
    return (f"{head}; {gave_up}: {events:,} events of {runs} runs left raw ({batches:,} batches {when}): the next "
            f"relay on this store rolls them up as it starts, `dcuscope stats --since` counts them meanwhile")


def _said(done: Compacted) -> str:
    return f"{done.events:,} events of {done.batches:,} batches into {done.segments} segments"


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    redact.install()  # a --db URL's password, should a driver's line name it
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
           float(settings.get("live_wait_s", LIVE_WAIT_S)), settings.get("owner", ""),
           int(settings.get("left_before_ns", 0))).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
