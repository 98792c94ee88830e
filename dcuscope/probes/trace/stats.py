"""The statistics document of several nodes (``dcuscope stats --json``), over :mod:`dcuscope.model.delays`."""

from __future__ import annotations

from typing import Iterable

from dcuscope.model.delays import node_stats
from dcuscope.model.journeys import join, journeys_document
from dcuscope.model.names import unique_name


def stats_document(traces: Iterable) -> dict:
    """``{"nodes": {NODE: node_stats}}`` for traces (objects with header, events, dropped),
    trace files or the runs of a stored session alike; and ``journeys`` where frames went from one
    pipeline to another (:mod:`dcuscope.model.journeys`).

    Two traces of the same node name are kept apart as NODE, NODE_2, ... (different runs).
    """
    traces = list(traces)
    nodes: dict[str, dict] = {}
    for trace in traces:
        nodes[unique_name(trace.header.node, nodes)] = node_stats(trace.header, trace.events, trace.dropped)
    doc = {"nodes": nodes}
    joined = join(traces, list(nodes))
    if joined.hops or joined.untraced or joined.ambiguous:
        doc["journeys"] = journeys_document(joined)
    return doc
