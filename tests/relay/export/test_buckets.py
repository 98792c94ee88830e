"""relay.export.buckets: bulk-fed histograms agree with numpy's, buckets upper-inclusive (Prometheus' le)."""

from __future__ import annotations

import numpy as np
import pytest

from dcuscope.relay.export.buckets import Histograms
from dcuscope.relay.export.framemetrics import NS_PER_S
from dcuscope.relay.export.metrics import BUCKETS_S

BOUNDS_NS = np.array([round(b * NS_PER_S) for b in BUCKETS_S], dtype=np.float64)


def reference(values: np.ndarray) -> np.ndarray:
    """Cumulative le-bucket counts by np.histogram: its bins are [a, b) but an le bucket is (a, b],
    so the bins are the bounds moved up by one ns (values are whole ns)."""
    edges = np.concatenate([[-np.inf], BOUNDS_NS + 1, [np.inf]])
    counts, _ = np.histogram(values, bins=edges)
    return np.cumsum(counts)


def test_bucket_counts_sums_and_counts_equal_numpys_over_many_series():
    rng = np.random.default_rng(7)
    h = Histograms(BOUNDS_NS)
    truth: dict[tuple, list[np.ndarray]] = {}
    for _ in range(20):
        batch = []
        for key in [("frame",), ("stage", "infer"), ("gap", "a", "b"), ("stage", "osd")]:
            # Log-uniform from 10 us to 100 s: beyond the last bound (10 s) too; some exactly on bounds.
            v = np.round(10 ** rng.uniform(4, 11, rng.integers(0, 300)))
            v = np.concatenate([v, rng.choice(BOUNDS_NS, rng.integers(0, 20)), [BOUNDS_NS[-1] + 1]])
            batch.append((key, v))
            truth.setdefault(key, []).append(v)
        h.add(batch)
    snap = {key: (cum, total) for key, cum, total in h.snapshot()}
    assert set(snap) == set(truth)
    for key, parts in truth.items():
        values = np.concatenate(parts)
        cum, total = snap[key]
        assert cum.tolist() == reference(values).tolist(), key
        assert cum[-1] == len(values) and (values > BOUNDS_NS[-1]).sum() == cum[-1] - cum[-2]
        assert total == pytest.approx(values.sum(), rel=1e-12)


def test_a_value_on_a_bound_counts_in_that_bounds_bucket_and_nans_are_skipped():
    h = Histograms([1.0, 2.0, 3.0])
    h.add([("x", np.array([1.0, 2.0, 2.0000001, 3.0, 3.5, np.nan, 0.0]))])
    (key, cum, total), = h.snapshot()
    assert cum.tolist() == [2, 3, 5, 6] and total == pytest.approx(11.5000001)


def test_series_held_before_any_value_are_empty_and_bad_bounds_are_refused():
    h = Histograms([1.0, 2.0])
    h.ensure(("frame",))
    h.add([])
    assert [(k, c.tolist(), s) for k, c, s in h.snapshot()] == [(("frame",), [0, 0, 0], 0.0)]
    for bad in ([], [2.0, 1.0], [1.0, 1.0]):
        with pytest.raises(ValueError, match="strictly increasing"):
            Histograms(bad)
