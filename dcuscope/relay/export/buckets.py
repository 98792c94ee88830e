"""Histograms of many labelled series over one bucket list, fed in bulk with numpy.

What a Prometheus histogram holds: per series the count of values in each bucket, their sum and
their number. Buckets are upper-inclusive (``le``): a value equal to a bound counts in that
bound's bucket; the last bucket (``+Inf``) takes every value above the last bound. A relay
ingests ~1,000 frames/s across ~20 series per node, so values come in arrays, many series at
once (:meth:`Histograms.add`), and cost one ``searchsorted`` and one ``bincount`` per call,
never one Python step per value.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable

import numpy as np


class Histograms:
    """Per key (any hashable: a family and its label values) bucket counts, sum and count."""

    def __init__(self, bounds: Iterable[float]) -> None:
        self.bounds = np.asarray(list(bounds), dtype=np.float64)
        if len(self.bounds) == 0 or np.any(np.diff(self.bounds) <= 0):
            raise ValueError("histogram bounds must be a non-empty, strictly increasing list")
        self._rows: dict[Hashable, int] = {}
        self._counts = np.zeros((0, len(self.bounds) + 1), np.int64)
        self._sums = np.zeros(0, np.float64)

    def __len__(self) -> int:
        return len(self._rows)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._rows

    def add(self, batch: Iterable[tuple[Hashable, np.ndarray]]) -> None:
        """Count the values of each ``(key, values)`` of ``batch`` (NaNs are skipped)."""
        keys, arrays = [], []
        for key, values in batch:
            values = np.asarray(values, dtype=np.float64).ravel()
            values = values[~np.isnan(values)]
            self.ensure(key)
            keys.append(self._rows[key])
            arrays.append(values)
        if not arrays:
            return
        values = np.concatenate(arrays)
        rows = np.repeat(np.asarray(keys, np.int64), [len(a) for a in arrays])
        width = self._counts.shape[1]
        # side="left": the first bound >= the value, so a value on a bound lands in its bucket (le).
        bucket = np.searchsorted(self.bounds, values, side="left")
        n = len(self._rows)
        self._counts += np.bincount(rows * width + bucket, minlength=n * width).reshape(n, width)
        self._sums += np.bincount(rows, weights=values, minlength=n)

    def ensure(self, key: Hashable) -> None:
        """Hold a series for ``key`` (empty until values come)."""
        if key in self._rows:
            return
        self._rows[key] = len(self._rows)
        self._counts = np.concatenate([self._counts, np.zeros((1, self._counts.shape[1]), np.int64)])
        self._sums = np.concatenate([self._sums, np.zeros(1)])

    def snapshot(self) -> list[tuple[Hashable, np.ndarray, float]]:
        """Per key (in the order first seen): cumulative bucket counts (the last is the count of
        all values, ``+Inf``) and the sum of the values."""
        cumulative = np.cumsum(self._counts, axis=1)
        return [(key, cumulative[row], float(self._sums[row])) for key, row in self._rows.items()]
