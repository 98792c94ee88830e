"""Relays on one PostgreSQL and one Redis: a browser on either gets every relay's DCUs, a Redis
outage degrades without losing anything, and a Redis master replaced by its replica (Redis Sentinel)
is followed. Real relays, PostgreSQL 15 and redis-server from Debian
(tests/pgserver.py, tests/redisserver.py), simulated nodes, a python-socketio client as the browser."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
import redis
import socketio

from dcuscope.relay.live.framepack import unpack_push
from tests.redisserver import RedisSentinel, RedisServer
from tests.relay.helpers import RelayProcess, finish_node, get_json, load_node, start_node, stored_equals_sent, wait_for

pytestmark = pytest.mark.xdist_group("fanout")
FRAMES = 800
"""Frames a source at most: 20 s at 40 fps."""


def has_figures(row: dict) -> bool:
    """Whether an overview row carries its run's window figures: fps, frame delay p99, bottleneck."""
    return bool(row["fps"] and row["p99_ms"] is not None and row["bottleneck"])


def held_by(relay: RelayProcess) -> dict[str, str]:
    """Node -> the relay holding it, as ``relay`` lists the fleet."""
    return {n["node"]: n["relay"] for n in get_json(f"{relay.url}/api/nodes", timeout=5)}


class Browser:
    """A Socket.IO client on a relay's /ui: every event it got, with its arrival time."""

    def __init__(self) -> None:
        self.sio = socketio.AsyncClient(reconnection=True, reconnection_delay=0.2)
        self.got: list[tuple[float, str, object]] = []
        self.sio.on("*", lambda event, data: self.got.append(
            (time.monotonic(), event, unpack_push(data) if event == "frames" else data)), namespace="/ui")

    async def open(self, url: str, nodes: list[str] | None) -> None:
        """Connect, subscribed from the start to ``nodes`` (as the page does)."""
        await self.sio.connect(url, namespaces=["/ui"], transports=["websocket"], wait_timeout=10,
                               auth={"subscribe": {"nodes": nodes, "max_frames": 500}})

    async def wait_frames(self, node: str, seconds: float, after: float = 0.0) -> bool:
        """Whether frames of ``node`` that came after ``after`` are here, or come within ``seconds``."""
        deadline = time.monotonic() + seconds
        while not self.frames(node, after) and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        return bool(self.frames(node, after))

    def frames(self, node: str, after: float = 0.0) -> list[dict]:
        return [f for t, e, d in self.got if e == "frames" and t >= after for f in d["nodes"].get(node, {}).get("frames", [])]

    def rows_of(self, node: str) -> list[dict]:
        """Every overview row of ``node`` it got, in order."""
        return [r for _, e, d in self.got if e == "overview" for r in d["rows"] if r["node"] == node]

    def rows(self, after: float = 0.0) -> dict[str, dict]:
        return {r["node"]: r for t, e, d in self.got if e == "overview" and t >= after for r in d["rows"]}


