"""The store writer's rounds: batches queued within a round's wait commit in one transaction and are
told together; a call ends the wait (a hello is not held back for batches)."""

from __future__ import annotations

import asyncio
import time
import uuid

from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.protocol.wire import encode_batch
from dcuscope.relay.store.base import BatchRow
from dcuscope.relay.store.writer import Storage

T0 = 1_700_000_000_000_000_000
WAIT_S = 0.6


def _row(run: str, seq: int) -> BatchRow:
    events = synth_events(4, 1, 25.0, T0 + seq * 1_000_000_000, seed=seq)
    return BatchRow(run, seq, len(events), False, encode_batch(run, seq, events)[40:])


async def _registered(tmp_path) -> tuple[Storage, str]:
    storage = Storage(tmp_path / "relay.db", group_wait_s=WAIT_S)
    storage.start(asyncio.get_running_loop())
    run = uuid.uuid4().hex
    assert await storage.call("own_run", run)
    await storage.call("register_run", run, "a", header_for("a", 1).to_dict(), None, None)
    return storage, run


def test_batches_queued_within_the_wait_commit_together_and_are_told_at_once(tmp_path):
    async def scenario():
        storage, run = await _registered(tmp_path)
        try:
            told: list[tuple[int, bool | None, BaseException | None, int, float]] = []
            loop = asyncio.get_running_loop()
            commits = storage.commits
            started = time.monotonic()
            for seq in range(5):
                storage.queue_batch(_row(run, seq), lambda new, error, seq=seq: told.append(
                    (seq, new, error, storage.commits, time.monotonic())))
                await asyncio.sleep(WAIT_S / 20)
            while len(told) < 5:
                await asyncio.sleep(0.01)
            assert [t[:3] for t in told] == [(seq, True, None) for seq in range(5)]
            # One transaction, its outcomes settled in one call of the event loop (the same commit count).
            assert storage.commits == commits + 1 and {t[3] for t in told} == {commits + 1}
            assert told[0][4] - started >= WAIT_S  # the first waited for the others
            # Queued again: found stored, told False, in a round of its own.
            again = loop.create_future()
            storage.queue_batch(_row(run, 2), lambda new, error: again.set_result((new, error)))
            assert await again == (False, None) and storage.commits == commits + 2
            assert await storage.call("stored_seqs", run) == {0, 1, 2, 3, 4}
        finally:
            storage.stop()

    asyncio.run(scenario())


def test_a_call_ends_the_rounds_wait(tmp_path):
    async def scenario():
        storage, run = await _registered(tmp_path)
        storage.group_wait_s = 30.0  # far longer than the test may take
        try:
            stored = asyncio.get_running_loop().create_future()
            storage.queue_batch(_row(run, 7), lambda new, error: stored.set_result((new, error)))
            await asyncio.sleep(0.05)  # the round waits for more batches
            assert not stored.done()
            # The call ends the wait: the batch commits first, then the call reads it.
            assert await asyncio.wait_for(storage.call("stored_seqs", run), 10) == {7}
            assert await stored == (True, None)
        finally:
            storage.stop()

    asyncio.run(scenario())
