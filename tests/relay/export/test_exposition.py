"""relay.export.exposition: the bulk writer's text is generate_latest's, byte for byte."""

from __future__ import annotations

import numpy as np
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.exposition import generate_latest
from prometheus_client.utils import floatToGoString

from dcuscope.relay.export.exposition import BulkHistogram, exposition

LE = [floatToGoString(b) for b in (0.0001, 0.00015, 0.5, 7.0, 10.0)] + ["+Inf"]


class Listed:
    def __init__(self, metrics):
        self.metrics = metrics

    def collect(self):
        return self.metrics


def families(bulk: bool) -> list:
    """The same families, their histograms as BulkHistogram or as prometheus_client's own."""
    rng = np.random.default_rng(3)
    series = [
        (["a"], [1]), (['we"ird\\node\nname', "x->y"], [0, 10**6 + 7, 3 * 10**7]), ([], [12, 999_999]),
    ]
    out = [GaugeMetricFamily("g_one", "A gauge with a \\ and\na newline", labels=["node"])]
    out[0].add_metric(['q"uote'], 1.5)
    for n, (labels, scale) in enumerate(series):
        names = ["from_stage", "to_stage", "node"][:len(labels)] if n else ["node"]
        cls = (lambda *a: BulkHistogram(*a, LE)) if bulk else (lambda name, doc, labels: HistogramMetricFamily(
            name, doc, labels=labels))
        h = cls(f"h{n}_seconds", f"histogram {n}", names)
        for s in scale:
            cumulative = np.cumsum(rng.integers(0, 5, len(LE)) * (s or 1))
            total = float(rng.uniform(0, 1e4))
            if bulk:
                h.add_series(labels, cumulative, total)
            else:
                h.add_metric(labels, list(zip(LE, cumulative.tolist())), total)
        out.append(h)
        c = CounterMetricFamily(f"c{n}", "a counter", labels=["k"])
        c.add_metric([str(n)], n * 2.5)
        out.append(c)
    return out


def test_bulk_text_equals_generate_latests_and_samples_equal_prometheus_clients():
    bulk, reference = families(bulk=True), families(bulk=False)
    expected = generate_latest(Listed(reference))
    assert exposition(bulk) == expected
    assert generate_latest(Listed(bulk)) == expected  # as a plain Metric, through its samples
    assert [m.samples for m in bulk] == [m.samples for m in reference]
    # The cases this covers: a label value to escape, counts Go writes with an exponent.
    assert b'from_stage="we\\"ird\\\\node\\nname"' in expected
    assert any(b"_bucket" in line and b"e+0" in line.split()[-1] for line in expected.splitlines())


def test_an_empty_bulk_histogram_writes_only_its_help_and_type():
    h = BulkHistogram("h_seconds", "nothing yet", ["node"], LE)
    assert exposition([h]) == generate_latest(Listed([HistogramMetricFamily("h_seconds", "nothing yet",
                                                                             labels=["node"])]))
