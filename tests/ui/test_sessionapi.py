"""Stored sessions over HTTP (relay/api/sessions.py): the frames and statistics of what nodes shipped."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from dcuscope.model.delays import chains, node_stats
from dcuscope.model.frametable import frame_table
from dcuscope.probes.ship import simnode
from dcuscope.protocol.events import TraceHeader
from tests.relay.helpers import get_json, http_status, wait_for
from tests.ui.helpers import RelayThread, sim_nodes

TOKEN = "ui-token"


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sessionapi")
    relay = RelayThread(tmp / "relay.db", token=TOKEN)
    try:
        # One session: both runs are live at once. Each paced run lasts 2 s, so they share a frame 0
        # 5 s ahead, which both nodes reach even when a loaded machine starts one of them late.
        t0 = time.clock_gettime_ns(time.CLOCK_REALTIME) + 5_000_000_000
        feeder = sim_nodes(relay.url, tmp, ["DCU-1", "DCU-2"], frames=60, sources=3, fps=30, paced=True,
                           token=TOKEN, offsets_ns=[0, 4_000_000], t0_ns=t0)
        feeder.wait(120)
        shipped = {}
        for node, out in zip(feeder.nodes, feeder.outs):
            z = np.load(out)
            shipped[node] = (TraceHeader.from_dict(json.loads(str(z["header"]))), z["events"])
        yield relay, shipped
    finally:
        relay.stop()


def test_session_nodes_frames_and_stats_match_what_was_shipped(stored):
    relay, shipped = stored
    sessions = get_json(f"{relay.url}/api/sessions", TOKEN)
    sid = sessions[0]["session"]
    nodes = get_json(f"{relay.url}/api/sessions/{sid}/nodes", TOKEN)
    assert sorted(n["node"] for n in nodes) == ["DCU-1", "DCU-2"]
    for summary in nodes:
        header, events = shipped[summary["node"]]
        table = frame_table(header, events)
        ch = chains(table)
        assert summary["frames"] == int(ch.complete.sum()) == 180
        assert summary["stages"] == header.stages and summary["ended"]

        # Paged in the order frames ended; every complete frame exactly once.
        got, since = [], 0
        while True:
            query = f"node={summary['node']}&since={since}&limit=50"
            page = get_json(f"{relay.url}/api/sessions/{sid}/frames?{query}", TOKEN)
            assert page["total"] == summary["frames"] and page["stages"] == header.stages
            if not page["frames"]:
                break
            assert [f["n"] for f in page["frames"]] == list(range(since + 1, page["cursor"] + 1))
            got += page["frames"]
            since = page["cursor"]
        assert len(got) == summary["frames"]
        assert {(f["source"], f["frame"]) for f in got} == {(int(s), int(f)) for s, f in
                                                             zip(table.source[ch.complete], table.frame[ch.complete])}
        ends = [f["end"] for f in got]
        assert ends == sorted(ends) and all(f["complete"] for f in got)
        assert all((f["end"] - f["origin"]) / 1e6 == f["delay_ms"] for f in got)
        assert page["has_exit"] == [s in simnode.STAGES for s in header.stages]  # not the sources, not the sink
        # Delays are differences on one clock: the clock correction leaves them as shipped.
        expected = node_stats(header, events)
        stats = get_json(f"{relay.url}/api/sessions/{sid}/stats?node={summary['node']}", TOKEN)
        assert stats["frames"] == expected["frames"]
        for stage, s in expected["stages"].items():
            assert stats["stages"][stage]["p95_ms"] == pytest.approx(s["p95_ms"], rel=1e-9)
        assert stats["frame"]["mean_ms"] == pytest.approx(expected["frame"]["mean_ms"], rel=1e-9)
        assert stats["bottleneck"]["stage"] == "infer"  # simnode's slowest stage by construction
        first = got[0]
        mux = header.stages.index("mux")
        assert first["enter"][mux] is not None and first["exit"][mux] > first["enter"][mux]
        assert first["stage_delay_ms"][mux] == (first["exit"][mux] - first["enter"][mux]) / 1e6
        assert first["stage_gap_ms"][mux] == (first["enter"][mux] - first["origin"]) / 1e6
        assert first["enter"][0] is None  # the origin stage has no enter


def test_session_routes_refuse_bad_requests(stored):
    relay, _ = stored
    base = f"{relay.url}/api/sessions"
    assert http_status(f"{base}/1/nodes") == 401  # the access policy covers these routes
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    assert http_status(f"{base}/999/nodes", bearer) == 404
    assert http_status(f"{base}/1/frames", bearer) == 400
    assert http_status(f"{base}/1/frames?node=nobody", bearer) == 404
    assert http_status(f"{base}/1/frames?node=DCU-1&since=x", bearer) == 400
    assert http_status(f"{base}/abc/nodes", bearer) == 404
    page = wait_for(lambda: get_json(f"{base}/1/frames?node=DCU-1&since=170&limit=100000", TOKEN), 10)
    assert len(page["frames"]) == 10 and page["cursor"] == 180
