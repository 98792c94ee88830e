"""A relay that freezes (SIGSTOP: a paused VM, a hung process) is not shown serving its DCUs: the
other relays of the fleet list them not connected, "relay silent", until it wakes. Two real relays
on one real PostgreSQL (tests/pgserver.py), one simulated node that knows relay A only (it cannot
move to B)."""

from __future__ import annotations

import asyncio
import signal

import pytest

from tests.relay.helpers import RelayProcess, finish_node, get_json, kill_all, start_node, wait_for
from tests.relay.test_fanout import Browser

pytestmark = pytest.mark.xdist_group("silent")
NODE = "DCU-S"


def as_listed(relay: RelayProcess) -> tuple[dict, dict] | None:
    """NODE's entry in ``relay``'s ``/api/nodes`` and its row in ``/api/overview`` (None while either lacks it)."""
    view = next((n for n in get_json(f"{relay.url}/api/nodes", timeout=3) if n["node"] == NODE), None)
    row = next((r for r in get_json(f"{relay.url}/api/overview", timeout=3)["rows"] if r["node"] == NODE), None)
    return (view, row) if view and row else None


def listed_as(relay: RelayProcess, state: str, held_by: str):
    """A predicate: ``relay`` lists NODE in ``state``, held by ``held_by``, in both lists."""
    def check():
        both = as_listed(relay)
        return both if both and all(x["state"] == state and x["relay"] == held_by for x in both) else None
    return check


def test_a_frozen_relays_dcu_is_listed_not_connected_relay_silent_until_it_wakes(tmp_path, pg_url):
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=["--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=["--name", "relay-b"])
    node = None
    try:
        node = start_node(a.url, NODE, tmp_path / "s.npz", frames=50, fps=25, paced=True, linger=True)
        view, row = wait_for(listed_as(b, "connected", "relay-a"), 15, 0.2, what="B listing the node connected to A")
        assert view["connected"] and row["connected"] and not view["stale"] and not row["stale"]

        a.proc.send_signal(signal.SIGSTOP)
        view, row = wait_for(listed_as(b, "relay silent", "relay-a"), 15, 0.2, what="B listing A as silent")
        for x in (view, row):
            assert x["connected"] is False and x["stale"] is True and x["silent_s"] >= 3.0, x
        assert row["alerts"][0] == f"relay silent: last heard {row['silent_s']:.0f} s ago", row["alerts"]

        async def pushed() -> list[dict]:
            """NODE's rows in the overview B pushes to a page (the connect snapshot, then once a second)."""
            page = Browser()
            await page.open(b.url, [NODE])
            for _ in range(50):
                got = [r for t, e, d in page.got if e == "overview" for r in d["rows"] if r["node"] == NODE]
                if len(got) >= 2:
                    break
                await asyncio.sleep(0.1)
            await page.sio.disconnect()
            return got

        # A pushes nothing now: B pushes its row, so that a page shows it (it would age out, unrefreshed).
        got = asyncio.run(pushed())
        assert len(got) >= 2 and all(r["state"] == "relay silent" and r["relay"] == "relay-a" for r in got), got

        a.proc.send_signal(signal.SIGCONT)
        view, row = wait_for(listed_as(b, "connected", "relay-a"), 15, 0.2, what="B listing the node connected again")
        assert view["connected"] and row["connected"] and "silent_s" not in row, row
        assert not any(alert.startswith("relay silent") for alert in row["alerts"]), row["alerts"]
        finish_node(node, 30)
    finally:
        a.proc.send_signal(signal.SIGCONT)  # a stopped relay ignores SIGTERM until it runs again
        kill_all([node] if node is not None else [])
        a.stop()
        b.stop()
