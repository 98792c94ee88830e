"""Whole-run statistics in bounded memory: exact up to a limit, then within 1 % (count, mean, max exact)."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.model.delays import node_stats, summarize
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.relay.live.run import LiveConfig, LiveRun
from dcuscope.relay.live.values import RELATIVE_ERROR, RunValues
from tests.relay.helpers import assert_stats_equal

T0 = 1_700_000_000_000_000_000


def close(exact: dict, approx: dict) -> None:
    assert approx["count"] == exact["count"]
    assert approx["max_ms"] == exact["max_ms"]
    assert approx["mean_ms"] == pytest.approx(exact["mean_ms"], rel=1e-9, abs=1e-9)
    for key in ("p50_ms", "p95_ms", "p99_ms"):
        assert abs(approx[key] - exact[key]) <= RELATIVE_ERROR * abs(exact[key]) + 1e-6, (key, exact, approx)


def test_below_the_limit_it_is_summarize_itself():
    rng = np.random.default_rng(1)
    values = rng.lognormal(2, 1, 5000)
    series = RunValues(exact_limit=10_000)
    for chunk in np.array_split(values, 7):
        series.extend(chunk)
    extra = rng.lognormal(2, 1, 50)
    assert series.exact and series.summary(extra) == summarize(np.concatenate([values, extra]))


@pytest.mark.parametrize("shape", ["lognormal", "with zeros and negatives", "one value"])
def test_past_the_limit_percentiles_stay_within_one_percent_in_fixed_memory(shape):
    rng = np.random.default_rng(2)
    if shape == "lognormal":
        values = rng.lognormal(3, 1.2, 300_000)  # ms, 0.1 ms .. seconds
    elif shape == "with zeros and negatives":
        values = np.concatenate([rng.normal(0.4, 0.5, 200_000), np.zeros(20_000), rng.lognormal(1, 2, 80_000)])
        rng.shuffle(values)
    else:
        values = np.full(300_000, 33.3)
    series = RunValues(exact_limit=1000)
    for chunk in np.array_split(values, 97):
        series.extend(chunk)
    assert not series.exact
    extra = values[:123] * 1.5
    close(summarize(np.concatenate([values, extra])), series.summary(extra))
    held = sum(a.nbytes for a in vars(series).values() if isinstance(a, np.ndarray))
    series.extend(np.tile(values, 3))
    assert sum(a.nbytes for a in vars(series).values() if isinstance(a, np.ndarray)) == held  # no growth
    close(summarize(np.tile(values, 4)), series.summary())


def test_a_long_run_past_the_limit_agrees_with_node_stats_within_one_percent():
    header = header_for("n", 2)
    events = synth_events(3000, 2, 30.0, T0, drop_rate=0.02, seed=5)
    exact, bounded = LiveRun(header), LiveRun(header, LiveConfig(exact_values=500))
    for i in range(0, len(events), 400):
        for run in (exact, bounded):
            run.add(events[i:i + 400])
            run.maintain()
    want = node_stats(header, events)
    assert_stats_equal(want, {k: v for k, v in exact.run_stats().items() if k != "percentile_error"})
    got = bounded.run_stats()
    assert exact.run_stats()["percentile_error"] == 0.0 and got["percentile_error"] == RELATIVE_ERROR
    assert got["fps"] == want["fps"] and got["frames"] == want["frames"] and got["dropped"] == want["dropped"]
    for group in ("stages", "gaps"):
        assert got[group].keys() == want[group].keys()
        for name in want[group]:
            close(want[group][name], got[group][name])
    close(want["frame"], got["frame"])


def test_a_lowered_limit_spills_into_the_histogram_and_frees_the_buffer():
    rng = np.random.default_rng(3)
    values = rng.lognormal(2, 1, 50_000)
    series = RunValues(exact_limit=100_000)
    series.extend(values)
    assert series.exact and series.nbytes >= 8 * 50_000
    series.lower_limit(60_000)  # still fits: stays exact, the buffer shrinks to what it holds
    assert series.exact and series.summary() == summarize(values) and series.nbytes <= 8 * 50_000
    series.lower_limit(1000)
    assert not series.exact and series.nbytes < 8 * 1000
    close(summarize(values), series.summary())
    series.extend(values[:10])
    close(summarize(np.concatenate([values, values[:10]])), series.summary())


def test_exact_values_kept_sorted_summarize_as_summarize_does_added_in_any_order():
    """The sorted path (merge, two lookups, numpy's linear lerp) gives summarize's figures."""
    rng = np.random.default_rng(7)
    values = RunValues(exact_limit=100_000)
    seen = []
    for size in rng.integers(0, 300, 60):
        batch = np.round(rng.lognormal(1.0, 1.2, size), 6) * rng.choice([1, -1], size, p=[0.95, 0.05])
        values.extend(batch)
        seen.extend(batch.tolist())
        extra = np.round(rng.lognormal(1.0, 1.0, int(rng.integers(0, 40))), 6)
        got, expected = values.summary(extra), summarize(np.concatenate([seen, extra]))
        assert got.keys() == expected.keys()
        for key in expected:
            assert got[key] == expected[key] or abs(got[key] - expected[key]) <= 1e-12 * abs(expected[key]), key


def test_values_finalised_between_summaries_are_merged_in_when_one_is_asked():
    """Finalisation appends; the next summary merges everything appended since the last one
    (several batches, some wholly above every value so far), and is summarize's to the last bit."""
    rng = np.random.default_rng(11)
    values = RunValues(exact_limit=100_000)
    seen = []
    for k in range(80):
        batch = np.round(rng.lognormal(1.0, 1.2, int(rng.integers(0, 200))), 6)
        if k % 9 == 4:
            batch = batch + (max(seen, default=0.0) + 1)  # all past the largest
        values.extend(batch)
        seen.extend(batch.tolist())
        if k % 3 == 2:
            got, expected = values.summary(), summarize(np.asarray(seen))
            assert got.keys() == expected.keys()
            for key in expected:
                assert got[key] == expected[key] or abs(got[key] - expected[key]) <= 1e-12 * abs(expected[key]), key
    assert values.exact and values.count == len(seen)


def test_open_values_equal_to_finalised_ones_and_beyond_both_ends_summarize_as_summarize_does():
    """The percentiles of finalised and open values are read from the two without merging them: ties
    between the two, and open values below or above every finalised one, land at summarize's ranks."""
    rng = np.random.default_rng(3)
    values = RunValues(exact_limit=100_000)
    held = np.round(rng.lognormal(1.0, 1.0, 997), 3)
    values.extend(held)
    for extra in (held[rng.integers(0, len(held), 40)], np.array([-5.0, 0.0, held.min()]),
                  np.array([held.max(), held.max() + 1, 1e6]), np.repeat(np.median(held), 500), np.array([7.0])):
        assert values.summary(extra) == summarize(np.concatenate([held, extra]))
