"""A *segment*: many stored batches of one run in one compact value, the store's long-term layout.

Batches arrive as the node packed them: 24 bytes an event, row by row, a few hundred events each,
which zlib barely shrinks (``relay.store.base``). Events are very regular, though: timestamps rise by
microseconds, a source's frame numbers rise by one, stage and point follow the graph's order and
``code`` is almost always 0. A segment stores them by column, as differences, then compresses:

- ``ts``: the first timestamp, then each event's difference from the one before (zigzag, so that
  an event a little earlier than the one before costs as little as one a little later);
- a *token* per event: the index of its (source, stage, point, code, frame step) in a table of the
  distinct ones, where the frame step is the difference from the frame of that source's previous
  event (0 or a few as frames go through the stages), the first event of a source stepping from
  that source's *base* frame;
- each column split into its bytes (the low bytes of all its values, then the next ones, as many
  as its largest value needs), so that equal bytes stand together;
- all of it compressed with zlib.

The timestamps' differences carry most of what is left (about 2.5 of the 3.5 bytes an event at
the paper's pace: nanoseconds of jitter do not compress). Nothing is lost: :func:`decode` gives
back the events, in their order, and each batch's count, so that a batch can be read alone.

Layout (little-endian)::

    offset size  field
    0      4     magic b"DCUS"
    4      1     SEGMENT_VERSION
    5      1     codec: 1 = zlib
    6      2     reserved, 0
    8      4     events
    12     4     batches
    16     ...   the compressed body: batch counts (u4 each), the table of tokens, the sources' base
                 frames, then the ts and token columns

Differences wrap around 2**64, so any int64 timestamps and frames come back exactly.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from dcuscope.protocol.events import EVENT_DTYPE
from dcuscope.relay.errors import RelayError

MAGIC = b"DCUS"
SEGMENT_VERSION = 1
ZLIB = 1
ZLIB_LEVEL = 3
"""Encoding 120,000 events at the paper's pace, bytes and CPU an event: level 1 3.56 B, 0.21 µs;
3 3.52 B, 0.24 µs; 6 (zlib's default) 3.47 B, 0.33 µs; 9 3.45 B, 1.54 µs (this machine)."""
HEAD = struct.Struct("<4sBBHII")
BODY = struct.Struct("<BBIIi")
"""ts bytes per value, token bytes per value, tokens, sources, reserved."""
TOKEN_DTYPE = np.dtype([("source", "<i4"), ("stage", "<i2"), ("point", "i1"), ("code", "i1"), ("step", "<i8")])
BASE_DTYPE = np.dtype([("source", "<i4"), ("frame", "<i8")])


class SegmentError(RelayError):
    """A stored segment that cannot be read (damaged, or written by a newer dcuscope)."""


def encode(counts: list[int] | np.ndarray, events: np.ndarray) -> bytes:
    """One segment of batches holding ``counts`` events each, ``events`` being theirs one after the other."""
    counts = np.asarray(counts, dtype="<u4")
    n = len(events)
    if int(counts.sum(dtype=np.int64)) != n:
        raise ValueError(f"batch counts add up to {int(counts.sum())}, not the {n} events given")
    events = np.ascontiguousarray(events, dtype=EVENT_DTYPE)
    ts = events["ts"].view(np.uint64)
    dts = np.empty(n, np.uint64)
    if n:
        dts[0] = ts[0]
        np.subtract(ts[1:], ts[:-1], out=dts[1:])
    dts = _zigzag(dts)
    steps, bases = _frame_steps(events["source"], events["frame"])
    keys = np.empty(n, TOKEN_DTYPE)
    for name in ("source", "stage", "point", "code"):
        keys[name] = events[name]
    keys["step"] = steps
    table, tokens = _tokens(keys)
    ts_bytes, token_bytes = _width(dts), _width(tokens)
    body = b"".join((BODY.pack(ts_bytes, token_bytes, len(table), len(bases), 0), counts.tobytes(), table.tobytes(),
                     bases.tobytes(), _split(dts, ts_bytes), _split(tokens.astype(np.uint64), token_bytes)))
    return HEAD.pack(MAGIC, SEGMENT_VERSION, ZLIB, 0, n, len(counts)) + zlib.compress(body, ZLIB_LEVEL)


def decode(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``(counts, events)`` of a segment: each batch's event count, and the events in order."""
    try:
        magic, version, codec, _, n, batches = HEAD.unpack_from(data)
    except struct.error:
        raise SegmentError(f"a segment of {len(data)} bytes is shorter than its header") from None
    if magic != MAGIC or codec != ZLIB:
        raise SegmentError(f"not a segment (magic {magic!r}, codec {codec})")
    if version != SEGMENT_VERSION:
        raise SegmentError(f"segment version {version}: this dcuscope reads {SEGMENT_VERSION}")
    try:
        body = zlib.decompress(memoryview(data)[HEAD.size:])
        ts_bytes, token_bytes, n_table, n_bases, _ = BODY.unpack_from(body)
        at = BODY.size
        counts, at = _take(body, at, np.dtype("<u4"), batches)
        table, at = _take(body, at, TOKEN_DTYPE, n_table)
        bases, at = _take(body, at, BASE_DTYPE, n_bases)
        dts, at = _join(body, at, n, ts_bytes)
        tokens, at = _join(body, at, n, token_bytes)
        if at != len(body) or int(counts.sum(dtype=np.int64)) != n or (n and int(tokens.max()) >= n_table):
            raise ValueError("its parts do not add up")
        keys = table[tokens.astype(np.intp)]
    except (zlib.error, struct.error, ValueError, IndexError) as exc:
        raise SegmentError(f"a damaged segment: {exc}") from None
    events = np.zeros(n, EVENT_DTYPE)
    for name in ("source", "stage", "point", "code"):
        events[name] = keys[name]
    events["ts"] = np.cumsum(_unzigzag(dts), dtype=np.uint64).view(np.int64)
    events["frame"] = _frames(keys["source"], keys["step"], bases)
    return counts, events


def _tokens(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct keys and each key's index among them. Sorting one integer per key is 30 times
    faster than sorting the records, so keys are packed in one when they fit (always, but for
    sources past 2**19 and frames jumping by thousands)."""
    step = _zigzag(keys["step"].view(np.uint64))
    source = keys["source"]
    if len(keys) and (int(step.max()) < 1 << 13 and int(source.min()) >= 0 and int(source.max()) < 1 << 19):
        packed = ((step << np.uint64(51)) | (source.astype(np.uint64) << np.uint64(32))
                  | (keys["stage"].view(np.uint16).astype(np.uint64) << np.uint64(16))
                  | (keys["point"].view(np.uint8).astype(np.uint64) << np.uint64(8)) | keys["code"].view(np.uint8))
        _, first, tokens = np.unique(packed, return_index=True, return_inverse=True)
        return keys[first], tokens
    return np.unique(keys, return_inverse=True)


def split_batches(counts: np.ndarray, events: np.ndarray) -> list[np.ndarray]:
    """The events of each batch of a segment, in order."""
    return np.split(events, np.cumsum(counts[:-1], dtype=np.int64)) if len(counts) else []


def _frame_steps(source: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each event's frame minus that of its source's previous event (the first: minus the base),
    and the bases: each source's first frame."""
    order = np.argsort(source, kind="stable")
    s, f = source[order], frame[order].view(np.uint64)
    first = np.ones(len(s), bool)
    first[1:] = s[1:] != s[:-1]
    step = np.empty(len(s), np.uint64)
    step[first] = 0
    if len(s) > 1:
        np.subtract(f[1:], f[:-1], out=step[1:], where=~first[1:])
    out = np.empty(len(s), np.int64)
    out[order] = step.view(np.int64)
    bases = np.empty(int(first.sum()), BASE_DTYPE)
    bases["source"], bases["frame"] = s[first], frame[order][first]
    return out, bases


def _frames(source: np.ndarray, step: np.ndarray, bases: np.ndarray) -> np.ndarray:
    order = np.argsort(source, kind="stable")
    s = source[order]
    first = np.ones(len(s), bool)
    first[1:] = s[1:] != s[:-1]
    if int(first.sum()) != len(bases) or not np.array_equal(s[first], bases["source"]):
        raise SegmentError("a damaged segment: its sources' base frames do not match its events")
    steps = step[order].view(np.uint64).copy()
    steps[first] = bases["frame"].view(np.uint64)
    # A running sum restarting at each source's first event: the cumulative sum less that before it.
    total = np.cumsum(steps, dtype=np.uint64)
    before = np.zeros(len(s), np.uint64)
    starts = np.flatnonzero(first)
    if len(s):
        start_total = total[starts] - steps[starts]
        before = np.repeat(start_total, np.diff(np.append(starts, len(s))))
    out = np.empty(len(s), np.int64)
    out[order] = (total - before).view(np.int64)
    return out


def _zigzag(d: np.ndarray) -> np.ndarray:
    signed = d.view(np.int64)
    return ((signed << 1) ^ (signed >> 63)).view(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    return (z >> np.uint64(1)) ^ (np.uint64(0) - (z & np.uint64(1)))


def _width(values: np.ndarray) -> int:
    """Bytes the largest of ``values`` needs (at least 1)."""
    top = int(values.max()) if len(values) else 0
    return max(1, (top.bit_length() + 7) // 8)


def _split(values: np.ndarray, width: int) -> bytes:
    """The low ``width`` bytes of each value, by byte: every value's first byte, then every second..."""
    return np.ascontiguousarray(values.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :width].T).tobytes()


def _join(body: bytes, at: int, n: int, width: int) -> tuple[np.ndarray, int]:
    if not 1 <= width <= 8:
        raise ValueError(f"a column of {width} bytes a value")
    end = at + n * width
    if end > len(body):
        raise ValueError("a column runs past the end")
    out = np.zeros((n, 8), np.uint8)
    out[:, :width] = np.frombuffer(body, np.uint8, n * width, at).reshape(width, n).T
    return out.view("<u8").reshape(n), end


def _take(body: bytes, at: int, dtype: np.dtype, count: int) -> tuple[np.ndarray, int]:
    end = at + dtype.itemsize * count
    if end > len(body):
        raise ValueError("a table runs past the end")
    return np.frombuffer(body, dtype, count, at), end
