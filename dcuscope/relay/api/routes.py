"""HTTP JSON API of the relay (aiohttp routes); each is READ in :mod:`dcuscope.relay.guard.policy`.

- ``GET /api/health``: {ok, uptime_s, runs, rejected, clock_rejected, paused, storage {ok, reconnects, timeouts,
  waiting_for_standby[, leases, error, since, failed_writes]}, limits, memory {live_bytes, live_budget_bytes, run_budget_bytes, runs_with_live_state},
  heap {available, arena, in_use, free, mmapped, reclaims, collected, last_reclaim_ms, last_trim_ms}: what
  malloc holds, and the passes that gave memory back after runs left it (:mod:`dcuscope.relay.heap`),
  refused {LIMIT or reason: what it refused}, proxy {trusted, proxied, proxied_open} (null without
  ``--trusted-proxy``), ...}; ok is false while storage fails
- ``GET /api/nodes``: [{node, run, session, connected, state, relay, clock {offset_us, uncertainty_us, ...},
  ptp, events, dropped, lost, drops, ...}], one per node (its newest run) of the whole fleet: on a shared
  store the DCUs other relays hold too, as they wrote them to the store at most a second ago (``stale``,
  not connected, state "relay silent" when their relay stopped refreshing them, :mod:`dcuscope.relay.api.fleet`)
- ``GET /api/overview``: {t_ns, relay, rows: [ROW, ...]}: one row per DCU of the fleet
  (:mod:`dcuscope.relay.live.overview`; as the ``overview`` pushes of :mod:`dcuscope.relay.api.ui`)
- ``GET /api/stats?node=NAME``, ``/api/frames``, ``/api/moments`` answer for any DCU of the fleet: one
  another relay holds is read from a mirror of its stored batches (:mod:`dcuscope.relay.live.mirror`)
- ``GET /api/stats?node=NAME``: ``model.delays.node_stats`` of the node's newest run (stage
  shares and bottleneck included), plus the same figures over the rolling ``window``, and
  ``clock`` {applied, why, correction_ns, uncertainty_ns, at_ns}: the correction applied to its
  timestamps and its bound (:mod:`dcuscope.relay.clock.entry`)
- ``GET /api/frames?node=NAME&since=CURSOR&limit=N``: complete frames after the cursor, each
  with every figure the page draws, its clock offset ``clock_ns`` and bound
  ``clock_uncertainty_ns`` included (:mod:`dcuscope.relay.live.framejson`)
- ``GET /api/moments?a=NODE&b=NODE[&source=URI | &source_a=ID&source_b=ID][&limit=N]``: the same
  moments of one camera on two nodes (their complete frames matched by capture time, within
  ``relay.api.moments.MATCH_TOLERANCE_NS``, 1 ms): per moment the capture time, each node's corrected origin
  and end, ``diff_ms`` (end of b - end of a: > 0 when a finished first), ``first``, ``error_ms``
  (both clock bounds summed); ``summary``: matched, unmatched and frames per node, mean/p50/p95 of
  the difference, the share each node finished first, and whether the mean exceeds the error bar
  (:mod:`dcuscope.relay.api.moments`). Sources are those both run headers name by URI unless given; the newest
  ``limit`` (200, at most 2000) moments are listed, the summary covers every kept frame
- ``GET /api/sessions``: stored sessions and their runs (node, times, counts, clock, stages), newest first
- ``GET /api/sessions/ID/{nodes,stats,frames}``: a stored session browsed like a live one
  (:mod:`dcuscope.relay.api.sessions`)

Beside them, ``GET /metrics`` (Prometheus, :mod:`dcuscope.relay.export.metrics`), READ too.
"""

from __future__ import annotations

import time

from aiohttp import web

from dcuscope.relay.api import moments as mo
from dcuscope.relay.api.fleet import Fleet
from dcuscope.relay.errors import RelayError, http_error
from dcuscope.relay.guard.policy import add_read
from dcuscope.relay.live.runview import RunView, frames_block
from dcuscope.relay.live.state import RelayState

