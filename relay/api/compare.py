"""Two stored runs compared, for the page's Compare tab: ``dcuscope compare``'s document over HTTP.

- ``GET /api/compare?base=SESSION&base_node=NAME&new=SESSION&new_node=NAME[&noise=PCT]``: the
  document of :func:`probes.trace.compare.compare` (per stage and end to end, each figure of NEW
  against BASE with its 95 % block-bootstrap interval and verdict), BASE and NEW being one node's
  run of a stored session each: two sessions, or two runs of one DCU.

The runs come paired from the stored sessions' cache (:mod:`relay.api.sessions`); the resampling
runs in a worker thread, and a comparison of ended runs is kept for the next request. The token
middleware of :mod:`relay.api.routes` guards the route like every ``/api`` route.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict

from aiohttp import web

from probes.trace.compare import NOISE_PCT, Input, compare
from relay.api.sessions import MAX_SESSION_DIGITS, SessionCache, StoredNode
from relay.errors import RelayError, http_error

CACHED = 8
MAX_NAME = 200


def add_compare_routes(app: web.Application, sessions: SessionCache) -> None:
    done: OrderedDict[tuple, dict] = OrderedDict()

    async def side(request: web.Request, role: str) -> StoredNode:
        text, name = request.query.get(role, ""), request.query.get(f"{role}_node", "")
        if not text.isdigit() or len(text) > MAX_SESSION_DIGITS or not text.isascii():
            raise http_error(web.HTTPBadRequest, f"{role}=SESSION is required: a session id, at most "
                                                 f"{MAX_SESSION_DIGITS} digits")
        if not name or len(name) > MAX_NAME:
            raise http_error(web.HTTPBadRequest, f"{role}_node=NAME is required (at most {MAX_NAME} characters)")
        try:
            nodes = await sessions.get(int(text))
        except RelayError as exc:
            raise http_error(web.HTTPNotFound, str(exc)) from exc
        for node in nodes:
            if node.node == name:
                if not node.order.size:
                    raise http_error(web.HTTPNotFound, f"session {text}, node {name[:100]!r}: no complete frame")
                return node
        raise http_error(web.HTTPNotFound, f"session {text} has no node {name[:100]!r}")

    async def handler(request: web.Request) -> web.Response:
        base, new = await side(request, "base"), await side(request, "new")
        try:
            noise = float(request.query.get("noise", NOISE_PCT))
            if not 0 <= noise < 100:
                raise ValueError
        except ValueError:
            raise http_error(web.HTTPBadRequest, "noise=PCT: a percentage from 0 to 100") from None
        key = (base.run, new.run, noise)
        if key in done:
            done.move_to_end(key)
            return web.json_response(done[key])
        inputs = [Input(label=f"{request.query[role]} · {n.node}", origin=f"session {request.query[role]}, run {n.run[:8]}",
                        node=n.node, fd=n.fd) for role, n in (("base", base), ("new", new))]
        doc = await asyncio.to_thread(compare, inputs, noise_pct=noise)
        if base.ended and new.ended:
            done[key] = doc
            while len(done) > CACHED:
                done.popitem(last=False)
        return web.json_response(doc)

    app.router.add_get("/api/compare", handler)
