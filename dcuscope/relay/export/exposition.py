"""The text of ``/metrics``: byte for byte what ``prometheus_client``'s ``generate_latest`` writes,
with the histograms written in bulk.

``generate_latest`` formats each sample on its own, validating and escaping every label of it
(~12 us a sample): at 8 nodes the histograms alone are ~7,000 samples, ~90 ms a scrape on the
relay's event loop. A :class:`BulkHistogram` holds its series as arrays of cumulative counts and
is written here a series at a time (its labels escaped once, each bucket line one format);
every other family goes through ``generate_latest`` itself. For any other reader (a registry's
``generate_latest``, tests), a BulkHistogram lists the same ``samples`` a HistogramMetricFamily
would.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from prometheus_client.core import Metric
from prometheus_client.exposition import generate_latest
from prometheus_client.samples import Sample
from prometheus_client.utils import floatToGoString


class BulkHistogram(Metric):
    """A histogram family (labels ``labels``, bucket bounds ``le`` as written, ``+Inf`` last)."""

    def __init__(self, name: str, documentation: str, labels: Sequence[str], le: Sequence[str]) -> None:
        self._samples: list[Sample] = []
        super().__init__(name, documentation, "histogram")
        self.labels, self.le = list(labels), list(le)
        self.series: list[tuple[list[str], np.ndarray, float]] = []

    def add_series(self, values: Sequence[str], cumulative: np.ndarray, total: float) -> None:
        """One series: its label values, cumulative counts per bucket (``len(le)``) and sum."""
        self.series.append((list(values), cumulative, total))
        self._samples = []

    @property
    def samples(self) -> list[Sample]:
        if not self._samples and self.series:
            for values, cumulative, total in self.series:
                labels = dict(zip(self.labels, values))
                self._samples += [Sample(f"{self.name}_bucket", dict(labels, le=le), float(c))
                                  for le, c in zip(self.le, cumulative.tolist())]
                self._samples += [Sample(f"{self.name}_count", labels, float(cumulative[-1])),
                                  Sample(f"{self.name}_sum", labels, total)]
        return self._samples

    @samples.setter
    def samples(self, value: list[Sample]) -> None:  # Metric.__init__ sets it
        self._samples = value


class _Listed:
    """Families already collected, in the shape ``generate_latest`` reads (a collector)."""

    def __init__(self, metrics: list[Metric]) -> None:
        self._metrics = metrics

    def collect(self) -> list[Metric]:
        return self._metrics


def exposition(metrics: Iterable[Metric]) -> bytes:
    """The text format of ``metrics``, as ``generate_latest`` writes it."""
    out: list[bytes] = []
    plain: list[Metric] = []
    for m in metrics:
        if isinstance(m, BulkHistogram):
            if plain:
                out.append(generate_latest(_Listed(plain)))
                plain = []
            out.append(_histogram_text(m).encode())
        else:
            plain.append(m)
    if plain:
        out.append(generate_latest(_Listed(plain)))
    return b"".join(out)


def _histogram_text(m: BulkHistogram) -> str:
    doc = m.documentation.replace("\\", r"\\").replace("\n", r"\n")
    lines = [f"# HELP {m.name} {doc}\n# TYPE {m.name} histogram\n"]
    for values, cumulative, total in m.series:
        pairs = sorted(zip(m.labels, (_escape(v) for v in values)))
        at = sum(1 for k, _ in pairs if k < "le")  # generate_latest sorts the labels, le among them
        before = "".join(f'{k}="{v}",' for k, v in pairs[:at])
        after = "".join(f',{k}="{v}"' for k, v in pairs[at:])
        plain = ",".join(f'{k}="{v}"' for k, v in pairs)
        plain = f"{{{plain}}}" if plain else ""
        lines += [f'{m.name}_bucket{{{before}le="{le}"{after}}} {_count(c)}\n'
                  for le, c in zip(m.le, cumulative.tolist())]
        lines.append(f"{m.name}_count{plain} {_count(int(cumulative[-1]))}\n{m.name}_sum{plain} "
                     f"{floatToGoString(total)}\n")
    return "".join(lines)


def _count(n: int) -> str:
    # floatToGoString(float(n)) without its cost below a million (Go's format turns exponential there).
    return f"{n}.0" if 0 <= n < 1_000_000 else floatToGoString(n)


def _escape(value: str) -> str:
    return value.replace("\\", r"\\").replace("\n", r"\n").replace('"', r"\"")
