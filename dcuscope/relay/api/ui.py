"""Socket.IO namespace ``/ui``: the fleet overview and the live views of the DCUs a browser shows.

A browser connects with its session cookie (:mod:`dcuscope.relay.guard.signin`), a script with ``Authorization:
Bearer T`` on the engine.io requests: :mod:`dcuscope.relay.guard.policy` must let it READ. With ``--redis``
every relay's emits reach every relay's browsers (:mod:`dcuscope.relay.api.fanout`), so a page on any relay
gets every DCU of the fleet; each relay sends only what it holds:

- ``overview`` {"t_ns", "relay": NAME, "rows": [ROW, ...], "gone": [NODE, ...]} once a second: one row
  per DCU this relay holds (:mod:`dcuscope.relay.live.overview`); ``gone``: DCUs it listed a second ago and
  no longer holds. A page merges the rows of every relay by node. Sent on connect too, for the whole
  fleet (the other relays' rows from the store, :mod:`dcuscope.relay.api.fleet`).
- ``nodes`` [node, ...] (as ``GET /api/nodes`` items) of the DCUs the browser subscribed to, once a
  second and on connect or subscribe; a list never says a DCU is gone (the overview does).
- ``frames`` {"t_ns": relay time of the push, "nodes": {NODE: block}} as soon as a subscribed DCU
  has frames completed since its previous push, at most ``push_hz`` (30) times a second; each block
  is shaped as ``GET /api/frames`` and holds the newest of those frames, at most ``max_frames``, packed
  (``packed`` instead of ``frames``: binary columns, :mod:`dcuscope.relay.live.framepack`; ``cursor`` tells how
  many completed in all, so a gap is visible and backfilled with ``GET /api/frames``);
- ``stats`` {"nodes": {NODE: stats}} once a second for subscribed DCUs whose events changed or whose
  rolling window still holds frames (it ends at the present: a silent DCU's empties), each as
  ``GET /api/stats?node=NODE`` (whole-run figures of long runs refresh less often, the rolling window
  every time; with many DCUs on a busy relay, less than once a second: the frames go first).

A browser sends ``subscribe`` {"nodes": [NAME, ...] or null for all, "max_frames": 1..500,
"overview": bool} to choose what it gets (answered {"ok": true} or {"ok": false, "error"}), or gives
it as it connects (``auth={"subscribe": {...}}``, so that nothing else reaches it meanwhile); by
default every DCU, 25 frames a push, and the overview. The relay builds a DCU's frames and statistics only while some browser of the
fleet shows it (:mod:`dcuscope.relay.api.interest`), so a page's cost, and the relays', follows what is on
screen, not the fleet's size.

Timestamps are ns since the epoch on the relay's clock (the node's correction applied); as
JavaScript numbers they keep about 0.25 µs, plenty for millisecond bars.
"""

from __future__ import annotations

import asyncio
import logging
import time
from functools import partial

import socketio
from socketio.exceptions import ConnectionRefusedError as Refused

from dcuscope.core.clocks import NEVER
from dcuscope.protocol.wire import MAX_NAME
from dcuscope.relay.api.fleet import Fleet
from dcuscope.relay.api.interest import ALL, MAX_FRAMES, Interest, Wish
from dcuscope.relay.guard.policy import Action, Policy, Refusal
from dcuscope.relay.live import framepack
from dcuscope.relay.live.pairing import DEFAULT_PUSH_HZ, Pairing
from dcuscope.relay.live.state import RelayState

NAMESPACE = "/ui"
OVERVIEW = "overview"
EVERY = "every-dcu"
HOUSEKEEPING_S = 0.1
DEFAULT_MAX_FRAMES = 25
MAX_SUBSCRIBED = 1024
FLEET_PERIOD_S = 1.0
STATS_BUDGET = 0.2
"""Share of each housekeeping period the statistics may take (at least one DCU's always)."""
VERSIONS_SLACK = 64
"""Runs no longer in memory whose pushed versions may linger before they are dropped."""

