"""Runs another relay holds, mirrored from the shared store for this relay's HTTP API.

On a shared store a page on relay B asks B for the frames, statistics or moments of a DCU relay
A holds (a page opened on a DCU, a backfill after missed pushes). B pairs that run's stored
batches into a live state of its own, as a relay taking the run over would (the same
:class:`dcuscope.relay.live.run.LiveRun`, fed batch by batch in their order), and keeps it: each later
request first reads only the batches stored since (at most every ``REFRESH_S``). The store has
a batch once its owner committed it, which is also when the owner's own live state gets it.

Frames are numbered by this pairing. The owner numbers them in the order they completed in its
own live state, which sees the same batches in the same order but may pair after two of them
where the mirror pairs after each: the two numberings agree at the batches' joins, and within a
batch a frame's number may differ by the few frames that completed with it.

Reads use a connection of their own, in a worker thread; at most ``MAX_MIRRORS`` runs are mirrored,
the least recently asked for dropped first, and a mirror not asked for in ``IDLE_S`` is dropped.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

from dcuscope.core.clocks import NEVER
from dcuscope.protocol.events import TraceHeader
from dcuscope.relay.clock.correction import Correction
from dcuscope.relay.clock.entry import clock_entry
from dcuscope.relay.errors import RelayError
from dcuscope.relay.live.run import LiveConfig, LiveRun
from dcuscope.relay.live.runview import RunView, window_end_ns
from dcuscope.relay.store.base import Database, RunRow, StoreUnavailable
from dcuscope.relay.store.engines import open_database
from dcuscope.relay.store.runs import run_clock

REFRESH_S = 0.5
IDLE_S = 60.0
MAX_MIRRORS = 8
BATCHES_PER_READ = 256


@dataclass
class Mirror:
    run: str
    node: str
    session: int
    header: TraceHeader
    live: LiveRun
    correction: Correction
    dropped: int
    lost: int
    relay: str
    last_seq: int = -1
    refreshed: float = NEVER
    used: float = field(default_factory=time.monotonic)
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    def stats(self, fresh: bool = True) -> dict:
        window = self.live.window_stats(window_end_ns(self.live, self.correction))
        return dict(self.live.run_stats(self.dropped), window=window, node=self.node, run=self.run,
                    session=self.session, lost=self.lost, clock=clock_entry(self.correction, time.time_ns()))

    def view(self) -> RunView:
        return RunView(self.node, self.run, self.session, self.header, self.live, self.correction, self.stats,
                       self.relay)


class Mirrors:
    """The runs mirrored by this relay (see the module's docstring)."""

    def __init__(self, db: str | Path, config: LiveConfig, budget: int) -> None:
        self.db, self.config, self.budget = db, config, budget
        self._mirrors: OrderedDict[str, Mirror] = OrderedDict()
        self._database: Database | None = None
        self._db_lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._mirrors)

    async def view(self, run: str, node: str, relay: str) -> RunView:
        """The run's view, its mirror brought up to date; RelayError if the store cannot say."""
        self._prune()
        mirror = self._mirrors.get(run)
        if mirror is None:
            mirror = await asyncio.to_thread(self._open, run, node, relay)
            mirror = self._mirrors.setdefault(run, mirror)
            while len(self._mirrors) > MAX_MIRRORS:
                self._mirrors.popitem(last=False)
        self._mirrors.move_to_end(run)
        mirror.relay, mirror.used = relay, time.monotonic()
        async with mirror.lock:
            if time.monotonic() - mirror.refreshed >= REFRESH_S:
                await asyncio.to_thread(self._refresh, mirror)
        return mirror.view()

    def drop(self, run: str) -> None:
        """This relay holds ``run`` now: its own live state answers for it."""
        self._mirrors.pop(run, None)

    def close(self) -> None:
        with self._db_lock:
            if self._database is not None:
                self._database.close()
                self._database = None

    def _prune(self) -> None:
        now = time.monotonic()
        for run in [r for r, m in self._mirrors.items() if now - m.used > IDLE_S]:
            del self._mirrors[run]

    def _read(self, fn):
        """``fn(database)`` on the mirrors' own connection (opened again after a failure)."""
        with self._db_lock:
            try:
                if self._database is None:
                    self._database = open_database(self.db, create=False)
                return fn(self._database)
            except StoreUnavailable as exc:
                if self._database is not None:
                    self._database.close()
                    self._database = None
                raise RelayError(f"cannot read the store: {exc}") from exc

    def _row(self, run: str) -> RunRow | None:
        """The run's row in the store (None if it has none)."""
        return next((r for r in self._read(lambda d: d.runs_with_prefix(run)) if r.run == run), None)

    def _open(self, run: str, node: str, relay: str) -> Mirror:
        row = self._row(run)
        if row is None:
            raise RelayError(f"run {run} of node {node!r} is not in the store")
        history = self._read(lambda d: d.run_history(run))
        _, correction = run_clock(run, row.clock, history)
        header = TraceHeader.from_dict(json.loads(row.header))
        return Mirror(run=run, node=node, session=int(row.session), header=header,
                      live=LiveRun(header, self.config, self.budget), correction=correction,
                      dropped=int(row.dropped), lost=int(row.lost), relay=relay)

    def _refresh(self, mirror: Mirror) -> None:
        while True:
            batches = self._read(lambda d: d.batches_after(mirror.run, mirror.last_seq, BATCHES_PER_READ))
            for seq, events in batches:
                mirror.live.add(events)
                mirror.live.maintain()
                mirror.last_seq = seq
            if len(batches) < BATCHES_PER_READ:
                break
        row = self._row(mirror.run)
        if row is not None:
            mirror.dropped, mirror.lost = int(row.dropped), int(row.lost)
            _, mirror.correction = run_clock(mirror.run, row.clock, self._read(lambda d: d.run_history(mirror.run)))
        mirror.refreshed = time.monotonic()
