"""Malformed payloads thrown at the relay: at the ingest WebSocket, and at the browsers' Socket.IO.

Ingest (``fuzz``): one payload per connection, each must end with the connection closed by the
relay. The client writes raw WebSocket frames (aiohttp), so it can send what no well-behaved
node would: text that is no JSON or no envelope, wrong versions, unknown types, bad UTF-8,
oversize frames, absurd names, sequence games, as well as malformed batches after a valid hello.

UI (``fuzz_ui``): Engine.IO/Socket.IO garbage on the ``/ui`` namespace; the relay may keep or
close such a connection, but must stay up and log no traceback.
"""

from __future__ import annotations

import asyncio
import json
import random
import uuid
import zlib
from collections import Counter
from dataclasses import dataclass, field

import aiohttp

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.wire import HEADER, MAX_MESSAGE_BYTES, PROTOCOL_VERSION, encode_batch

EVENTS = synth_events(20, 2, 25.0, 1_700_000_000_000_000_000)[:16]
V = PROTOCOL_VERSION
ENDED = (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING, aiohttp.WSMsgType.ERROR)


@dataclass
class FuzzReport:
    sent: int = 0
    closed: int = 0
    errors_seen: int = 0
    kinds: Counter = field(default_factory=Counter)
    not_closed: Counter = field(default_factory=Counter)


def _msg(kind, data, ident=1, v=V) -> str:
    d = {"v": v, "type": kind, "data": data}
    if ident is not None:
        d["id"] = ident
    return json.dumps(d)


class BadUtf8(bytes):
    """A text frame whose bytes are no UTF-8."""