log = logging.getLogger(__name__)


def node_room(node: str, max_frames: int) -> str:
    """The room of browsers showing ``node`` with ``max_frames`` frames a push."""
    return f"dcu:{max_frames}:{node}"


def every_room(max_frames: int) -> str:
    """The room of browsers showing every DCU with ``max_frames`` frames a push."""
    return f"{EVERY}:{max_frames}"


class UiNamespace(socketio.AsyncNamespace):
    def __init__(self, state: RelayState, fleet: Fleet, policy: Policy) -> None:
        super().__init__(NAMESPACE)
        self.state, self.fleet = state, fleet
        self._policy = policy
        self.wishes: dict[str, Wish] = {}
        """sid -> what that browser shows (:class:`dcuscope.relay.api.interest.Wish`)."""
        self._rooms: dict[str, set[str]] = {}

    async def trigger_event(self, event: str, *args):
        """Dispatch as python-socketio does, but a browser's malformed message (an event of the
        wrong arity, a ``connect`` it sends itself) is ignored with one log line, not a traceback."""
        sid = args[0] if args else None
        if event == "connect":
            if sid in self.wishes:
                log.info("ui: %s sent a connect event: ignored", sid)
                return None
            # The server's own connect: a refusal must reach python-socketio.
            return await super().trigger_event(event, *args)
        try:
            return await super().trigger_event(event, *args)
        except Exception as exc:  # noqa: BLE001 - a browser's garbage must not log a traceback
            log.info("ui: %s from %s ignored: %s: %s", str(event)[:40], sid, type(exc).__name__, str(exc)[:100])
            return {"ok": False, "error": "malformed message"}

    async def on_connect(self, sid: str, environ: dict, auth: object = None) -> None:
        verdict = self._policy.check(environ["aiohttp.request"], Action.READ)
        if isinstance(verdict, Refusal):
            raise Refused(verdict.reason)
        # A page may subscribe as it connects (auth {"subscribe": {...}}): nothing else reaches it meanwhile.
        asked = auth.get("subscribe") if isinstance(auth, dict) else None
        wish, overview = Wish(None, DEFAULT_MAX_FRAMES), True
        if asked is not None:
            parsed = _parse_wish(asked)
            if isinstance(parsed, str):
                raise Refused(f"subscribe: {parsed}")
            wish, overview = parsed
        self._rooms[sid] = set()
        await self._join(sid, _rooms(wish, overview))
        self.wishes[sid] = wish
        await self.emit("nodes", self._views(wish), to=sid)
        if overview:
            await self.emit("overview", self.snapshot(), to=sid)

    async def on_disconnect(self, sid: str, reason: object = None) -> None:
        self.wishes.pop(sid, None)
        self._rooms.pop(sid, None)

    async def on_subscribe(self, sid: str, data: object = None) -> dict:
        if sid not in self.wishes:
            return {"ok": False, "error": "not connected"}
        parsed = _parse_wish(data)
        if isinstance(parsed, str):
            return {"ok": False, "error": parsed}
        wish, overview = parsed
        await self._join(sid, _rooms(wish, overview))
        self.wishes[sid] = wish
        views = self._views(wish)
        if views:
            await self.emit("nodes", views, to=sid)
        return {"ok": True}

    def _views(self, wish: Wish) -> list[dict]:
        return self.fleet.node_views() if wish.nodes is None else self.fleet.views_of(wish.nodes)

    async def _join(self, sid: str, rooms: set[str]) -> None:
        held = self._rooms.get(sid)
        if held is None:
            return
        for room in held - rooms:
            await self.leave_room(sid, room)
        for room in rooms - held:
            await self.enter_room(sid, room)
        self._rooms[sid] = set(rooms)

    def snapshot(self) -> dict:
        """The whole fleet's rows (``overview``'s shape; ``GET /api/overview``)."""
        return {"t_ns": time.time_ns(), "relay": self.state.relay_name, "rows": self.fleet.overview(), "gone": []}


