"""The compiled summaries of delay series (model/c/stats.c) against numpy's, their reference: every
figure of ``summarize`` equal to the bit, on the series of real traces, on inputs made to take every
path of the selection (duplicates, sorted, reversed, constant, a sequence that defeats its pivots,
NaN, infinities), and through the relay's whole-run series (``RunValues``), whose new values the
core sorts in between two summaries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dcuscope.model import compiled
from dcuscope.model.delays import (NS_PER_MS, delay_stats, frame_delays, series, summaries, summarize,
                                   summarize_numpy)
from dcuscope.model.frametable import frame_table
from dcuscope.relay.live.values import RunValues


@pytest.fixture(scope="module")
def core() -> compiled.CompiledCore:
    loaded = compiled.load()
    assert loaded is not None, compiled.unavailable_reason()
    return loaded


def same(a: dict, b: dict) -> bool:
    """Equal, NaN equal to NaN, and each figure to the bit (0.0 and -0.0 apart)."""
    def key(v):
        if isinstance(v, float):
            return ("nan",) if math.isnan(v) else (v, math.copysign(1, v))
        return (v, 0)
    return a.keys() == b.keys() and all(key(a[k]) == key(b[k]) for k in a)


def defeats_median_of_three(n: int) -> np.ndarray:
    """Musser's sequence against median-of-3 pivots: quickselect would take n^2 / 4 steps."""
    k = n // 2
    out = np.empty(n)
    for i in range(1, k + 1):
        out[i - 1] = i if i % 2 else k + i - 1
        out[k + i - 1] = 2 * i
    return out


def hostile(rng) -> list[np.ndarray]:
    cases = []
    for n in (0, 1, 2, 3, 4, 5, 7, 8, 9, 16, 17, 100, 101, 999, 4000):
        cases += [rng.exponential(3, n), np.round(rng.normal(5, 2, n), 1), rng.integers(0, 3, n).astype(float),
                  np.full(n, 7.5), np.sort(rng.exponential(3, n)), np.sort(rng.exponential(3, n))[::-1].copy(),
                  np.concatenate([np.arange(n // 2), np.arange(n - n // 2)[::-1]]).astype(float),
                  defeats_median_of_three(n) if n % 2 == 0 else rng.normal(0, 1e9, n)]
    cases += [np.array([1.0, np.nan, 2.0]), np.array([np.inf, 1.0, 2.0]), np.array([-np.inf, np.inf, 3.0]),
              np.array([-0.5, 0.0, 0.5]), np.array([1e300, 1e300]), np.array([5e-7, -5e-7, 1.5e-6])]
    return cases


def test_on_real_traces_every_series_is_summarized_to_numpys_last_bit(core, real_traces):
    for name in ("tee", "two"):
        trace = real_traces[name]
        s = series(frame_delays(frame_table(trace.header, trace.events)))
        arrays = [s.frame, s.glass, *s.stages.values(), *s.service.values(), *s.wait.values(), *s.gaps.values()]
        assert sum(len(a) > 100 for a in arrays) >= 4, name
        got = summaries([a / NS_PER_MS for a in arrays])
        for a, figures in zip(arrays, got):
            assert same(figures, summarize_numpy(a / NS_PER_MS)), (name, figures)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # numpy's, on infinities
def test_every_path_of_the_selection_gives_numpys_figures(core):
    rng = np.random.default_rng(7)
    cases = hostile(rng)
    got = summaries(cases)
    assert len(got) == len(cases)
    for values, figures in zip(cases, got):
        assert same(figures, summarize_numpy(values)), (values[:8], figures)
    # One at a time as in many, and the caller's values untouched (the core reorders its own copy).
    before = [c.copy() for c in cases]
    for values, kept in zip(cases[:40], before):
        assert same(summarize(values), summarize_numpy(values))
        np.testing.assert_array_equal(values, kept)


def test_whole_run_series_equal_their_values_summarized_whatever_comes_between(core):
    """Each RunValues summarized with its open frames' values, many at once, round after round with
    new values between (the core sorts them in): each summary is numpy's of all of its values."""
    rng = np.random.default_rng(3)
    limits = [10_000, 10_000, 10_000, 300]  # the last spills into its histogram: summarized apart, as before
    held = [RunValues(limit) for limit in limits]
    every: list[list[np.ndarray]] = [[] for _ in held]
    for round_ in range(30):
        asked = []
        for k, rv in enumerate(held):
            new = rng.exponential(2 + k, int(rng.integers(0, 60)))
            if k == 1 and round_ == 20:
                new = np.append(new, np.nan)  # a NaN: that series leaves the compiled path
            rv.extend(new)
            every[k].append(new)
            asked.append((rv, rng.exponential(2, int(rng.integers(0, 12)))))
        got = RunValues.summaries(asked)
        for k, ((rv, extra), figures) in enumerate(zip(asked, got)):
            assert same(figures, rv.summary(extra)), (round_, k)
            if rv.exact:
                assert same(figures, summarize_numpy(np.concatenate([*every[k], extra]))), (round_, k)
    assert not held[3].exact and held[0].exact


def test_the_statistics_of_a_trace_are_the_same_without_the_compiled_core(real_traces, monkeypatch):
    trace = real_traces["two"]
    fd = frame_delays(frame_table(trace.header, trace.events))
    with_core = delay_stats(fd, trace.header.sources)
    monkeypatch.setattr(compiled, "load", lambda: None)
    assert repr(delay_stats(fd, trace.header.sources)) == repr(with_core)
