"""The batch codec and the JSON message validators: round trips and every rejection."""

from __future__ import annotations

import struct
import uuid
import zlib

import numpy as np
import pytest

from dcuscope.protocol.errors import LimitExceeded, ProtocolError
from dcuscope.protocol.events import (DROP, DROP_REASONS, EVENT_DTYPE, FACT, FACT_KINDS, KEY, LINK, LINK_KINDS, POINT_NAMES,
                           READY, STOPPED, codes_valid)
from dcuscope.protocol.wire import (HEADER, HEADER_SIZE, MAX_BATCH_EVENTS, decode_batch, decode_clock, decode_end,
                            decode_hello, decode_payload, encode_batch, sanitize_ptp)
from dcuscope.probes.ship.simnode import header_for, synth_events

RUN = "4e70076ed9fd4f4a8510a89aee6824d1"  # fixed: parallel workers must collect the same test ids
N_STAGES = 8


def events(n: int = 50) -> np.ndarray:
    return synth_events(n, 2, 25.0, 1_700_000_000_000_000_000)[:n]


@pytest.mark.parametrize("compress", [False, True])
def test_round_trip(compress):
    ev = events()
    data = encode_batch(RUN, 7, ev, compress)
    b = decode_batch(data, N_STAGES)
    assert (b.run, b.seq, b.compressed) == (RUN, 7, compress)
    assert np.array_equal(b.events, ev)
    assert np.array_equal(decode_payload(b.payload, b.compressed), ev)


def _batch(**over) -> bytes:
    ev = events(4)
    raw = ev.tobytes()
    f = dict(magic=b"DCUB", version=1, flags=0, reserved=0, run=uuid.UUID(RUN).bytes, seq=1, count=4,
             length=len(raw), payload=raw)
    f.update(over)
    return HEADER.pack(f["magic"], f["version"], f["flags"], f["reserved"], f["run"], f["seq"], f["count"],
                       f["length"]) + f["payload"]


@pytest.mark.parametrize("data, message", [
    ("text", "must be binary"),
    (b"DCUB\x01", "truncated"),
    (_batch(magic=b"XXXX"), "bad magic"),
    (_batch(version=2), "unsupported batch version 2"),
    (_batch(flags=0x80), "unknown batch flags"),
    (_batch(reserved=1), "unknown batch flags"),
    (_batch(count=0), "count 0"),
    (_batch(count=MAX_BATCH_EVENTS + 1), "outside"),
    (_batch(count=5), "need"),
    (_batch(length=10), "header says"),
    (_batch(seq=1 << 63), "too large"),
    (_batch(payload=events(4).tobytes()[:-1], length=95), "need"),
])
def test_rejects(data, message):
    with pytest.raises(ProtocolError, match=message):
        decode_batch(data, N_STAGES)


def test_rejects_zlib_bomb_and_garbage():
    bomb = zlib.compress(b"\0" * (50 * 1024 * 1024))
    with pytest.raises(ProtocolError, match="inflates"):
        decode_batch(_batch(flags=1, payload=bomb, length=len(bomb)), N_STAGES)
    with pytest.raises(ProtocolError, match="does not inflate"):
        decode_batch(_batch(flags=1, payload=b"not zlib", length=8), N_STAGES)


@pytest.mark.parametrize("field, value", [("stage", 8), ("stage", -1), ("point", 7), ("code", 1),
                                          ("source", -1), ("frame", -5), ("ts", 0), ("frame", 1 << 50)])
def test_rejects_impossible_events(field, value):
    ev = events(4)
    ev[field][2] = value
    with pytest.raises(ProtocolError, match="event 2 invalid"):
        decode_batch(encode_batch(RUN, 1, ev), N_STAGES)


def test_every_drop_reason_passes_the_wire_and_no_other():
    """``stopped`` (a live run's queued frames, dropped at its stop) is one of the closed set."""
    ev = events(len(DROP_REASONS) + 1)
    ev["point"], ev["code"] = DROP, [*DROP_REASONS, 0]
    assert ev["code"][STOPPED] == STOPPED and DROP_REASONS[STOPPED] == "stopped"
    assert np.array_equal(decode_batch(encode_batch(RUN, 1, ev), N_STAGES).events, ev)
    ev["code"][2] = max(DROP_REASONS) + 1
    with pytest.raises(ProtocolError, match="event 2 invalid"):
        decode_batch(encode_batch(RUN, 1, ev), N_STAGES)