class Ticker:
    """The relay's heartbeat: pushes what browsers show as soon as it is paired (when, its
    :class:`dcuscope.relay.live.pairing.Pairing` says), and refreshes the fleet's rows once a second."""

    def __init__(self, state: RelayState, ui: UiNamespace, fleet: Fleet, interest: Interest,
                 push_hz: float = DEFAULT_PUSH_HZ) -> None:
        self.state, self.ui, self.fleet, self.interest = state, ui, fleet, interest
        self.pairing = Pairing(state, push_hz)
        self.pushes = 0
        self._fleet_at = NEVER
        self._listed: set[str] = set()
        self._stats_at = NEVER
        self._stats_due: list[str] = []
        self._stats_share = 1
        self._stats_versions: dict[str, int | None] = {}

    async def run(self) -> None:
        await asyncio.gather(self.pairing.run(self.push_frames), self._housekeeping_loop(), self.interest.run())

    async def _housekeeping_loop(self) -> None:
        while True:
            started = time.monotonic()
            try:
                await self.housekeeping()
            except Exception:  # noqa: BLE001 - the heartbeat must survive a bad tick
                log.exception("relay tick failed")
            await asyncio.sleep(max(0.0, HOUSEKEEPING_S - (time.monotonic() - started)))

    async def push_frames(self) -> None:
        """Push the new frames of every run some browser shows (a round of :meth:`Pairing.run`)."""
        wanted = self.interest.wanted()
        shown = self.pairing.take(partial(self.interest.limit, wanted))
        if not wanted:
            return
        everyone: dict[int, dict[str, dict]] = {m: {} for m in wanted.get(ALL, ())}
        t_ns = time.time_ns()
        for rs, limit in shown:
            if rs.live.visible <= rs.pushed:
                continue
            # Built once, for the largest request, and cut for the others.
            head, cols = self.state.frames_columns(rs, rs.pushed, limit)
            rs.pushed = rs.live.visible
            cut = _Cuts(head, cols, len(rs.header.stages))
            for m, blocks in everyone.items():
                blocks[rs.node] = cut(m)
            for m in wanted.get(rs.node, ()):
                await self.ui.emit("frames", {"t_ns": t_ns, "nodes": {rs.node: cut(m)}}, room=node_room(rs.node, m))
        for m, blocks in everyone.items():
            if blocks:
                await self.ui.emit("frames", {"t_ns": t_ns, "nodes": blocks}, room=every_room(m))
        self.pushes += 1

    async def housekeeping(self) -> None:
        if not self.state.storage.leases_fresh():
            return  # this relay was silent (frozen) longer than its leases: runs it may have lost are not pushed
        now = time.monotonic()
        wanted = self.interest.wanted()
        self.pairing.idle(partial(self.interest.limit, wanted))  # what browsers show the pusher pairs as it comes
        if now - self._fleet_at >= FLEET_PERIOD_S:
            self._fleet_at = now
            self.state.release_ended()  # before the rows are built: a run that left is in none
            await self._push_fleet(wanted)
        if wanted:
            await self._push_stats(wanted)

    async def _push_fleet(self, wanted: dict[str, set[int]]) -> None:
        rows = await self.fleet.refresh()
        gone = sorted(self._listed - rows.keys())
        self._listed = set(rows)
        # A silent relay pushes nothing: the others push its rows, marked so, for every page to show.
        silent = self.fleet.silent_rows()
        if rows or gone or silent:
            await self.ui.emit("overview", {"t_ns": time.time_ns(), "relay": self.state.relay_name,
                                            "rows": [*rows.values(), *silent], "gone": gone}, room=OVERVIEW)
        if not wanted:
            return
        views = {node: view for node, view in self.fleet.views.items() if self.interest.limit(wanted, node)}
        if views:
            for m in wanted.get(ALL, ()):
                await self.ui.emit("nodes", list(views.values()), room=every_room(m))
        for node, view in views.items():
            for m in wanted.get(node, ()):
                await self.ui.emit("nodes", [view], room=node_room(node, m))

    async def _push_stats(self, wanted: dict[str, set[int]]) -> None:
        # Each shown DCU's statistics once a second, spread over the housekeeping ticks of that
        # second and capped at STATS_BUDGET of each tick: the frames go first, so with many DCUs on
        # a busy host the statistics refresh less often instead of holding up pushes.
        state = self.state
        now = time.monotonic()
        if not self._stats_due and now - self._stats_at >= FLEET_PERIOD_S:
            self._stats_at = now
            self._stats_due = sorted(n for n in state.nodes if self.interest.limit(wanted, n))
            ticks = max(1, round(FLEET_PERIOD_S / HOUSEKEEPING_S))
            self._stats_share = max(1, -(-len(self._stats_due) // ticks))
        everyone = {}
        deadline = now + STATS_BUDGET * HOUSEKEEPING_S
        done = 0
        while self._stats_due and done < self._stats_share and (done == 0 or time.monotonic() < deadline):
            node = self._stats_due.pop(0)
            done += 1
            rs = state.node_run(node)
            # Unchanged since the last push: no new events, and a window with nothing left to age out.
            version = rs.live.events if rs is not None and rs.window.settled(rs.live) else None
            if rs is None or not state.holds(rs) or (version is not None
                                                     and self._stats_versions.get(rs.run) == version):
                continue
            self._stats_versions[rs.run] = version
            stats = state.stats(rs, fresh=False)
            everyone[node] = stats
            for m in wanted.get(node, ()):
                await self.ui.emit("stats", {"nodes": {node: stats}}, room=node_room(node, m))
        if len(self._stats_versions) > len(state.runs) + VERSIONS_SLACK:
            # Keyed by run: a node restarting all day would add one a restart, for as long as a page is open.
            self._stats_versions = {r: v for r, v in self._stats_versions.items() if r in state.runs}
        if everyone:
            for m in wanted.get(ALL, ()):
                await self.ui.emit("stats", {"nodes": everyone}, room=every_room(m))


class _Cuts:
    """A run's pushed block, its frames packed (:mod:`dcuscope.relay.live.framepack`) once per size asked."""

    def __init__(self, head: dict, cols: tuple, stages: int) -> None:
        self.head = {key: value for key, value in head.items() if key != "frames"}
        self.cols, self.stages = cols, stages
        self._made: dict[int, dict] = {}

    def __call__(self, limit: int) -> dict:
        size = min(limit, self.cols[0].shape[1])
        if size not in self._made:
            self._made[size] = dict(self.head, packed=framepack.packed(*self.cols, self.stages, last=size))
        return self._made[size]


def _parse_wish(data: object) -> tuple[Wish, bool] | str:
    """A ``subscribe`` message as (what the browser shows, whether it wants the overview), or why not."""
    if not isinstance(data, dict):
        return "subscribe takes {nodes, max_frames, overview}"
    nodes = data.get("nodes")
    if nodes is not None and not (isinstance(nodes, list) and len(nodes) <= MAX_SUBSCRIBED and
                                  all(isinstance(n, str) and len(n) <= MAX_NAME for n in nodes)):
        return "nodes must be a list of node names or null"
    max_frames = data.get("max_frames", DEFAULT_MAX_FRAMES)
    if not isinstance(max_frames, int) or isinstance(max_frames, bool) or not 1 <= max_frames <= MAX_FRAMES:
        return f"max_frames must be 1..{MAX_FRAMES}"
    overview = data.get("overview", True)
    if not isinstance(overview, bool):
        return "overview must be true or false"
    return Wish(None if nodes is None else frozenset(nodes), max_frames), overview


def _rooms(wish: Wish, overview: bool) -> set[str]:
    rooms = {every_room(wish.max_frames)} if wish.nodes is None else {node_room(n, wish.max_frames) for n in wish.nodes}
    return rooms | ({OVERVIEW} if overview else set())
