"""What nodes and the relay say to each other over the ingest WebSocket (``GET /ingest``).

Each batch travels as one binary WebSocket frame, each other message as one JSON text frame
(the envelope of :mod:`dcuscope.protocol.envelope`).

Events travel in binary batches: a 40-byte header, then the events as the raw bytes of an
``EVENT_DTYPE`` array (24 bytes each, little-endian), optionally zlib-compressed::

    offset size  field
    0      4     magic b"DCUB"
    4      1     batch format version (BATCH_VERSION)
    5      1     flags: bit 0 = payload is zlib-compressed; other bits must be 0
    6      2     reserved, 0
    8      16    run id (the node's session: a UUID made when its run starts)
    24     8     sequence number, from 0, one per batch of the run
    32     4     event count
    36     4     payload length in bytes (what follows the header, exactly)

The other messages are small JSON objects (``hello``, ``clock``, ``end``), validated here too:
every decoder raises :class:`ProtocolError` with a one-line reason and never anything else,
so the ingest can answer any payload with an error and a closed connection.
"""

from __future__ import annotations

import math
import struct
import uuid
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dcuscope.protocol.errors import LimitExceeded, ProtocolError
from dcuscope.protocol.events import EVENT_DTYPE, POINT_NAMES, TraceHeader, codes_valid

MAGIC = b"DCUB"
BATCH_VERSION = 1
PROTOCOL_VERSION = 2
"""Version of the message envelope and the JSON messages (``v`` of every text frame, ``proto`` of
``hello``); 1 was the Socket.IO transport."""
INGEST_PATH = "/ingest"
"""Where nodes open their WebSocket: ``ws://HOST:PORT/ingest``."""
SILENCE_S = 3.0
"""A peer that sends nothing this long (no message, no answer to a ping) is taken as gone: a node
waiting for its relay (batches in flight, a request) moves on to its next relay, a relay lets the
node's run go (another relay may take it). A frozen relay (SIGSTOP, a paused VM) keeps its TCP connections open: only silence
tells."""
HEARTBEAT_S = SILENCE_S * 2 / 3
"""A node pings a relay silent this long; it has the rest of ``SILENCE_S`` to answer."""
RELAY_HEARTBEAT_S = 4.0
"""A relay pings a node silent this long and lets its run go if no pong comes within half as long
again (aiohttp's heartbeat: 6 s in all). More patient than the node: a node that moves on says so
by connecting elsewhere, while a relay's busy event loop may read a pong late."""
FLAG_ZLIB = 0x01
HEADER = struct.Struct("<4sBBH16sQII")
HEADER_SIZE = HEADER.size  # 40

MAX_BATCH_EVENTS = 65536
"""Events one batch may hold: 1.5 MiB raw, under the relay's message size limit."""
MAX_MESSAGE_BYTES = 2 * 1024 * 1024
"""The largest WebSocket message the relay accepts (``max_msg_size``); larger closes with 1009."""
MAX_STAGES = 256
MAX_NAME = 200
MAX_SOURCES = 1024
MAX_CLOCK_SAMPLES = 64
MAX_DOUBT = 1024
"""Batches a hello may ask about (``doubt``): a node's window is 64."""
CLOCK_VIAS = ("websocket", "udp")
"""Transports a clock report's samples may come by (``clock.via``; absent: websocket)."""
SOURCE_LIMIT = 1 << 19
FRAME_LIMIT = 1 << 44
"""Source ids and frame numbers must fit these so that (source, frame) packs in one int64 key."""
INT64_MAX = (1 << 63) - 1
SECRET_CHARS = 32
"""Length of a run's resume secret (hex), issued by the relay in the reply to its first hello."""


@dataclass(frozen=True)
class Batch:
    run: str
    """Run id as 32 hex digits."""
    seq: int
    events: np.ndarray
    """Read-only EVENT_DTYPE array (a view on the decoded bytes)."""
    payload: bytes
    """The payload as it arrived (compressed or not), what storage keeps."""
    compressed: bool