def test_every_point_and_code_is_judged_as_the_event_model_says():
    """Every (point, code) of the wire's bytes, looked up in one table: a ready event's code is its
    group (any but 0), a drop's a reason, a fact's a kind, a link's and its key's which way it
    crossed; every other point carries 0. A code read wider than a byte (a trace file's column) is
    judged by its value, never wrapped into range."""
    point = np.repeat(np.arange(-128, 128), 256).astype(np.int8)
    code = np.tile(np.arange(-128, 128), 256).astype(np.int8)
    p, c = point.astype(int), code.astype(int)
    allowed = np.where(p == READY, c != 0, np.where(p == DROP, np.isin(c, list(DROP_REASONS)),
                       np.where(p == FACT, np.isin(c, list(FACT_KINDS)),
                                np.where((p == LINK) | (p == KEY), np.isin(c, list(LINK_KINDS)), c == 0))))
    in_range = (p >= 0) & (p < len(POINT_NAMES))
    assert np.array_equal(codes_valid(point, code)[in_range], allowed[in_range])
    assert not codes_valid(point, code)[~in_range].any()
    wide_point, wide_code = np.array([DROP, FACT, 0, READY, READY]), np.array([1 + 256, 1 + 256, 256, 300, 0])
    assert codes_valid(wide_point, wide_code).tolist() == [False, False, False, True, False]


def test_random_mutations_raise_only_protocol_errors():
    rng = np.random.default_rng(0)
    good = encode_batch(RUN, 3, events(20))
    zgood = encode_batch(RUN, 3, events(20), compress=True)
    accepted = 0
    for i in range(20000):
        base = bytearray(good if i % 2 else zgood)
        kind = i % 4
        if kind == 0:
            data = rng.bytes(int(rng.integers(0, 200)))
        elif kind == 1:
            data = bytes(base[:int(rng.integers(0, len(base)))])
        else:
            for _ in range(int(rng.integers(1, 6))):
                base[int(rng.integers(0, len(base)))] = int(rng.integers(0, 256))
            data = bytes(base)
        try:
            b = decode_batch(data, N_STAGES)
        except ProtocolError:
            continue
        accepted += 1
        assert len(b.events) and (b.events["stage"] < N_STAGES).all() and (b.events["point"] <= 2).all()
    assert accepted < 20000 * 0.6  # most mutations must be caught


def hello(**over) -> dict:
    d = {"proto": 2, "run": RUN, "header": header_for("n1", 2).to_dict(), "lost": 0, "ptp": {"state": "locked"}}
    d.update(over)
    return d


def test_hello():
    h = decode_hello(hello(), "n1")
    assert h.run == RUN and h.header.stages[:2] == ["src0", "src1"] and h.ptp == {"state": "locked"}
    assert h.spooled is False and h.spool is None


def test_a_drained_runs_hello_and_a_nodes_spool_facts():
    h = decode_hello(hello(spooled=True, spool={"bytes": 5000, "oldest_ns": 1_700_000_000_000_000_000}), "n1")
    assert h.spooled is True and h.spool == {"bytes": 5000, "oldest_ns": 1_700_000_000_000_000_000}
    assert decode_hello(hello(spool={"bytes": 0, "oldest_ns": None}), "n1").spool == {"bytes": 0, "oldest_ns": None}
    # Facts it cannot read are dropped, not the connection: they only inform.
    for bad in ("lots", {"bytes": -1}, {"bytes": "5"}, {"bytes": 1e400}, {"oldest_ns": 5}, [1, 2]):
        assert decode_hello(hello(spool=bad), "n1").spool is None, bad
    assert decode_hello(hello(spool={"bytes": 7, "oldest_ns": -3}), "n1").spool == {"bytes": 7, "oldest_ns": None}
    assert decode_clock({"samples": [], "spool": {"bytes": 9, "oldest_ns": 11}}).spool == {"bytes": 9, "oldest_ns": 11}
    with pytest.raises(ProtocolError, match="hello.spooled must be true or false"):
        decode_hello(hello(spooled="yes"), "n1")


@pytest.mark.parametrize("data, message", [
    ([], "must be an object"),
    (hello(proto=1), "unsupported protocol version 1"),
    (hello(proto="2"), "proto must be an integer"),
    (hello(run="zz"), "run must be a UUID"),
    (hello(lost=-1), "lost must be an integer"),
    (hello(lost=True), "lost must be an integer"),
    (hello(header={**header_for("n1", 2).to_dict(), "stages": []}), "stages"),
    (hello(header={**header_for("n1", 2).to_dict(), "stages": [1, 2]}), "stage name"),
    (hello(header={**header_for("n1", 2).to_dict(), "stages": ["x"] * 300}), "stages"),
    (hello(header={**header_for("n1", 2).to_dict(), "sources": {"a": "b"}}), "source ids"),
    (hello(header=header_for("other", 2).to_dict()), "names node 'other'"),
    (hello(header="x"), "header must be an object"),
    (hello(header={**header_for("n1", 2).to_dict(), "kinds": {"nosuchstage": "infer"}}), "kinds must map"),
    (hello(header={**header_for("n1", 2).to_dict(), "kinds": {"mux": 3}}), "kinds must map"),
    (hello(header={**header_for("n1", 2).to_dict(), "kinds": []}), "kinds must be an object"),
])
def test_hello_rejects(data, message):
    with pytest.raises(ProtocolError, match=message):
        decode_hello(data, "n1")


