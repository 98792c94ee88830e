"""2,500 malformed payloads at the ingest WebSocket while a well-behaved node streams: every bad
connection is closed, the relay stays up, the good node's data and statistics stay exact; and
garbage at the browsers' Socket.IO: the relay stays up and logs no traceback."""

from __future__ import annotations

import asyncio
import time

import pytest

from dcuscope.model.delays import node_stats
from tests.relay.fuzzer import Case, fuzz, fuzz_ui
from tests.relay.helpers import RelayProcess, assert_stats_equal, finish_node, get_json, load_node, start_node

PAYLOADS = 2_500
"""About 90 of each of the 28 kinds: every variant of each (11 at most) comes up."""
UI_PAYLOADS = 500
UI_WORKERS = 32
"""Each garbage packet the relay leaves open costs its connection fuzz_ui's 0.3 s wait: 32 at once."""
NODE_FRAMES = 500
"""The good node's run: 10 s at 50 fps, longer than the two fuzzers take on an idle machine (about 8 s)."""


@pytest.mark.long
def test_fuzz_while_a_node_streams(tmp_path):
    # 16 ingest fuzzers, then 32 UI ones, and the good node share one address: above the default per-peer cap.
    relay = RelayProcess(tmp_path / "relay.db", token="t0k", args=["--limit", "connections_per_peer=64"])
    try:
        node = start_node(relay.url, "good", tmp_path / "good.npz", frames=NODE_FRAMES, sources=2, fps=50, paced=True,
                          drop_rate=0.01, token="t0k")
        started = time.monotonic()
        report = asyncio.run(fuzz(relay.url, PAYLOADS, token="t0k", workers=16, timeout=5.0))
        elapsed = time.monotonic() - started
        streaming = node.poll() is None
        ui_kinds = asyncio.run(fuzz_ui(relay.url, UI_PAYLOADS, token="t0k", workers=UI_WORKERS))
        assert relay.alive()
        counters = finish_node(node, 120)

        assert report.sent == PAYLOADS and elapsed < 240
        assert not report.not_closed, report.not_closed
        assert report.closed == PAYLOADS
        assert set(report.kinds) == Case.kinds() and len(report.kinds) >= 28 and min(report.kinds.values()) > 50
        assert len(ui_kinds) == 10 and sum(ui_kinds.values()) == UI_PAYLOADS
        health = get_json(f"{relay.url}/api/health", "t0k")
        assert health["ok"] and health["rejected"] >= report.errors_seen > PAYLOADS // 2

        # The well-behaved node never noticed: one connection, everything acknowledged, exact stats.
        assert counters["connects"] == 1 and counters["lost"] == 0 and counters["acked"] == counters["events"]
        header, events = load_node(tmp_path / "good.npz")
        assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node=good", "t0k"))
        # Runs closed for what they sent left memory and are kept out of the session.
        assert not [n for n in get_json(f"{relay.url}/api/nodes", "t0k") if n["node"].startswith("fuzz")]
        assert health["released_runs"] >= 16
        sessions = get_json(f"{relay.url}/api/sessions", "t0k")
        assert [r["node"] for s in sessions for r in s["runs"]] == ["good"]
        print(f"fuzz: {PAYLOADS} payloads in {elapsed:.1f} s, node streaming throughout: {streaming}, "
              f"kinds: {dict(report.kinds)}")
    finally:
        assert relay.stop() == 0
    assert "Traceback" not in relay.log.read_text()
