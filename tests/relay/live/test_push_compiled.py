"""The compiled push (model/c/push.c) against numpy's ``framepack.corrected``, its reference: the same
columns, to the ns and the bit, for a live run's shown frames of real traces and for random columns
under random clock corrections (several segments, drift, growth, missing times)."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.model import compiled
from dcuscope.relay.clock.correction import NO_CORRECTION, Correction, Segment
from dcuscope.relay.live import framepack
from dcuscope.relay.live.run import LiveRun


@pytest.fixture(scope="module")
def core():
    loaded = compiled.load()
    assert loaded is not None, compiled.unavailable_reason()
    return loaded


def both(ints, floats, corr, stages):
    fast = framepack.corrected(ints, floats, corr, stages)
    slow = framepack.corrected_numpy(ints, floats, corr, stages)
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_array_equal(fast[1], slow[1])
    return fast


def corrections(rng, t0: int) -> list[Correction]:
    out = [NO_CORRECTION, Correction("estimate", "one", (Segment(0, t0, 37_000_123, 20, 16_000, 500),), 7)]
    for _ in range(6):
        n = int(rng.integers(1, 5))
        starts = np.sort(rng.integers(t0 - 10**9, t0 + 10**10, n))
        out.append(Correction("estimate", "random", tuple(
            Segment(int(f), int(f + rng.integers(-10**9, 10**9)), int(rng.integers(-10**9, 10**9)),
                    int(rng.integers(-100_000, 100_000)), int(rng.integers(0, 10**6)), int(rng.integers(0, 5000)))
            for f in starts), int(rng.integers(0, 1000))))
    return out


@pytest.mark.parametrize("name", ["tee", "two"])
def test_a_live_runs_pushed_frames_of_real_traces_alike(core, real_traces, name):
    trace = real_traces[name]
    run = LiveRun(trace.header)
    for at in range(0, len(trace.events), 150):
        run.add(trace.events[at:at + 150])
        run.maintain()
    ints, floats = run.recent_columns(0, 500)
    assert ints.shape[1] > 100 and ints.flags.f_contiguous
    rng = np.random.default_rng(3)
    for corr in corrections(rng, int(trace.events["ts"].min())):
        both(ints, floats, corr, len(trace.header.stages))


def test_random_columns_under_random_corrections_alike(core):
    rng = np.random.default_rng(4)
    t0 = 1_700_000_000_000_000_000
    for _ in range(60):
        stages, k = int(rng.integers(1, 9)), int(rng.integers(0, 40))
        ints = t0 + rng.integers(0, 10**10, (k, framepack.int_rows(stages)))
        ints[rng.random(ints.shape) < 0.2] = -1
        floats = rng.normal(1e6, 1e6, (k, framepack.float_rows(stages)))
        floats[rng.random(floats.shape) < 0.2] = np.nan
        for corr in corrections(rng, t0)[::3]:
            both(ints.T, floats.T, corr, stages)  # kept a frame a row, as the engine keeps them
    c_ordered = np.ascontiguousarray(ints.T)
    assert not c_ordered.flags.f_contiguous or k <= 1  # numpy's path takes what the compiled one cannot
    both(c_ordered, np.ascontiguousarray(floats.T), corrections(rng, t0)[1], stages)
