"""Tracepoints on every stage of a built pipeline, without touching element code.

    tracer = attach(pipeline, node="dcu1")          # after building, before PLAYING
    pipeline.set_state(Gst.State.PLAYING)
    ...
    events = tracer.drain()                          # EVENT_DTYPE, stages index tracer.header.stages
    tracer.detach()

Stages are the top-level children of the pipeline that frames with an identity pass through,
in pipeline order, preceded by every ``framestamp`` element (origin stages, found also inside
source bins). Tracepoints: origin on a framestamp's src pad; enter on every sink pad and exit
on every src pad of every other stage (a sink bin has only its ghost sink pad: enter only).
Elements upstream of the framestamps carry no identity and are not stages. A pipeline without
framestamp (frames identified upstream, e.g. an appsrc) has as stages everything after its sources.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from dcuscope.core.clocks import CLOCKS
from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import Gst
from dcuscope.probes.capture.native import DEFAULT_TRIGGER, BuildError, NativeRing, load, unavailable_reason
from dcuscope.probes.capture.ring import DEFAULT_CAPACITY, PythonRing, RingStats
from dcuscope.protocol.events import ENTER, EXIT, LINK, ORIGIN, TraceHeader

BACKENDS = ("auto", "native", "python")
FRAMESTAMP = "framestamp"
# Properties that say where a source's frames come from, most telling first.
_SOURCE_PROPERTIES = ("uri", "location", "device")


@dataclass
class _Tracepoint:
    pad: Gst.Pad
    handle: int


def make_ring(backend: str = "auto", capacity: int = DEFAULT_CAPACITY,
              trigger: str = DEFAULT_TRIGGER) -> NativeRing | PythonRing:
    """A ring of the wanted backend; ``auto`` takes the native one when it can be loaded.
    ``trigger``: what fires native tracepoints, the tracer's hooks or pad probes (probes.capture.native)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown probe backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend == "python" or (backend == "auto" and load() is None):
        return PythonRing(capacity)
    if load() is None:
        raise BuildError(f"native probes unavailable: {unavailable_reason()}")
    return NativeRing(capacity, trigger=trigger)


class Tracer:
    """The tracepoints of one pipeline and the ring they write to."""

    def __init__(self, header: TraceHeader, ring: NativeRing | PythonRing, clock_id: int):
        self.header = header
        self.ring = ring
        self.clock_id = clock_id
        self._points: list[_Tracepoint] = []
        self._probed: set[Gst.Pad] = set()  # the pads themselves: the set holds them, so identity is exact
        self._signals: list[tuple[Gst.Element, int]] = []
        self._lock = threading.Lock()  # guards the tracepoint list (attach time, not per frame)
        self._attached = True
        self.stage_elements: dict[Gst.Element, int] = {}
        """Each stage's element (framestamps included) -> its stage index."""

    @property
    def backend(self) -> str:
        return self.ring.backend

    @property
    def trigger(self) -> str:
        """What fires the tracepoints: "hooks" or "probes" (native), "probes" (Python)."""
        return getattr(self.ring, "trigger", "probes")

    def add(self, pad: Gst.Pad, stage: int, point: int) -> None:
        """Put a tracepoint on ``pad`` (once per pad)."""
        with self._lock:
            if not self._attached or pad in self._probed:
                return
            self._probed.add(pad)
            self._points.append(_Tracepoint(pad, self.ring.attach(pad, stage, point, self.clock_id)))

    def watch(self, element: Gst.Element, stage: int) -> None:
        """Trace pads that ``element`` adds later (sometimes pads) as they appear."""

        def on_pad_added(elem: Gst.Element, pad: Gst.Pad) -> None:
            self.add(pad, stage, ENTER if pad.get_direction() == Gst.PadDirection.SINK else EXIT)

        self._signals.append((element, element.connect("pad-added", on_pad_added)))

    @property
    def tracepoints(self) -> int:
        return len(self._points)

    def drain(self, max_events: int | None = None) -> np.ndarray:
        """Events recorded since the last drain, in ring order (not sorted by time)."""
        return self.ring.drain(max_events)

    def push(self, events: np.ndarray) -> int:
        """Add events the node learned elsewhere (drops, facts) to the ring, after those
        already in it; returns how many went in (all or, ring full, none: counted dropped)."""
        return self.ring.push(events)

    def stage_of(self, element: Gst.Element) -> int | None:
        """The stage index of ``element`` or of the stage that contains it, None if outside."""
        while element is not None:
            if element in self.stage_elements:
                return self.stage_elements[element]
            element = element.get_parent()
        return None

    def stats(self) -> RingStats:
        return self.ring.stats()

    @property
    def dropped(self) -> int:
        return self.ring.stats().dropped

    @property
    def unidentified(self) -> int:
        return self.ring.stats().unidentified

    def detach(self) -> None:
        """Remove every tracepoint; events still in the ring can be drained afterwards."""
        with self._lock:
            self._attached = False
            for element, handler in self._signals:
                element.disconnect(handler)
            for tp in self._points:
                self.ring.detach(tp.pad, tp.handle)
            self._signals.clear()
            self._points.clear()
            self._probed.clear()


