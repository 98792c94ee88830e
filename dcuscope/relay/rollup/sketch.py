"""A mergeable sketch of delays: fixed logarithmic buckets (DDSketch's mapping), exact count, sum, min, max.

Why this one. Rollups are merged a great deal: a minute's rows of several ranges of batches, then
minutes into hours, then a month's hours into one answer, and runs of one DCU into its row. A
sketch whose buckets are *fixed* merges by adding counts, exactly, in any order and any grouping,
and its error never grows with merging. DDSketch's mapping gives each bucket a fixed relative
width: a value ``x > 0`` falls in bucket ``ceil(log(x) / log(GAMMA))`` with ``GAMMA = (1 + ALPHA) /
(1 - ALPHA)``, whose representative ``2 GAMMA**k / (GAMMA + 1)`` is within ``ALPHA`` (1 %) of every
value in it. A quantile read from the sketch is therefore within 1 % of the value of the order
statistic of that rank (p99 of a 30 ms delay: ±0.3 ms), whatever the distribution; HDR histograms
bound the error the same way but with fixed precision digits, and t-digest merges are not exact.
Delays of 1 µs to 100 s take at most 921 buckets; a minute of one stage uses a few dozen.

Exact: ``count``, ``total_ns`` (values are whole nanoseconds: sums are exact), ``min_ns``,
``max_ns``, and so the mean. From the sketch: the quantiles. Values of 0 ns or less go in a bucket
of their own (0).

Stored as bytes (:meth:`Sketch.encode`): a header, then the counts of buckets ``offset..`` as
little-endian integers of the width their largest needs.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from dcuscope.relay.errors import RelayError

ALPHA = 0.01
"""The relative error of a quantile: within this fraction of the order statistic's value."""
GAMMA = (1 + ALPHA) / (1 - ALPHA)
LOG_GAMMA = math.log(GAMMA)
HEAD = struct.Struct("<BqqqqqiI")
"""version, count, zeros, total_ns, min_ns, max_ns, offset, buckets (then the width byte and counts)."""
VERSION = 1
WIDTHS = {1: "<u1", 2: "<u2", 4: "<u4", 8: "<u8"}


class SketchError(RelayError):
    """Stored sketch bytes that cannot be read."""


@dataclass
class Sketch:
    count: int = 0
    zeros: int = 0
    """Values of 0 ns or less."""
    total_ns: int = 0
    min_ns: int = 0
    max_ns: int = 0
    offset: int = 0
    """The bucket index of ``counts[0]``."""
    counts: np.ndarray | None = None

    @classmethod
    def of(cls, values_ns: np.ndarray) -> "Sketch":
        """The sketch of ``values_ns`` (whole ns, float or int; NaN left out)."""
        v = np.asarray(values_ns, dtype=np.float64)
        v = np.rint(v[~np.isnan(v)])
        if not len(v):
            return cls()
        positive = v[v > 0]
        out = cls(count=len(v), zeros=int(len(v) - len(positive)), total_ns=int(v.sum()),
                  min_ns=int(v.min()), max_ns=int(v.max()))
        if len(positive):
            keys = np.ceil(np.log(positive) / LOG_GAMMA).astype(np.int64)
            out.offset = int(keys.min())
            out.counts = np.bincount(keys - out.offset).astype(np.int64)
        return out

    def merge(self, other: "Sketch") -> "Sketch":
        """Both together (neither changed)."""
        if not other.count:
            return self.copy()
        if not self.count:
            return other.copy()
        out = Sketch(count=self.count + other.count, zeros=self.zeros + other.zeros,
                     total_ns=self.total_ns + other.total_ns, min_ns=min(self.min_ns, other.min_ns),
                     max_ns=max(self.max_ns, other.max_ns))
        parts = [s for s in (self, other) if s.counts is not None]
        if parts:
            out.offset = min(s.offset for s in parts)
            counts = np.zeros(max(s.offset + len(s.counts) for s in parts) - out.offset, np.int64)
            for s in parts:
                counts[s.offset - out.offset:s.offset - out.offset + len(s.counts)] += s.counts
            out.counts = counts
        return out

    def copy(self) -> "Sketch":
        return Sketch(self.count, self.zeros, self.total_ns, self.min_ns, self.max_ns, self.offset,
                      None if self.counts is None else self.counts.copy())

    @property
    def mean_ns(self) -> float | None:
        return self.total_ns / self.count if self.count else None

    def quantile(self, q: float) -> float | None:
        """The value at quantile ``q`` (0..1), in ns: within ALPHA of the order statistic of rank
        ``floor(q * (count - 1))`` (0-based), clamped to the exact min and max; None if empty."""
        if not self.count:
            return None
        rank = math.floor(q * (self.count - 1))
        if rank < self.zeros:
            return float(min(0, self.max_ns)) if self.min_ns <= 0 else 0.0
        k = int(np.searchsorted(np.cumsum(self.counts), rank - self.zeros, side="right"))
        value = 2 * GAMMA ** (self.offset + k) / (GAMMA + 1)
        return float(min(max(value, self.min_ns), self.max_ns))

    def encode(self) -> bytes:
        """The sketch as bytes (an empty one: none, e.g. the service times of frames without a ready point)."""
        if not self.count:
            return b""
        counts = self.counts if self.counts is not None else np.zeros(0, np.int64)
        top = int(counts.max()) if len(counts) else 0
        width = next(w for w in WIDTHS if top < 1 << (8 * w))
        return (HEAD.pack(VERSION, self.count, self.zeros, self.total_ns, self.min_ns, self.max_ns, self.offset,
                          len(counts)) + bytes([width]) + counts.astype(WIDTHS[width]).tobytes())

    @classmethod
    def decode(cls, data: bytes | None) -> "Sketch":
        if not data:
            return cls()
        try:
            version, count, zeros, total, lo, hi, offset, n = HEAD.unpack_from(data)
            width = data[HEAD.size]
            if version != VERSION or width not in WIDTHS or len(data) != HEAD.size + 1 + n * width:
                raise ValueError("its parts do not add up")
            counts = np.frombuffer(data, WIDTHS[width], n, HEAD.size + 1).astype(np.int64)
        except (struct.error, IndexError, ValueError) as exc:
            raise SketchError(f"a damaged sketch: {exc}") from None
        if int(counts.sum()) + zeros != count:
            raise SketchError("a damaged sketch: its buckets do not add up to its count")
        return cls(count, zeros, total, lo, hi, offset, counts if n else None)
