"""A run that ended, as the fleet lists it: its row keeps its whole run's figures (said so) while its
window empties, it leaves the live rows after ``--limit ended_keep_s`` (stored still), and the demo's log
says it ended once."""

from __future__ import annotations

import time

from dcuscope.demo import status_lines
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.live.run import LiveConfig
from tests.relay.helpers import finish_node, get_json, start_node, wait_for
from tests.ui.helpers import RelayThread

KEEP_S = 4.0
WINDOW_S = 1.0


def row_of(url: str, node: str) -> dict | None:
    return next((r for r in get_json(f"{url}/api/overview")["rows"] if r["node"] == node), None)


def test_an_ended_run_keeps_its_whole_run_figures_then_leaves_the_live_rows_and_is_logged_once(tmp_path):
    relay = RelayThread(tmp_path / "relay.db", limits=Limits(ended_keep_s=KEEP_S), live=LiveConfig(window_s=WINDOW_S))
    try:
        node = start_node(relay.url, "vm", tmp_path / "vm.npz", frames=60, sources=2, fps=25.0)
        finish_node(node)
        ended_at = time.monotonic()
        row = wait_for(lambda: (r := row_of(relay.url, "vm")) and r["ended"] and r, 5, 0.1, "vm's row, ended")
        whole = get_json(f"{relay.url}/api/stats?node=vm")
        assert whole["frames"]["complete"] == 120 and whole["frame"]["p99_ms"] is not None
        # Its window empties within WINDOW_S; the row keeps the run's last whole-run figures, labelled so.
        wait_for(lambda: get_json(f"{relay.url}/api/stats?node=vm")["window"]["frames"]["complete"] == 0, 5, 0.1,
                 "vm's window emptied")
        row = row_of(relay.url, "vm")
        assert row["fps"] is None and row["figures"] == "whole run"
        assert row["p99_ms"] == whole["frame"]["p99_ms"], (row["p99_ms"], whole["frame"]["p99_ms"])
        assert row["bottleneck"]["stage"] == whole["bottleneck"]["stage"]

        # The demo's log says it ended once, not every 5 s after.
        said: set = set()
        assert status_lines(relay.url, said) == ["vm: ended (120 frames)"]
        assert status_lines(relay.url, said) == []

        # Still listed until ended_keep_s after its node left, then out of the live rows, stored still.
        assert row_of(relay.url, "vm") is not None and time.monotonic() - ended_at < KEEP_S
        wait_for(lambda: row_of(relay.url, "vm") is None, KEEP_S + 5, 0.2, "vm's row gone")
        assert time.monotonic() - ended_at >= KEEP_S - 0.5
        assert [n["node"] for n in get_json(f"{relay.url}/api/nodes")] == []
        runs = [r for s in get_json(f"{relay.url}/api/sessions") for r in s["runs"]]
        assert [(r["node"], bool(r["ended_ns"])) for r in runs] == [("vm", True)]
    finally:
        relay.stop()