@dataclass(frozen=True)
class Hello:
    run: str
    header: TraceHeader
    lost: int
    ptp: dict = field(default_factory=dict)
    floor: int = 0
    """Every batch below this sequence number was acknowledged or given up by the node."""
    secret: str | None = None
    """The resume secret the relay issued at the run's first hello; required to resume it."""
    doubt: tuple[int, ...] = ()
    """Batches the node sent and then evicted unacknowledged: the relay answers which of them it
    stored (``stored`` in its reply), so that the node counts those delivered, the others lost."""
    spooled: bool = False
    """A past run sent again from the node's spool (a drain): stored as itself, never the node's live run."""
    spool: dict | None = None
    """The node's spool: {bytes, oldest_ns} (:func:`sanitize_spool`); None: it keeps none."""


@dataclass(frozen=True)
class ClockReport:
    samples: list[tuple[int, int, int, int]]
    """NTP samples (t1 node send, t2 relay receive, t3 relay send, t4 node receive), ns."""
    lost: int
    ptp: dict
    floor: int = 0
    """As :attr:`Hello.floor`."""
    via: str = "websocket"
    """Transport of the samples' exchanges (one of CLOCK_VIAS)."""
    doubt: tuple[int, ...] = ()
    """As :attr:`Hello.doubt` (the report is then a request: the reply says ``stored``)."""
    forged: int = 0
    """UDP clock answers the node refused for a wrong tag (forged or altered on the way), in its run."""
    spool: dict | None = None
    """As :attr:`Hello.spool`."""


def encode_batch(run: str, seq: int, events: np.ndarray, compress: bool = False) -> bytes:
    """One batch message for ``events`` (EVENT_DTYPE, at most MAX_BATCH_EVENTS)."""
    if events.dtype != EVENT_DTYPE:
        raise ValueError(f"events must be EVENT_DTYPE, not {events.dtype}")
    if not 0 < len(events) <= MAX_BATCH_EVENTS:
        raise ValueError(f"a batch holds 1..{MAX_BATCH_EVENTS} events, not {len(events)}")
    raw = np.ascontiguousarray(events).tobytes()
    payload = zlib.compress(raw, 1) if compress else raw
    flags = FLAG_ZLIB if compress else 0
    head = HEADER.pack(MAGIC, BATCH_VERSION, flags, 0, uuid.UUID(hex=run).bytes, seq, len(events), len(payload))
    return head + payload


def decode_batch(data: object, n_stages: int, max_events: int = MAX_BATCH_EVENTS,
                 check: Callable[[np.ndarray, int], None] | None = None) -> Batch:
    """Parse and validate one batch; ``n_stages`` bounds the stage index of every event. ``check``:
    what validates its events, :func:`check_events` or another that refuses the same ones."""
    if isinstance(data, (bytearray, memoryview)):
        data = bytes(data)
    if not isinstance(data, bytes):
        raise ProtocolError(f"batch must be binary, not {type(data).__name__}")
    if len(data) < HEADER_SIZE:
        raise ProtocolError(f"batch truncated: {len(data)} bytes, header needs {HEADER_SIZE}")
    magic, version, flags, reserved, run, seq, count, length = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError("not a dcuscope batch (bad magic)")
    if version != BATCH_VERSION:
        raise ProtocolError(f"unsupported batch version {version} (this relay reads {BATCH_VERSION})")
    if flags & ~FLAG_ZLIB or reserved:
        raise ProtocolError(f"unknown batch flags {flags:#x}/{reserved:#x}")
    if not 0 < count <= max_events:
        raise ProtocolError(f"batch event count {count} outside 1..{max_events}")
    if seq > INT64_MAX:
        raise ProtocolError(f"batch sequence number {seq} too large")
    payload = data[HEADER_SIZE:]
    if length != len(payload):
        raise ProtocolError(f"batch payload is {len(payload)} bytes, header says {length}")
    size = count * EVENT_DTYPE.itemsize
    if flags & FLAG_ZLIB:
        raw = _inflate(payload, size)
    else:
        raw = payload
    if len(raw) != size:
        raise ProtocolError(f"batch holds {len(raw)} bytes of events, {count} events need {size}")
    events = np.frombuffer(raw, dtype=EVENT_DTYPE)
    (check or check_events)(events, n_stages)
    return Batch(run.hex(), int(seq), events, payload, bool(flags & FLAG_ZLIB))  # the run id as uuid.UUID(bytes=run).hex writes it


