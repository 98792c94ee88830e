"""Relays that stop without dying lose nothing and hold nothing hostage (issue 32).

Real relays on a real PostgreSQL, real simulated nodes (``probes.ship.simnode`` processes, paced), real
faults: a relay SIGSTOPped (a paused VM, a hung process), the network between the nodes and a relay
cut while it still reaches its store, a relay's connection to PostgreSQL cut and PostgreSQL
restarted, Redis frozen. Cuts are iptables DROP rules inside network namespaces the tests make
(tests/relay/nsnet.py): packets vanish, as in a real cut, and the host's own network is untouched.

Each test ends with every run complete: stored == sent as sorted arrays (nothing lost, nothing
stored twice), its end stored, one session. The time from the fault until every node is stored
again on another relay is printed (``-s``; the goal is at most 10 s: BENCHMARKS.md, "Failover"; docs/benchmarks-log.md, issue 32).
"""

from __future__ import annotations

import asyncio
import signal
import subprocess
import time

import pytest

from dcuscope.relay.store.runs import list_sessions
from tests.pgserver import PostgresServer
from tests.relay.helpers import (RelayProcess, finish_node, get_json, kill_all, load_node, start_node,
                                 stored_equals_sent, wait_for)
from tests.relay.nsnet import Namespace, netns_permitted
from tests.relay.api.test_fanout import Browser

pytestmark = pytest.mark.long
RECOVERY_S = 45
"""What the tests wait for the nodes to be stored again elsewhere (the goal, 10 s, is what they print)."""


def own_runs(relay: RelayProcess) -> list[dict]:
    """The ``/api/nodes`` entries of the runs ``relay`` holds itself ([]: it does not answer)."""
    try:
        me = get_json(f"{relay.url}/api/health", timeout=2)["relay"]
        return [n for n in get_json(f"{relay.url}/api/nodes", timeout=2) if n["relay"] == me]
    except OSError:
        return []


def holds(relay: RelayProcess) -> dict[str, int]:
    """Node -> events stored, for the nodes connected to ``relay`` as it lists them itself."""
    return {n["node"]: n["events"] for n in own_runs(relay) if n["connected"] and not n["ended"]}


def stored_again(relay: RelayProcess, nodes: set[str], since: float, what: str) -> float:
    """Seconds from ``since`` until ``relay`` holds every one of ``nodes`` and stored events of each
    since it took them, printed. A node whose run ended meanwhile counts once ``relay`` stored its end:
    its last batches and its end may be stored between two looks (a loaded machine)."""
    first: dict[str, int] = {}

    def check() -> bool:
        runs = own_runs(relay)
        held = {n["node"]: n["events"] for n in runs if n["connected"] and not n["ended"]}
        ended = {n["node"] for n in runs if n["ended"]}
        for node in nodes & held.keys():
            first.setdefault(node, held[node])
        return all(n in ended or (n in held and held[n] > first[n]) for n in nodes)

    try:
        wait_for(check, RECOVERY_S, 0.1, what=f"every node stored again on the other relay after {what}")
    except AssertionError as exc:
        raise AssertionError(f"{exc}; the relay lists {own_runs(relay)}; its log ends "
                             f"{relay.log.read_text()[-2000:] if relay.log else ''}") from None
    took = time.monotonic() - since
    print(f"\n{what}: every node stored again on the other relay {took:.1f} s after the fault")
    return took


def complete(store: str, tmp_path, counters: dict[str, dict]) -> None:
    """Every node's run whole in ``store``, ended, in one session."""
    for name, c in counters.items():
        assert c["acked"] == c["events"] and c["lost"] == 0, c
        _, sent = load_node(tmp_path / f"{name}.npz")
        stored_equals_sent(store, name, sent)
    sessions = list_sessions(store)
    assert len(sessions) == 1, sessions
    runs = sessions[0]["runs"]
    assert {r["node"] for r in runs} == set(counters) and all(r["ended_ns"] and r["written"] for r in runs), runs


def node(urls: str, name: str, tmp_path, frames: int, **kw) -> subprocess.Popen:
    """A paced node of 2 cameras at 25 fps: ``frames`` / 25 seconds of events."""
    return start_node(urls, name, tmp_path / f"{name}.npz", frames=frames, sources=2, fps=25, paced=True,
                      seed=hash(name) % 1000, **kw)