def attach(pipeline: Gst.Pipeline, node: str, clock: str = "realtime", capacity: int = DEFAULT_CAPACITY,
           backend: str = "auto", sources: dict[int, str] | None = None, trigger: str = DEFAULT_TRIGGER) -> Tracer:
    """Put tracepoints on every stage of ``pipeline`` (built, not yet PLAYING).

    ``sources`` maps source ids to descriptions; ids it lacks are described from the pipeline
    (the source's ``uri``, ``location`` or ``device``, else its factory name).
    """
    if not isinstance(pipeline, Gst.Bin):
        raise TypeError(f"attach() needs a Gst.Pipeline (or Gst.Bin), not {type(pipeline).__name__}")
    if clock not in CLOCKS:
        raise ValueError(f"unknown clock {clock!r}; expected one of {', '.join(CLOCKS)}")
    children = _children(pipeline)
    stamps = sorted(_framestamps(children), key=lambda fs: (fs.get_property("source-id"), fs.get_name()))
    # Without a framestamp, frames must arrive already identified (an appsrc fed by another
    # node, a test): every element downstream of the sources is then a stage.
    hosts = [_top_level(fs, pipeline) for fs in stamps] or [e for e in children if not _has_sink_pads(e)]
    stage_elements = _downstream_in_order(children, hosts, pipeline)
    if not stamps and not stage_elements:
        raise PipelineError(f"pipeline {pipeline.get_name()} has no {FRAMESTAMP} element and no linked "
                            "elements after its sources: there is nothing to trace")
    ring = make_ring(backend, capacity, trigger)
    elements = stamps + stage_elements
    names = _unique([e.get_name() for e in elements])
    kinds = {name: e.get_factory().get_name() for name, e in zip(names, elements) if e.get_factory() is not None}
    described = {fs.get_property("source-id"): _describe_source(fs, host, pipeline) for fs, host in zip(stamps, hosts)}
    header = TraceHeader(
        node=node, clock=clock, stages=names, sources={**described, **(sources or {})},
        started_ns=ring.now(CLOCKS[clock]),
        versions={"gstreamer": Gst.version_string(), "probes": ring.backend,
                  "trigger": getattr(ring, "trigger", "probes")}, kinds=kinds,
    )
    header.links = _branch_links(stamps, hosts, stage_elements, pipeline)
    tracer = Tracer(header, ring, CLOCKS[clock])
    tracer.stage_elements = {element: index for index, element in enumerate(elements)}
    for index, fs in enumerate(stamps):
        tracer.add(fs.get_static_pad("src"), index, ORIGIN)
    for index, element in enumerate(stage_elements, start=len(stamps)):
        tracer.watch(element, index)  # first, so that no pad slips in between (add() dedupes)
        for pad in element.pads:
            tracer.add(pad, index, ENTER if pad.get_direction() == Gst.PadDirection.SINK else EXIT)
    if tracer.backend == "native" and tracer.trigger == "hooks":
        _watch_links(tracer, pipeline, {host: index for index, host in enumerate(hosts) if index < len(stamps)})
    return tracer


LINK_SINKS = ("udpsink", "multiudpsink", "shmsink")
LINK_SOURCES = ("udpsrc", "shmsrc")


def _watch_links(tracer: Tracer, pipeline: Gst.Pipeline, sources: dict[Gst.Element, int]) -> None:
    """Watches (no tracepoint: what crosses to or from another pipeline, docs/journeys.md) on the
    sink pad of every RTP or shared-memory sink, the src pad of every udpsrc and shmsrc, and the
    sink pad of every RTP depayloader, each for the stage it belongs to (a source's: its stamp's).
    The hooks alone fire them (not pad probes, not Python probes)."""
    for element in pipeline.iterate_recurse():
        factory = element.get_factory()
        name = factory.get_name() if factory is not None else ""
        pad = (element.get_static_pad("sink") if name in LINK_SINKS or (name.startswith("rtp") and name.endswith("depay"))
               else element.get_static_pad("src") if name in LINK_SOURCES else None)
        stage = sources.get(_top_level(element, pipeline), tracer.stage_of(element))
        if pad is not None and stage is not None:
            tracer.add(pad, stage, LINK)


def _children(bin_: Gst.Bin) -> list[Gst.Element]:
    # GstBin prepends children: reverse to get the order they were added in.
    return list(reversed(bin_.children))


def _has_sink_pads(element: Gst.Element) -> bool:
    return any(pad.get_direction() == Gst.PadDirection.SINK for pad in element.pads)


