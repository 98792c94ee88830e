"""Well-formed hostile clients against node identity, on a real relay with a good node streaming
beside them: run hijack (issue 12, attack 1), leaked runs of restarting nodes (4), impersonation
of a node name (5), hostile runs in a real node's session (8). The good node's stored events
equal what it sent, its statistics stay exact, and it never notices."""

from __future__ import annotations

import asyncio
import uuid

import pytest

from dcuscope.model.delays import node_stats
from dcuscope.probes.ship.simnode import synth_events
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay.store.runs import list_sessions, load_runs
from tests.relay.helpers import (HandNode, RelayProcess, assert_stats_equal, finish_node, get_json, load_node,
                                 sort_events, start_node, wait_for)

TOKEN = "t0k"
RSS_BOUND_MB = 300


def _good(relay: RelayProcess, tmp_path, name: str = "good", token: str = TOKEN, frames: int = 300,
          linger: bool = False):
    node = start_node(relay.url, name, tmp_path / f"{name}.npz", frames=frames, sources=2, fps=50, paced=True,
                      drop_rate=0.01, token=token, linger=linger)
    nodes = wait_for(lambda: [n for n in get_json(f"{relay.url}/api/nodes", TOKEN) if n["node"] == name
                              and n["events"] > 0], 20, what=f"{name} streaming")
    return node, nodes[0]


def _check_good(relay: RelayProcess, tmp_path, node, name: str = "good") -> dict:
    """The good node noticed nothing, and the relay holds exactly what it sent."""
    counters = finish_node(node, 90)
    assert counters["connects"] == 1 and counters["lost"] == 0 and counters["acked"] == counters["events"]
    header, events = load_node(tmp_path / f"{name}.npz")
    wait_for(lambda: [n for n in get_json(f"{relay.url}/api/nodes", TOKEN) if n["node"] == name][0]["ended"], 10,
             what="end of the good run")
    assert_stats_equal(node_stats(header, events), get_json(f"{relay.url}/api/stats?node={name}", TOKEN))
    return counters


def _stored(db, run: str, events) -> None:
    (stored,) = [r for r in load_runs(db, run, corrected=False)]
    assert len(stored.events) == len(events)
    assert (sort_events(stored.events) == sort_events(events)).all()


def test_a_public_run_id_cannot_be_hijacked(tmp_path):
    """Attack 1: the good run's id and stages are public in /api/nodes; a second connection saying
    hello with them (no secret, or a guessed one) used to supersede the real node and slip
    batches into its run at sequence numbers it had not used yet."""
    relay = RelayProcess(tmp_path / "r.db", token=TOKEN)
    try:
        node, seen = _good(relay, tmp_path)

        async def attack() -> list[str]:
            refusals = []
            for secret in (None, "0" * 32, uuid.uuid4().hex):
                with pytest.raises(ConnectionError) as caught:
                    await HandNode.open(relay.url, "good", seen["run"], TOKEN, stages=2, secret=secret)
                refusals.append(str(caught.value))
            return refusals

        refusals = asyncio.run(attack())
        assert all("resuming it takes the secret issued at its first hello" in r for r in refusals), refusals
        _check_good(relay, tmp_path, node)
        header, events = load_node(tmp_path / "good.npz")
        health = get_json(f"{relay.url}/api/health", TOKEN)
        assert health["refused"]["resume_secret"] == 3
        print(f"hijack: relay peak RSS {relay.peak_rss_mb():.0f} MB")
        assert relay.peak_rss_mb() < RSS_BOUND_MB
    finally:
        assert relay.stop() == 0
    _stored(tmp_path / "r.db", seen["run"], events)
    assert "Traceback" not in relay.log.read_text()


def test_a_second_live_run_under_a_streaming_name_is_refused(tmp_path):
    """Attack 5: a connection using the good node's name with a new run took over its /api/stats
    and UI, and kept them after the real node ended. Refused while the name is live, counted as
    a conflict of the good run; with per-node tokens (--node-tokens) another node's token cannot
    use the name at all."""
    tokens = tmp_path / "nodes.txt"
    good_token, evil_token = "good-secret-token-0001", "evil-secret-token-0002"
    tokens.write_text(f"# node token\ngood {good_token}\nevil {evil_token}\n")
    relay = RelayProcess(tmp_path / "r.db", token=TOKEN, args=["--node-tokens", str(tokens)])
    try:
        node, seen = _good(relay, tmp_path, token=good_token)

        async def attack() -> tuple[str, str]:
            with pytest.raises(ConnectionError) as shared:
                await HandNode.open(relay.url, "good", uuid.uuid4().hex, TOKEN, stages=2)
            # A secret presented for a run never stored claims no resume: still a second live run.
            with pytest.raises(ConnectionError, match="a second live run under the same name is refused"):
                await HandNode.open(relay.url, "good", uuid.uuid4().hex, TOKEN, stages=2, secret=uuid.uuid4().hex)
            with pytest.raises(ConnectionError) as own:
                await HandNode.open(relay.url, "good", uuid.uuid4().hex, evil_token, stages=2)
            evil = await HandNode.open(relay.url, "evil", uuid.uuid4().hex, evil_token, stages=2)
            await evil.close()
            return str(shared.value), str(own.value)

        shared, own = asyncio.run(attack())
        assert "a second live run under the same name is refused" in shared
        assert "hello names node 'good' but the connection is 'evil'" in own
        view = [n for n in get_json(f"{relay.url}/api/nodes", TOKEN) if n["node"] == "good"]
        assert len(view) == 1 and view[0]["run"] == seen["run"] and view[0]["conflicts"] == 2
        _check_good(relay, tmp_path, node)
        # Ended: the name is free again, but only for a holder of the node's own token or the shared one.
        with pytest.raises(ConnectionError, match="hello names node 'good' but the connection is 'evil'"):
            asyncio.run(HandNode.open(relay.url, "good", uuid.uuid4().hex, evil_token, stages=2))
        assert [n["run"] for n in get_json(f"{relay.url}/api/nodes", TOKEN) if n["node"] == "good"] == [seen["run"]]
        assert get_json(f"{relay.url}/api/health", TOKEN)["refused"]["name_taken"] == 2
        print(f"impersonation: relay peak RSS {relay.peak_rss_mb():.0f} MB")
        assert relay.peak_rss_mb() < RSS_BOUND_MB
    finally:
        assert relay.stop() == 0
    assert "Traceback" not in relay.log.read_text()