def test_a_browser_on_one_relay_gets_every_relays_dcus_and_only_those_it_shows(tmp_path, pg_url, redis_server):
    # Its last checks read both runs after they ended: on a loaded machine, past the 60 s an ended run
    # stays in the live rows by default.
    args = ["--redis", redis_server.url, "--limit", "ended_keep_s=3600"]
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=[*args, "--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=[*args, "--name", "relay-b"])
    try:
        # Frames flow until the watch below is over (at most FRAMES a source, 20 s): on a loaded machine
        # the watch starts late, and a run whose frames were over would read fps 0 and no bottleneck.
        on_a = start_node(a.url, "DCU-A", tmp_path / "a.npz", frames=FRAMES, sources=2, fps=40, paced=True, until_stdin=True)
        on_b = start_node(b.url, "DCU-B", tmp_path / "b.npz", frames=FRAMES, sources=2, fps=40, paced=True, until_stdin=True)
        both = {"DCU-A": "relay-a", "DCU-B": "relay-b"}
        wait_for(lambda: held_by(a) == both and held_by(b) == both, 30, what="each relay lists both DCUs")

        async def watch() -> tuple[Browser, Browser]:
            shows_a, shows_b = Browser(), Browser()
            await shows_a.open(b.url, ["DCU-A"])  # a DCU of the other relay
            await shows_b.open(b.url, ["DCU-B"])
            # Until each got frames of its DCU and a row with A's figures (at most 20 s), and 1 s more
            # for any it should not get.
            for _ in range(200):
                if all(b.frames(n) and any(map(has_figures, b.rows_of("DCU-A"))) for b, n in ((shows_a, "DCU-A"), (shows_b, "DCU-B"))):
                    break
                await asyncio.sleep(0.1)
            await asyncio.sleep(1.0)
            for browser in (shows_a, shows_b):
                await browser.sio.disconnect()
            return shows_a, shows_b

        shows_a, shows_b = asyncio.run(watch())
        assert shows_a.frames("DCU-A") and not shows_a.frames("DCU-B")
        assert shows_b.frames("DCU-B") and not shows_b.frames("DCU-A")
        # Pushes are routed by room: B received A's pushes (DCU-A's frames, A's overview rows) for its
        # pages; A, with no page, received nothing of B's, though B pushed DCU-B's frames all along.
        fanout_a, fanout_b = (get_json(f"{r.url}/api/health")["fanout"] for r in (a, b))
        assert fanout_a["received"] == 0 and fanout_a["rooms"] == 0, fanout_a
        assert fanout_b["received"] > 0, fanout_b
        for browser in (shows_a, shows_b):
            rows = browser.rows()
            assert rows.keys() == {"DCU-A", "DCU-B"}
            assert rows["DCU-A"]["relay"] == "relay-a" and rows["DCU-B"]["relay"] == "relay-b"
            # Some row carried A's figures (not every one: the first come before A's window has any).
            figures = browser.rows_of("DCU-A")
            assert any(map(has_figures, figures)), figures[-3:]
            stats = [d for _, e, d in browser.got if e == "stats"]
            assert stats and all(len(d["nodes"]) == 1 for d in stats)

        # B answers for A's DCU from the store: the same frames as A's own live state, every one A sent whole.
        finish_node(on_a, 60)
        finish_node(on_b, 60)
        mirrored = get_json(f"{b.url}/api/frames?node=DCU-A&limit=2000")
        own = get_json(f"{a.url}/api/frames?node=DCU-A&limit=2000")
        key = lambda f: (f["source"], f["frame"], f["delay_ms"])  # noqa: E731
        events = load_node(tmp_path / "a.npz")[1]
        sent = np.unique(events[events["stage"] == events["stage"].max()][["source", "frame"]])  # reached the sink
        assert len(own["frames"]) == len(sent) and sorted(map(key, mirrored["frames"])) == sorted(map(key, own["frames"]))
        stats_b, stats_a = get_json(f"{b.url}/api/stats?node=DCU-A"), get_json(f"{a.url}/api/stats?node=DCU-A")
        assert stats_b["frames"] == stats_a["frames"] and stats_b["frame"]["p99_ms"] == stats_a["frame"]["p99_ms"]
        overview = get_json(f"{b.url}/api/overview")
        assert [r["node"] for r in overview["rows"]] == ["DCU-A", "DCU-B"] and overview["relay"] == "relay-b"
        health = get_json(f"{b.url}/api/health")
        assert health["relay"] == "relay-b" and health["fanout"]["mode"] == "redis" and health["fanout"]["ok"]
    finally:
        a.stop()
        b.stop()


def test_a_redis_restart_loses_nothing_and_pushes_resume_by_themselves(tmp_path, pg_url, redis_server):
    args = ["--redis", redis_server.url]
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=[*args, "--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=[*args, "--name", "relay-b"])
    node = start_node(a.url, "DCU-A", tmp_path / "a.npz", frames=600, sources=2, fps=40, paced=True)
    try:
        wait_for(lambda: "DCU-A" in held_by(b), 30, what="B lists A's DCU")

        async def watch() -> tuple[Browser, float, float]:
            browser = Browser()
            await browser.open(b.url, ["DCU-A"])
            # within a second unloaded; a loaded machine is slower
            assert await browser.wait_frames("DCU-A", 20), "no live frames of A's DCU on B before the outage"
            redis_server.stop()
            down = time.monotonic()
            await asyncio.sleep(1.5)
            assert get_json(f"{b.url}/api/health")["fanout"]["ok"] is False
            assert get_json(f"{a.url}/api/health")["fanout"]["ok"] is False
            quiet = time.monotonic()
            await asyncio.sleep(2.0)
            missed = browser.frames("DCU-A", after=quiet)
            redis_server.start()
            up = time.monotonic()
            for _ in range(300):
                await asyncio.sleep(0.1)
                if browser.frames("DCU-A", after=up):
                    break
            resumed = time.monotonic() - up
            await asyncio.sleep(1.0)
            await browser.sio.disconnect()
            assert not missed, "frames of another relay's DCU came through while Redis was down"
            return browser, down, resumed

        browser, _, resumed = asyncio.run(watch())
        # The relays reconnect every second (python-socketio's own backoff would wait up to a minute).
        assert resumed < 15.0, f"pushes resumed {resumed:.1f} s after Redis came back"
        for relay in (a, b):
            health = get_json(f"{relay.url}/api/health")["fanout"]
            assert health["ok"] and health["outages"] == 1, health
        counters = finish_node(node, 60)
        assert counters["acked"] == counters["events"] and counters["lost"] == 0  # ingest went on untouched
        header, sent = load_node(tmp_path / "a.npz")
        stored_equals_sent(pg_url, "DCU-A", sent)
        # What B's browser missed is in the store: B answers for it (the page backfills from there).
        frames = get_json(f"{b.url}/api/frames?node=DCU-A&limit=2000")["frames"]
        assert len(frames) == 1200
        for relay, name in ((a, "a"), (b, "b")):
            lines = [ln for ln in (tmp_path / f"{name}.log").read_text().splitlines() if "redis" in ln.lower()]
            assert len([ln for ln in lines if "cannot" in ln]) == 1, lines  # one line per change
            assert len([ln for ln in lines if "connected;" in ln]) == 2, lines  # at start, and once back
    finally:
        if node.poll() is None:
            node.kill()
        a.stop()
        b.stop()


@pytest.fixture
def sentinel_redis():
    """A Redis master, its replica, and a Sentinel watching them (tests/redisserver.py)."""
    servers = []
    try:
        master = RedisServer().start()
        servers.append(master)
        replica = RedisServer(replica_of=master).start()
        servers.append(replica)
        # The Sentinel learns the replicas from the master's INFO: at its start, then every 10 s.
        wait_for(lambda: redis.Redis(port=master.port).info("replication").get("connected_slaves") == 1, 20,
                 what="the replica following the master")
        sentinel = RedisSentinel(master).start()
        servers.append(sentinel)
        wait_for(lambda: redis.Redis(port=sentinel.port).execute_command("SENTINEL", "REPLICAS", RedisSentinel.SERVICE),
                 20, what="the Sentinel knowing the replica")
        yield master, replica, sentinel
    finally:
        for server in reversed(servers):
            server.close()


def test_a_redis_master_replaced_by_its_replica_is_followed_through_sentinel(tmp_path, pg_url, sentinel_redis):
    master, replica, sentinel = sentinel_redis
    args = ["--redis", sentinel.url]
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=[*args, "--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=[*args, "--name", "relay-b"])
    node = start_node(a.url, "DCU-A", tmp_path / "a.npz", frames=400, sources=2, fps=40, paced=True)  # 10 s
    try:
        wait_for(lambda: "DCU-A" in held_by(b), 30, what="B lists A's DCU")

        async def watch() -> float:
            browser = Browser()
            await browser.open(b.url, ["DCU-A"])
            assert await browser.wait_frames("DCU-A", 20), "no live frames of A's DCU on B before the master died"
            master.kill9()
            died = time.monotonic()
            await asyncio.sleep(0.5)  # frames pushed before the kill may still arrive
            await browser.wait_frames("DCU-A", 30, after=time.monotonic())
            resumed = time.monotonic() - died
            await browser.sio.disconnect()
            return resumed

        resumed = asyncio.run(watch())
        print(f"\nRedis master killed: pushes of A's DCU on B again {resumed:.1f} s later (Sentinel: down after 1 s)")
        assert resumed < 15.0, f"pushes resumed {resumed:.1f} s after the master died"
        assert redis.Redis(port=replica.port).info("replication")["role"] == "master"  # Sentinel promoted it
        for relay in (a, b):
            health = get_json(f"{relay.url}/api/health")["fanout"]
            assert health["ok"] and health["outages"] == 1 and health["url"] == sentinel.url, health
        counters = finish_node(node, 60)
        assert counters["acked"] == counters["events"] and counters["lost"] == 0
        _, sent = load_node(tmp_path / "a.npz")
        stored_equals_sent(pg_url, "DCU-A", sent)
    finally:
        if node.poll() is None:
            node.kill()
        a.stop()
        b.stop()


def test_a_forwarded_packet_carries_its_parts_as_they_are_and_a_broken_one_is_refused():
    """What relays forward to one another's browsers: the Socket.IO packet's text and binary parts, byte for
    byte, after a header naming the room; anything cut short or of an unknown kind is refused, saying why."""
    from dcuscope.relay.api.fanout import FORWARD, forward_message, read_forward

    parts = ['451-["frames",{"nodes":{"DCU-1":{"packed":{"ints":{"_placeholder":true,"num":0}}}}}]', b"\x00\x01" * 500, b""]
    message = forward_message("/", "dcu:25:DCU-1", ["sid-1"], parts)
    assert read_forward(message) == (parts, "/", "dcu:25:DCU-1", ["sid-1"])
    for broken, why in ((message[:-1001], "cut short"), (message[:30], "no header line"), (b"{}", "not a forwarded"),
                        (message.replace(b'"room"', b'"rome"'), "bad header"),
                        (message[:message.index(b"\n", len(FORWARD)) + 1], "no text part"),
                        (message.replace(b"\nT", b"\nX", 1), "unknown kind")):
        with pytest.raises(ValueError, match=why):
            read_forward(broken)
