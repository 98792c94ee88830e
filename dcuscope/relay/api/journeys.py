"""``GET /api/journeys``: frames that went from one held run's pipeline to another's (RTP, shared
memory), joined on the relay's clock (:mod:`dcuscope.relay.live.journeys`): the hops' and the paths'
statistics as ``dcuscope stats`` gives them for a stored session, the newest ``limit`` journeys,
each part placed on the relay's clock (what the page's Journeys tab draws), and with ``hops=N``
the newest N frames that crossed a hop, by arrival (the Stage view's hop row)."""

from __future__ import annotations

from aiohttp import web

from dcuscope.model.journeys import Joined, Journey, journeys_document
from dcuscope.relay.api.routes import int_arg
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.live.state import RelayState

DEFAULT_LIMIT = 30
MAX_LIMIT = 1000
MAX_CROSSED = 5000


def journeys_view(joined: Joined, limit: int, crossed: int = 0) -> dict:
    doc = journeys_document(joined)
    doc["frames"] = [frame_view(j, joined) for j in joined.journeys[-limit:]]
    if crossed:
        newest = sorted(joined.crossed, key=lambda c: c.arrived_ns)[-crossed:]
        doc["crossed"] = [{"n": c.arrived_ns, "hop": c.hop, "sent_ns": c.sent_ns, "arrived_ns": c.arrived_ns,
                           "clock_error_ns": c.error_ns} for c in newest]
    return doc


def frame_view(journey: Journey, joined: Joined) -> dict:
    """One journey: its parts one after the other, each at its offset from the journey's start (ns:
    small numbers, exact in a page's doubles, which timestamps of this era are not), a hop's with
    this frame's clock error."""
    parts, at = [], 0
    for k, (name, ns) in enumerate(journey.parts):
        hop = name in joined.hops
        part = {"name": name, "kind": "hop" if hop else "node", "at_ns": at, "ns": ns}
        if hop:
            part["clock_error_ns"] = journey.errors_ns.get(k)
        parts.append(part)
        at += ns
    return {"nodes": journey.nodes, "start_ns": journey.start_ns, "end_ns": journey.end_ns,
            "total_ns": journey.total_ns, "total_ms": journey.total_ns / 1e6, "parts": parts}


def add_journey_routes(app: web.Application, state: RelayState) -> None:
    async def journeys(request: web.Request) -> web.Response:
        limit = int_arg(request, "limit", DEFAULT_LIMIT, 1, MAX_LIMIT)
        crossed = int_arg(request, "hops", 0, 0, MAX_CROSSED)
        return web.json_response(journeys_view(state.joined(), limit, crossed))

    add_read(app, "/api/journeys", journeys)
