"""The relay's compiled batch decoding and check refuse exactly the events numpy's ``check_events`` refuses, and
the relay says what is wrong with numpy's words."""

from __future__ import annotations

import re

import numpy as np
import pytest

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.errors import ProtocolError
from dcuscope.protocol.events import EVENT_DTYPE, READY
from dcuscope.protocol.wire import FRAME_LIMIT, HEADER, SOURCE_LIMIT, check_events, decode_batch, encode_batch
from dcuscope.relay.ingest.endpoint import _check_compiled, _decode_compiled
from dcuscope.model import compiled as cmerge
from dcuscope.relay.live.run import LiveRun

T0 = 1_700_000_000_000_000_000
STAGES = 3


@pytest.fixture(scope="module")
def compiled() -> cmerge.CompiledCore:
    merge = cmerge.load()
    assert merge is not None, cmerge.unavailable_reason()
    return merge


def _numpy_first(events: np.ndarray) -> int:
    try:
        check_events(events, STAGES)
    except ProtocolError as exc:
        return int(re.match(r"event (\d+) invalid", str(exc)).group(1))
    return -1


BAD = [("point", 7), ("point", -1), ("stage", -1), ("stage", STAGES), ("source", -1), ("source", SOURCE_LIMIT),
       ("frame", -1), ("frame", FRAME_LIMIT), ("ts", 0), ("ts", -5)]


@pytest.mark.parametrize("field,value", BAD)
def test_a_field_out_of_range_is_found_where_numpy_finds_it(compiled, field, value):
    events = synth_events(40, 2, 30.0, T0, seed=3)
    events = events[events["stage"] < STAGES].copy()
    assert compiled.first_invalid(events, STAGES) == -1 == _numpy_first(events)
    at = len(events) // 2
    events[field][at] = value
    events["ts"][at + 3] = 0  # a later one too: the first is said
    assert compiled.first_invalid(events, STAGES) == at == _numpy_first(events)


def test_codes_a_point_does_not_allow_are_refused(compiled):
    events = synth_events(20, 1, 30.0, T0, seed=4)
    events = events[events["stage"] < STAGES].copy()
    at = len(events) // 3
    for point, code in ((READY, 0), (0, 3), (5, 127), (6, -100)):
        bad = events.copy()
        bad["point"][at], bad["code"][at] = point, code
        assert compiled.first_invalid(bad, STAGES) == at == _numpy_first(bad)
    events["point"][at], events["code"][at] = READY, 2  # a ready event's group size
    assert compiled.first_invalid(events, STAGES) == -1 == _numpy_first(events)


def test_random_records_are_judged_alike(compiled):
    rng = np.random.default_rng(7)
    for _ in range(200):
        events = np.frombuffer(rng.integers(0, 256, 24 * 64, np.uint8).tobytes(), EVENT_DTYPE).copy()
        # Most fields in range, so that the first invalid event falls anywhere, not always at 0.
        ok = rng.random(64) < 0.97
        events["ts"][ok] = np.abs(events["ts"][ok]) % (1 << 62) + 1
        events["frame"][ok] = np.abs(events["frame"][ok]) % FRAME_LIMIT
        events["source"][ok] = np.abs(events["source"][ok]) % SOURCE_LIMIT
        events["stage"][ok] = np.abs(events["stage"][ok]) % STAGES
        events["point"][ok] = np.abs(events["point"][ok]) % 3
        events["code"][ok] = 0
        assert compiled.first_invalid(events, STAGES) == _numpy_first(events)


def test_the_relay_refuses_a_bad_batch_in_numpys_words(compiled):
    events = synth_events(10, 1, 30.0, T0, seed=5)
    events = events[events["stage"] < STAGES].copy()
    events["stage"][4] = STAGES
    data = encode_batch("ab" * 16, 0, events, compress=True)
    check = lambda e, n: _check_compiled(compiled, e, n)  # noqa: E731
    with pytest.raises(ProtocolError) as by_numpy:
        decode_batch(data, STAGES)
    with pytest.raises(ProtocolError) as by_compiled:
        decode_batch(data, STAGES, check=check)
    assert str(by_compiled.value) == str(by_numpy.value) and str(by_numpy.value).startswith("event 4 invalid")
    events["stage"][4] = 0
    assert len(decode_batch(encode_batch("ab" * 16, 0, events), STAGES, check=check).events) == len(events)


