"""Stored sessions, browsed like live ones: HTTP routes over the relay's database.

- ``GET /api/sessions/{session}/nodes``: [{node, run, stages, sources, frames, events, first_ns,
  last_ns, dropped, lost, clock, ended}], one per run of the session, ``node`` its name
  (:func:`dcuscope.relay.store.runs.run_name`: a node seen twice, ``NODE · run ID8`` each)
- ``GET /api/sessions/{session}/frames?node=NAME&since=CURSOR&limit=N``: the node's complete
  frames in the order their chains ended, shaped as ``GET /api/frames`` (cursor = position, from 1)
- ``GET /api/sessions/{session}/stats?node=NAME``: ``model.delays.node_stats`` over the node's
  stored events (stage shares and bottleneck included), and the ``clock`` entry of
  :mod:`dcuscope.relay.clock.entry` (the correction applied, at the run's last event, and its bound)

Timestamps are moved to the relay's clock as ``dcuscope export`` moves them: each by the estimate
in force at its time, from the run's stored clock history (:func:`dcuscope.relay.store.runs.load_runs`); as
live, runs are paired on their node's own clock and only the frames' times are moved, each frame
with the offset subtracted at its origin (``clock_ns``) and its bound (``clock_uncertainty_ns``), a
frames block the correction and bound at its last frame (``correction_ns``, ``uncertainty_ns``). A session is paired once, in a
worker thread with its own read connection (WAL: ingest keeps writing meanwhile), and kept
for the next requests; a session still being recorded is re-read after ``LIVE_TTL_S``.

Register with ``add_session_routes(app, state)`` before the app starts; the token middleware of
:mod:`dcuscope.relay.api.routes` guards these routes like every ``/api`` route.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from aiohttp import web

from dcuscope.model.delays import FrameDelays, delay_stats, frame_delays
from dcuscope.model.facts import Accounting
from dcuscope.model.frametable import frame_table
from dcuscope.protocol.events import TraceHeader
from dcuscope.relay.api.routes import int_arg
from dcuscope.relay.clock.correction import Correction
from dcuscope.relay.clock.entry import clock_entry
from dcuscope.relay.errors import RelayError, http_error
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.live.framejson import block, frame_dicts
from dcuscope.relay.live.state import RelayState
from dcuscope.relay.store.runs import StoredRun, load_runs, run_names

CACHED_SESSIONS = 3
LIVE_TTL_S = 2.0
MAX_FRAMES_PER_REQUEST = 10000
"""More than /api/frames allows: a page loads a whole stored session in a few requests."""
MAX_SESSION_DIGITS = 18
"""Longer ids name no session: SQLite integers stop at 19 digits, Python's int() at 4,300."""
ROUTES = ("/api/sessions/{session:\\d+}/nodes", "/api/sessions/{session:\\d+}/frames",
          "/api/sessions/{session:\\d+}/stats")


@dataclass
class StoredNode:
    """One run of a stored session, paired: its frames' delays and the order of its complete
    frames by the end of their chain (the order in which a live relay would have shown them)."""

    node: str
    run: str
    header: TraceHeader
    dropped: int
    lost: int
    clock: dict
    ended: bool
    events: int
    fd: FrameDelays
    order: np.ndarray
    """Rows of ``fd`` of the complete frames, by chain end: position k is cursor k + 1."""
    stats: dict
    correction: Correction
    """The run's stored clock correction (:attr:`dcuscope.relay.store.runs.StoredRun.correction`), applied to the
    frames' times shown: pairing is on the node's clock, as live."""

    def summary(self) -> dict:
        n = len(self.order)
        t, ch = self.fd.table, self.fd.chains
        first, last = self.correction.correct(t.origin[self.order]), self.correction.correct(ch.end[self.order])
        return {"node": self.node, "run": self.run, "stages": self.header.stages, "kinds": self.header.kinds,
                "sources": {str(k): v for k, v in self.header.sources.items()}, "frames": n, "events": self.events,
                "links": self.header.links, "lineage_unknown": self.header.lineage_unknown,
                "first_ns": int(first.min()) if n else None,
                "last_ns": int(last.max()) if n else None,
                "dropped": self.dropped, "lost": self.lost, "clock": self.clock, "ended": self.ended}

    def frames_view(self, since: int, limit: int) -> dict:
        """Frames at positions since+1 .. since+limit, shaped as ``RelayState.frames_view``."""
        lo, hi = min(since, len(self.order)), min(since + limit, len(self.order))
        rows = self.order[lo:hi]
        frames = frame_dicts(np.arange(lo + 1, hi + 1), self.fd, self.correction, rows)
        corr, bound = self.correction.at(int(self.fd.chains.end[rows[-1]]) if len(rows) else 0)
        return block(self.node, self.run, self.header.stages, self.header.kinds, self.fd.chains.has_exit, frames,
                     self.correction.applied, cursor=hi, total=len(self.order), correction_ns=corr, uncertainty_ns=bound)