class Case:
    """How to misbehave: (needs_hello, kind, frames) where frames are str/bytes to send."""

    def __init__(self, rng: random.Random, run: str, node: str) -> None:
        self.rng, self.run, self.node = rng, run, node
        self.secret: str | None = None
        """The run's resume secret, issued at its first hello: later connections present it."""

    def pick(self) -> tuple[bool, str, list]:
        needs_hello, kind, make = self.rng.choice(self._choices())
        return needs_hello, kind, make()

    def _choices(self) -> list:
        r = self.rng
        header = header_for(self.node, 2).to_dict()
        return [
            # Envelope level (no hello needed).
            (False, "random-text", lambda: [r.choice("x9!7 [") + r.randbytes(r.randrange(0, 300)).decode("latin-1")]),
            (False, "bad-utf8", lambda: [BadUtf8(b'{"v": 2, "type": "\xff\xfe"}')]),
            (False, "bad-json", lambda: [f'{{"v": {V}, "type": "hello", "data": {{"proto": {V},']),
            (False, "not-an-object", lambda: [json.dumps(r.choice([[1, 2], 5, "hello", None, True]))]),
            (False, "wrong-version", lambda: [_msg("hello", self.hello(), v=r.choice([0, 1, 3, "2", None, True]))]),
            (False, "unknown-type", lambda: [_msg(r.choice(["delete", "admin", "ack", "reply", "batch", "", 5]), {})]),
            (False, "bad-id", lambda: [_msg("sync", None, ident=r.choice([-1, "x", 1.5, [1], True, 1 << 64]))]),
            (False, "extra-fields", lambda: [json.dumps({"v": V, "type": "sync", "admin": True})]),
            (False, "batch-before-hello", lambda: [encode_batch(self.run, 0, EVENTS)]),
            (False, "clock-before-hello", lambda: [_msg(r.choice(["clock", "end"]), {})]),
            (False, "hello-wrong-types", lambda: [_msg("hello", r.choice([
                None, 1, "x", [], {"proto": str(V)}, {"proto": V, "run": 5},
                {"proto": V, "run": self.run, "header": {"node": self.node, "stages": "abc", "clock": "r"}},
                {"proto": V, "run": self.run, "header": {"node": self.node, "stages": ["a"] * 100000, "clock": "r"}},
                {"proto": 9, "run": self.run}, dict(self.hello(), floor=-1), dict(self.hello(), lost="many")]))]),
            (False, "absurd-names", lambda: [_msg("hello", dict(self.hello(), header=dict(header, **r.choice([
                {"node": "x" * 5000}, {"node": "bad\nname"}, {"node": ""}, {"node": 7},
                {"stages": ["\x00"] + header["stages"][1:]}, {"stages": ["y" * 300] + header["stages"][1:]}]))))]),
            (False, "oversize-text", lambda: [_msg("hello", {"proto": V, "pad": "x" * (MAX_MESSAGE_BYTES + 10)})]),
            # Batches and messages after a valid hello.
            (True, "random-bytes", lambda: [r.randbytes(r.randrange(0, 2000))]),
            (True, "truncated", lambda: [self.good()[:r.randrange(0, len(self.good()))]]),
            (True, "batch-version", lambda: [self.batch(version=r.choice([0, 2, 255]))]),
            (True, "bad-magic", lambda: [self.batch(magic=b"JUNK")]),
            (True, "huge-count", lambda: [self.batch(count=r.choice([70000, 1 << 31, (1 << 32) - 1]))]),
            (True, "count-mismatch", lambda: [self.batch(count=r.randrange(1, 16))]),
            (True, "length-lie", lambda: [self.batch(length=r.randrange(1 << 32))]),
            (True, "zlib-bomb", lambda: [self.batch(flags=1, payload=_BOMB, length=len(_BOMB))]),
            (True, "bad-events", lambda: [_bad_events(self.run, r)]),
            (True, "other-run", lambda: [encode_batch(uuid.uuid4().hex, 1, EVENTS)]),
            (True, "seq-overflow", lambda: [self.batch(seq=r.choice([1 << 63, (1 << 64) - 1]))]),
            (True, "oversize-batch", lambda: [b"\0" * (MAX_MESSAGE_BYTES + 1)]),
            (True, "clock-garbage", lambda: [_msg("clock", r.choice([{"samples": [[1, 2]]}, {"samples": "x"}, 5,
                                                                     {"samples": [[1, 2, 3, 4]] * 999},
                                                                     {"floor": -5}, {"floor": "x"}]))]),
            (True, "end-garbage", lambda: [_msg("end", r.choice([{"events": -1}, {"dropped": "many"}, []]))]),
            (True, "hello-twice", lambda: [_msg("hello", self.hello())]),
        ]

    @staticmethod
    def kinds() -> set[str]:
        """Every kind of misbehaviour a case may pick."""
        return {kind for _, kind, _ in Case(random.Random(0), uuid.UUID(int=0).hex, "fuzz")._choices()}

    def hello(self) -> dict:
        hello = {"proto": V, "run": self.run, "header": header_for(self.node, 2).to_dict(), "lost": 0}
        if self.secret is not None:
            hello["secret"] = self.secret
        return hello

    def good(self) -> bytes:
        return encode_batch(self.run, self.rng.randrange(1 << 40), EVENTS)

    def batch(self, **over) -> bytes:
        good = self.good()
        names = ("magic", "version", "flags", "reserved", "run", "seq", "count", "length")
        fields = dict(zip(names, HEADER.unpack_from(good)), **over)
        body = over.get("payload", good[HEADER.size:])
        return HEADER.pack(*(fields[k] for k in names)) + body


_BOMB = zlib.compress(b"\0" * (8 * 1024 * 1024), 9)


def _bad_events(run: str, r: random.Random) -> bytes:
    ev = EVENTS.copy()
    field_, value = r.choice([("stage", 99), ("stage", -3), ("point", 7), ("code", 1), ("ts", -5),
                              ("source", -1), ("frame", -1)])
    ev[field_][r.randrange(len(ev))] = value
    return encode_batch(run, r.randrange(1000), ev)


async def _send(ws: aiohttp.ClientWebSocketResponse, frame) -> None:
    if isinstance(frame, BadUtf8):
        await ws.send_frame(bytes(frame), aiohttp.WSMsgType.TEXT)
    elif isinstance(frame, bytes):
        await ws.send_bytes(frame)
    else:
        await ws.send_str(frame)


async def _one(session: aiohttp.ClientSession, url: str, token: str | None, case: Case, report: FuzzReport,
               timeout: float) -> None:
    needs_hello, kind, frames = case.pick()
    report.kinds[kind] += 1
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    async with session.ws_connect(url.replace("http://", "ws://") + "/ingest", headers=headers, max_msg_size=0) as ws:
        if needs_hello:
            await ws.send_str(_msg("hello", case.hello()))
            reply = await ws.receive(timeout)
            assert reply.type == aiohttp.WSMsgType.TEXT and json.loads(reply.data)["data"]["ok"] is True, reply
            case.secret = json.loads(reply.data)["data"].get("secret", case.secret)
        report.sent += 1
        try:
            for frame in frames:
                await _send(ws, frame)
        except (ConnectionError, aiohttp.ClientError):
            pass  # the relay already closed it
        closed = False
        try:
            while True:
                msg = await ws.receive(timeout)
                if msg.type in ENDED:
                    closed = True
                    break
                if msg.type == aiohttp.WSMsgType.TEXT and json.loads(msg.data).get("type") == "error":
                    report.errors_seen += 1
        except asyncio.TimeoutError:
            pass
        if closed:
            report.closed += 1
        else:
            report.not_closed[kind] += 1


