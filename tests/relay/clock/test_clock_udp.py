"""The UDP clock exchange on a real relay process with real nodes on loopback: samples arrive over
UDP and the relay's correction holds the injected truth (offset and drift) within its stated
bound; hostile datagrams and forged or replayed samples are dropped and counted, unanswered,
and a good node's estimate is unaffected; a replayed request is answered once and costs its node
nothing; without UDP a node falls back to the WebSocket."""

from __future__ import annotations

import asyncio
import os
import socket
import struct
import subprocess
import sys
import time
import uuid

import pytest

from dcuscope.core.clocks import CLOCKS, PretendClock
from dcuscope.probes.clocks.udpclock import BURST, UdpClock, clock_difference_ns
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.clockdatagram import DATAGRAM_BYTES, VERSION, Tagger, decode_answer, enable_rx_timestamps, encode_request, new_secret, parse_offer, recv_stamped
from dcuscope.protocol.events import ORIGIN
from dcuscope.relay.clock.correction import ClockSample, ntp_sample
from dcuscope.relay.clock.udp import ClockUdp, NonceWindow
from dcuscope.relay.config import RelayConfig
from dcuscope.relay.guard.limits import Limits
from dcuscope.relay.server import start_relay
from tests.relay.helpers import (ROOT, HandNode, RelayProcess, env, finish_node, get_json, start_node, wait_for)

FRAMES, SOURCES, FPS, SEED = 250, 2, 50.0, 5


def _start(relay: RelayProcess, tmp_path, node: str, offset_ns: int, drift_ppm: float):
    t0 = time.clock_gettime_ns(time.CLOCK_REALTIME) + 500_000_000
    proc = start_node(relay.url, node, tmp_path / f"{node}.npz", frames=FRAMES, sources=SOURCES, fps=FPS,
                      paced=True, t0_ns=t0, seed=SEED, offset_ns=offset_ns,
                      extra=["--clock-drift-ppm", str(drift_ppm)])
    return proc, t0


def _frames_hold_the_truth(relay: RelayProcess, node: str, t0: int) -> dict:
    """Every frame's corrected origin equals its true time within the bound it carries; the node's
    clock view."""
    truth = synth_events(FRAMES, SOURCES, FPS, t0, seed=SEED)
    truth = truth[truth["point"] == ORIGIN]
    true_origin = {(int(s), int(f)): int(t) for s, f, t in zip(truth["source"], truth["frame"], truth["ts"])}
    got = get_json(f"{relay.url}/api/frames?node={node}&limit=2000")
    assert got["clock"] == "estimate", got["clock"]
    frames = got["frames"]
    assert len(frames) == FRAMES * SOURCES
    worst = max(abs(f["origin"] - true_origin[(f["source"], f["frame"])]) - f["clock_uncertainty_ns"] for f in frames)
    assert worst <= 0, f"a frame's corrected time is {worst} ns beyond its stated bound"
    return next(n for n in get_json(f"{relay.url}/api/nodes") if n["node"] == node)["clock"]


@pytest.mark.parametrize("offset_ns,drift_ppm", [(37_000_000, 0.0), (-2_500_000_000, 50.0)])
def test_samples_arrive_over_udp_and_the_correction_holds_the_truth(tmp_path, offset_ns, drift_ppm):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate")
    try:
        proc, t0 = _start(relay, tmp_path, "B", offset_ns, drift_ppm)
        counters = finish_node(proc, 60)
        assert counters["clock_via"] == "udp"
        udp = get_json(f"{relay.url}/api/health")["clock_udp"]
        assert udp["answered"] >= 32 and udp["port"] == relay.port
        clock = _frames_hold_the_truth(relay, "B", t0)
        assert clock["rejected"] == 0 and clock["samples"] >= 16 and clock["via"] == "udp", clock
        # Loopback with kernel timestamps: the best exchange's round trip is tens of microseconds.
        assert clock["rtt_us"] < 200, clock
    finally:
        relay.stop()


