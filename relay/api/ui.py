"""Socket.IO namespace ``/ui``: live bars and statistics pushed to browsers, throttled and batched.

Connect with ``auth={"token": T}`` (or ``?token=T``) when the relay has a token. The relay
then pushes:

- ``nodes`` [node, ...] (as ``GET /api/nodes``) on connect and once a second;
- ``frames`` {"t_ns": relay time of the push, "nodes": {NODE: block}} at most ``push_hz``
  (10) times a second, only when frames completed since the previous push; each block is
  shaped as ``GET /api/frames`` and holds the newest of those frames, at most ``max_frames``
  per node (``cursor`` tells how many completed in all, so a gap is visible);
- ``stats`` {"nodes": {NODE: stats}} once a second for nodes whose events changed, each as
  ``GET /api/stats?node=NODE``, its ``clock`` entry included (session statistics of long runs refresh less often, the
  rolling window every time; with many nodes on a busy relay, less than once a second, as
  the frames are pushed first).

A browser may send ``subscribe`` {"nodes": [NAME, ...] or null for all, "max_frames": 1..500}
to choose which nodes' frames it gets and how many per push (default all nodes, 25).

Timestamps are ns since the epoch on the relay's clock (the node's correction applied); as
JavaScript numbers they keep about 0.25 µs, plenty for millisecond bars.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

import socketio
from socketio.exceptions import ConnectionRefusedError as Refused

from probes.wire import MAX_NAME
from relay.guard.auth import socket_token, token_matches
from relay.live.state import RelayState

NAMESPACE = "/ui"
ROOM = "browsers"
DEFAULT_PUSH_HZ = 10.0
IDLE_PERIOD_S = 0.5
"""The tick's period while no browser is subscribed."""
DEFAULT_MAX_FRAMES = 25
MAX_FRAMES = 500
STATS_PERIOD_S = 1.0
STATS_BUDGET = 0.2
"""Share of a tick's period the statistics of one tick may take (at least one node's always)."""
VERSIONS_SLACK = 64
"""Runs no longer in memory whose pushed versions may linger before they are dropped."""

log = logging.getLogger(__name__)


@dataclass
class Subscription:
    nodes: frozenset[str] | None = None
    max_frames: int = DEFAULT_MAX_FRAMES


class UiNamespace(socketio.AsyncNamespace):
    def __init__(self, state: RelayState, token: str | None) -> None:
        super().__init__(NAMESPACE)
        self.state = state
        self._token = token
        self.subscriptions: dict[str, Subscription] = {}

    async def trigger_event(self, event: str, *args):
        """Dispatch as python-socketio does, but a browser's malformed message (an event of the
        wrong arity, a ``connect`` it sends itself) is ignored with one log line, not a traceback."""
        sid = args[0] if args else None
        if event == "connect":
            if sid in self.subscriptions:
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
        if not token_matches(self._token, socket_token(auth, environ)):
            raise Refused("unauthorized: wrong or missing token")
        self.subscriptions[sid] = Subscription()
        await self.enter_room(sid, ROOM)
        await self.emit("nodes", self.state.nodes_view(), to=sid)

    async def on_disconnect(self, sid: str, reason: object = None) -> None:
        self.subscriptions.pop(sid, None)

    async def on_subscribe(self, sid: str, data: object = None) -> dict:
        if sid not in self.subscriptions or not isinstance(data, dict):
            return {"ok": False, "error": "subscribe takes {nodes, max_frames}"}
        nodes = data.get("nodes")
        if nodes is not None and not (isinstance(nodes, list) and len(nodes) <= 1024 and
                                      all(isinstance(n, str) and len(n) <= MAX_NAME for n in nodes)):
            return {"ok": False, "error": "nodes must be a list of node names or null"}
        max_frames = data.get("max_frames", DEFAULT_MAX_FRAMES)
        if not isinstance(max_frames, int) or isinstance(max_frames, bool) or not 1 <= max_frames <= MAX_FRAMES:
            return {"ok": False, "error": f"max_frames must be 1..{MAX_FRAMES}"}
        self.subscriptions[sid] = Subscription(frozenset(nodes) if nodes is not None else None, max_frames)
        return {"ok": True}