def test_hello_beyond_the_relays_limits_names_the_limit():
    header = {**header_for("n1", 2).to_dict(), "kinds": {}}
    decode_hello(hello(header={**header, "stages": ["x" * 100] * 64}), "n1", max_stages=64, max_name=100)
    with pytest.raises(LimitExceeded, match=r"65 stages, more than this relay takes \(64: --limit stages=N\)") as e:
        decode_hello(hello(header={**header, "stages": [f"s{i}" for i in range(65)]}), "n1", max_stages=64)
    assert e.value.limit == "stages"
    with pytest.raises(LimitExceeded, match=r"stage name has 101 characters.*--limit name_chars=N") as e:
        decode_hello(hello(header={**header, "stages": ["x" * 101]}), "n1", max_name=100)
    assert e.value.limit == "name_chars"
    with pytest.raises(LimitExceeded, match="hello.header.node has 3 characters"):
        decode_hello(hello(header={**header, "node": "abc", "stages": ["a"]}), max_name=2)
    with pytest.raises(ProtocolError, match="1..256 names"):  # the protocol's bound whatever the relay's
        decode_hello(hello(header={**header, "stages": ["x"] * 300}), "n1", max_stages=1000)


def test_clock_and_end_messages():
    r = decode_clock({"samples": [[1, 5, 6, 10]], "lost": 3, "ptp": {"state": "bogus", "master_offset_ns": 1e400}})
    assert r.samples == [(1, 5, 6, 10)] and r.lost == 3 and r.ptp == {"state": "unavailable"}
    for bad in ({"samples": [[1, 2, 3]]}, {"samples": [[4, 5, 6, 1]]}, {"samples": "x"},
                {"samples": [[1, 2, 3, 4]] * 100}, {"samples": [[1.5, 2, 3, 4]]}):
        with pytest.raises(ProtocolError):
            decode_clock(bad)
    assert r.via == "websocket" and decode_clock({"samples": [], "via": "udp"}).via == "udp"
    for via in ("tcp", ["udp"], "udp" * 100):
        with pytest.raises(ProtocolError, match="clock.via must be one of websocket, udp"):
            decode_clock({"via": via})
    assert decode_end({"events": 5, "dropped": 1, "lost": 2}) == (5, 1, 2, None)
    assert decode_end({"events": 5, "dropped": 1, "lost": 2, "ended_ns": 7}) == (5, 1, 2, 7)
    with pytest.raises(ProtocolError):
        decode_end({"events": "5"})
    with pytest.raises(ProtocolError, match="end.ended_ns"):
        decode_end({"events": 5, "ended_ns": -1})


def test_ptp_sanitized():
    assert sanitize_ptp(None) == {"state": "unavailable"}
    got = sanitize_ptp({"state": "locked", "master_offset_ns": -12, "gm_present": True, "gm_identity": "a.b.c",
                        "evil": {"x": 1}})
    assert got == {"state": "locked", "master_offset_ns": -12, "gm_present": True, "gm_identity": "a.b.c"}
    full = {"state": "lost", "reason": "lost a.b.c:\tgrandmaster gone", "port_state": "MASTER", "timestamping": "software",
            "interface": "veth1", "system_clock": {"synced": False, "by": "ptp4l", "follows_ptp": True, "maxerror_us": 16e6,
                                                   "esterror_us": 5, "freq_ppm": -1.5, "detail": "x" * 300, "pid": 3}}
    got = sanitize_ptp(full)
    assert got["reason"] == "lost a.b.c: grandmaster gone" and got["port_state"] == "MASTER" and got["state"] == "lost"
    assert got["system_clock"] == {"synced": False, "by": "ptp4l", "follows_ptp": True, "maxerror_us": 16_000_000,
                                   "esterror_us": 5, "freq_ppm": -1.5, "detail": "x" * 200}
    assert sanitize_ptp({"state": "locked", "timestamping": "magic", "system_clock": {"by": "me", "synced": 1}}) == {
        "state": "locked", "system_clock": {"synced": False, "follows_ptp": False, "by": None}}


def test_header_layout():
    assert HEADER_SIZE == 40 and EVENT_DTYPE.itemsize == 24
    assert struct.calcsize("<4sBBH16sQII") == HEADER_SIZE