def test_runs_of_restarting_and_cycling_nodes_leave_memory(tmp_path):
    """Attack 4: a node restarting while its old socket stayed open left the old run's live state
    in memory for good, and connect cycles left every run held. A silent old connection loses
    its name to the new run and is closed; runs beyond runs_held leave memory (they stay stored)."""
    held = 16
    relay = RelayProcess(tmp_path / "r.db", token=TOKEN,
                         args=["--limit", f"runs_held={held}", "--limit", "silent_s=0.5"])
    events = synth_events(1000, 4, 50.0, 1_700_000_000_000_000_000)

    async def restarts(n: int) -> list[HandNode]:
        kept_open = []
        for _ in range(n):
            run = uuid.uuid4().hex
            deadline = asyncio.get_running_loop().time() + 10
            while True:  # refused while the former run is heard from within silent_s
                try:
                    hand = await HandNode.open(relay.url, "restarter", run, TOKEN, stages=4)
                    break
                except ConnectionError as exc:
                    assert "a second live run under the same name is refused" in str(exc)
                    assert asyncio.get_running_loop().time() < deadline
                    await asyncio.sleep(0.2)
            assert (await hand.batch(encode_batch(run, 0, events)))["ok"]
            kept_open.append(hand)  # never closed: the "crashed" node's socket stays open
        return kept_open

    async def cycles(n: int) -> None:
        for k in range(n):
            hand = await HandNode.open(relay.url, f"cycle-{k}", uuid.uuid4().hex, TOKEN, stages=1)
            await hand.close()

    async def attack() -> None:
        kept = await restarts(8)
        await cycles(400)
        for hand in kept:
            await hand.close()

    try:
        # The good run stays live through the attack however long that takes on a loaded machine
        # (it would rightly be released once ended, as the oldest detached run).
        node, _ = _good(relay, tmp_path, frames=400, linger=True)
        asyncio.run(attack())
        health = wait_for(lambda: (h := get_json(f"{relay.url}/api/health", TOKEN))["runs"] <= held and h, 10,
                          what="runs released")
        names = [n["node"] for n in get_json(f"{relay.url}/api/nodes", TOKEN)]
        assert names.count("restarter") == 1 and "good" in names
        assert health["released_runs"] >= 8 - 1 + 400 - held
        _check_good(relay, tmp_path, node)
        peak = relay.peak_rss_mb()
        print(f"restarts and cycles: relay peak RSS {peak:.0f} MB, runs held {health['runs']}, "
              f"released {health['released_runs']}")
        assert peak < RSS_BOUND_MB
    finally:
        assert relay.stop() == 0
    # Released runs stayed stored: every restart's batch is there.
    restarter = [r for s in load_sessions(tmp_path / "r.db") for r in s if r == "restarter"]
    assert len(restarter) == 8
    assert "Traceback" not in relay.log.read_text()


def load_sessions(db) -> list[list[str]]:
    return [[r["node"] for r in s["runs"]] for s in list_sessions(db)]


def test_a_refused_run_is_kept_out_of_the_good_nodes_session(tmp_path):
    """Attack 8 (last part): a hostile run said hello while the good node streamed, joining its
    live session; now a run the relay closes for what it sent is kept apart: out of the
    session's runs, its nodes view, and exports."""
    relay = RelayProcess(tmp_path / "r.db", token=TOKEN)
    try:
        node, seen = _good(relay, tmp_path)

        async def attack() -> None:
            run = uuid.uuid4().hex
            hostile = await HandNode.open(relay.url, "hostile", run, TOKEN, stages=2)
            await hostile.link.send_batch(b"DCUB" + b"\0" * 60)  # malformed: closed
            await asyncio.wait_for(hostile.link.closed(), 5)
            await hostile.close()

        asyncio.run(attack())
        _check_good(relay, tmp_path, node)
        sessions = get_json(f"{relay.url}/api/sessions", TOKEN)
        assert [[r["node"] for r in s["runs"]] for s in sessions] == [["good"]]
        stored = get_json(f"{relay.url}/api/sessions/{sessions[0]['session']}/nodes", TOKEN)
        assert [n["node"] for n in stored] == ["good"]
        assert [n["node"] for n in get_json(f"{relay.url}/api/nodes", TOKEN)] == ["good"]
        print(f"hostile run in the session: relay peak RSS {relay.peak_rss_mb():.0f} MB")
    finally:
        assert relay.stop() == 0
    assert [r.header.node for r in load_runs(tmp_path / "r.db", 1)] == ["good"]
    assert seen["session"] == 1
