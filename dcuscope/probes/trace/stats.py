"""The statistics document of several nodes (``dcuscope stats --json``), over :mod:`dcuscope.model.delays`."""

from __future__ import annotations

from typing import Iterable

from dcuscope.model.delays import node_stats


def stats_document(traces: Iterable) -> dict:
    """``{"nodes": {NODE: node_stats}}`` for traces (objects with header, events, dropped),
    trace files or the runs of a stored session alike.

    Two traces of the same node name are kept apart as NODE, NODE_2, ... (different runs).
    """
    nodes: dict[str, dict] = {}
    for trace in traces:
        nodes[unique_name(trace.header.node, nodes)] = node_stats(trace.header, trace.events, trace.dropped)
    return {"nodes": nodes}


def unique_name(name: str, taken) -> str:
    """``name``, or ``name_2``, ``name_3``... the first not in ``taken``."""
    if name not in taken:
        return name
    k = 2
    while f"{name}_{k}" in taken:
        k += 1
    return f"{name}_{k}"
