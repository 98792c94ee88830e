"""The probe event record and the exporter interface, shared by probes, trace files and relay.

An event is one tracepoint hit for one frame: (stage, point, source, frame, timestamp). The
node name and the stage names travel once, in the :class:`TraceHeader`; events refer to a
stage by its index in ``header.stages``. Events move in numpy structured arrays of
:data:`EVENT_DTYPE`, never as per-event Python objects.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np

FORMAT_VERSION = 1

ORIGIN, ENTER, EXIT = 0, 1, 2
POINT_NAMES = ("origin", "enter", "exit")

EVENT_DTYPE = np.dtype(
    [("ts", "<i8"), ("frame", "<i8"), ("source", "<i4"), ("stage", "<i2"), ("point", "<i1"), ("_pad", "<i1")]
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
        )


EXPORTER_CLOSE_S = 10.0
"""The longest an exporter's ``close`` may take (sending what is buffered included): the
shipping thread's ``stop`` waits at least this long for it."""


class Exporter(Protocol):
    """Where the probe shipping thread sends events. Called from that thread only."""

    def start(self, header: TraceHeader) -> None: ...

    def write(self, events: np.ndarray) -> None:
        """``events``: a structured array of EVENT_DTYPE, in the order they were recorded."""

    def close(self, dropped: int) -> None:
        """The run ended; ``dropped`` events were lost in the node's buffer. Returns within
        ``EXPORTER_CLOSE_S``."""
