"""A DCU's long history, from the store's rollups (:mod:`dcuscope.relay.store.history`): HTTP routes.

- ``GET /api/history/nodes``: [{node, first_ns, last_ns}], every DCU with rollups (hours);
- ``GET /api/history?node=NAME&since=30d[&until_ns=NS]``: ``{summary, history}``: the node's statistics
  over that time (``dcuscope stats --db --node --since``'s, exact figures and those from the sketch
  named) and per stage, and end to end, a point per minute or hour (p50, p99, frames), a time
  without frames having none (a gap). ``since`` is a duration back from ``until_ns`` (default now).
  Frames still in raw batches (not compacted yet) are counted too, and ``summary.raw`` says which
  minutes those were; ``history.newest_ns`` is the newest event's time (the page's span ends there).

Each request reads in a worker thread on a connection of its own (ingest goes on meanwhile).
The token middleware of :mod:`dcuscope.relay.api.routes` guards them like every ``/api`` route.
"""

from __future__ import annotations

import asyncio
import time

from aiohttp import web

from dcuscope.relay.errors import RelayError, http_error
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.live.state import RelayState
from dcuscope.relay.store.history import nodes, parse_duration_ns, span

MAX_NAME = 200
MAX_NS = 1 << 62


def add_history_routes(app: web.Application, state: RelayState) -> None:
    db = state.storage.db

    async def history_nodes(request: web.Request) -> web.Response:
        try:
            return web.json_response(await asyncio.to_thread(nodes, db))
        except RelayError as exc:
            raise http_error(web.HTTPServiceUnavailable, str(exc)) from exc

    async def node_history(request: web.Request) -> web.Response:
        node = request.query.get("node", "")
        if not node or len(node) > MAX_NAME:
            raise http_error(web.HTTPBadRequest, f"node=NAME is required (at most {MAX_NAME} characters)")
        try:
            back = parse_duration_ns(request.query.get("since", "1d"))
            until = int(request.query.get("until_ns", time.time_ns()))
            if not back <= until <= MAX_NS:
                raise ValueError(f"until_ns must be {back}..{MAX_NS}")
        except (RelayError, ValueError) as exc:
            raise http_error(web.HTTPBadRequest, f"since=DURATION (e.g. 30d), until_ns=NS: {exc}") from None

        try:
            return web.json_response(await asyncio.to_thread(span, db, node, until - back, until))
        except RelayError as exc:
            raise http_error(web.HTTPServiceUnavailable, str(exc)) from exc

    add_read(app, "/api/history/nodes", history_nodes)
    add_read(app, "/api/history", node_history)