def test_a_batch_of_known_sources_is_told_from_one_naming_a_new_source_where_it_first_does(compiled):
    """The compiled lookup of a batch's sources among a run's (sorted) ids finds the first unknown
    one where numpy finds it, reading the source field of the records in place (and a plain array),
    for runs of one id, of many, and ids that only differ past the first."""
    rng = np.random.default_rng(9)
    for _ in range(300):
        ids = np.unique(rng.integers(0, 40, int(rng.integers(1, 12)))).astype(np.int64)
        events = np.zeros(int(rng.integers(0, 200)), EVENT_DTYPE)
        events["source"] = rng.choice(ids, len(events))
        if len(events) and rng.random() < 0.5:
            events["source"][int(rng.integers(0, len(events)))] = int(rng.integers(0, 45))
        unknown = np.flatnonzero(~np.isin(events["source"], ids))
        expected = int(unknown[0]) if len(unknown) else -1
        assert compiled.first_unknown(events["source"], ids) == expected
        assert compiled.first_unknown(np.ascontiguousarray(events["source"]), ids) == expected


def test_a_live_run_notes_a_new_source_among_known_ones(compiled):
    """A batch whose sources are all known notes nothing; one naming a new id among them notes it,
    with its own watermark, whether its events came first or last."""
    run = LiveRun(header_for("n", 2, T0))
    events = synth_events(20, 2, 25.0, T0)
    assert run.admit_sources(events["source"], 8) == 2 and run.admit_sources(events["source"], 8) == 2
    for where in (0, -1):
        batch = events.copy()
        batch["source"][where] = 5 if where == 0 else 7
        before = len(run._src_ids)
        assert run.admit_sources(batch["source"], 8) == before + 1
    assert run._src_ids.tolist() == [0, 1, 5, 7] and run._watermark.tolist() == [-1] * 4


def _outcome(decode, data) -> tuple:
    try:
        b = decode(data, STAGES)
    except ProtocolError as exc:
        return ("refused", str(exc))
    return (b.run, b.seq, b.events.tobytes(), b.payload, b.compressed)


def _batches() -> list[bytes]:
    """Sound batches, compressed or not, and each way a header or payload can be wrong."""
    events = synth_events(30, 2, 30.0, T0, seed=6)
    events = events[events["stage"] < STAGES].copy()
    plain, packed = encode_batch("cd" * 16, 7, events), encode_batch("cd" * 16, 8, events, compress=True)
    head = list(HEADER.unpack_from(plain))

    def with_header(**fields) -> bytes:
        names = ("magic", "version", "flags", "reserved", "run", "seq", "count", "length")
        values = dict(zip(names, head), **fields)
        return HEADER.pack(*(values[n] for n in names)) + plain[HEADER.size:]

    bad_event = events.copy()
    bad_event["point"][5] = 9
    return [plain, packed, plain[:39], b"", plain[:-1], plain + b"x", with_header(magic=b"DCUX"), with_header(version=2),
            with_header(flags=2), with_header(reserved=1), with_header(count=0), with_header(count=70000),
            with_header(count=len(events) + 1), with_header(seq=1 << 63), with_header(length=5),
            encode_batch("cd" * 16, 9, bad_event), encode_batch("cd" * 16, 9, bad_event, compress=True),
            packed[:-3], bytearray(plain), memoryview(plain), "text"]


def test_the_compiled_decoding_takes_and_refuses_exactly_what_numpys_does_in_its_words(compiled):
    for data in _batches():
        assert _outcome(lambda d, n: _decode_compiled(compiled, d, n), data) == _outcome(decode_batch, data), data[:48]
    assert _outcome(lambda d, n: _decode_compiled(compiled, d, n), _batches()[0])[0] == "cd" * 16
