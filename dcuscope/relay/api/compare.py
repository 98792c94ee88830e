"""Two stored runs compared, for the page's Compare tab: ``dcuscope compare``'s document over HTTP.

- ``GET /api/compare?base=RUN&new=RUN[&noise=PCT]``: the document of :func:`dcuscope.model.compare.compare`
  (per stage and end to end, each figure of NEW against BASE with its 95 % block-bootstrap interval and
  verdict; two runs of different pipelines only on the stages both have, the rest ``not in both``).
  RUN is a stored run's id or a prefix of it of 6 or more hex digits that names one run, as
  ``dcuscope compare run:ID`` takes it. Either side may instead be ``base=SESSION&base_node=NAME``
  (``new=SESSION&new_node=NAME``): the run of node NAME in that session, where it has exactly one.
  Each input's ``label`` is :func:`dcuscope.relay.store.runs.run_label`'s, as the CLI names the same run.
  Errors: 400 for a malformed id or noise, a prefix of several runs, a session with several runs of
  the node; 404 for no such run, session or node, or a run without a complete frame.

The runs come paired from the stored sessions' cache (:mod:`dcuscope.relay.api.sessions`), a run's session
looked up by its id; the resampling runs in a worker thread, and a comparison of ended runs is kept
for the next request. The token middleware of :mod:`dcuscope.relay.api.routes` guards the route like every
``/api`` route.
"""

from __future__ import annotations

import asyncio
from collections import OrderedDict

from aiohttp import web

from dcuscope.model.compare import NOISE_PCT, Input, compare, distinct_labels
from dcuscope.relay.api.sessions import MAX_SESSION_DIGITS, SessionCache, StoredNode
from dcuscope.relay.errors import RelayError, http_error
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.store.runs import find_runs, run_label

CACHED = 8
MAX_NAME = 200
MAX_RUN_DIGITS = 64
HEX = frozenset("0123456789abcdef")


def add_compare_routes(app: web.Application, sessions: SessionCache) -> None:
    done: OrderedDict[tuple, dict] = OrderedDict()

    async def nodes_of(session: int) -> list[StoredNode]:
        try:
            return await sessions.get(session)
        except RelayError as exc:
            raise http_error(web.HTTPNotFound, str(exc)) from exc

    async def by_run(role: str, text: str) -> tuple[int, list[StoredNode], StoredNode]:
        prefix = text.lower()
        if not 6 <= len(prefix) <= MAX_RUN_DIGITS or not set(prefix) <= HEX:
            raise http_error(web.HTTPBadRequest, f"{role}=RUN is required: a stored run's id or its first 6 or more "
                                                 f"hex digits (or {role}=SESSION&{role}_node=NAME)")
        try:
            found = await asyncio.to_thread(find_runs, sessions.path, prefix)
        except RelayError as exc:
            raise http_error(web.HTTPNotFound, str(exc)) from exc
        if len(found) > 1:
            raise http_error(web.HTTPBadRequest, f"{role}={prefix} begins {len(found)} run ids: give more digits")
        for run, session in found:
            nodes = await nodes_of(session)
            for node in nodes:
                if node.run == run:
                    return session, nodes, node
        raise http_error(web.HTTPNotFound, f"no stored run {prefix}")

    async def by_session(role: str, text: str, name: str) -> tuple[int, list[StoredNode], StoredNode]:
        if not text.isascii() or not text.isdigit() or len(text) > MAX_SESSION_DIGITS:
            raise http_error(web.HTTPBadRequest, f"{role}=SESSION with {role}_node: a session id, at most "
                                                 f"{MAX_SESSION_DIGITS} digits")
        if not name or len(name) > MAX_NAME:
            raise http_error(web.HTTPBadRequest, f"{role}_node=NAME: a node's name (at most {MAX_NAME} characters)")
        nodes = await nodes_of(int(text))
        runs = [n for n in nodes if n.header.node == name]
        if not runs:
            raise http_error(web.HTTPNotFound, f"session {text} has no node {name[:100]!r}")
        if len(runs) > 1:
            raise http_error(web.HTTPBadRequest, f"session {text} holds {len(runs)} runs of node {name[:100]!r}: "
                                                 f"name one as {role}=RUN ({', '.join(n.run[:8] for n in runs)})")
        return int(text), nodes, runs[0]

    async def side(request: web.Request, role: str) -> tuple[Input, StoredNode]:
        text, name = request.query.get(role, ""), request.query.get(f"{role}_node")
        session, nodes, node = await (by_run(role, text) if name is None else by_session(role, text, name))
        if not node.order.size:
            raise http_error(web.HTTPNotFound, f"run {node.run[:8]} of {node.header.node[:100]!r}: no complete frame")
        twins = sum(n.header.node == node.header.node for n in nodes) > 1
        return Input(label=run_label(session, node.header.node, node.run, twins), origin=f"run {node.run}",
                     node=node.header.node, fd=node.fd, kinds=node.header.kinds), node

    async def handler(request: web.Request) -> web.Response:
        (base, base_node), (new, new_node) = await side(request, "base"), await side(request, "new")
        try:
            noise = float(request.query.get("noise", NOISE_PCT))
            if not 0 <= noise < 100:
                raise ValueError
        except ValueError:
            raise http_error(web.HTTPBadRequest, "noise=PCT: a percentage from 0 to 100") from None
        key = (base_node.run, new_node.run, noise)
        if key in done:
            done.move_to_end(key)
            return web.json_response(done[key])
        base.label, new.label = distinct_labels([base.label, new.label])  # a run against itself
        doc = await asyncio.to_thread(compare, [base, new], noise_pct=noise)
        if base_node.ended and new_node.ended:
            done[key] = doc
            while len(done) > CACHED:
                done.popitem(last=False)
        return web.json_response(doc)

    add_read(app, "/api/compare", handler)
