"""The whole fleet as one relay answers for it: its own DCUs live, the others' from the shared store.

Once a second (:meth:`Fleet.refresh`) the relay builds the overview row (:mod:`dcuscope.relay.live.overview`)
and node view of every DCU it holds, and, on a shared store, upserts them into the store's
``fleet`` table and reads back the rows of the other relays' DCUs. ``/api/nodes`` and
``/api/overview`` then list the fleet; ``/api/stats``, ``/api/frames`` and ``/api/moments`` read a
DCU another relay holds from a mirror of its stored batches (:mod:`dcuscope.relay.live.mirror`).

Every row and node view carries a ``state``: "connected", "disconnected" (its run not ended),
"ended", or "relay silent". A row of a live run that its relay stopped refreshing for ``STALE_S`` is
marked ``stale`` and listed as not connected, whatever that relay last wrote (frozen, it serves
nobody; cut off from the store, nothing says it does): ``state`` "relay silent", ``silent_s`` since
it last wrote the row, ``relay`` still naming it, ``fps`` None (nobody measures its rate now), and
on the overview row the alert "relay silent: last heard N s ago". A relay that died lets its DCUs
reconnect to another within seconds, whose rows then take over; one nobody refreshed for
``ROW_TTL_S`` is deleted. A run that ended stays listed for ``Limits.ended_keep_s`` (its relay then
releases it, :meth:`RelayState.release_ended`); its row, no longer refreshed, leaves the others'
lists after ``STALE_S``.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass

from dcuscope.relay.errors import RelayError
from dcuscope.relay.live.mirror import Mirrors
from dcuscope.relay.live.overview import CountHistory, connection_state, overview_row
from dcuscope.relay.live.runview import RunView
from dcuscope.relay.live.state import RelayState, RunState

STALE_S = 3.0
RELAY_SILENT = "relay silent"
ROW_TTL_S = 300.0
ROW_WINDOW_AGE_S = 1.0
"""The rows are rebuilt once a second, and a window's statistics up to a second old serve them: for a
DCU a page shows, the ones its statistics push made (at most every 0.5 s, WINDOW_MAX_AGE_S), not a
second computation of the same window (~1.5 ms a DCU, 0.3 µs per paced event)."""

log = logging.getLogger(__name__)


@dataclass
class Remote:
    """A DCU another relay holds, as it last wrote it to the store."""

    run: str
    relay: str
    updated_ns: int
    view: dict
    row: dict

    def stale(self, now_ns: int) -> bool:
        return not self.row.get("ended") and now_ns - self.updated_ns > STALE_S * 1e9

    def heard(self, entry: dict, now_ns: int) -> dict:
        """``entry`` (its stored row or view) as listed at ``now_ns``: marked ``stale``, and not
        connected while its relay is silent."""
        if not self.stale(now_ns):
            return dict(entry, stale=False, state=connection_state(entry["connected"], entry["ended"]))
        return dict(entry, stale=True, connected=False, state=RELAY_SILENT,
                    silent_s=round((now_ns - self.updated_ns) / 1e9, 1))

    def row_at(self, now_ns: int) -> dict:
        """Its overview row as listed at ``now_ns`` (:meth:`heard`; a silent relay is an alert)."""
        row = self.heard(self.row, now_ns)
        if row["stale"]:
            row["alerts"] = [f"relay silent: last heard {row['silent_s']:.0f} s ago", *row["alerts"]]
            row["fps"] = None
        return row


class Fleet:
    def __init__(self, state: RelayState) -> None:
        self.state = state
        self.shared = state.storage.shared
        self.mirrors = Mirrors(state.storage.db, state.live_config, state.run_budget(1)) if self.shared else None
        self.rows: dict[str, dict] = {}
        """Node -> the row of a DCU this relay holds, as of the last refresh."""
        self.views: dict[str, dict] = {}
        """Node -> the node view of a DCU this relay holds, as of the last refresh (``relay`` added)."""
        self.remote: dict[str, Remote] = {}
        self._drops: dict[str, CountHistory] = {}
        self._incomplete: dict[str, CountHistory] = {}
        self._store_failing = False

    # --- once a second ----------------------------------------------------------------------------

    def build_rows(self) -> dict[str, dict]:
        """The rows of the DCUs this relay holds, built now."""
        state, now = self.state, time.monotonic()
        rows, views = {}, {}
        for node, run in sorted(state.nodes.items()):
            rs = state.runs.get(run)
            if rs is None or not state.holds(rs):
                continue
            view = views[node] = self.local_view(rs)
            window = state.window(rs, fresh=False, max_age_s=ROW_WINDOW_AGE_S)
            drops = self._drops.setdefault(run, CountHistory()).recent(view["drops"], now)
            incomplete = self._incomplete.setdefault(run, CountHistory()).recent(view["frames"]["evicted"], now)
            whole = rs.whole.get(rs.live, rs.dropped, False, len(state.runs)) if rs.ended else None
            rows[node] = overview_row(view, window, state.relay_name, state.frame_limits.limit_ns(node), drops,
                                      incomplete, whole)
        self._drops = {r: h for r, h in self._drops.items() if r in state.runs}
        self._incomplete = {r: h for r, h in self._incomplete.items() if r in state.runs}
        self.rows, self.views = rows, views
        return rows

    async def refresh(self) -> dict[str, dict]:
        """Build this relay's rows; on a shared store, write them and read the others'. Returns the rows."""
        rows = self.build_rows()
        if not self.shared:
            return rows
        now = time.time_ns()
        out = [(node, row["run"], self.state.relay_name, row["updated_ns"], json.dumps(self.views[node]),
                json.dumps(row)) for node, row in rows.items()]
        try:
            if out:
                await self.state.storage.call("put_fleet", out)
            stored = await self.state.storage.call("fleet_rows", now - int(ROW_TTL_S * 1e9))
        except RelayError as exc:  # storage says it fails, once; the page keeps the last rows
            if not self._store_failing:
                log.info("fleet rows not refreshed: %s", exc)
            self._store_failing = True
            return rows
        self._store_failing = False
        remote = {}
        for node, run, relay, updated_ns, view, row in stored:
            if node in rows:
                continue
            row = json.loads(row)
            if row.get("ended") and now - int(updated_ns) > STALE_S * 1e9:
                continue  # its relay no longer lists it (Limits.ended_keep_s), or is gone: it is stored, not live
            remote[node] = Remote(run, relay, int(updated_ns), json.loads(view), row)
        self.remote = remote
        if self.mirrors is not None:
            for node in rows:
                self.mirrors.drop(rows[node]["run"])
        return rows

    # --- what the API lists -----------------------------------------------------------------------

    def overview(self) -> list[dict]:
        """Every DCU's row: this relay's as of the last refresh, the others' as stored."""
        now = time.time_ns()
        out = [dict(row, stale=False) for row in self.rows.values()]
        out += [r.row_at(now) for node, r in self.remote.items() if node not in self.rows]
        return sorted(out, key=lambda r: r["node"])

    def silent_rows(self) -> list[dict]:
        """The rows of other relays' DCUs whose relay went silent (:meth:`Remote.row_at`)."""
        now = time.time_ns()
        return [r.row_at(now) for node, r in self.remote.items() if node not in self.rows and r.stale(now)]

    def node_views(self) -> list[dict]:
        """``GET /api/nodes``: this relay's DCUs live, then the others' as stored, by name."""
        state = self.state
        local = {node: self.local_view(state.runs[run]) for node, run in state.nodes.items() if run in state.runs}
        now = time.time_ns()
        for node, r in self.remote.items():
            rs = state.node_run(node)
            if node not in local or (rs is not None and not state.holds(rs)):
                local[node] = r.heard(r.view, now)
        return [local[node] for node in sorted(local)]

    def local_view(self, rs: RunState) -> dict:
        """The node view of a run this relay keeps, with the relay's name and the DCU's state."""
        view = self.state.node_view(rs)
        return view | {"relay": self.state.relay_name, "state": connection_state(view["connected"], view["ended"])}

    def views_of(self, nodes) -> list[dict]:
        """The node views of ``nodes`` (those known), for a browser that subscribed to them."""
        wanted = set(nodes)
        return [v for v in self.node_views() if v["node"] in wanted]

    async def run_view(self, node: str) -> RunView | None:
        """The run the API reads for ``node``: this relay's live state while it holds it (or no
        other relay does), else a mirror of the stored run another relay holds."""
        state = self.state
        rs = state.node_run(node)
        if rs is not None and state.holds(rs):
            return state.view(rs)
        remote = self.remote.get(node)
        if remote is not None and self.mirrors is not None:
            return await self.mirrors.view(remote.run, node, remote.relay)
        return state.view(rs) if rs is not None else None

    def close(self) -> None:
        if self.mirrors is not None:
            self.mirrors.close()