def _udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setblocking(False)
    enable_rx_timestamps(s)
    return s


def _answers(s: socket.socket) -> list[tuple[int, int, int, int]]:
    """(nonce, t2, t3, t4) of every answer waiting on ``s``."""
    out = []
    while True:
        try:
            data, _, t4, _ = recv_stamped(s)
        except BlockingIOError:
            return out
        answer = decode_answer(data)
        if answer is not None:
            out.append((answer.nonce, answer.t2, answer.t3, t4))


def _health_udp(relay: RelayProcess) -> dict:
    return get_json(f"{relay.url}/api/health")["clock_udp"]


def test_hostile_datagrams_are_dropped_counted_and_never_answered(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate")
    attacker = _udp_socket()
    target = ("127.0.0.1", relay.port)
    try:
        proc, t0 = _start(relay, tmp_path, "B", 37_000_000, 0.0)
        wait_for(lambda: _health_udp(relay)["answered"] > 0, 20, what="the good node's first UDP exchange")
        for i in range(40):
            attacker.sendto(os.urandom(32), target)  # garbage of the right size
            attacker.sendto(b"DCUQ\x01", target)  # truncated
            attacker.sendto(encode_request(os.urandom(16), i), target)  # a key nobody was given
            attacker.sendto(b"x" * 4000, target)  # oversize
            time.sleep(0.002)  # within the socket buffer: each of these is counted
        wait_for(lambda: _health_udp(relay)["oversize"] >= 40, 10, what="the oversize datagrams counted")
        udp = _health_udp(relay)
        assert udp["malformed"] == 80 and udp["oversize"] == 40 and udp["unknown_key"] == 40, udp
        flood = encode_request(os.urandom(16), 7)
        for _ in range(20_000):
            try:
                attacker.sendto(flood, target)
            except BlockingIOError:
                time.sleep(0.001)
        counters = finish_node(proc, 60)
        udp = _health_udp(relay)
        assert 40 < udp["unknown_key"] <= 40 + 20_000
        assert _answers(attacker) == []  # nothing was ever answered
        assert counters["clock_via"] == "udp"
        clock = _frames_hold_the_truth(relay, "B", t0)
        assert clock["rejected"] == 0 and clock["via"] == "udp" and clock["rtt_us"] < 200, clock
    finally:
        attacker.close()
        relay.stop()


async def _exchange(s: socket.socket, port: int, key: bytes, nonce: int) -> list[int]:
    t1 = time.time_ns()
    s.sendto(encode_request(key, nonce), ("127.0.0.1", port))
    for _ in range(100):
        answers = _answers(s)
        if answers:
            n, t2, t3, t4 = answers[0]
            assert n == nonce
            return [t1, t2, t3, t4]
        await asyncio.sleep(0.01)
    raise AssertionError("no answer from the relay")


def _clock_of(relay: RelayProcess, run: str) -> dict:
    return next(n for n in get_json(f"{relay.url}/api/nodes") if n["run"] == run)["clock"]


def test_forged_replayed_and_foreign_samples_are_rejected_and_a_key_is_rate_bound(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate", args=["--limit", "clock_packets_per_s=20"])
    s = _udp_socket()

    async def scenario():
        a_run, b_run = uuid.uuid4().hex, uuid.uuid4().hex
        a = await HandNode.open(relay.url, "A", a_run)
        b = await HandNode.open(relay.url, "B", b_run)
        try:
            assert a.reply["clock_port"] == relay.port and a.reply["clock_key"] != b.reply["clock_key"]
            key_a, key_b = bytes.fromhex(a.reply["clock_key"]), bytes.fromhex(b.reply["clock_key"])
            good = await _exchange(s, relay.port, key_a, 1)
            foreign = await _exchange(s, relay.port, key_b, 2)  # answered for B's connection
            await a.link.call("clock", {"samples": [good], "via": "udp"}, 5)
            assert _clock_of(relay, a_run)["samples"] == 1
            forged = [good[0], good[1] + 1_000, good[2] + 1_000, good[3]]
            for sample in (good, forged, foreign):  # a replay, a forgery, another connection's pair
                await a.link.call("clock", {"samples": [sample], "via": "udp"}, 5)
            clock = _clock_of(relay, a_run)
            assert clock["samples"] == 1 and clock["rejected"] == 3, clock
            # A key holder beyond its rate: the surplus is dropped, not answered.
            for n in range(200):
                s.sendto(encode_request(key_a, 100 + n), ("127.0.0.1", relay.port))
            await asyncio.sleep(0.5)
            answered = len(_answers(s))
            assert 0 < answered <= 20 + 12, answered  # one second's worth, plus what refilled meanwhile
            assert _health_udp(relay)["rate_key"] >= 200 - answered
        finally:
            await a.close()
        # The connection is gone: so is its key.
        await asyncio.sleep(0.3)
        before = _health_udp(relay)["unknown_key"]
        s.sendto(encode_request(key_a, 999), ("127.0.0.1", relay.port))
        await asyncio.sleep(0.3)
        assert _answers(s) == [] and _health_udp(relay)["unknown_key"] == before + 1
        await b.close()

    try:
        asyncio.run(scenario())
    finally:
        s.close()
        relay.stop()


def test_without_udp_a_node_falls_back_to_the_websocket(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate", args=["--clock-port", "0"])
    try:
        proc, t0 = _start(relay, tmp_path, "B", 37_000_000, 0.0)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err.decode()[-2000:]
        assert err.decode().count("clock samples go over the WebSocket") == 1
        assert get_json(f"{relay.url}/api/health")["clock_udp"] is None
        clock = _frames_hold_the_truth(relay, "B", t0)
        assert clock["samples"] >= 8 and clock["via"] == "websocket", clock
    finally:
        relay.stop()


def test_a_clock_port_the_relay_cannot_have_is_a_one_line_error(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        for value, said in ((str(port), "cannot listen on UDP"), ("70000", "--clock-port must be 0..65535")):
            done = subprocess.run([sys.executable, "-m", "dcuscope.relay", "--port", "0", "--db", str(tmp_path / "r.db"),
                                   "--clock-port", value], cwd=ROOT, env=env(), capture_output=True, text=True,
                                  timeout=30)
            assert done.returncode == 2 and said in done.stderr, done.stderr
            assert len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_a_node_whose_udp_goes_unanswered_falls_back_to_the_websocket(tmp_path, caplog):
    """The relay offers UDP, but its datagrams vanish (a firewall): a silent socket holds the port."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", clock="estimate"))
        port = relay.clock_port
        relay.ingest.clock_udp.stop()  # the offer stays, the answers stop
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as silent:
            silent.bind(("127.0.0.1", port))
            exporter = RelayExporter(f"http://127.0.0.1:{relay.port}", "A", close_timeout_s=8.0)
            try:
                exporter.start(header_for("A", 2))
                deadline = time.monotonic() + 20
                while exporter.counters()["clock_via"] != "websocket":
                    assert time.monotonic() < deadline, "no clock report over the WebSocket"
                    await asyncio.sleep(0.05)
                await asyncio.to_thread(exporter.close, 0)
                assert relay.state.runs[exporter.run_id].clock.estimate().samples >= 8
                assert silent.recv(64)  # the node did try UDP
            finally:
                await relay.stop()

    asyncio.run(scenario())
    said = [r.getMessage() for r in caplog.records if "clock samples go over the WebSocket" in r.getMessage()]
    assert len(said) == 1 and "no answer to UDP clock exchanges" in said[0], said


@pytest.mark.parametrize("clock", ["monotonic", "tai"])
def test_kernel_receive_times_are_moved_to_the_probes_clock(tmp_path, clock):
    """The kernel stamps CLOCK_REALTIME; a node on another clock reports t1 and t4 on its own:
    each sample's offset is that clock's distance to CLOCK_REALTIME, within half its round trip."""
    clock_id = CLOCKS[clock]

    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", clock="estimate"))
        node = await HandNode.open(f"http://127.0.0.1:{relay.port}", "A", uuid.uuid4().hex)
        port, key, _ = parse_offer(node.reply)
        udp = await UdpClock.open("127.0.0.1", port, key, PretendClock(clock_id=clock_id))
        try:
            samples = await udp.burst()
            truth = clock_difference_ns(clock_id, reads=50)  # not skewed by a preemption between two reads
        finally:
            udp.close()
            await node.close()
            await relay.stop()
        assert len(samples) == BURST
        for t1, t2, t3, t4 in samples:
            s = ntp_sample(t1, t2, t3, t4)
            assert 0 <= s.rtt_ns < 50_000_000 and abs(s.offset_ns - truth) <= s.rtt_ns // 2 + 2_000, (s, truth)

    asyncio.run(scenario())


SHIFT_NS = 5_000_000
"""What the on-path proxy adds to the relay's t2 and t3."""
NODE_OFFSET_NS = 37_000_000


class AnswerRewriter:
    """An on-path attacker: a UDP proxy the node talks to, that forwards its requests to the relay
    and the relay's answers back, t2 and t3 moved by ``SHIFT_NS`` (tag left as it was; with
    ``strip``, the answer is also made an untagged one)."""

    def __init__(self, relay_port: int, strip: bool = False) -> None:
        self.front, self.back = _udp_socket(), _udp_socket()
        self.front.bind(("127.0.0.1", 0))
        self.back.connect(("127.0.0.1", relay_port))
        self.port = self.front.getsockname()[1]
        self.strip, self.node, self.answers = strip, None, 0
        loop = asyncio.get_running_loop()
        loop.add_reader(self.front.fileno(), self._from_node)
        loop.add_reader(self.back.fileno(), self._from_relay)

    def _from_node(self) -> None:
        data, self.node = self.front.recvfrom(2048)
        self.back.send(data)

    def _from_relay(self) -> None:
        data = bytearray(self.back.recv(2048))
        nonce, t2, t3 = struct.unpack_from("<Qqq", data, 8)
        struct.pack_into("<qq", data, 16, t2 + SHIFT_NS, t3 + SHIFT_NS)
        if self.strip:
            data[4] = VERSION
            del data[DATAGRAM_BYTES:]
        self.front.sendto(bytes(data), self.node)
        self.answers += 1

    def close(self) -> None:
        loop = asyncio.get_running_loop()
        for s in (self.front, self.back):
            loop.remove_reader(s.fileno())
            s.close()


async def _burst(port: int, key: bytes, secret: bytes | None) -> tuple[list[ClockSample], int]:
    """The samples of one burst by a node NODE_OFFSET_NS ahead of the relay, and the answers it refused."""
    udp = await UdpClock.open("127.0.0.1", port, key, PretendClock(offset_ns=NODE_OFFSET_NS), secret)
    try:
        return [ntp_sample(*times) for times in await udp.burst()], udp.forged
    finally:
        udp.close()


def _holds_offset(samples: list[ClockSample], offset_ns: int) -> bool:
    return all(abs(s.offset_ns - offset_ns) <= s.rtt_ns // 2 + 2_000 for s in samples)


def test_a_tagged_exchange_is_answered_only_by_the_relay_and_an_untagged_one_still_works():
    """Over loopback with a real relay side and node side: an honest tagged exchange gives the
    offsets an untagged one gives; a proxy that moves the answers' times moves an untagged node's
    offset by as much, while a tagged node refuses and counts every such answer, stripped of its
    tag or not. The relay answers the old format for a key without a secret only."""
    async def scenario():
        udp = ClockUdp(Limits(), 256)
        udp.start("127.0.0.1", 0)
        secret = new_secret()
        tagged_syncs, plain_syncs = {}, {}
        tagged, plain = udp.register(tagged_syncs, secret), udp.register(plain_syncs)
        try:
            honest, forged = await _burst(udp.port, tagged, secret)
            assert len(honest) == BURST and forged == 0 and _holds_offset(honest, NODE_OFFSET_NS), honest
            assert {s.at_ns for s in honest} == {t2 for t2, _ in tagged_syncs}  # the pairs the relay answered
            old, _ = await _burst(udp.port, plain, None)
            assert len(old) == BURST and _holds_offset(old, NODE_OFFSET_NS), old
            assert len(tagged_syncs) == len(plain_syncs) == BURST

            proxy = AnswerRewriter(udp.port)
            try:  # the attack is real: an untagged node takes the moved times
                moved, _ = await _burst(proxy.port, plain, None)
                assert len(moved) == BURST and _holds_offset(moved, NODE_OFFSET_NS - SHIFT_NS), moved
                refused, forged = await _burst(proxy.port, tagged, secret)
                assert refused == [] and forged == proxy.answers - BURST > 0
            finally:
                proxy.close()
            proxy = AnswerRewriter(udp.port, strip=True)
            try:
                refused, forged = await _burst(proxy.port, tagged, secret)
                assert refused == [] and forged == proxy.answers > 0
            finally:
                proxy.close()

            s = _udp_socket()
            try:  # wrong tags, or none, for the tagged key; a tag for the plain one
                before = dict(udp.counts)
                s.sendto(encode_request(tagged, 1), ("127.0.0.1", udp.port))
                s.sendto(encode_request(tagged, 2, Tagger(new_secret(), tagged)), ("127.0.0.1", udp.port))
                s.sendto(encode_request(plain, 3, Tagger(secret, plain)), ("127.0.0.1", udp.port))
                for _ in range(100):
                    if udp.counts["bad_tag"] == before["bad_tag"] + 3:
                        break
                    await asyncio.sleep(0.01)
                assert udp.counts["bad_tag"] == before["bad_tag"] + 3 and udp.counts["answered"] == before["answered"]
                assert _answers(s) == []
            finally:
                s.close()
        finally:
            udp.stop()

    asyncio.run(scenario())


def test_only_a_private_connection_gets_a_clock_secret_and_its_node_refuses_moved_answers(tmp_path, caplog):
    """The ingest's one condition (``private_channel``: TLS in use) said yes without TLS: the hello
    reply carries a secret, a node's datagrams pass an on-path proxy that moves every answer, and the
    node refuses them, counts them, says so once naming the relay, and its estimate holds the truth
    over the WebSocket. A plaintext connection gets no secret."""
    async def scenario():
        relay = await start_relay(RelayConfig(port=0, db=tmp_path / "r.db", clock="estimate"))
        url = f"http://127.0.0.1:{relay.port}"
        exporter = None
        try:
            plain = await HandNode.open(url, "P", uuid.uuid4().hex)
            await plain.close()
            assert "clock_secret" not in plain.reply and parse_offer(plain.reply).secret is None
            relay.ingest.private_channel = lambda request: True
            private = await HandNode.open(url, "Q", uuid.uuid4().hex)
            await private.close()
            offer = parse_offer(private.reply)
            assert offer is not None and len(offer.secret) == 32
            assert parse_offer(dict(private.reply, clock_secret=private.reply["clock_secret"][:-2])) is None

            proxy = AnswerRewriter(relay.clock_port)
            relay.ingest.clock_udp.port = proxy.port  # the node's datagrams take the attacker's path
            try:
                exporter = RelayExporter(url, "A", pretend=PretendClock(offset_ns=NODE_OFFSET_NS), close_timeout_s=8.0)
                exporter.start(header_for("A", 2))
                deadline = time.monotonic() + 20
                while not (exporter.counters()["clock_via"] == "websocket" and exporter.run_id in relay.state.runs
                           and relay.state.runs[exporter.run_id].clock_forged):
                    assert time.monotonic() < deadline, "no clock report over the WebSocket telling the forged answers"
                    await asyncio.sleep(0.05)
                await asyncio.to_thread(exporter.close, 0)
            finally:
                proxy.close()
            counters, rs = exporter.counters(), relay.state.runs[exporter.run_id]
            assert counters["clock_forged"] == proxy.answers > 0, (counters, proxy.answers)
            assert relay.state.clock_view(rs)["forged"] == proxy.answers  # the relay's page shows them too
            estimate = rs.clock.estimate()
            assert abs(estimate.offset_ns - NODE_OFFSET_NS) <= estimate.uncertainty_ns, estimate
        finally:
            await relay.stop()

    asyncio.run(scenario())
    said = [r.getMessage() for r in caplog.records if "refused for a wrong tag" in r.getMessage()]
    assert len(said) == 1 and "from 127.0.0.1" in said[0], said


REPLAYS = 400


async def _captured_request(key: bytes, secret: bytes | None) -> bytes:
    """One request exactly as the node's own code sends it, caught on its way and never delivered."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as catcher:
        catcher.bind(("127.0.0.1", 0))
        catcher.setblocking(False)
        udp = await UdpClock.open("127.0.0.1", catcher.getsockname()[1], key, PretendClock(), secret)
        try:
            assert await udp.burst(count=1, spacing_s=0, timeout_s=0.02) == []
        finally:
            udp.close()
        return catcher.recv(2048)


async def _settled(udp: ClockUdp, total: int) -> None:
    """Until the relay has taken ``total`` datagrams in all (whatever it made of them), at most 5 s."""
    deadline = time.monotonic() + 5
    while sum(udp.counts.values()) < total and time.monotonic() < deadline:
        await asyncio.sleep(0.005)


@pytest.mark.parametrize("tagged", [True, False], ids=["tagged", "plain"])
def test_a_replayed_request_is_answered_once_and_costs_the_node_nothing(tagged):
    """A bystander replays one genuine, captured request REPLAYS times while the node runs a burst:
    the relay answers it once, drops and counts the other copies before they reach the key's rate
    bucket, and every exchange of the node's burst completes."""
    async def scenario():
        udp = ClockUdp(Limits(), 256)
        udp.start("127.0.0.1", 0)
        secret = new_secret() if tagged else None
        key = udp.register({}, secret)
        attacker = _udp_socket()
        node = await UdpClock.open("127.0.0.1", udp.port, key, PretendClock(), secret)
        try:
            request = await _captured_request(key, secret)
            answers = 0

            async def replay() -> None:
                nonlocal answers
                sent, chunk = 0, REPLAYS // BURST
                while sent < REPLAYS:  # in chunks spread over the node's burst, each taken before the next
                    for _ in range(chunk):
                        attacker.sendto(request, ("127.0.0.1", udp.port))
                    sent += chunk
                    await _settled(udp, sent)
                    answers += len(_answers(attacker))
                    await asyncio.sleep(0.02)

            samples, _ = await asyncio.gather(node.burst(), replay())
            await _settled(udp, REPLAYS + len(samples))
            answers += len(_answers(attacker))
            counts = dict(udp.counts)
            figures = f"{answers} answers to {REPLAYS} replays, {len(samples)}/{BURST} exchanges completed, {counts}"
            assert answers == 1 and counts["replayed"] == REPLAYS - 1, figures
            assert len(samples) == BURST and counts["answered"] == 1 + BURST, figures
            assert counts["rate_key"] == counts["rate_total"] == 0, figures
        finally:
            node.close()
            attacker.close()
            udp.stop()

    asyncio.run(scenario())


def test_a_key_forgets_the_nonces_it_answered_after_the_window_and_keeps_a_bounded_number():
    window = NonceWindow(30.0, 4)
    window.add(1, 100.0)
    assert window.seen(1, 129.9) and not window.seen(2, 129.9)
    assert not window.seen(1, 130.1) and len(window) == 0  # a copy captured longer ago is answered again
    for nonce in range(10):
        window.add(nonce, 200.0)
    assert len(window) == 4 and [window.seen(n, 200.0) for n in (5, 6, 9)] == [False, True, True]