def said_lost(log: str) -> int:
    """The lines in which a relay that woke up said it lost its runs: another relay took them (its
    renewal), or its store connection was lost (PostgreSQL ended it, idle in a transaction)."""
    return log.count("another relay took 2 runs") + log.count("the store connection was lost; the nodes of 3 runs")


def listed(relay: RelayProcess, node: str) -> tuple[dict, dict] | None:
    """``node``'s entry in ``relay``'s ``/api/nodes`` and its row in ``/api/overview`` (None: either lacks it)."""
    view = next((n for n in get_json(f"{relay.url}/api/nodes", timeout=3) if n["node"] == node), None)
    row = next((r for r in get_json(f"{relay.url}/api/overview", timeout=3)["rows"] if r["node"] == node), None)
    return (view, row) if view and row else None


async def pushed_rows(relay: RelayProcess, node: str) -> list[dict]:
    """``node``'s rows in the overview ``relay`` pushes to a page (the connect snapshot, then once a second)."""
    page = Browser()
    await page.open(relay.url, [node])
    for _ in range(50):
        got = [r for t, e, d in page.got if e == "overview" for r in d["rows"] if r["node"] == node]
        if len(got) >= 2:
            break
        await asyncio.sleep(0.1)
    await page.sio.disconnect()
    return got