def declared_bytes(data: bytes) -> int:
    """What a batch will weigh once inflated, read from its header before anything is inflated:
    header + event count x 24 (the count capped at MAX_BATCH_EVENTS: a larger one is refused
    anyway), at least the message's own length."""
    if len(data) < HEADER_SIZE:
        return len(data)
    count = HEADER.unpack_from(data)[6]
    return max(len(data), HEADER_SIZE + min(count, MAX_BATCH_EVENTS) * EVENT_DTYPE.itemsize)


def _inflate(payload: bytes, size: int) -> bytes:
    # Bounded: a few bytes that inflate to gigabytes must not get past max_length.
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(payload, size)
    except zlib.error as exc:
        raise ProtocolError(f"batch payload does not inflate: {exc}") from exc
    if not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise ProtocolError("batch payload inflates to more or less than its event count")
    return raw


def check_events(events: np.ndarray, n_stages: int) -> None:
    """Reject events a pipeline cannot produce (vectorised: one pass per field)."""
    point, code = events["point"], events["code"]
    bad = (
        (point < 0) | (point >= len(POINT_NAMES)) | ~codes_valid(point, code)
        | (events["stage"] < 0) | (events["stage"] >= n_stages)
        | (events["source"] < 0) | (events["source"] >= SOURCE_LIMIT)
        | (events["frame"] < 0) | (events["frame"] >= FRAME_LIMIT)
        | (events["ts"] <= 0)
    )
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        e = events[i]
        raise ProtocolError(
            f"event {i} invalid: stage={e['stage']} point={e['point']} source={e['source']} "
            f"frame={e['frame']} ts={e['ts']}"
        )


def decode_payload(payload: bytes, compressed: bool) -> np.ndarray:
    """Events of a stored payload (as kept by storage: validated when it arrived)."""
    raw = zlib.decompress(payload) if compressed else payload
    return np.frombuffer(raw, dtype=EVENT_DTYPE)


# --- JSON messages -------------------------------------------------------------------------

def _dict(obj: object, what: str) -> dict:
    if not isinstance(obj, dict):
        raise ProtocolError(f"{what} must be an object, not {type(obj).__name__}")
    return obj


def _int(obj: object, what: str, lo: int = 0, hi: int = INT64_MAX) -> int:
    # bool is an int in Python; a JSON true is not a count.
    if not isinstance(obj, int) or isinstance(obj, bool) or not lo <= obj <= hi:
        raise ProtocolError(f"{what} must be an integer in {lo}..{hi}")
    return int(obj)


def _str(obj: object, what: str, limit: int = MAX_NAME) -> str:
    if not isinstance(obj, str) or not 0 < len(obj) <= limit or not obj.isprintable():
        raise ProtocolError(f"{what} must be a printable string of 1..{limit} characters")
    return obj


def _name(obj: object, what: str, limit: int) -> str:
    """A node or stage name: a printable string, at most ``limit`` characters (the relay's)."""
    text = _str(obj, what)
    if len(text) > limit:
        raise LimitExceeded("name_chars", f"{what} has {len(text)} characters, more than this relay takes "
                                          f"({limit}: --limit name_chars=N)")
    return text


def _run_id(obj: object) -> str:
    text = _str(obj, "run", 64)
    try:
        value = uuid.UUID(hex=text)
    except ValueError as exc:
        raise ProtocolError("run must be a UUID in hex") from exc
    return value.hex