class Ticker:
    """The relay's heartbeat: pairs and evicts frames of every run, and pushes to browsers."""

    def __init__(self, state: RelayState, ui: UiNamespace, push_hz: float = DEFAULT_PUSH_HZ) -> None:
        self.state, self.ui = state, ui
        self.period = 1.0 / push_hz
        self._stats_at = 0.0
        self._stats_due: list[str] = []
        self._stats_share = 1
        self._stats_versions: dict[str, int] = {}
        self.pushes = 0

    async def run(self) -> None:
        while True:
            started = time.monotonic()
            try:
                await self.tick()
            except Exception:  # noqa: BLE001 - the heartbeat must survive a bad tick
                log.exception("relay tick failed")
            # Nobody watching: pairing waits longer and merges more at once (its cost is mostly
            # per call); a read (the API, /metrics) pairs what came first, a browser arriving is
            # served at the next tick.
            period = self.period if self.ui.subscriptions else max(self.period, IDLE_PERIOD_S)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - started)))

    async def tick(self) -> None:
        for rs in self.state.runs.values():
            rs.live.maintain()
        subs = dict(self.ui.subscriptions)
        if subs:
            await self._push_frames(subs)
        else:
            for rs in self.state.runs.values():
                rs.pushed = rs.live.visible
        if subs:
            await self._push_stats()

    async def _push_frames(self, subs: dict[str, Subscription]) -> None:
        # Each node's block is built once, for the largest request, and cut per browser.
        wanted: dict[str, int] = {}
        for sub in subs.values():
            for node in (self.state.nodes if sub.nodes is None else sub.nodes & self.state.nodes.keys()):
                wanted[node] = max(wanted.get(node, 0), sub.max_frames)
        blocks = {}
        for node, limit in wanted.items():
            rs = self.state.runs[self.state.nodes[node]]
            if rs.live.visible > rs.pushed:
                blocks[node] = self.state.frames_view(rs, rs.pushed, limit, newest=True)
        for rs in self.state.runs.values():
            rs.pushed = rs.live.visible
        if not blocks:
            return
        t_ns = time.time_ns()
        for sid, sub in subs.items():
            mine = {node: _cut(block, sub.max_frames) for node, block in blocks.items()
                    if sub.nodes is None or node in sub.nodes}
            if mine:
                await self.ui.emit("frames", {"t_ns": t_ns, "nodes": mine}, to=sid)
        self.pushes += 1

    async def _push_stats(self) -> None:
        # Each node's statistics once a second, spread over the ticks of that second and capped
        # at STATS_BUDGET of each tick's period: frames go first, so with many nodes on a busy
        # host the statistics refresh less often instead of holding up every push.
        now = time.monotonic()
        if not self._stats_due and now - self._stats_at >= STATS_PERIOD_S:
            self._stats_at = now
            self._stats_due = sorted(self.state.nodes)
            ticks = max(1, round(STATS_PERIOD_S / self.period))
            self._stats_share = max(1, -(-len(self._stats_due) // ticks))
            await self.ui.emit("nodes", self.state.nodes_view(), room=ROOM)
        changed = {}
        deadline = now + STATS_BUDGET * self.period
        done = 0
        while self._stats_due and done < self._stats_share and (done == 0 or time.monotonic() < deadline):
            node = self._stats_due.pop(0)
            done += 1
            run = self.state.nodes.get(node)
            rs = self.state.runs.get(run) if run else None
            if rs is not None and self._stats_versions.get(run) != rs.live.events:
                self._stats_versions[run] = rs.live.events
                changed[node] = self.state.stats(rs, fresh=False)
        if len(self._stats_versions) > len(self.state.runs) + VERSIONS_SLACK:
            # Keyed by run: a node restarting all day would add one a restart, for as long as a page is open.
            self._stats_versions = {r: v for r, v in self._stats_versions.items() if r in self.state.runs}
        if changed:
            await self.ui.emit("stats", {"nodes": changed}, room=ROOM)


def _cut(block: dict, limit: int) -> dict:
    if len(block["frames"]) <= limit:
        return block
    return dict(block, frames=block["frames"][-limit:])
