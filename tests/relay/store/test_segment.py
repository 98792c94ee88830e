"""Segments (relay/store/segment.py): any events come back exactly, in order, by batch; the paper's pace
takes under 4 bytes an event; a damaged segment is refused with SegmentError, never anything else."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from dcuscope.probes.ship.simnode import synth_events
from dcuscope.protocol.events import EVENT_DTYPE
from dcuscope.relay.store.segment import HEAD, SegmentError, decode, encode, split_batches

T0 = 1_700_000_000_000_000_000
PAPER_RATE = 4300


def random_events(rng: np.random.Generator, n: int, small: bool) -> np.ndarray:
    """Events of random bytes (any int64 time and frame, any stage, point and code); ``small``: few
    sources whose frames step by little, as frames do (the packed tokens' path)."""
    events = np.frombuffer(rng.integers(0, 256, n * EVENT_DTYPE.itemsize, dtype=np.uint8).tobytes(), EVENT_DTYPE).copy()
    if small:
        events["source"] = rng.integers(0, 4, n)
        events["frame"] = rng.integers(-3, 4, n).cumsum() + int(rng.integers(-2**62, 2**62))
    return events


def random_counts(rng: np.random.Generator, n: int) -> list[int]:
    cuts = sorted(rng.integers(0, n + 1, int(rng.integers(0, 6))).tolist())
    return np.diff([0, *cuts, n]).tolist()


@pytest.mark.parametrize("small", [False, True])
def test_any_events_come_back_exactly_in_order_and_by_batch(small):
    rng = np.random.default_rng(7 + small)
    for n in [0, 1, 2, *rng.integers(3, 3000, 40).tolist()]:
        events = random_events(rng, n, small)
        counts = random_counts(rng, n)
        got_counts, got = decode(encode(counts, events))
        assert got.tobytes() == events.tobytes()
        assert got_counts.tolist() == counts
        assert [len(b) for b in split_batches(got_counts, got)] == counts


def test_the_papers_pace_takes_under_4_bytes_an_event_a_sixth_of_a_raw_batch_and_half_a_zlib_one():
    fps = PAPER_RATE / (12 * 2)  # 2 sources, 12 events a frame (simnode's)
    events = synth_events(int(fps * 30), 2, fps, T0, drop_rate=0.01, seed=3)[:100_000]
    counts = [215] * (len(events) // 215) + [len(events) % 215]
    size = len(encode(counts, events))
    assert size / len(events) < 4.0
    assert events.nbytes / size > 6
    batches = sum(len(zlib.compress(events[i:i + 215].tobytes())) for i in range(0, len(events), 215))
    assert batches / size > 2


def test_counts_that_do_not_add_up_are_refused():
    with pytest.raises(ValueError, match="add up"):
        encode([3], np.zeros(2, EVENT_DTYPE))


def test_a_damaged_segment_is_refused_with_one_error_whatever_the_damage():
    rng = np.random.default_rng(11)
    events = synth_events(50, 2, 25.0, T0)
    good = encode([len(events) // 2, len(events) - len(events) // 2], events)
    body = zlib.decompress(good[HEAD.size:])
    damaged = [b"", good[:10], b"XXXX" + good[4:], good[:4] + b"\x09" + good[5:], good[:HEAD.size + 20],
               good[:HEAD.size] + zlib.compress(body[:-7]), good[:HEAD.size] + zlib.compress(body + b"\0"),
               good[:8] + (len(events) + 1).to_bytes(4, "little") + good[12:]]
    for _ in range(200):
        b = bytearray(good)
        b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
        damaged.append(bytes(b))
    for data in damaged:
        try:
            counts, got = decode(data)
        except SegmentError:
            continue
        # A flip zlib's check misses could only come back as events of the right number.
        assert int(counts.sum()) == len(got)
    with pytest.raises(SegmentError, match="version"):
        decode(good[:4] + b"\x09" + good[5:])
