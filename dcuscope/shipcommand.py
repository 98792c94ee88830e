"""``dcuscope ship TRACE --relay URL``: stream a trace file that another process is writing (the
GStreamer tracer in any application, or ``dcuscope run``) to a relay, live, with the same
lossless, acknowledged, resumable protocol and clock exchange as ``dcuscope run --relay``.

It reads the file as it grows (probes.follow). It connects once the file's stages have stayed
the same for ``--settle`` seconds (a pipeline that builds itself while it starts, decodebin's,
names its stages then), and ends when the trace's end line arrives (the traced process ended)
or on Ctrl-C/SIGTERM. Should stages still appear later, the node starts a new run on the relay
with the larger graph (said on stderr): a relay run's stages are fixed.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from core import signals
from core.errors import DcuscopeError
from probes.errors import ExportError
from probes.events import EVENT_DTYPE, TraceHeader
from probes.follow import TraceFollower
from probes.relayexport import RelayExporter
from probes.relaylink import check_token

POLL_S = 0.1


def add_ship_parser(sub) -> None:
    p = sub.add_parser(
        "ship", help="stream a trace file that a running process writes (e.g. the GStreamer tracer) to a relay",
        description="Read TRACE as it grows and stream its events to a relay, live, as `dcuscope run --relay` "
                    "does: acknowledged batches, resent after a reconnect, with the clock exchange of this "
                    "host. Ends when the trace ends (its process exited) or on Ctrl-C.",
        epilog="example:\n  GST_PLUGIN_PATH=\"$(dcuscope plugin-path)\" GST_TRACERS=\"dcuscope(node=CAM-1,"
               "trace=cam1.trace.jsonl)\" \\\n      gst-launch-1.0 ... &\n"
               "  dcuscope ship cam1.trace.jsonl --relay http://monitor:3000",
        formatter_class=__import__("argparse").RawDescriptionHelpFormatter)
    p.add_argument("trace", type=Path, metavar="TRACE", help="the trace file being written")
    p.add_argument("--relay", required=True, metavar="URL", help="the relay, http://HOST:PORT")
    p.add_argument("--token", help="the relay's node token, if it asks for one")
    p.add_argument("--node", help="the node's name on the relay (default: the trace's)")
    p.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="seconds the trace's stages must stay the same before connecting (default 1)")
    p.add_argument("--wait", type=float, default=60.0, metavar="S",
                   help="give up when TRACE names no stage after S seconds (default 60)")
    p.set_defaults(func=_ship, holds_signals=True)


def _ship(args) -> int:
    if args.settle < 0 or args.wait <= 0:
        raise DcuscopeError("--settle must be >= 0 and --wait > 0")
    check_token(args.relay, args.token)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if signals.held():
        return 0
    shipper = _Ship(args.trace, args.relay, args.token, args.node)
    try:
        return shipper.run(stop, args.settle, args.wait)
    finally:
        signals.finishing()


class _Ship:
    def __init__(self, trace: Path, relay: str, token: str | None, node: str | None) -> None:
        self.follower = TraceFollower(trace)
        self.relay, self.token, self.node = relay, token, node
        self.exporter: RelayExporter | None = None
        self.sent = 0
        self.runs = 0

    def run(self, stop: threading.Event, settle_s: float, wait_s: float) -> int:
        pending, header = self._settle(stop, settle_s, wait_s)
        if header is None:
            return 0 if stop.is_set() else 1
        self._connect(header)
        self._write(pending)
        ended, dropped = self.follower.ended, 0
        while not ended and not stop.is_set():
            update = self.follower.poll()
            if update.header_changed:
                print(f"ship: {self.follower.path} names new stages; a new run on the relay", file=sys.stderr)
                self._close(0)
                self._connect(update.header)
            self._write(update.events)
            ended, dropped = update.ended, update.dropped
            if not ended:
                stop.wait(POLL_S)
        self._close(dropped)
        state = "ended" if ended else "still being written"
        print(f"ship: {self.sent} events of {self._name(self.follower.header)} sent to {self.relay} in "
              f"{self.runs} run(s); the trace is {state}", file=sys.stderr)
        return 0

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
                    print(f"ship: error: {self.follower.path} names no stage after {wait_s:g} s "
                          "(is the traced process running, with GST_TRACERS=dcuscope(trace=...)?)", file=sys.stderr)
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
        self.exporter = RelayExporter(self.relay, self._name(header), token=self.token, clock=header.clock)
        self.exporter.start(header)
        self.runs += 1

    def _write(self, events: list[np.ndarray] | np.ndarray) -> None:
        if isinstance(events, list):
            events = np.concatenate(events) if events else np.empty(0, EVENT_DTYPE)
        if len(events):
            self.exporter.write(events)
            self.sent += len(events)

    def _close(self, dropped: int) -> None:
        exporter, self.exporter = self.exporter, None
        if exporter is not None:
            exporter.close(dropped)
            if exporter.refused:
                raise ExportError(exporter.refused)
