"""The compiled delay series (model/c/stats.c) against numpy's, their reference: series gathered from
frames' values (``series_of``) equal to the bit, dict order included, on real traces and on values made
to take every path (NaN anywhere, gaps from every previous stage, no service times, busy times past
2^53 ns); every figure of ``summarize`` equal to the bit, on the series of real traces, on inputs made
to take every path of the selection (duplicates, sorted, reversed, constant, a sequence that defeats
its pivots, NaN, infinities), and through the relay's whole-run series (``RunValues``), whose new
values the core sorts in between two summaries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dcuscope.model import compiled
from dcuscope.model.delays import (NS_PER_MS, STAGE_COLUMNS, FrameValues, Series, delay_stats, frame_delays,
                                   frame_values, series, series_of, series_of_numpy, summaries, summarize,
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


def same_series(a: Series, b: Series) -> bool:
    """Equal to the bit, every dict in the same order."""
    def bits(x: np.ndarray) -> tuple:
        return x.dtype.str, x.shape, x.tobytes()
    dicts = ("stages", "gaps", "service", "wait")
    return (all(list(getattr(a, d)) == list(getattr(b, d)) for d in dicts)
            and all(bits(getattr(a, d)[k]) == bits(getattr(b, d)[k]) for d in dicts for k in getattr(a, d))
            and bits(a.frame) == bits(b.frame) and bits(a.glass) == bits(b.glass)
            and list(a.busy.items()) == list(b.busy.items()) and all(type(v) is int for v in a.busy.values())
            and (a.span_ns, a.threads) == (b.span_ns, b.threads))


def made_values(rng, n: int, s: int, nan: float, big: bool = False) -> FrameValues:
    """Values of n frames through s stages, NaN at a rate ``nan`` anywhere, each gap from any stage before."""
    def column() -> np.ndarray:
        v = rng.exponential(3e6, (n, s)) * (1e9 if big else 1)
        v[rng.random((n, s)) < nan] = np.nan
        return v
    prev = np.where(rng.random((n, s)) < 0.2, -1, rng.integers(0, s, (n, s))).astype(np.int16)
    glass = rng.exponential(5e7, n)
    glass[rng.random(n) < nan] = np.nan
    origin = rng.integers(0, 10**12, n)
    return FrameValues({k: column() for k in STAGE_COLUMNS}, prev=prev, first=rng.random((n, s)) < 0.6,
                       frame=rng.exponential(4e7, n), glass=glass, origin=origin,
                       end=origin + rng.integers(0, 10**8, n))


def test_series_gathered_by_the_core_are_numpys_to_the_bit(core, real_traces):
    for name in ("tee", "two"):
        trace = real_traces[name]
        fd = frame_delays(frame_table(trace.header, trace.events))
        values, stages = frame_values(fd), fd.table.stages
        got = series_of(values, stages, fd.chains.has_exit, {stages[0]: 3})
        assert same_series(got, series_of_numpy(values, stages, fd.chains.has_exit, {stages[0]: 3})), name
        assert got.gaps and (name == "tee" or got.service), name
    rng = np.random.default_rng(11)
    for n, s, nan in ((0, 3, 0.0), (1, 1, 0.0), (5, 2, 0.5), (300, 8, 0.1), (1000, 5, 0.0), (200, 4, 1.0),
                      (129, 12, 0.3), (2000, 3, 0.02)):
        values = made_values(rng, n, s, nan, big=n == 129)
        stages = [f"s{k}" for k in range(s)]
        for has_exit in (np.ones(s, bool), rng.random(s) < 0.5, np.zeros(s, bool)):
            valid = FrameValues(values.per_stage, prev=np.where(np.isnan(values.per_stage["gap"]), -1, np.maximum(values.prev, 0)),
                                first=values.first, frame=values.frame, glass=values.glass, origin=values.origin,
                                end=values.end)  # the judge's: a gap always has its previous stage
            assert same_series(series_of(valid, stages, has_exit), series_of_numpy(valid, stages, has_exit)), (n, s, nan)
    big = made_values(rng, 129, 12, 0.0, big=True)
    assert max(series_of(big, [f"s{k}" for k in range(12)], np.ones(12, bool)).busy.values()) > 2**53


def test_the_relays_window_statistics_are_the_same_with_series_gathered_by_numpy(core, real_traces, monkeypatch):
    from dcuscope.model import delays

    trace = real_traces["two"]
    fd = frame_delays(frame_table(trace.header, trace.events))
    with_core = delay_stats(fd, trace.header.sources)
    monkeypatch.setattr(delays, "series_of", series_of_numpy)
    assert repr(delay_stats(fd, trace.header.sources)) == repr(with_core)


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
