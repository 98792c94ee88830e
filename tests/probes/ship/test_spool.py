"""The node's spool on disk: records with length and checksum, a torn or corrupt tail cut and
counted, segments deleted once acknowledged, the folder's byte bound (the oldest dropped and
counted), owner-only files, and an outbox whose memory bound reads batches back from disk."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from dcuscope.probes.ship.outbox import Outbox
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.probes.ship.spool import Spool
from dcuscope.probes.ship.spoolfile import SpoolError, scan
from dcuscope.protocol.wire import decode_batch

T0 = 1_700_000_000_000_000_000


def spool_run(spool: Spool, run: str = "a" * 32, batches: int = 10, size: int = 1000):
    rs = spool.create_run(run, "N", header_for("N", 1).to_dict(), ["http://127.0.0.1:1"])
    payloads = {}
    for seq in range(batches):
        payloads[seq] = os.urandom(size)
        assert rs.append(seq, 7, payloads[seq]) == []
    return rs, payloads


def test_a_spooled_run_reads_back_as_written_and_its_files_are_its_owners_only(tmp_path):
    spool = Spool(tmp_path / "spool", 64 << 20)
    rs, payloads = spool_run(spool)
    rs.set_secret("ab" * 16)
    rs.close(end_heard=False)
    assert stat.S_IMODE((tmp_path / "spool").stat().st_mode) == 0o700
    folder = tmp_path / "spool" / rs.run
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert {p.name: stat.S_IMODE(p.stat().st_mode) for p in folder.iterdir()} == {
        "run.json": 0o600, "lock": 0o600, "000000000000.seg": 0o600}
    again = spool.open_run(rs.run)
    assert again.meta["secret"] == "ab" * 16 and again.torn_bytes == 0
    assert again.pending() == [(seq, 7) for seq in range(10)]
    assert all(again.read(seq) == payloads[seq] for seq in payloads)
    assert spool.open_run(rs.run) is None  # held: one shipper at a time
    (listed,) = spool.runs()
    assert (listed.run, listed.node, listed.batches, listed.events, listed.in_use) == (rs.run, "N", 10, 70, True)
    again.close(end_heard=False)


@pytest.mark.parametrize("damage", ["torn", "corrupt", "no head"])
def test_a_torn_or_corrupt_tail_is_cut_and_counted_and_the_rest_kept(tmp_path, damage):
    spool = Spool(tmp_path, 64 << 20)
    rs, payloads = spool_run(spool)
    rs.close(end_heard=False)
    (seg,) = (tmp_path / rs.run).glob("*.seg")
    size = seg.stat().st_size
    data = bytearray(seg.read_bytes())
    if damage == "torn":  # a crash in the middle of the last record's write
        seg.write_bytes(bytes(data[:size - 500]))
        kept, cut = 9, 1020 - 500
    elif damage == "corrupt":  # a bit flipped in the 7th record's payload: it and all after it go
        data[16 + 6 * 1020 + 20 + 3] ^= 0x40
        seg.write_bytes(bytes(data))
        kept, cut = 6, 4 * 1020
    else:
        data[0:8] = b"NOTSPOOL"
        seg.write_bytes(bytes(data))
        kept, cut = 0, size
    again = spool.open_run(rs.run)
    assert again.torn_bytes == cut
    assert again.pending() == [(seq, 7) for seq in range(kept)]
    assert all(again.read(seq) == payloads[seq] for seq in range(kept))
    if kept:
        assert scan(seg)[1] == 0 and seg.stat().st_size == 16 + kept * 1020  # truncated for good
    again.close(end_heard=False)


def test_acknowledged_segments_are_deleted_and_a_finished_run_leaves_nothing(tmp_path):
    spool = Spool(tmp_path, 1 << 20)  # segments of 128 KiB
    rs, _ = spool_run(spool, batches=300, size=1000)
    segments = sorted((tmp_path / rs.run).glob("*.seg"))
    assert len(segments) == 3
    first = len(scan(segments[0])[0])
    for seq in range(200):
        rs.acked(seq)
    assert not segments[0].exists() and segments[2].exists()
    assert rs.meta["acked_events"] == 7 * first  # counted for a drain after a crash
    for seq in range(200, 300):
        rs.acked(seq)
    assert rs.close(end_heard=False) is False and (tmp_path / rs.run / "run.json").exists()  # the end unheard
    again = spool.open_run(rs.run)
    assert again.pending() == [] and again.close(end_heard=True) is True
    assert not (tmp_path / rs.run).exists()


def test_beyond_its_bound_the_oldest_batches_go_first_and_are_counted_lost(tmp_path):
    spool = Spool(tmp_path, 1 << 20)
    old, _ = spool_run(spool, "b" * 32, batches=600, size=1000)  # ~600 KB in 5 segments
    old.close(end_heard=False)
    new, _ = spool_run(spool, "c" * 32, batches=500, size=1000)  # 500 KB more: the old run's first segments go
    lost_old = spool.open_run("b" * 32)
    assert lost_old.meta["lost"] > 0 and lost_old.meta["lost"] == 7 * (600 - len(lost_old.pending()))
    assert lost_old.pending()[-1] == (599, 7)  # the newest kept
    lost_old.close(end_heard=False)
    assert spool.bytes() <= 1 << 20
    # Only this run left to drop from: its own oldest go, said to the caller (the relay is told).
    spool.drop("b" * 32)
    dropped = []
    for seq in range(500, 1700):
        dropped += new.append(seq, 7, os.urandom(1000))
    assert dropped and dropped[0] == (0, 7) and [s for s, _ in dropped] == list(range(len(dropped)))
    assert new.meta["lost"] == 7 * len(dropped) and spool.bytes() <= 1 << 20
    new.close(end_heard=False)


def test_a_folder_that_cannot_be_used_is_one_clear_error(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(SpoolError, match=r"the spool folder .*file/spool cannot be used: Not a directory"):
        Spool(tmp_path / "file" / "spool")


def test_an_outbox_with_a_spool_reads_back_from_disk_what_its_memory_bound_let_go(tmp_path):
    spool = Spool(tmp_path, 64 << 20)
    rs = spool.create_run("d" * 32, "N", header_for("N", 1).to_dict(), [])
    box = Outbox("d" * 32, batch_events=100, max_buffer_events=300, spool=rs)
    events = synth_events(100, 1, 25.0, T0)  # 1,200 events: 12 batches, 3 kept in memory
    for i in range(0, len(events), 100):
        box.put(events[i:i + 100])
        box.cut()
    assert box.lost == 0 and box.unacked_n == len(events) and box.spooled_n == len(events)
    assert sum(1 for data, _ in box.unacked.values() if data is not None) == 3
    got = []
    while box.may_send():
        item = box.take()
        got.append(decode_batch(item[0], len(header_for("N", 1).stages)).events)
    np.testing.assert_array_equal(np.concatenate(got), events)
    for seq in range(12):
        box.ack({"seq": seq, "ok": True})
    assert box.acked == len(events) and box.spooled_n == 0
    rs.close(end_heard=True)
    assert not (tmp_path / ("d" * 32)).exists()
