"""One OpenTelemetry trace per frame, as the SDK's own span type (``ReadableSpan``), from a :class:`FrameBatch`.

A trace::

    frame                      origin -> end of its chain (the frame delay)
    ├── gap A->B               exit of A (or the origin) -> enter of B, one per gap
    └── stage NAME             enter -> exit, one per stage the frame went through with both
        ├── wait               enter -> when the stage began the work that carried the frame out
        └── service            that moment -> exit (where the node's probes give it)

Times are the relay's (clock-corrected, as /api/frames shows them), so traces of several nodes
line up. Trace ids are a hash of (run, source, frame): the same frame sent twice is one trace.
Span ids follow from the trace id and the span's place in it. Attributes carry the ``dcuscope.``
prefix; the resource names the node (``service.instance.id``), which is what backends group by.
"""

from __future__ import annotations

import hashlib
import math

from opentelemetry.sdk.resources import Resource
from opentelemetry.sdk.trace import ReadableSpan
from opentelemetry.sdk.util.instrumentation import InstrumentationScope
from opentelemetry.trace import SpanContext, TraceFlags

from dcuscope.model.frametable import MISSING
from dcuscope.relay.export.otlpframes import FrameBatch

SERVICE_NAME = "dcuscope-relay"
SCOPE = InstrumentationScope("dcuscope.relay")
NS_PER_MS = 1e6
_SAMPLED = TraceFlags(TraceFlags.SAMPLED)
_MASK64 = (1 << 64) - 1
_SPAN_STEP = 0x9E3779B97F4A7C15
"""Odd: consecutive span ids of a trace never repeat within 2**64 spans."""


def node_resource(node: str) -> Resource:
    """The resource of one node's spans (``OTEL_RESOURCE_ATTRIBUTES`` adds to it)."""
    return Resource.create({"service.name": SERVICE_NAME, "service.instance.id": node, "dcuscope.node": node})


def trace_id(run: str, source: int, frame: int) -> int:
    """128 bits of a hash of the frame's identity, never 0 (OTLP's "no trace")."""
    digest = hashlib.blake2b(f"{run}/{source}/{frame}".encode(), digest_size=16).digest()
    return int.from_bytes(digest, "big") or 1


class _Ids:
    """Span ids of one trace: the trace id's low 64 bits stepped by an odd constant."""

    def __init__(self, tid: int) -> None:
        self.tid, self._next = tid, tid & _MASK64

    def context(self) -> SpanContext:
        self._next = (self._next + _SPAN_STEP) & _MASK64
        return SpanContext(self.tid, self._next or 1, is_remote=False, trace_flags=_SAMPLED)


def spans_of(batch: FrameBatch, resource: Resource) -> list[ReadableSpan]:
    """Every span of every frame of ``batch``."""
    b = {name: getattr(batch, name).tolist() for name in
         ("source", "frame", "over", "origin", "end", "capture", "delay", "glass", "clock_ns", "uncertainty_ns",
          "enter", "exit", "start", "before", "prev", "stage_delay", "gap", "service", "wait")}
    spans: list[ReadableSpan] = []
    for i in range(len(batch)):
        ids = _Ids(trace_id(batch.run, b["source"][i], b["frame"][i]))
        root = ids.context()
        spans.append(ReadableSpan("frame", root, None, resource, _frame_attributes(batch, b, i),
                                  start_time=b["origin"][i], end_time=b["end"][i], instrumentation_scope=SCOPE))
        _stage_spans(batch, b, i, ids, root, resource, spans)
        _gap_spans(batch, b, i, ids, root, resource, spans)
    return spans


def _frame_attributes(batch: FrameBatch, b: dict, i: int) -> dict:
    source, over = b["source"][i], b["over"][i]
    attrs = {"dcuscope.node": batch.node, "dcuscope.run": batch.run, "dcuscope.source.id": source,
             "dcuscope.source.uri": batch.uris.get(source, ""), "dcuscope.frame": b["frame"][i],
             "dcuscope.delay_ms": b["delay"][i] / NS_PER_MS, "dcuscope.over_limit": over,
             "dcuscope.sampled_why": "over_limit" if over else "sampled", "dcuscope.clock.applied": batch.clock,
             "dcuscope.clock.offset_ns": b["clock_ns"][i], "dcuscope.clock.uncertainty_ns": b["uncertainty_ns"][i]}
    if batch.limit_ns is not None:
        attrs["dcuscope.limit_ms"] = batch.limit_ns / NS_PER_MS
    if b["capture"][i] != MISSING:
        attrs["dcuscope.capture_ns"] = b["capture"][i]
        attrs["dcuscope.glass_ms"] = b["glass"][i] / NS_PER_MS
    return attrs


def _stage_spans(batch: FrameBatch, b: dict, i: int, ids: _Ids, root: SpanContext, resource: Resource,
                 spans: list[ReadableSpan]) -> None:
    enter, exit_, start = b["enter"][i], b["exit"][i], b["start"][i]
    for s, name in enumerate(batch.stages):
        if enter[s] == MISSING or exit_[s] == MISSING:
            continue
        ctx = ids.context()
        attrs = {"dcuscope.stage": name, "dcuscope.stage.kind": batch.kinds.get(name, ""),
                 "dcuscope.delay_ms": b["stage_delay"][i][s] / NS_PER_MS}
        timed = start[s] != MISSING
        if timed:
            attrs["dcuscope.service_ms"] = b["service"][i][s] / NS_PER_MS
            attrs["dcuscope.wait_ms"] = b["wait"][i][s] / NS_PER_MS
        spans.append(ReadableSpan(f"stage {name}", ctx, root, resource, attrs, start_time=enter[s], end_time=exit_[s],
                                  instrumentation_scope=SCOPE))
        if timed:
            for part, t0, t1 in (("wait", enter[s], start[s]), ("service", start[s], exit_[s])):
                spans.append(ReadableSpan(part, ids.context(), ctx, resource,
                                          {"dcuscope.stage": name, f"dcuscope.{part}_ms": b[part][i][s] / NS_PER_MS},
                                          start_time=t0, end_time=t1, instrumentation_scope=SCOPE))


def _gap_spans(batch: FrameBatch, b: dict, i: int, ids: _Ids, root: SpanContext, resource: Resource,
               spans: list[ReadableSpan]) -> None:
    gap, before, enter, prev = b["gap"][i], b["before"][i], b["enter"][i], b["prev"][i]
    for s, name in enumerate(batch.stages):
        if math.isnan(gap[s]):
            continue
        src = batch.stages[prev[s]]
        spans.append(ReadableSpan(f"gap {src}->{name}", ids.context(), root, resource,
                                  {"dcuscope.gap": f"{src}->{name}", "dcuscope.from_stage": src,
                                   "dcuscope.to_stage": name, "dcuscope.gap_ms": gap[s] / NS_PER_MS},
                                  start_time=before[s], end_time=enter[s], instrumentation_scope=SCOPE))
