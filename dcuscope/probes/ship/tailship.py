"""Stream a trace file that is being written (by the GStreamer tracer in any process, or by
``dcuscope run``) to a relay, live, with the relay exporter of ``dcuscope run --relay``
(acknowledged, resumable, with the clock exchange of this host).

It reads the file as it grows (:mod:`dcuscope.probes.trace.follow`). It connects once the file's stages have
stayed the same for ``settle_s`` (a pipeline that builds itself while it starts, decodebin's,
names its stages then), and ends when the trace's end line arrives or ``stop`` is set. Should
stages still appear later, the node starts a new run on the relay with the larger graph (said
once): a relay run's stages are fixed.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from dcuscope.core.clocks import PretendClock
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS, Delivery
from dcuscope.probes.ship.errors import ExportError
from dcuscope.probes.ship.nodetls import RelayTls
from dcuscope.probes.ship.relayexport import RelayExporter
from dcuscope.probes.ship.shifted import Shifted
from dcuscope.probes.trace.follow import TraceFollower
from dcuscope.protocol.events import EVENT_DTYPE, EXPORTER_CLOSE_S, TraceHeader

POLL_S = 0.1


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class TailShipper:
    def __init__(self, trace: Path, relay: str, token: str | None = None, node: str | None = None,
                 say: Callable[[str], None] = _stderr, close_timeout_s: float = EXPORTER_CLOSE_S,
                 tls: RelayTls | None = None, spool=None, pretend: PretendClock | None = None) -> None:
        """``pretend``: the --clock-offset-ms testing aid (:mod:`dcuscope.probes.ship.shifted`), for
        the trace's clock."""
        self.tls, self.spool, self.pretend = tls, spool, pretend
        self.follower = TraceFollower(trace)
        self.close_timeout_s = close_timeout_s
        self.relay, self.token, self.node, self.say = relay, token, node, say
        self.exporter: RelayExporter | None = None
        self.sent = 0
        self.runs = 0
        self._delivered = Delivery()
        """What the relay runs closed so far delivered."""

    @property
    def delivery(self) -> Delivery:
        """What this shipper's relay runs delivered: the closed ones, and the open one so far."""
        return self._delivered + self.exporter.delivery() if self.exporter is not None else self._delivered

    def run(self, stop: threading.Event, settle_s: float = 1.0, wait_s: float = 60.0) -> int:
        """Ship until the trace ends or ``stop`` is set; 0 done, 1 the trace never named a stage,
        UNACKNOWLEDGED_STATUS the relays did not acknowledge every event."""
        pending, header = self._settle(stop, settle_s, wait_s)
        if header is None:
            return 0 if stop.is_set() else 1
        self._connect(header)
        self._write(pending)
        ended, dropped = self.follower.ended, 0
        while not ended and not stop.is_set():
            update = self.follower.poll()
            if update.header_changed:
                self.say(f"ship: {self.follower.path} names new stages; a new run on the relay")
                self._close(0)
                self._connect(update.header)
            self._write(update.events)
            ended, dropped = update.ended, update.dropped
            if not ended:
                stop.wait(POLL_S)
        if not ended:  # stopped: what was written until now still goes
            update = self.follower.poll()
            if not update.header_changed:
                self._write(update.events)
                ended, dropped = update.ended, update.dropped
        self._close(dropped)
        state = "ended" if ended else "still being written"
        delivery = self.delivery
        self.say(f"ship: {self._name(self.follower.header)}, {self.runs} run(s), the trace is {state}; "
                 f"{delivery.line()}")
        return 0 if delivery.complete else UNACKNOWLEDGED_STATUS

    def _settle(self, stop, settle_s: float, wait_s: float) -> tuple[list[np.ndarray], TraceHeader | None]:
        """Events read until the stages stayed the same for settle_s (or the trace ended)."""
        pending: list[np.ndarray] = []
        deadline, stable_since = time.monotonic() + wait_s, None
        while not stop.is_set():
            update = self.follower.poll()
            pending.append(update.events)
            now = time.monotonic()
            if update.header is None:
                if now > deadline:
                    self.say(f"ship: error: {self.follower.path} names no stage after {wait_s:g} s "
                             "(is the traced process running, with GST_TRACERS=dcuscope(trace=...)?)")
                    return pending, None
            elif update.header_changed or stable_since is None:
                stable_since = now
            if update.ended or (stable_since is not None and now - stable_since >= settle_s):
                return pending, self.follower.header
            stop.wait(POLL_S)
        return pending, None

    def _name(self, header: TraceHeader | None) -> str:
        return self.node or (header.node if header else "?")

    def _connect(self, header: TraceHeader) -> None:
        self.exporter = RelayExporter(self.relay, self._name(header), token=self.token, clock=header.clock,
                                      close_timeout_s=self.close_timeout_s, tls=self.tls, spool=self.spool,
                                      pretend=self.pretend)
        self._out = Shifted(self.exporter, self.pretend) if self.pretend is not None and self.pretend.shifts \
            else self.exporter
        self._out.start(header)
        self.runs += 1

    def _write(self, events: list[np.ndarray] | np.ndarray) -> None:
        if isinstance(events, list):
            events = np.concatenate(events) if events else np.empty(0, EVENT_DTYPE)
        if len(events):
            self._out.write(events)
            self.sent += len(events)

    def _close(self, dropped: int) -> None:
        exporter, self.exporter = self.exporter, None
        if exporter is not None:
            exporter.close(dropped)
            self._delivered += exporter.delivery()
            if exporter.refused:
                raise ExportError(exporter.refused)
