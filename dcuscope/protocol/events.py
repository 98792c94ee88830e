"""The probe event record and the exporter interface, shared by probes, trace files and relay.

An event is one tracepoint hit for one frame: (stage, point, source, frame, timestamp, code).
The node name and the stage names travel once, in the :class:`TraceHeader`; events refer to a
stage by its index in ``header.stages``. Events move in numpy structured arrays of
:data:`EVENT_DTYPE`, never as per-event Python objects.

Points (format 3; format 1 had only the first three, format 2 no ``link`` and ``key``):

- ``origin``: the frame got its identity (a ``framestamp``'s src pad);
- ``enter`` / ``exit``: the frame entered a stage (sink pad) / left it (src pad);
- ``ready``: when the stage could start working on the output buffer that carries the frame:
  the later of "the thread that pushes it returned from its previous push on that pad" and
  "the last frame of that buffer entered the stage". Service = exit - ready, wait = ready -
  enter (:mod:`dcuscope.model.delays`). ``code`` = how many frames the output buffer holds (at most
  127) on its first frame, minus that on the others, so that a batch's work is counted once
  in a stage's busy time;
- ``capture``: the frame's capture time as its source knows it (an RTSP camera's RTCP sender
  reports), at the origin stage: a point before ``origin``;
- ``drop``: the frame was dropped at ``stage``, ``code`` = reason (:data:`DROP_REASONS`);
- ``fact``: not a frame but a value: ``code`` = kind (:data:`FACT_KINDS`), ``frame`` = value,
  ``source`` = the source it is about (0 for a stage fact), ``stage`` = the stage;
- ``link``: the frame left this pipeline for another or came from one, at ``stage`` (``code`` =
  :data:`LINK_KINDS`): sent (the push into the sink that sends it returned: its first RTP packet
  or its shared-memory buffer went) or arrived (its first packet reached the pipeline's source
  element; a shmsrc's buffer was made);
- ``key``: right after each ``link``, the same ``ts``, ``source``, ``stage`` and ``code``, with
  ``frame`` = the link key both ends compute (a 44-bit hash of the RTP packets' SSRC and
  timestamp, or of the shared buffer's bytes): :mod:`dcuscope.model.journeys` joins them.

The first :data:`FRAME_POINTS` points are per-frame timestamps, paired into the frame table.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np

FORMAT_VERSION = 3
READABLE_FORMATS = (1, 2, 3)
"""Trace formats this dcuscope reads: 1 (origin, enter, exit only), 2 and 3 (links)."""

ORIGIN, ENTER, EXIT, READY, CAPTURE, DROP, FACT, LINK, KEY = range(9)
POINT_NAMES = ("origin", "enter", "exit", "ready", "capture", "drop", "fact", "link", "key")
FRAME_POINTS = 5
"""Points 0..4 (origin, enter, exit, ready, capture) are timestamps of one frame at one stage."""
GROUP = 5
FRAME_CELLS = 6
"""A frame table's cells per (frame, stage): the five points' timestamps, then (at GROUP) the
``code`` of the frame's ready event there: > 0 on the first frame of an output buffer."""

DROP_REASONS = {0: "unknown", 1: "late", 2: "qos", 3: "queue full", 4: "error", 5: "stopped"}
"""``code`` of a ``drop`` event -> why the frame was dropped: ``late``, older than the mux's
``max-latency``; ``stopped``, still queued when a live run stopped (not drained, see
:mod:`dcuscope.pipeline.livestop`)."""
LATE = 1
STOPPED = 5

FACT_THREAD, FACT_NOMINAL_MHZ, FACT_LOST_UPSTREAM, FACT_DECODER_DROPPED = 1, 2, 3, 4
FACT_KINDS = {FACT_THREAD: "thread", FACT_NOMINAL_MHZ: "nominal_mhz", FACT_LOST_UPSTREAM: "lost_upstream",
              FACT_DECODER_DROPPED: "decoder_dropped"}
"""``code`` of a ``fact`` event -> what its ``frame`` field holds: ``thread``, the number of the
streaming thread that pushes a stage's output (a stage fact, sent when it changes);
``nominal_mhz``, a source's nominal frame rate (caps framerate) in millihertz; ``lost_upstream``,
frames a source lost before its origin (RTP sequence gaps), cumulative; ``decoder_dropped``,
frames its decoder dropped, cumulative."""

