"""Batch sequence numbers seen: the same answers as a set, memory only for the ones out of order."""

from __future__ import annotations

import numpy as np

from dcuscope.relay.live.seqset import SeqSet


def test_behaves_as_a_set_under_resends_gaps_and_floors():
    rng = np.random.default_rng(3)
    seen, plain = SeqSet(), set()
    for _ in range(20_000):
        # Mostly in order, with resends of recent ones, jumps ahead, and the odd floor (the node
        # gave up everything below it).
        seq = max(0, len(plain) + int(rng.integers(-40, 5)))
        if rng.random() < 0.02:
            seen.advance(seq)
            plain.update(range(seq))
        else:
            assert (seq in seen) == (seq in plain)
            seen.add(seq)
            plain.add(seq)
    for seq in range(max(plain) + 10):
        assert (seq in seen) == (seq in plain), seq
    assert len(seen) == len(plain)


def test_an_in_order_run_holds_nothing_individually():
    seen = SeqSet({5, 3, 4, 0, 1, 2})
    assert seen.low == 6 and seen.held == 0
    for seq in range(6, 1_000_000):
        seen.add(seq)
    assert seen.low == 1_000_000 and seen.held == 0 and 999_999 in seen and 1_000_000 not in seen


def test_a_floor_forgets_the_gap_of_batches_that_never_come():
    seen = SeqSet()
    for seq in range(20, 1000):  # 0..19 were evicted by the node
        seen.add(seq)
    assert seen.low == 0 and seen.held == 980
    seen.advance(20)
    assert seen.low == 1000 and seen.held == 0 and 5 in seen and 1000 not in seen
    seen.advance(3)  # an old floor changes nothing
    assert seen.low == 1000