def pair_run(run: StoredRun, name: str) -> StoredNode:
    """Pair a stored run's events into frames and their delays (:mod:`dcuscope.model.delays`)."""
    fd = frame_delays(frame_table(run.header, run.events))
    accounting = Accounting(run.header.stages)
    accounting.add(run.events)
    ch = fd.chains
    c = np.flatnonzero(ch.complete)
    stats = dict(delay_stats(fd, run.header.sources, run.dropped, accounting), node=name, run=run.run, session=run.session,
                 lost=run.lost, clock=clock_entry(run.correction, run.last_ns))
    return StoredNode(node=name, run=run.run, header=run.header, dropped=run.dropped, lost=run.lost,
                      clock=run.clock, ended=run.ended, events=len(run.events), fd=fd,
                      order=c[np.argsort(ch.end[c], kind="stable")], stats=stats, correction=run.correction)


def load_session_nodes(path, session: int) -> list[StoredNode]:
    """Every run of a stored session, paired (blocking: call it in a worker thread)."""
    runs = load_runs(path, session, corrected=False)
    return [pair_run(run, name) for run, name in zip(runs, run_names([(r.header.node, r.run) for r in runs]))]


class SessionCache:
    """Paired sessions, the few most recent; one load at a time per session."""

    def __init__(self, path, size: int = CACHED_SESSIONS) -> None:
        self.path = path
        self.size = size
        self._entries: OrderedDict[int, tuple[float, list[StoredNode]]] = OrderedDict()
        self._loading: dict[int, asyncio.Future] = {}

    async def get(self, session: int) -> list[StoredNode]:
        entry = self._entries.get(session)
        if entry is not None:
            at, nodes = entry
            if all(n.ended for n in nodes) or time.monotonic() - at < LIVE_TTL_S:
                self._entries.move_to_end(session)
                return nodes
        pending = self._loading.get(session)
        if pending is None:
            pending = asyncio.ensure_future(asyncio.to_thread(load_session_nodes, self.path, session))
            self._loading[session] = pending
            pending.add_done_callback(lambda _: self._loading.pop(session, None))
        nodes = await asyncio.shield(pending)
        self._entries[session] = (time.monotonic(), nodes)
        self._entries.move_to_end(session)
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return nodes


def add_session_routes(app: web.Application, state: RelayState) -> SessionCache:
    """Add the ``/api/sessions/{session}/...`` routes; returns their cache (tests look at it)."""
    cache = SessionCache(state.storage.db)

    async def session_nodes(request: web.Request) -> list[StoredNode]:
        text = request.match_info["session"]
        if len(text) > MAX_SESSION_DIGITS or not text.isascii():
            raise http_error(web.HTTPNotFound, f"no session {text[:20]!r}: a session id is at most "
                                               f"{MAX_SESSION_DIGITS} digits 0-9")
        try:
            return await cache.get(int(text))
        except RelayError as exc:
            raise http_error(web.HTTPNotFound, str(exc)) from exc

    async def node_of(request: web.Request) -> StoredNode:
        name = request.query.get("node")
        if not name:
            raise http_error(web.HTTPBadRequest, "node=NAME is required")
        for node in await session_nodes(request):
            if node.node == name:
                return node
        raise http_error(web.HTTPNotFound, f"session {request.match_info['session']} has no node {name[:100]!r}")

    async def nodes(request: web.Request) -> web.Response:
        return web.json_response([n.summary() for n in await session_nodes(request)])

    async def frames(request: web.Request) -> web.Response:
        node = await node_of(request)
        since = int_arg(request, "since", 0, 0, 1 << 62)
        limit = int_arg(request, "limit", 200, 1, MAX_FRAMES_PER_REQUEST)
        return web.json_response(node.frames_view(since, limit))

    async def stats(request: web.Request) -> web.Response:
        return web.json_response((await node_of(request)).stats)

    for route, handler in zip(ROUTES, (nodes, frames, stats)):
        add_read(app, route, handler)
    return cache


def has_session_routes(app: web.Application) -> bool:
    """Whether ``add_session_routes`` was already called on ``app``."""
    canon = {r.canonical for r in app.router.resources()}
    return any(route.replace(":\\d+", "") in canon for route in ROUTES)