def _is_framestamp(element: Gst.Element) -> bool:
    factory = element.get_factory()
    return factory is not None and factory.get_name() == FRAMESTAMP


def _framestamps(children: list[Gst.Element]) -> list[Gst.Element]:
    found = []
    for child in children:
        if _is_framestamp(child):
            found.append(child)
        elif isinstance(child, Gst.Bin):
            found.extend(e for e in child.iterate_recurse() if _is_framestamp(e))
    return found


def _top_level(element: Gst.Element, pipeline: Gst.Pipeline) -> Gst.Element:
    while element.get_parent() is not None and element.get_parent() != pipeline:
        element = element.get_parent()
    return element


def _peers(element: Gst.Element, direction: Gst.PadDirection, pipeline: Gst.Pipeline) -> list[Gst.Element]:
    """Top-level elements linked to ``element``'s pads of ``direction``."""
    out = []
    for pad in element.pads:
        peer = pad.get_peer() if pad.get_direction() == direction else None
        owner = peer.get_parent_element() if peer is not None else None
        if owner is not None:
            out.append(_top_level(owner, pipeline))
    return out


def _downstream_in_order(children: list[Gst.Element], hosts: list[Gst.Element],
                         pipeline: Gst.Pipeline) -> list[Gst.Element]:
    """Top-level elements downstream of the hosts, topologically sorted (ties: order added)."""
    rank = {e: i for i, e in enumerate(children)}
    reached: list[Gst.Element] = []  # in the order found
    todo = list(hosts)
    while todo:
        for nxt in _peers(todo.pop(), Gst.PadDirection.SRC, pipeline):
            if nxt not in reached and nxt not in hosts:
                reached.append(nxt)
                todo.append(nxt)
    indegree = {e: sum(u in reached for u in _peers(e, Gst.PadDirection.SINK, pipeline)) for e in reached}
    ordered: list[Gst.Element] = []
    ready = sorted((e for e, d in indegree.items() if d == 0), key=lambda e: rank.get(e, 0))
    while ready:
        element = ready.pop(0)
        ordered.append(element)
        for nxt in _peers(element, Gst.PadDirection.SRC, pipeline):
            if nxt in indegree:
                indegree[nxt] -= 1
                if indegree[nxt] == 0:
                    ready.append(nxt)
                    ready.sort(key=lambda e: rank.get(e, 0))
    # A cycle (a feedback loop) leaves elements unsorted: keep them, in the order added.
    ordered += sorted((e for e in reached if e not in ordered), key=lambda e: rank.get(e, 0))
    return ordered


def _branch_links(stamps: list[Gst.Element], hosts: list[Gst.Element], stage_elements: list[Gst.Element],
                  pipeline: Gst.Pipeline) -> list[list[int]]:
    """The graph (TraceHeader.links) when it branches (a tee: several sinks); [] for a chain,
    whose stage order says it all (and whose traces stay as they were)."""
    index = {e: len(stamps) + i for i, e in enumerate(stage_elements)}
    links = []
    for origin, host in enumerate(hosts[:len(stamps)]):
        links += [[origin, index[p]] for p in _peers(host, Gst.PadDirection.SRC, pipeline) if p in index]
    for element in stage_elements:
        links += [[index[element], index[p]] for p in _peers(element, Gst.PadDirection.SRC, pipeline) if p in index]
    fan_out = {}
    for a, _ in links:
        fan_out[a] = fan_out.get(a, 0) + 1
    return sorted(links) if any(n > 1 for n in fan_out.values()) else []


def _unique(names: list[str]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(name if seen[name] == 1 else f"{name}_{seen[name] - 1}")
    return out


def _property_description(element: Gst.Element) -> str | None:
    for prop in _SOURCE_PROPERTIES:
        if element.find_property(prop) is not None:
            value = element.get_property(prop)
            if value:
                return str(value)
    return None


def _describe(element: Gst.Element) -> str:
    inner = list(element.iterate_recurse()) if isinstance(element, Gst.Bin) else []
    for candidate in [element] + inner:
        text = _property_description(candidate)
        if text:
            return text
    # A bin without such a property: name what produces its frames (its source elements).
    origin = next(iter(element.iterate_sources()), element) if isinstance(element, Gst.Bin) else element
    factory = origin.get_factory()
    return factory.get_name() if factory is not None else origin.get_name()


def _describe_source(stamp: Gst.Element, host: Gst.Element, pipeline: Gst.Pipeline) -> str:
    """Where the frames that ``stamp`` stamps come from."""
    if host != stamp:
        return _describe(host)  # a source bin: its uri/location/device is inside
    element, seen = stamp, set()
    while element not in seen:
        seen.add(element)
        upstream = _peers(element, Gst.PadDirection.SINK, pipeline)
        if not upstream:
            break
        element = upstream[0]
    return _describe(element) if element is not stamp else stamp.get_name()