def decode_hello(obj: object, node: str | None = None, *, max_stages: int = MAX_STAGES,
                 max_name: int = MAX_NAME) -> Hello:
    """A node's first message on a connection: who it is and how to read its events (its
    header must name ``node`` when given). ``max_stages`` and ``max_name`` are the relay's
    bounds on stages and on node and stage name length (at most the protocol's); beyond them,
    :class:`LimitExceeded` names the limit."""
    d = _dict(obj, "hello")
    proto = _int(d.get("proto"), "hello.proto", 0, 1 << 16)
    if proto != PROTOCOL_VERSION:
        raise ProtocolError(f"unsupported protocol version {proto} (this relay speaks {PROTOCOL_VERSION})")
    run = _run_id(d.get("run"))
    h = _dict(d.get("header"), "hello.header")
    stages = h.get("stages")
    if not isinstance(stages, list) or not 0 < len(stages) <= MAX_STAGES:
        raise ProtocolError(f"hello.header.stages must be a list of 1..{MAX_STAGES} names")
    if len(stages) > max_stages:
        raise LimitExceeded("stages", f"hello declares {len(stages)} stages, more than this relay takes "
                                      f"({max_stages}: --limit stages=N)")
    for s in stages:
        _name(s, "stage name", max_name)
    sources = _dict(h.get("sources", {}), "hello.header.sources")
    if len(sources) > MAX_SOURCES:
        raise ProtocolError(f"hello.header.sources holds more than {MAX_SOURCES} entries")
    for k, v in sources.items():
        if not (isinstance(k, str) and k.isdigit() and int(k) < SOURCE_LIMIT):
            raise ProtocolError("hello.header.sources keys must be source ids")
        if not isinstance(v, str) or len(v) > 4096:
            raise ProtocolError("hello.header.sources values must be strings")
    versions = _dict(h.get("versions", {}), "hello.header.versions")
    if len(versions) > 64 or not all(isinstance(k, str) and isinstance(v, str) and len(k) + len(v) < 400
                                     for k, v in versions.items()):
        raise ProtocolError("hello.header.versions must map names to version strings")
    kinds = _dict(h.get("kinds", {}), "hello.header.kinds")
    if not (kinds.keys() <= set(stages) and all(isinstance(v, str) and len(v) <= MAX_NAME for v in kinds.values())):
        raise ProtocolError("hello.header.kinds must map stage names to element factory names")
    links = h.get("links", [])
    if not (isinstance(links, list) and len(links) <= 4 * MAX_STAGES and all(
            isinstance(l, list) and len(l) == 2 and all(type(i) is int and 0 <= i < len(stages) for i in l)
            for l in links)):
        raise ProtocolError("hello.header.links must be [from, to] pairs of stage indices")
    unknown = h.get("lineage_unknown", [])
    if not (isinstance(unknown, list) and set(unknown) <= set(stages)):
        raise ProtocolError("hello.header.lineage_unknown must name stages")
    header_node = _name(h.get("node"), "hello.header.node", max_name)
    if node is not None and header_node != node:
        raise ProtocolError(f"hello names node {header_node!r} but the connection is {node!r}")
    _str(h.get("clock"), "hello.header.clock", 32)
    _int(h.get("started_ns", 0), "hello.header.started_ns")
    _int(h.get("format", 1), "hello.header.format", 0, 1 << 16)
    try:
        header = TraceHeader.from_dict(h)
    except (KeyError, TypeError, ValueError) as exc:
        raise ProtocolError(f"hello.header unreadable: {exc}") from exc
    lost = _int(d.get("lost", 0), "hello.lost")
    secret = d.get("secret")
    if secret is not None and not (isinstance(secret, str) and len(secret) == SECRET_CHARS
                                   and all(c in "0123456789abcdef" for c in secret)):
        raise ProtocolError(f"hello.secret must be {SECRET_CHARS} hex digits")
    spooled = d.get("spooled", False)
    if not isinstance(spooled, bool):
        raise ProtocolError("hello.spooled must be true or false")
    return Hello(run, header, lost, sanitize_ptp(d.get("ptp")), _int(d.get("floor", 0), "hello.floor"), secret,
                 _doubt(d, "hello"), spooled, sanitize_spool(d.get("spool")))


def sanitize_spool(obj: object) -> dict | None:
    """A node's spool facts with their types: {bytes: int >= 0, oldest_ns: int or None}; None if absent or malformed."""
    if not isinstance(obj, dict):
        return None
    size, oldest = _finite_int(obj.get("bytes")), obj.get("oldest_ns")
    oldest = _finite_int(oldest) if oldest is not None else None
    if size is None or size < 0:
        return None
    return {"bytes": size, "oldest_ns": oldest if oldest is not None and oldest > 0 else None}


def _doubt(d: dict, what: str) -> tuple[int, ...]:
    doubt = d.get("doubt", [])
    if not (isinstance(doubt, list) and len(doubt) <= MAX_DOUBT):
        raise ProtocolError(f"{what}.doubt must be a list of at most {MAX_DOUBT} batch numbers")
    return tuple(_int(seq, f"{what}.doubt batch number") for seq in doubt)