async def fuzz(url: str, count: int, token: str | None = None, workers: int = 16, seed: int = 0,
               timeout: float = 5.0) -> FuzzReport:
    """Throw ``count`` malformed payloads at ``url``'s ingest from ``workers`` concurrent connections."""
    report = FuzzReport()
    todo = iter(range(count))

    async def worker(k: int) -> None:
        rng = random.Random(seed * 1000 + k)
        # One run per worker: concurrent hellos of one run would close each other's connections.
        case = Case(rng, uuid.UUID(int=rng.getrandbits(128)).hex, f"fuzz-{k}")
        async with aiohttp.ClientSession() as session:
            for _ in todo:
                try:
                    await _one(session, url, token, case, report, timeout)
                except (aiohttp.ClientError, asyncio.TimeoutError, AssertionError, ConnectionError) as exc:
                    report.not_closed[f"setup-failed: {type(exc).__name__}: {str(exc)[:80]}"] += 1

    await asyncio.gather(*(worker(k) for k in range(workers)))
    return report


UI = "/ui"


def _ui_garbage(r: random.Random) -> tuple[str, list]:
    return r.choice([
        ("random-text", [r.choice("x9!7 {") + r.randbytes(r.randrange(0, 300)).decode("latin-1")]),
        ("random-sio", ["4" + r.choice("x7-!") + r.randbytes(r.randrange(0, 300)).decode("latin-1")]),
        ("eio-type-9", ["9"]),
        ("random-binary", [r.randbytes(r.randrange(1, 300))]),
        ("bad-json", [f'42{UI},["subscribe", {{"nodes": [']),
        ("many-attachments", [f'4599999-{UI},["subscribe",{{"_placeholder":true,"num":0}}]', b"x", b"y"]),
        ("unknown-event", [f'42{UI},1' + json.dumps([r.choice(["delete", "connect", "disconnect", ""]), {}])]),
        ("too-many-args", [f'42{UI},1["subscribe",1,2,3]']),
        ("subscribe-garbage", [f'42{UI},1' + json.dumps(["subscribe", r.choice([None, 5, {"nodes": 3},
                                                                                  {"max_frames": -1}])])]),
        ("oversize", ["4" + "x" * (1 << 20)]),
    ])


async def fuzz_ui(url: str, count: int, token: str | None = None, workers: int = 8, seed: int = 0,
                  timeout: float = 0.3) -> Counter:
    """Throw ``count`` garbage packets at the browsers' Socket.IO namespace, one per connection."""
    kinds: Counter = Counter()
    todo = iter(range(count))
    ws_url = url.replace("http://", "ws://") + "/socket.io/?EIO=4&transport=websocket"

    async def one(session: aiohttp.ClientSession, rng: random.Random) -> None:
        kind, frames = _ui_garbage(rng)
        kinds[kind] += 1
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        async with session.ws_connect(ws_url, max_msg_size=0, headers=headers) as ws:
            opening = await ws.receive(5)
            assert opening.type == aiohttp.WSMsgType.TEXT and opening.data.startswith("0"), opening
            await ws.send_str(f"40{UI},{{}}")
            try:
                for frame in frames:
                    await _send(ws, frame)
                while (await ws.receive(timeout)).type not in ENDED:
                    pass
            except (ConnectionError, aiohttp.ClientError, asyncio.TimeoutError):
                pass

    async def worker(k: int) -> None:
        rng = random.Random(seed * 1000 + k)
        async with aiohttp.ClientSession() as session:
            for _ in todo:
                await one(session, rng)

    await asyncio.gather(*(worker(k) for k in range(workers)))
    return kinds


if __name__ == "__main__":
    import sys
    print(asyncio.run(fuzz(sys.argv[1], int(sys.argv[2]))))