MAX_FRAMES_PER_REQUEST = 2000


def add_routes(app: web.Application, state: RelayState, fleet: Fleet, ui, counters) -> None:
    """``counters()`` returns extra figures for /api/health (rejected connections, pushes)."""

    async def run_of(request: web.Request, key: str = "node") -> RunView:
        node = request.query.get(key)
        if not node:
            raise http_error(web.HTTPBadRequest, f"{key}=NAME is required")
        try:
            view = await fleet.run_view(node)
        except RelayError as exc:
            raise http_error(web.HTTPServiceUnavailable, f"node {node[:100]!r}: {exc}") from None
        if view is None:
            raise http_error(web.HTTPNotFound, f"no node named {node[:100]!r}")
        return view

    async def health(request: web.Request) -> web.Response:
        storage = state.storage.health()  # not ok while writes fail (a full disk)
        return web.json_response({"ok": storage["ok"], "uptime_s": time.time() - state.started,
                                  "runs": len(state.runs), "clock": state.clock_mode, "storage": storage,
                                  **counters()})

    async def nodes(request: web.Request) -> web.Response:
        return web.json_response(fleet.node_views())

    async def overview(request: web.Request) -> web.Response:
        return web.json_response(ui.snapshot())

    async def stats(request: web.Request) -> web.Response:
        return web.json_response((await run_of(request)).stats(True))

    async def frames(request: web.Request) -> web.Response:
        view = await run_of(request)
        since = int_arg(request, "since", 0, 0, 1 << 62)
        limit = int_arg(request, "limit", 200, 1, MAX_FRAMES_PER_REQUEST)
        view.live.maintain()
        return web.json_response(frames_block(view, since, limit))

    async def moments(request: web.Request) -> web.Response:
        a, b = await run_of(request, "a"), await run_of(request, "b")
        if a.node == b.node:
            raise http_error(web.HTTPBadRequest, "a and b must name two different nodes")
        limit = int_arg(request, "limit", mo.DEFAULT_LIMIT, 1, mo.MAX_LIMIT)
        ids = None
        if "source_a" in request.query or "source_b" in request.query:
            if "source_a" not in request.query or "source_b" not in request.query or "source" in request.query:
                raise http_error(web.HTTPBadRequest, "give source_a=ID and source_b=ID together, or source=URI")
            ids = (int_arg(request, "source_a", 0, -(1 << 62), 1 << 62), int_arg(request, "source_b", 0, -(1 << 62), 1 << 62))
        sides = [mo.Side(v.node, v.header.sources, v.live.recent(0, state.live_config.recent_frames, newest=True)[1],
                         v.correction) for v in (a, b)]
        try:
            pairs = mo.pairs_of(*sides, uri=request.query.get("source"), ids=ids)
        except mo.MomentsError as exc:
            raise http_error(web.HTTPNotFound, str(exc)) from None
        return web.json_response(mo.compare(pairs, limit))

    async def sessions(request: web.Request) -> web.Response:
        return web.json_response(await state.storage.call("list_sessions"))

    add_read(app, "/api/health", health)
    add_read(app, "/api/nodes", nodes)
    add_read(app, "/api/overview", overview)
    add_read(app, "/api/stats", stats)
    add_read(app, "/api/frames", frames)
    add_read(app, "/api/moments", moments)
    add_read(app, "/api/sessions", sessions)


def int_arg(request: web.Request, name: str, default: int, lo: int, hi: int) -> int:
    """Query argument ``name`` as an integer clamped to [lo, hi]; 400 if it is not one."""
    try:
        value = int(request.query.get(name, default))
    except ValueError:
        raise http_error(web.HTTPBadRequest, f"{name} must be an integer") from None
    return max(lo, min(hi, value))
