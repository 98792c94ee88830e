"""Whole-run values in bounded memory: exact while small, a log histogram beyond.

A relay may watch many nodes for days; keeping every frame's delays for whole-run percentiles
would grow without bound (13 values a frame: ~270 MB an hour for one DCU at 360 frames/s).

- :class:`RunValues` keeps the values themselves up to ``exact_limit``, so statistics of
  runs of that size are exactly ``model.delays.summarize``'s. They are kept sorted (the
  values finalised since the last summary are merged in when the next is asked, once, not at
  every finalisation), with the sum of their nanoseconds: the relay asks for a run's statistics
  every second while a page shows it, and a
  percentile is then two lookups in the values plus a merge of the few open frames' ones,
  where selecting it afresh among all of them (``np.percentile``) cost most of a summary. Past it, the values move into
  a histogram with logarithmic buckets (as DDSketch): count, mean and max stay exact, and
  each percentile is within ``RELATIVE_ERROR`` of the exact one. Only the buckets that hold
  values are kept (10 bytes each: ~1 KB for delays spanning a decade, 32 KB at most).
- :class:`OriginSpans` keeps, per source, what frames/s needs: count, first and last origin.
"""

from __future__ import annotations

import math

import numpy as np

from dcuscope.model import compiled as compiled_core
from dcuscope.model.delays import NS_PER_MS, PERCENTILES, linear_percentiles, summarize, summary_of
from dcuscope.relay.rollup.sketch import ALPHA, GAMMA, LOG_GAMMA

RELATIVE_ERROR = ALPHA
"""Largest relative error of a percentile once a series is past its exact limit: the rollups' (the
same buckets' width, :mod:`dcuscope.relay.rollup.sketch`)."""
_SMALLEST = 1e-6  # ms: |values| below this count as zero
_LARGEST = 1e8  # ms: a bigger value lands in the last bucket (its max is still exact)
_BUCKETS = math.ceil(math.log(_LARGEST / _SMALLEST) / LOG_GAMMA) + 1


