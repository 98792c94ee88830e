"""Malformed payloads thrown at the relay's ingest over raw Engine.IO/Socket.IO websockets.

One payload per connection: each must end with the connection closed by the relay. The
client speaks the wire protocol itself (aiohttp websocket) so that it can send what no
well-behaved Socket.IO client would: broken packets, stray binary frames, absurd attachment
counts, events with wrong arguments, as well as malformed batches after a valid hello.
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

from relay.protocol import HEADER, MAX_MESSAGE_BYTES, encode_batch
from relay.simnode import header_for, synth_events

NS = "/ingest"
EVENTS = synth_events(20, 2, 25.0, 1_700_000_000_000_000_000)[:16]


@dataclass
class FuzzReport:
    sent: int = 0
    closed: int = 0
    errors_seen: int = 0
    kinds: Counter = field(default_factory=Counter)
    not_closed: Counter = field(default_factory=Counter)


def _text(event: str, data, ack: int | None = None) -> str:
    return f"42{NS}," + ("" if ack is None else str(ack)) + json.dumps([event, data] if data is not ... else [event])


def _binary_event(event: str, ack: int | None = 1) -> str:
    return f"451-{NS}," + ("" if ack is None else str(ack)) + json.dumps([event, {"_placeholder": True, "num": 0}])


class Case:
    """How to misbehave: (needs_hello, kind, frames) where frames are str/bytes to send."""

    def __init__(self, rng: random.Random, run: str, node: str) -> None:
        self.rng, self.run, self.node = rng, run, node

    def pick(self) -> tuple[bool, str, list]:
        r = self.rng
        good = encode_batch(self.run, r.randrange(1 << 40), EVENTS)
        hdr = dict(zip(("magic", "version", "flags", "reserved", "run", "seq", "count", "length"),
                       HEADER.unpack_from(good)))
        payload = good[HEADER.size:]

        def batch(**over):
            f = dict(hdr, **over)
            body = over.get("payload", payload)
            return HEADER.pack(*(f[k] for k in ("magic", "version", "flags", "reserved", "run", "seq", "count",
                                                "length"))) + body

        choices = [
            # Engine.IO / Socket.IO level garbage (no hello needed).
            # (a first character that is no Engine.IO packet type: random text could be a valid ping)
            (False, "random-text", lambda: [r.choice("x9!7 {") + r.randbytes(r.randrange(0, 300)).decode("latin-1")]),
            (False, "random-sio",
             lambda: ["4" + r.choice("x7-!") + r.randbytes(r.randrange(0, 300)).decode("latin-1")]),
            (False, "eio-type-9", lambda: ["9"]),
            (False, "random-binary", lambda: [r.randbytes(r.randrange(1, 300))]),
            (False, "bad-json", lambda: [f'42{NS},["hello", {{"proto": 1,']),
            (False, "many-attachments", lambda: [f'4599999-{NS},["batch",{{"_placeholder":true,"num":0}}]',
                                                 b"x", b"y"]),
            (False, "unknown-event", lambda: [_text(r.choice(["delete", "admin", "connect", ""]) or "x", {"a": 1}, 1)]),
            (False, "too-many-args", lambda: [f'42{NS},1["sync",1,2,3]']),
            (False, "batch-before-hello", lambda: [_binary_event("batch"), good]),
            (False, "hello-wrong-types", lambda: [_text("hello", r.choice([
                None, 1, "x", [], {"proto": "1"}, {"proto": 1, "run": 5},
                {"proto": 1, "run": self.run, "header": {"node": self.node, "stages": "abc", "clock": "r"}},
                {"proto": 1, "run": self.run, "header": {"node": self.node, "stages": ["a"] * 100000, "clock": "r"}},
                {"proto": 9, "run": self.run}]), 1)]),
            (False, "hello-huge", lambda: [_text("hello", {"proto": 1, "pad": "x" * (MAX_MESSAGE_BYTES + 10)}, 1)]),
            # Batches after a valid hello.
            (True, "random-bytes", lambda: [_binary_event("batch"), r.randbytes(r.randrange(0, 2000))]),
            (True, "truncated", lambda: [_binary_event("batch"), good[:r.randrange(0, len(good))]]),
            (True, "wrong-version", lambda: [_binary_event("batch"), batch(version=r.choice([0, 2, 255]))]),
            (True, "bad-magic", lambda: [_binary_event("batch"), batch(magic=b"JUNK")]),
            (True, "huge-count",
             lambda: [_binary_event("batch"), batch(count=r.choice([70000, 1 << 31, (1 << 32) - 1]))]),
            (True, "count-mismatch", lambda: [_binary_event("batch"), batch(count=r.randrange(1, 16))]),
            (True, "length-lie", lambda: [_binary_event("batch"), batch(length=r.randrange(1 << 32))]),
            (True, "zlib-bomb", lambda: [_binary_event("batch"), batch(flags=1, payload=_BOMB, length=len(_BOMB))]),
            (True, "bad-events", lambda: [_binary_event("batch"), _bad_events(self.run, r)]),
            (True, "other-run", lambda: [_binary_event("batch"), encode_batch(uuid.uuid4().hex, 1, EVENTS)]),
            (True, "oversize", lambda: [_binary_event("batch"), b"\0" * (MAX_MESSAGE_BYTES + 1)]),
            (True, "wrong-type", lambda: [_text("batch", r.choice(["DCUB", 12, [1, 2], {"a": 1}, None, True]), 1)]),
            (True, "clock-garbage", lambda: [_text("clock", r.choice([{"samples": [[1, 2]]}, {"samples": "x"}, 5,
                                                                       {"samples": [[1, 2, 3, 4]] * 999}]), 1)]),
            (True, "end-garbage", lambda: [_text("end", r.choice([{"events": -1}, {"dropped": "many"}, []]), 1)]),
            (True, "hello-twice", lambda: [_text("hello", self.hello(), 1)]),
        ]
        needs_hello, kind, make = r.choice(choices)
        return needs_hello, kind, make()

    def hello(self) -> dict:
        return {"proto": 1, "run": self.run, "header": header_for(self.node, 2).to_dict(), "lost": 0}


_BOMB = zlib.compress(b"\0" * (8 * 1024 * 1024), 9)


def _bad_events(run: str, r: random.Random) -> bytes:
    ev = EVENTS.copy()
    field_, value = r.choice([("stage", 99), ("stage", -3), ("point", 7), ("_pad", 1), ("ts", -5),
                              ("source", -1), ("frame", -1)])
    ev[field_][r.randrange(len(ev))] = value
    return encode_batch(run, r.randrange(1000), ev)


async def _one(session: aiohttp.ClientSession, url: str, token: str | None, case: Case, report: FuzzReport,
               timeout: float) -> None:
    needs_hello, kind, frames = case.pick()
    report.kinds[kind] += 1
    ws_url = url.replace("http://", "ws://") + "/socket.io/?EIO=4&transport=websocket"
    async with session.ws_connect(ws_url, max_msg_size=0, autoping=True) as ws:
        opening = await ws.receive(timeout)
        assert opening.type == aiohttp.WSMsgType.TEXT and opening.data.startswith("0"), opening
        await ws.send_str(f"40{NS}," + json.dumps({"token": token, "node": case.node}))
        reply = await ws.receive(timeout)
        assert reply.type == aiohttp.WSMsgType.TEXT and reply.data.startswith(f"40{NS}"), reply
        if needs_hello:
            await ws.send_str(_text("hello", case.hello(), 1))
            ack = await ws.receive(timeout)
            assert ack.type == aiohttp.WSMsgType.TEXT and '"ok":true' in ack.data.replace(" ", ""), ack
        report.sent += 1
        try:
            for frame in frames:
                if isinstance(frame, bytes):
                    await ws.send_bytes(frame)
                else:
                    await ws.send_str(frame)
        except (ConnectionError, aiohttp.ClientError):
            pass  # the relay already closed it
        closed = False
        try:
            while True:
                msg = await ws.receive(timeout)
                if msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING,
                                aiohttp.WSMsgType.ERROR):
                    closed = True
                    break
                if msg.type == aiohttp.WSMsgType.TEXT:
                    if msg.data == "2":
                        await ws.send_str("3")
                    elif "relay_error" in msg.data or msg.data.startswith(f"44{NS}") or '"ok": false' in msg.data \
                            or '"ok":false' in msg.data:
                        report.errors_seen += 1
        except asyncio.TimeoutError:
            pass
        if closed:
            report.closed += 1
        else:
            report.not_closed[kind] += 1


async def fuzz(url: str, count: int, token: str | None = None, workers: int = 16, seed: int = 0,
               timeout: float = 5.0) -> FuzzReport:
    """Throw ``count`` malformed payloads at ``url`` from ``workers`` concurrent connections."""
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


if __name__ == "__main__":
    import sys
    print(asyncio.run(fuzz(sys.argv[1], int(sys.argv[2]))))
