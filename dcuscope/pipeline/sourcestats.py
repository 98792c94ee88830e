"""Per-source counters of what happened to a source's frames before they got their identity.

A source is keyed by its ``framestamp``'s ``source-id``; its elements are those of the
top-level bin that holds the framestamp (a :class:`dcuscope.pipeline.sources.SourceBin`), or, for a
framestamp placed at the top level (gst-launch), everything upstream of it. Reading the
counters walks those elements and reads a few properties: cheap enough to do once a second
from any thread, and it never raises, whatever the pipeline holds or whatever state it is in.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from dcuscope.core.gst import Gst

FRAMESTAMP = "framestamp"
JITTERBUFFER = "rtpjitterbuffer"


@dataclass(frozen=True)
class SourceCounters:
    nominal_fps: float | None
    """The frame rate its framestamp's src pad negotiated; None while not negotiated or for a
    variable rate (0/1)."""
    lost_upstream: int
    """RTP *packets* its jitter buffers gave up on (their ``stats`` ``num-lost``), cumulative; 0
    for a source without RTP. Packets, not frames: a compressed frame spans one to many
    packets, so this is an upper bound of the frames hit (each lost packet damages at most one
    frame), and a damaged frame may still be decoded (with artefacts) rather than lost."""
    decoder_dropped: int
    """Frames its decoders dropped (QoS: too late, or undecodable), cumulative, as seen by the
    :class:`SourceStats` watching the bus; 0 without one."""


class SourceStats:
    """Watches ``pipeline``'s bus for its decoders' QoS messages, which are the only way a
    decoder tells how many frames it dropped. Make it before the pipeline starts; ``close`` it
    after. Its handler runs in the thread that posts the message (no main loop needed)."""

    def __init__(self, pipeline: Gst.Pipeline):
        self.pipeline = pipeline
        self._lock = threading.Lock()
        self._last: dict[str, int] = {}  # decoder path -> its last cumulative count
        self._dropped: dict[str, int] = {}  # decoder path -> drops, across its counter's resets
        self._bus = pipeline.get_bus()
        self._bus.enable_sync_message_emission()
        self._handler = self._bus.connect("sync-message::qos", self._on_qos)

    def close(self) -> None:
        if self._handler is not None:
            self._bus.disconnect(self._handler)
            self._bus.disable_sync_message_emission()
            self._handler = None

    def counters(self) -> dict[int, SourceCounters]:
        return source_counters(self.pipeline, self)

    def decoder_dropped(self, elements: list[Gst.Element]) -> int:
        """Drops counted so far for the decoders among ``elements``."""
        paths = {e.get_path_string() for e in elements if _is_decoder(e)}
        with self._lock:
            return sum(n for path, n in self._dropped.items() if path in paths)

    def _on_qos(self, _bus, message: Gst.Message) -> None:
        if not isinstance(message.src, Gst.Element) or not _is_decoder(message.src):
            return
        fmt, _processed, dropped = message.parse_qos_stats()
        if fmt != Gst.Format.BUFFERS or dropped < 0:  # -1: unknown
            return
        path = message.src.get_path_string()
        with self._lock:
            last = self._last.get(path, 0)
            # The count restarts at a flush (a looping file's seek): what it says then is all new.
            self._dropped[path] = self._dropped.get(path, 0) + (dropped - last if dropped >= last else dropped)
            self._last[path] = dropped


def source_counters(pipeline: Gst.Pipeline, stats: SourceStats | None = None) -> dict[int, SourceCounters]:
    """Counters of every source of ``pipeline``, by framestamp ``source-id`` (in that order).
    ``stats``: the bus watcher that counts decoder drops (``decoder_dropped`` is 0 without one)."""
    counters = {}
    for stamp in _recursive(pipeline, _is_framestamp):
        elements = _source_elements(stamp, pipeline)
        counters[stamp.get_property("source-id")] = SourceCounters(
            nominal_fps=nominal_fps(stamp.get_static_pad("src")),
            lost_upstream=sum(_packets_lost(e) for e in elements if _factory(e) == JITTERBUFFER),
            decoder_dropped=stats.decoder_dropped(elements) if stats is not None else 0,
        )
    return dict(sorted(counters.items()))


def nominal_fps(pad: Gst.Pad) -> float | None:
    """The frame rate in ``pad``'s negotiated caps; None if none yet, or variable (0/1)."""
    caps = pad.get_current_caps()
    if caps is None or caps.is_empty():
        return None
    ok, num, den = caps[0].get_fraction("framerate")
    return num / den if ok and num > 0 and den > 0 else None


def _packets_lost(jitterbuffer: Gst.Element) -> int:
    stats = jitterbuffer.get_property("stats")
    ok, lost = stats.get_uint64("num-lost") if stats is not None else (False, 0)
    return int(lost) if ok else 0


def _source_elements(stamp: Gst.Element, pipeline: Gst.Pipeline) -> list[Gst.Element]:
    host = stamp
    while host.get_parent() is not None and host.get_parent() != pipeline:
        host = host.get_parent()
    if host is not stamp and isinstance(host, Gst.Bin):
        return _recursive(host, lambda _e: True)
    return _upstream(stamp)


def _upstream(element: Gst.Element) -> list[Gst.Element]:
    """Every element upstream of ``element`` among its siblings, and all inside those that are bins."""
    found, todo, seen = [], [element], set()
    while todo:
        current = todo.pop()
        for pad in current.sinkpads:
            peer = pad.get_peer()
            parent = peer.get_parent_element() if peer is not None else None
            if parent is None or parent.get_path_string() in seen:
                continue
            seen.add(parent.get_path_string())
            found.append(parent)
            if isinstance(parent, Gst.Bin):
                found.extend(_recursive(parent, lambda _e: True))
            todo.append(parent)
    return found


def _recursive(bin_: Gst.Bin, keep) -> list[Gst.Element]:
    """The elements inside ``bin_`` at any depth that ``keep`` accepts; a consistent snapshot
    even while elements come and go (the iterator restarts when the bin changes under it)."""
    iterator, found = bin_.iterate_recurse(), []
    while True:
        result, element = iterator.next()
        if result == Gst.IteratorResult.OK:
            if keep(element):
                found.append(element)
        elif result == Gst.IteratorResult.RESYNC:
            iterator.resync()
            found.clear()
        else:  # DONE, or ERROR: what was found
            return found


def _factory(element: Gst.Element) -> str | None:
    factory = element.get_factory()
    return factory.get_name() if factory is not None else None


def _is_framestamp(element: Gst.Element) -> bool:
    return _factory(element) == FRAMESTAMP


def _is_decoder(element: Gst.Element) -> bool:
    factory = element.get_factory()
    return factory is not None and "Decoder" in (factory.get_metadata("klass") or "")