def decode_clock(obj: object) -> ClockReport:
    """A node's periodic report: completed NTP samples, transport losses, PTP state."""
    d = _dict(obj, "clock")
    samples = d.get("samples", [])
    if not isinstance(samples, list) or len(samples) > MAX_CLOCK_SAMPLES:
        raise ProtocolError(f"clock.samples must be a list of at most {MAX_CLOCK_SAMPLES}")
    out = []
    for s in samples:
        if not isinstance(s, list) or len(s) != 4:
            raise ProtocolError("clock sample must be [t1, t2, t3, t4]")
        t1, t2, t3, t4 = (_int(t, "clock sample time", -INT64_MAX, INT64_MAX) for t in s)
        if t4 < t1 or t3 < t2:
            raise ProtocolError("clock sample times out of order")
        out.append((t1, t2, t3, t4))
    via = d.get("via", "websocket")
    if via not in CLOCK_VIAS:
        raise ProtocolError(f"clock.via must be one of {', '.join(CLOCK_VIAS)}, not {str(via)[:20]!r}")
    return ClockReport(out, _int(d.get("lost", 0), "clock.lost"), sanitize_ptp(d.get("ptp")),
                       _int(d.get("floor", 0), "clock.floor"), via, _doubt(d, "clock"),
                       _int(d.get("forged", 0), "clock.forged"), sanitize_spool(d.get("spool")))


def decode_end(obj: object) -> tuple[int, int, int, int | None]:
    """``end``: (events the node shipped, dropped in its probe buffer, lost in transport, when the run
    ended on the node: ns, or None when not said; a run drained from a spool ended long before)."""
    d = _dict(obj, "end")
    ended = d.get("ended_ns")
    return (_int(d.get("events", 0), "end.events"), _int(d.get("dropped", 0), "end.dropped"),
            _int(d.get("lost", 0), "end.lost"), None if ended is None else _int(ended, "end.ended_ns"))


PTP_STATES = ("unavailable", "unlocked", "locked", "lost")


def _text(value: object, limit: int) -> str | None:
    """A string cut to ``limit``, any control character made a space (it is shown in pages)."""
    return "".join(c if c.isprintable() else " " for c in value[:limit]) if isinstance(value, str) else None


def _finite_int(value: object) -> int | None:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return int(max(-INT64_MAX, min(INT64_MAX, value)))
    return None


def sanitize_ptp(obj: object) -> dict:
    """Keep only the PTP fields the relay knows, with their types; anything else is dropped."""
    if not isinstance(obj, dict):
        return {"state": "unavailable"}
    state = obj.get("state")
    out: dict = {"state": state if state in PTP_STATES else "unavailable"}
    for key, limit in (("reason", 200), ("gm_identity", 64), ("port_state", 32), ("interface", 64)):
        if (text := _text(obj.get(key), limit)) is not None:
            out[key] = text
    if (offset := _finite_int(obj.get("master_offset_ns"))) is not None:
        out["master_offset_ns"] = offset
    if isinstance(obj.get("gm_present"), bool):
        out["gm_present"] = obj["gm_present"]
    if obj.get("timestamping") in ("software", "hardware"):
        out["timestamping"] = obj["timestamping"]
    if isinstance(obj.get("system_clock"), dict):
        out["system_clock"] = _sanitize_system_clock(obj["system_clock"])
    return out


def _sanitize_system_clock(obj: dict) -> dict:
    out: dict = {"synced": obj.get("synced") is True, "follows_ptp": obj.get("follows_ptp") is True,
                 "by": obj.get("by") if obj.get("by") in ("phc2sys", "ptp4l", "chrony", "ntpd", "timesyncd") else None}
    for key in ("maxerror_us", "esterror_us"):
        if (value := _finite_int(obj.get(key))) is not None:
            out[key] = value
    freq = obj.get("freq_ppm")
    if isinstance(freq, (int, float)) and not isinstance(freq, bool) and math.isfinite(freq):
        out["freq_ppm"] = float(freq)
    if (detail := _text(obj.get("detail"), 200)) is not None:
        out["detail"] = detail
    return out