RTP_OUT, RTP_IN, SHM_OUT, SHM_IN = 1, 2, 3, 4
LINK_KINDS = {RTP_OUT: "rtp sent", RTP_IN: "rtp arrived", SHM_OUT: "shm sent", SHM_IN: "shm arrived"}
"""``code`` of a ``link`` (and its ``key``) event -> which way the frame crossed, over what."""
LINK_TRANSPORT = {RTP_OUT: "net", RTP_IN: "net", SHM_OUT: "shm", SHM_IN: "shm"}
SENT_KINDS, ARRIVED_KINDS = (RTP_OUT, SHM_OUT), (RTP_IN, SHM_IN)


def _code_table() -> np.ndarray:
    """``[point, code as a byte]``: whether that point allows that code (a point out of range: none)."""
    table = np.zeros((256, 256), bool)
    table[:KEY + 1, 0] = True
    table[READY, :] = True
    table[READY, 0] = False
    for point, allowed in ((DROP, DROP_REASONS), (FACT, FACT_KINDS), (LINK, LINK_KINDS), (KEY, LINK_KINDS)):
        table[point, 0] = False
        table[point, np.array(list(allowed), np.int8).view(np.uint8)] = True
    return table


CODE_TABLE = _code_table()
"""``[point, code as a byte]`` (256 x 256 bools): whether that point allows that code (the relay's
compiled batch check reads it, :mod:`dcuscope.model.compiled`)."""


def codes_valid(point: np.ndarray, code: np.ndarray) -> np.ndarray:
    """Per event: its ``code`` is one its point allows (group size, reason, fact kind, or 0)."""
    point, code = np.asarray(point), np.asarray(code)
    if point.dtype == np.int8 and code.dtype == np.int8:  # the wire's and the trace's event dtype
        return CODE_TABLE[point.view(np.uint8), code.view(np.uint8)]
    point, code = point.astype(np.int64), code.astype(np.int64)
    fits = (point >= 0) & (point < 256) & (code >= -128) & (code < 128)
    return np.where(point == READY, code != 0,
                    fits & CODE_TABLE[np.where(fits, point, 255), np.where(fits, code, 0).astype(np.int8).view(np.uint8)])


EVENT_DTYPE = np.dtype(
    [("ts", "<i8"), ("frame", "<i8"), ("source", "<i4"), ("stage", "<i2"), ("point", "<i1"), ("code", "<i1")]
)


@dataclass
class TraceHeader:
    """Who produced a stream of events and how to read them."""

    node: str
    clock: str
    stages: list[str]
    """Stage names in pipeline order; the first is the origin stage (where frames are stamped)."""
    sources: dict[int, str] = field(default_factory=dict)
    """Source id -> human-readable description (URI, device, pattern)."""
    started_ns: int = 0
    versions: dict[str, str] = field(default_factory=dict)
    format: int = FORMAT_VERSION
    kinds: dict[str, str] = field(default_factory=dict)
    """Stage name -> the factory of its element (``infer`` for a stage named ``pgie``): what
    the UI colours by. Optional: traces written before it have none."""
    links: list[list[int]] = field(default_factory=list)
    """``[a, b]`` pairs of stage indices: stage a feeds stage b (the graph, branches as branches).
    Written by the GStreamer tracer; optional."""
    lineage_unknown: list[str] = field(default_factory=list)
    """Stages that took identified frames in and pushed buffers without identity: downstream of
    them frames cannot be traced to their sources (the GStreamer tracer never guesses)."""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["sources"] = {str(k): v for k, v in self.sources.items()}
        return d

    @staticmethod
    def from_dict(d: dict) -> "TraceHeader":
        return TraceHeader(
            node=str(d["node"]), clock=str(d["clock"]), stages=[str(s) for s in d["stages"]],
            sources={int(k): str(v) for k, v in d.get("sources", {}).items()},
            started_ns=int(d.get("started_ns", 0)), versions=dict(d.get("versions", {})),
            format=int(d.get("format", FORMAT_VERSION)),
            kinds={str(k): str(v) for k, v in d.get("kinds", {}).items()},
            links=[[int(a), int(b)] for a, b in d.get("links", [])],
            lineage_unknown=[str(s) for s in d.get("lineage_unknown", [])],
        )


EXPORTER_CLOSE_S = 60.0
"""The longest an exporter's ``close`` may take by default (sending what is buffered included; the
relay exporter keeps trying every relay it was given this long: ``--close-timeout``). An exporter
with a ``close_timeout_s`` of its own is waited for that long."""


class Exporter(Protocol):
    """Where the probe shipping thread sends events. Called from that thread only."""

    def start(self, header: TraceHeader) -> None: ...

    def write(self, events: np.ndarray) -> None:
        """``events``: a structured array of EVENT_DTYPE, in the order they were recorded."""

    def close(self, dropped: int) -> None:
        """The run ended; ``dropped`` events were lost in the node's buffer. Returns within
        ``EXPORTER_CLOSE_S``."""
