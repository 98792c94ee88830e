"""Probes for one ``dcuscope run``: tracepoints on the built pipeline, shipped to a trace file
and/or a relay, with a one-line summary at the end."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from pipeline.build import BuiltPipeline
from pipeline.config import PipelineConfig
from probes.errors import ExportError
from probes.events import CAPTURE, Exporter, TraceHeader
from probes.relayexport import RelayExporter
from probes.relaylink import check_token
from probes.shipper import Shipper
from probes.sourcewatch import SourceWatch
from probes.sysclock import DEFAULT_UDS
from probes.tracefile import TraceFileWriter
from probes.tracer import Tracer, attach


class _Shifted:
    """Exporter wrapper that moves every timestamp the node's clock took by ``offset_ns``: the
    --clock-offset-ms testing aid, so that a node can pretend its clock is off and the relay must
    notice. Capture times are left as they are: they are the camera's clock (an RTSP sender's
    reports), which a node whose own clock is off still receives unchanged, and which two DCUs
    of one camera must share for their frames to be matched (relay.moments)."""

    def __init__(self, inner: Exporter, offset_ns: int):
        self.inner, self.offset_ns = inner, offset_ns

    def start(self, header: TraceHeader) -> None:
        header.started_ns += self.offset_ns
        self.inner.start(header)

    def write(self, events: np.ndarray) -> None:
        shifted = events.copy()
        shifted["ts"][shifted["point"] != CAPTURE] += self.offset_ns
        self.inner.write(shifted)

    def close(self, dropped: int) -> None:
        self.inner.close(dropped)


@dataclass
class RunProbes:
    tracer: Tracer
    shipper: Shipper
    trace: Path | None
    progress: TextIO | None
    relay: RelayExporter | None = None
    watch: SourceWatch | None = None

    def stop(self) -> None:
        """Stop shipping and write the summary; raises ExportError if the relay refused the node
        (``dcuscope run`` then exits non-zero with that one line)."""
        self.shipper.stop()
        if self.watch is not None:
            self.watch.stop()
        tracepoints = self.tracer.tracepoints
        self.tracer.detach()
        if self.progress is not None:
            where = f"trace: {self.trace}" if self.trace else "events sent to the relay"
            dropped = self.tracer.dropped
            self.progress.write(f"probes: {self.shipper.shipped} events from {tracepoints} tracepoints "
                                f"({self.tracer.backend}), {dropped} dropped; {where}\n")
            for error in self.shipper.errors:
                self.progress.write(f"probes: {error}\n")
        if self.relay is not None and self.relay.refused:
            raise ExportError(self.relay.refused)


def default_trace_path(node: str) -> Path:
    return Path.cwd() / f"{node}.trace.jsonl"


def start_probes(built: BuiltPipeline, config: PipelineConfig, relay: str | None = None, token: str | None = None,
                 clock_offset_ns: int = 0, progress: TextIO | None = None,
                 ptp_socket: str = DEFAULT_UDS) -> RunProbes:
    """Attach tracepoints to every element of ``built`` (not yet playing) and start shipping."""
    if relay is not None:
        check_token(relay, token)  # a wrong token ends the run before it starts, not after
    sources = {s.index: s.config.description for s in built.sources}
    tracer = attach(built.pipeline, config.node, clock=config.probes.clock, sources=sources)
    trace = config.probes.trace
    if trace is None and relay is None:
        trace = default_trace_path(config.node)
    exporters: list[Exporter] = []
    if trace is not None:
        exporters.append(TraceFileWriter(trace))
    relay_exporter = None
    if relay is not None:
        relay_exporter = RelayExporter(relay, config.node, token=token, clock=config.probes.clock,
                                       clock_offset_ns=clock_offset_ns, ptp_socket=ptp_socket)
        exporters.append(relay_exporter)
    if clock_offset_ns:
        exporters = [_Shifted(e, clock_offset_ns) for e in exporters]
    watch = SourceWatch(tracer, built.pipeline).start()
    shipper = Shipper(tracer, exporters, before_ship=watch.poll).start()
    return RunProbes(tracer, shipper, trace, progress, relay_exporter, watch)
