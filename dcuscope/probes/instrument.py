"""Probes for one ``dcuscope run``: tracepoints on the built pipeline, shipped to a trace file
and/or a relay, with a one-line summary at the end."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from dcuscope.core.clocks import CLOCKS, PretendClock
from dcuscope.core.errors import UsageError
from dcuscope.pipeline.build import BuiltPipeline
from dcuscope.pipeline.config import PipelineConfig
from dcuscope.probes.capture.native import unavailable_reason
from dcuscope.probes.capture.processtracer import ProcessTracer
from dcuscope.probes.capture.shipper import Shipper
from dcuscope.probes.capture.sourcewatch import SourceWatch
from dcuscope.probes.capture.tracer import Tracer, attach
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS
from dcuscope.probes.ship.delivery import Delivery
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.relaylink import check_token
from dcuscope.probes.ship.shifted import Shifted
from dcuscope.probes.ship.tailship import TailShipper
from dcuscope.probes.trace.errors import TraceError
from dcuscope.probes.trace.tracefile import TraceFileWriter
from dcuscope.protocol.events import EXPORTER_CLOSE_S, Exporter


@dataclass
class RunProbes:
    tracer: Tracer
    shipper: Shipper
    trace: Path | None
    progress: TextIO | None
    relay: RelayExporter | None = None
    watch: SourceWatch | None = None

    def stop(self) -> Delivery | None:
        """Stop shipping and write the summary; what the relay stored (None without --relay).
        Raises ExportError if the relay refused the node (``dcuscope run`` then exits non-zero
        with that one line)."""
        self.shipper.stop()
        if self.watch is not None:
            self.watch.stop()
        tracepoints = self.tracer.tracepoints
        self.tracer.detach()
        delivery = self.relay.delivery() if self.relay is not None else None
        if self.progress is not None:
            where = f"; trace: {self.trace}" if self.trace else ""
            dropped = self.tracer.dropped
            self.progress.write(f"probes: {self.shipper.shipped} events from {tracepoints} tracepoints "
                                f"({self.tracer.backend}, {self.tracer.trigger}), {dropped} dropped{where}\n")
            for error in self.shipper.errors:
                self.progress.write(f"probes: {error}\n")
        if self.relay is not None and self.relay.refused:
            raise ExportError(self.relay.refused)
        if self.progress is not None and delivery is not None:
            self.progress.write(f"probes: {delivery.line()}\n")
        return delivery


def default_trace_path(node: str) -> Path:
    return Path.cwd() / f"{node}.trace.jsonl"


@dataclass
class LaunchProbes:
    """Probes of a ``launch:`` pipeline: the dcuscope GStreamer tracer, made in this process,
    writes the trace; a thread follows it to the relay."""

    tracer: ProcessTracer
    trace: Path
    progress: TextIO | None
    close_timeout_s: float = EXPORTER_CLOSE_S
    shipper: TailShipper | None = None
    thread: threading.Thread | None = None

    def stop(self) -> Delivery | None:
        """Finish the trace and write the summary; what the relay stored (None without --relay)."""
        try:
            stages, events, dropped = self.tracer.finish()  # the end line: the shipper sends the rest, closes
        except TraceError as exc:
            stages = None
            if self.progress is not None:
                self.progress.write(f"probes: {exc}\n")
        if self.thread is not None:
            self.thread.join(self.close_timeout_s + 5.0)
        if self.progress is not None and stages is not None:
            self.progress.write(f"probes: {events} events from {stages} stages (the dcuscope tracer, every element), "
                                f"{dropped} dropped; trace: {self.trace}\n")
        return self.shipper.delivery if self.shipper is not None else None


def _start_tracer(config: PipelineConfig, relay: str | None, token: str | None, progress: TextIO | None,
                  close_timeout_s: float, tls: RelayTls | None, spool=None,
                  pretend: PretendClock | None = None) -> LaunchProbes:
    trace = config.probes.trace or default_trace_path(config.node)
    probes = LaunchProbes(ProcessTracer(config.node, trace, config.probes.clock), Path(trace), progress, close_timeout_s)
    if relay is not None:
        probes.shipper = TailShipper(Path(trace), relay, token, config.node,
                                     say=lambda line: progress.write(line + "\n") if progress else None,
                                     close_timeout_s=close_timeout_s, tls=tls, spool=spool, pretend=pretend)
        # No stop event: it ends with the trace's end line, which stop() has the tracer write.
        probes.thread = threading.Thread(target=probes.shipper.run, args=(threading.Event(), 1.0, 1e9),
                                         name="dcuscope-tailship", daemon=True)
        probes.thread.start()
    return probes


def start_probes(built: BuiltPipeline, config: PipelineConfig, relay: str | None = None, token: str | None = None,
                 clock_offset_ns: int = 0, progress: TextIO | None = None, clock_drift_ppm: float = 0.0,
                 ptp_socket: str = DEFAULT_UDS, close_timeout_s: float = EXPORTER_CLOSE_S,
                 tls: RelayTls | None = None, spool=None) -> RunProbes | LaunchProbes:
    """Attach tracepoints to every element of ``built`` (not yet playing) and start shipping.
    ``clock_offset_ns`` and ``clock_drift_ppm``: testing aids (:class:`dcuscope.core.clocks.PretendClock`).
    A ``launch:`` pipeline is traced by the dcuscope GStreamer tracer (:class:`LaunchProbes`)."""
    if relay is not None:
        check_token(relay, token, tls=tls)  # a wrong token ends the run before it starts, not after
    pretend = PretendClock(int(clock_offset_ns), float(clock_drift_ppm), CLOCKS[config.probes.clock])
    if config.launch is not None:
        if pretend.shifts and relay is None:
            raise UsageError("--clock-offset-ms and --clock-drift-ppm: a launch: pipeline's trace file holds its own "
                             "clock; the pretence is for what it sends a relay (give --relay)")
        return _start_tracer(config, relay, token, progress, close_timeout_s, tls, spool,
                             pretend if pretend.shifts else None)
    sources = {s.index: s.config.description for s in built.sources}
    tracer = attach(built.pipeline, config.node, clock=config.probes.clock, sources=sources,
                    trigger=config.probes.trigger)
    if tracer.backend == "python" and progress is not None:  # said, not silent: a few times the cost per event
        progress.write(f"probes: Python probes (no service/wait split), as the native library is unavailable: "
                       f"{unavailable_reason()}\n")
    trace = config.probes.trace
    if trace is None and relay is None:
        trace = default_trace_path(config.node)
    exporters: list[Exporter] = []
    if trace is not None:
        exporters.append(TraceFileWriter(trace))
    relay_exporter = None
    if relay is not None:
        relay_exporter = RelayExporter(relay, config.node, token=token, clock=config.probes.clock, pretend=pretend,
                                       ptp_socket=ptp_socket, close_timeout_s=close_timeout_s, tls=tls, spool=spool)
        exporters.append(relay_exporter)
    if pretend.shifts:
        exporters = [Shifted(e, pretend) for e in exporters]
    watch = SourceWatch(tracer, built.pipeline).start()
    shipper = Shipper(tracer, exporters, before_ship=watch.poll).start()
    return RunProbes(tracer, shipper, trace, progress, relay_exporter, watch)