class RunValues:
    """One series (a stage's delays, a gap, the frame delay), in ms."""

    def __init__(self, exact_limit: int) -> None:
        self.exact_limit = exact_limit
        self._exact = np.zeros(64)
        self._n_exact = 0
        """``_exact[:_n_exact]``: the values; ascending up to ``_n_sorted``, then as they came."""
        self._n_sorted = 0
        self._exact_ns = 0.0
        """Their sum in whole nanoseconds (exact: integers, see ``summarize``)."""
        self._nan = False
        """A NaN among them: kept out of the sorted path (``summarize`` says what it makes of it)."""
        # Occupied buckets, ascending: -(i + 1) for negative values in bucket i, 0 for (near)
        # zeros, i + 1 for positive ones; that order is the values' order.
        self._hist: np.ndarray | None = None
        self._counts = np.zeros(0, np.int64)
        self._count = 0
        self._sum = 0.0
        self._max = -math.inf

    @property
    def exact(self) -> bool:
        return self._hist is None

    @property
    def count(self) -> int:
        return self._count + self._n_exact

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays held (the exact values' buffer or the histogram)."""
        return self._exact.nbytes + (self._hist.nbytes + self._counts.nbytes if self._hist is not None else 0)

    def lower_limit(self, exact_limit: int) -> None:
        """Keep at most ``exact_limit`` values exactly from now on (a run's share of memory
        shrank): values beyond it move into the histogram now, and the buffer shrinks to fit."""
        if exact_limit >= self.exact_limit:
            return
        self.exact_limit = exact_limit
        if self._hist is None and self._n_exact > exact_limit:
            self._spill()
        elif len(self._exact) > max(64, exact_limit):
            self._exact = self._exact[:max(64, self._n_exact)].copy()

    def _spill(self) -> None:
        self._hist = np.zeros(0, np.int16)
        self._add(self._exact[:self._n_exact])
        self._exact, self._n_exact, self._n_sorted, self._exact_ns = np.zeros(0), 0, 0, 0.0

    def extend(self, values: np.ndarray) -> None:
        values = np.asarray(values, np.float64).ravel()
        if not len(values):
            return
        if self._hist is None and self._n_exact + len(values) <= self.exact_limit:
            if self._n_exact + len(values) > len(self._exact):
                bigger = np.zeros(min(self.exact_limit, max(2 * len(self._exact), self._n_exact + len(values))))
                bigger[:self._n_exact] = self._exact[:self._n_exact]
                self._exact = bigger
            # Appended as they come: sorted in only when a summary is asked (:meth:`_sort`), so a
            # run whose statistics nobody reads costs no merge, and one shown merges once a summary.
            n = self._n_exact
            if np.isnan(values).any():
                self._nan = True
            self._exact[n:n + len(values)] = values
            self._n_exact += len(values)
            self._exact_ns += float(np.rint(values * NS_PER_MS).sum())
            return
        if self._hist is None:
            self._spill()
        self._add(values)

    def summary(self, extra: np.ndarray | None = None) -> dict:
        """``summarize`` of these values and ``extra`` (frames not yet final), shaped as it."""
        extra = np.zeros(0) if extra is None else np.asarray(extra, np.float64).ravel()
        if self._hist is None:
            if self._nan or np.isnan(extra).any() or self._n_exact + len(extra) == 0:
                return summarize(np.concatenate([self._exact[:self._n_exact], extra]))
            self._sort()
            return self._sorted_summary(np.sort(extra))
        keys, counts = _merge(self._hist, self._counts, extra)
        count = self._count + len(extra)
        top = max(self._max, float(extra.max()) if len(extra) else -math.inf)
        p50, p95, p99 = (min(top, _quantile(keys, counts, count, p / 100)) for p in PERCENTILES)
        return {"count": count, "mean_ms": (self._sum + float(extra.sum())) / count,
                "p50_ms": p50, "p95_ms": p95, "p99_ms": p99, "max_ms": top}

    @staticmethod
    def summaries(asked: list[tuple["RunValues", np.ndarray]]) -> list[dict]:
        """:meth:`summary` of each (series, extra): the exact ones without NaN, the usual case, in one
        call of the compiled core where it loads (their new values sorted in there too), the others
        one by one."""
        core = compiled_core.load()
        out: list[dict | None] = [None] * len(asked)
        together = []
        for i, (series, extra) in enumerate(asked):
            extra = np.asarray(extra, np.float64).ravel()
            if series.count + len(extra) == 0:
                out[i] = summary_of(0, 0, 0, 0, 0, 0)
            elif core is not None and series._hist is None and not series._nan and not np.isnan(extra).any():
                together.append((i, series, extra))
            else:
                out[i] = series.summary(extra)
        if together:
            figures = core.summarize_held([s._exact for _, s, _ in together], [s._n_sorted for _, s, _ in together],
                                          [s._n_exact for _, s, _ in together], [s._exact_ns for _, s, _ in together],
                                          [e for _, _, e in together])
            for (i, series, _), row in zip(together, figures.tolist()):
                series._n_sorted = series._n_exact
                out[i] = summary_of(*row)
        return out

    def _sort(self) -> None:
        """Merge the values appended since the last summary into the sorted ones: one pass over them."""
        n, m = self._n_sorted, self._n_exact
        if m == n:
            return
        new = np.sort(self._exact[n:m])
        at = np.searchsorted(self._exact[:n], new)
        if len(at) and at[0] < n:
            self._exact[:m] = np.insert(self._exact[:n], at, new)
        else:  # all at or past the largest: in place
            self._exact[n:m] = new
        self._n_sorted = m

    def _sorted_summary(self, extra: np.ndarray) -> dict:
        """``summarize`` of the (sorted) exact values and ``extra`` (sorted), to its last bit
        but for the percentiles' interpolation, done as numpy's "linear" method does it."""
        held = self._exact[:self._n_exact]
        count = len(held) + len(extra)
        total_ns = self._exact_ns + float(np.rint(extra * NS_PER_MS).sum())
        p50, p95, p99 = linear_percentiles(count, lambda ranks: _merged_at(held, extra, ranks))
        top = max(float(held[-1]) if len(held) else -math.inf, float(extra[-1]) if len(extra) else -math.inf)
        return {"count": count, "mean_ms": total_ns / count / NS_PER_MS, "p50_ms": p50, "p95_ms": p95,
                "p99_ms": p99, "max_ms": top}

    def _add(self, values: np.ndarray) -> None:
        if not len(values):
            return
        self._hist, self._counts = _merge(self._hist, self._counts, values)
        self._count += len(values)
        self._sum += float(values.sum())
        self._max = max(self._max, float(values.max()))


def _merged_at(held: np.ndarray, extra: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """The values at ``ranks`` of ``held`` and ``extra`` (both ascending) merged as ``np.insert(held,
    np.searchsorted(held, extra), extra)`` merges them, without building it (a copy of every held
    value, up to ``exact_limit``, for six lookups)."""
    if not len(extra):
        return held[ranks]
    placed = np.searchsorted(held, extra) + np.arange(len(extra))  # each extra value's rank, ascending
    k = np.searchsorted(placed, ranks)  # extra values ranked before each rank
    hit = k < len(placed)
    hit[hit] = placed[k[hit]] == ranks[hit]
    out = np.empty(len(ranks))
    out[hit] = extra[k[hit]]
    out[~hit] = held[ranks[~hit] - k[~hit]]
    return out


def _merge(keys: np.ndarray, counts: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The buckets ``keys`` with ``counts``, and ``values`` added to them."""
    if not len(values):
        return keys, counts
    magnitude = np.abs(values)
    index = np.ceil(np.log(np.maximum(magnitude, _SMALLEST) / _SMALLEST) / LOG_GAMMA).astype(np.int64)
    np.clip(index, 0, _BUCKETS - 1, out=index)
    signed = np.where(magnitude < _SMALLEST, 0, np.where(values > 0, index + 1, -(index + 1)))
    new, n = np.unique(signed, return_counts=True)
    merged, at = np.unique(np.concatenate([keys, new]), return_inverse=True)
    total = np.zeros(len(merged), np.int64)
    np.add.at(total, at, np.concatenate([counts, n]))
    return merged.astype(np.int16), total


def _quantile(keys: np.ndarray, counts: np.ndarray, count: int, q: float) -> float:
    """The value at rank q * (count - 1), from most negative to most positive."""
    rank = q * (count - 1)
    key = int(keys[min(len(keys) - 1, int(np.searchsorted(np.cumsum(counts), math.floor(rank) + 1)))])
    if key == 0:
        return 0.0
    return _representative(key - 1) if key > 0 else -_representative(-key - 1)


def _representative(index: int) -> float:
    # Bucket i holds (SMALLEST * gamma^(i-1), SMALLEST * gamma^i]; this point is within the
    # relative error of every value in it.
    return _SMALLEST * 2 * GAMMA ** index / (GAMMA + 1)


class OriginSpans:
    """Per source: complete frames counted, earliest and latest origin (ns)."""

    def __init__(self) -> None:
        self.count: dict[int, int] = {}
        self.first: dict[int, int] = {}
        self.last: dict[int, int] = {}

    def extend(self, origins: np.ndarray, sources: np.ndarray) -> None:
        for sid in np.unique(sources).tolist():
            o = origins[sources == sid]
            self.count[sid] = self.count.get(sid, 0) + len(o)
            self.first[sid] = min(self.first.get(sid, int(o.min())), int(o.min()))
            self.last[sid] = max(self.last.get(sid, int(o.max())), int(o.max()))

    def fps(self, ids: list[int], origins: np.ndarray, sources: np.ndarray) -> dict[str, float]:
        """model.delays.fps_by_source's rule, (n - 1) / span, over these and ``origins``."""
        out = {}
        for sid in ids:
            o = origins[sources == sid]
            n = self.count.get(sid, 0) + len(o)
            lows, highs = ([int(o.min())], [int(o.max())]) if len(o) else ([], [])
            if sid in self.first:
                lows.append(self.first[sid])
                highs.append(self.last[sid])
            span = max(highs) - min(lows) if lows else 0
            out[str(sid)] = (n - 1) * 1e9 / span if n >= 2 and span > 0 else 0.0
        return out