def test_a_frozen_relay_holds_nothing_hostage_and_stores_nothing_when_it_wakes(tmp_path, pg_url):
    """Relay A SIGSTOPped for twice its leases: its nodes move to B, which takes their runs once the
    leases expire, one node streaming on, the other ending its run during the freeze (batches still
    unacknowledged). Woken, A finds both runs taken, lets them go, says so in one line. A third node
    knows relay A only: B lists it not connected, "relay silent", in its API and its pushes, until A
    wakes and serves it again."""
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=["--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=["--name", "relay-b"])
    nodes = {}
    try:
        urls = f"{a.url},{b.url}"
        nodes["DCU-L"] = node(urls, "DCU-L", tmp_path, 375)  # 15 s: it streams through the freeze
        nodes["DCU-A"] = node(a.url, "DCU-A", tmp_path, 375)  # relay A only: it waits for A
        wait_for(lambda: holds(a).keys() == {"DCU-L", "DCU-A"}, 30, what="two nodes on relay A")
        nodes["DCU-S"] = node(urls, "DCU-S", tmp_path, 125)  # 5 s: it ends during the freeze
        wait_for(lambda: "DCU-S" in holds(a), 30, 0.05, what="the short node on relay A")
        view, row = wait_for(lambda: listed(b, "DCU-A"), 10, what="B listing DCU-A")
        assert view["state"] == row["state"] == "connected" and view["relay"] == "relay-a", (view, row)
        a.proc.send_signal(signal.SIGSTOP)
        frozen = time.monotonic()
        stored_again(b, {"DCU-L", "DCU-S"}, frozen, "a relay frozen")
        leases = get_json(f"{b.url}/api/health")["storage"]["leases"]
        assert leases["fresh"] and leases["renewed_s_ago"] < leases["lease_s"], leases

        view, row = listed(b, "DCU-A")
        for x in (view, row):
            assert x["state"] == "relay silent" and x["connected"] is False and x["silent_s"] >= 3.0, x
        assert row["alerts"][0] == f"relay silent: last heard {row['silent_s']:.0f} s ago", row["alerts"]
        # A pushes nothing now: B pushes its rows, so that a page shows them (they would age out).
        got = asyncio.run(pushed_rows(b, "DCU-A"))
        assert len(got) >= 2 and all(r["state"] == "relay silent" and r["relay"] == "relay-a" for r in got), got

        time.sleep(max(0.0, 8 - (time.monotonic() - frozen)))  # frozen for 8 s, twice its leases
        a.proc.send_signal(signal.SIGCONT)
        wait_for(lambda: said_lost(a.log.read_text()), 10, what="A saying it lost its runs")
        wait_for(lambda: get_json(f"{a.url}/api/health")["storage"]["leases"]["fresh"], 5, what="A renewing again")
        view, row = wait_for(lambda: (x := listed(b, "DCU-A")) and x[0]["state"] == "connected" and x, 15,
                             what="B listing DCU-A connected to A again")
        assert row["connected"] and "silent_s" not in row and not any(t.startswith("relay silent") for t in row["alerts"])
        counters = {n: finish_node(p, 90) for n, p in nodes.items()}
    finally:
        a.proc.send_signal(signal.SIGCONT)  # a stopped relay ignores SIGTERM until it runs again
        kill_all(nodes.values())
        a.stop()
        b.stop()
    log = a.log.read_text()
    assert said_lost(log) == 1 and "Traceback" not in log, log[-3000:]
    complete(pg_url, tmp_path, counters)


@pytest.fixture
def netns():
    why = netns_permitted()
    if why is not None:
        pytest.skip(why)


def test_nodes_cut_off_from_their_relay_move_to_the_other_though_it_still_reaches_its_store(tmp_path, pg_url, netns):
    """The nodes run in a network namespace of their own; the path from there to relay A is cut
    (dropped, not refused), while A and PostgreSQL go on. The nodes hear nothing from A for 3 s
    and move to B; A hears nothing from them, lets their runs go, and B takes them."""
    with Namespace() as ns:
        a = RelayProcess(pg_url, log=tmp_path / "a.log", args=["--name", "relay-a", "--host", ns.host_addr])
        b = RelayProcess(pg_url, log=tmp_path / "b.log", args=["--name", "relay-b", "--host", ns.host_addr])
        nodes = {}
        try:
            urls = f"{a.url},{b.url}"
            nodes = {n: node(urls, n, tmp_path, 300, prefix=ns.prefix) for n in ("DCU-1", "DCU-2")}  # 12 s each
            wait_for(lambda: holds(a).keys() == set(nodes), 30, what="both nodes on relay A")
            time.sleep(1)
            ns.drop(a.port)
            cut = time.monotonic()
            stored_again(b, set(nodes), cut, "the nodes' path to their relay cut")
            assert ns.dropped() > 0 and get_json(f"{a.url}/api/health")["ok"], "A reached its store all along"
            counters = {n: finish_node(p, 90) for n, p in nodes.items()}
        finally:
            kill_all(nodes.values())
            a.stop()
            b.stop()
    assert "Traceback" not in a.log.read_text()
    complete(pg_url, tmp_path, counters)


def test_a_node_in_bulk_cut_off_from_its_relay_leaves_it_though_its_socket_holds_its_sends(tmp_path, pg_url, netns):
    """A node not paced (a DCU catching up: megabytes queued) when its path to relay A is cut: TCP
    keeps the unacknowledged bytes, the kernel's buffer and the WebSocket's fill, and the node's
    send waits on them. It still hears A's silence and moves to B within seconds; waiting for the
    send, it stayed on A for TCP's own timeout, many minutes (a CI run saw it on a loaded machine).
    Everything was stored before the cut: on B the node only resends and ends at once, before B
    wrote a row of it, and B lists the run ended as its own, not A's stale row of it."""
    with Namespace() as ns:
        a = RelayProcess(pg_url, log=tmp_path / "a.log", args=["--name", "relay-a", "--host", ns.host_addr])
        b = RelayProcess(pg_url, log=tmp_path / "b.log", args=["--name", "relay-b", "--host", ns.host_addr])
        bulk = None
        try:
            bulk = start_node(f"{a.url},{b.url}", "DCU-B", tmp_path / "DCU-B.npz", frames=5000, sources=8,
                              prefix=ns.prefix)  # 480,000 events written at once, about 11 MB
            wait_for(lambda: holds(a).get("DCU-B", 0) > 0, 30, 0.02, what="the node on relay A")
            ns.drop(a.port)
            stored_again(b, {"DCU-B"}, time.monotonic(), "a bulk node's path to its relay cut")
            counters = {"DCU-B": finish_node(bulk, 90)}
        finally:
            kill_all([bulk] if bulk else [])
            a.stop()
            b.stop()
    assert counters["DCU-B"]["connects"] >= 2  # A's acknowledgements may all have come before the cut: then it only ends on B
    complete(pg_url, tmp_path, counters)


def test_a_relay_cut_off_from_postgresql_lets_its_nodes_go_and_a_postgresql_restart_loses_nothing(tmp_path, netns):
    """Relay A runs in a network namespace, reaching PostgreSQL through it; B on the host. A's path
    to PostgreSQL is cut mid-run: A cannot renew its leases nor store, lets its nodes go, and B
    takes their runs once the leases expire. Then PostgreSQL itself restarts under B: nodes are
    held back (or let go and resume) until it is back."""
    with Namespace() as ns:
        pg = PostgresServer(listen=[ns.host_addr]).start()
        try:
            store = pg.new_database()
            through_ns = pg.url(store.rsplit("/", 1)[1], host=ns.host_addr)
            a = RelayProcess(through_ns, log=tmp_path / "a.log", prefix=ns.prefix,
                             args=["--name", "relay-a", "--host", ns.ns_addr])
            b = RelayProcess(store, log=tmp_path / "b.log", args=["--name", "relay-b"])
            nodes = {}
            try:
                urls = f"{a.url},{b.url}"
                nodes = {n: node(urls, n, tmp_path, 500) for n in ("DCU-1", "DCU-2")}  # 20 s each
                wait_for(lambda: holds(a).keys() == set(nodes), 30, what="both nodes on relay A")
                time.sleep(1)
                ns.drop(pg.port)
                cut = time.monotonic()
                stored_again(b, set(nodes), cut, "a relay's connection to PostgreSQL cut")
                pg.stop("fast")
                time.sleep(2)
                pg.resume()
                restarted = time.monotonic()
                stored_again(b, set(nodes), restarted, "PostgreSQL restarted")
                ns.restore()
                counters = {n: finish_node(p, 90) for n, p in nodes.items()}
            finally:
                kill_all(nodes.values())
                a.stop()
                b.stop()
            for log in (a.log, b.log):
                assert "Traceback" not in log.read_text(), log.read_text()[-3000:]
            complete(store, tmp_path, counters)
        finally:
            pg.close()


def test_a_frozen_redis_holds_back_no_node_and_pushes_resume_when_it_wakes(tmp_path, pg_url, redis_server):
    """Redis SIGSTOPped (it keeps its connections, answers nothing) while a page on relay B shows a
    DCU of relay A: storing goes on, and the page gets A's frames again once Redis wakes."""
    args = ["--redis", redis_server.url]
    a = RelayProcess(pg_url, log=tmp_path / "a.log", args=[*args, "--name", "relay-a"])
    b = RelayProcess(pg_url, log=tmp_path / "b.log", args=[*args, "--name", "relay-b"])
    proc = None
    try:
        proc = node(a.url, "DCU-1", tmp_path, 300)  # 12 s
        wait_for(lambda: "DCU-1" in holds(a), 30, what="the node on relay A")

        async def watch() -> tuple[Browser, float, float]:
            page = Browser()
            await page.open(b.url, ["DCU-1"])
            for _ in range(200):
                if page.frames("DCU-1"):
                    break
                await asyncio.sleep(0.1)
            assert page.frames("DCU-1"), "the page got A's frames through Redis"
            redis_server.proc.send_signal(signal.SIGSTOP)
            frozen = time.monotonic()
            before = holds(a)["DCU-1"]
            await asyncio.sleep(4)  # four times the fan-out's Redis timeout
            assert holds(a)["DCU-1"] > before, "A stored on while Redis was frozen"
            redis_server.proc.send_signal(signal.SIGCONT)
            woke = time.monotonic()
            for _ in range(200):
                if page.frames("DCU-1", after=woke):
                    break
                await asyncio.sleep(0.1)
            await page.sio.disconnect()
            return page, frozen, woke

        page, frozen, woke = asyncio.run(watch())
        again = min(t for t, e, d in page.got if e == "frames" and t >= woke and d["nodes"].get("DCU-1"))
        print(f"\nRedis frozen for {woke - frozen:.1f} s: the page got A's frames again {again - woke:.1f} s after it woke")
        counters = {"DCU-1": finish_node(proc, 90)}
    finally:
        if redis_server.proc is not None:
            redis_server.proc.send_signal(signal.SIGCONT)
        kill_all([proc] if proc is not None else [])
        a.stop()
        b.stop()
    complete(pg_url, tmp_path, counters)
