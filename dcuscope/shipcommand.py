"""``dcuscope ship TRACE --relay URL``: stream a trace file that another process is writing (the
GStreamer tracer in any application, or ``dcuscope run``) to a relay, live, with the same
lossless, acknowledged, resumable protocol and clock exchange as ``dcuscope run --relay``
(:mod:`dcuscope.probes.ship.tailship`), until the trace ends (its process exited) or Ctrl-C/SIGTERM."""

from __future__ import annotations

import argparse
import os
import signal
import threading
from pathlib import Path

from dcuscope.core import signals
from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.nodetls import TOKEN_ENV, add_tls_arguments, tls_from_args


def add_ship_parser(sub) -> None:
    p = sub.add_parser(
        "ship", help="stream a trace file that a running process writes (e.g. the GStreamer tracer) to a relay",
        description="Read TRACE as it grows and stream its events to a relay, live, as `dcuscope run --relay` "
                    "does: acknowledged batches, resent after a reconnect, with the clock exchange of this "
                    "host. Ends when the trace ends (its process exited) or on Ctrl-C.",
        epilog="example:\n  GST_PLUGIN_PATH=\"$(dcuscope plugin-path)\" GST_TRACERS=\"dcuscope(node=CAM-1,"
               "trace=cam1.trace.jsonl)\" \\\n      gst-launch-1.0 ... &\n"
               "  dcuscope ship cam1.trace.jsonl --relay http://monitor:3000\n\n"
               "Exit status: 0 every event acknowledged by a relay, 1 TRACE named no stage within --wait,\n"
               f"2 bad arguments, {UNACKNOWLEDGED_STATUS} events not all acknowledged within --close-timeout "
               "(the last line counts\nthem; TRACE still holds them).",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trace", type=Path, metavar="TRACE", help="the trace file being written")
    p.add_argument("--relay", required=True, metavar="URL[,URL...]",
                   help="the relay, http://HOST:PORT; or several, comma-separated, tried in turn")
    p.add_argument("--token", default=os.environ.get(TOKEN_ENV),
                   help=f"the relay's node token, if it asks for one (default ${TOKEN_ENV})")
    add_tls_arguments(p)
    p.add_argument("--node", help="the node's name on the relay (default: the trace's)")
    p.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="seconds the trace's stages must stay the same before connecting (default 1)")
    p.add_argument("--wait", type=float, default=60.0, metavar="S",
                   help="give up when TRACE names no stage after S seconds (default 60)")
    p.add_argument("--close-timeout", type=float, default=60.0, metavar="S",
                   help="once TRACE ended, keep trying every --relay for up to S seconds until all that was sent "
                        "is acknowledged (default 60); what is still unacknowledged then is reported lost")
    p.set_defaults(func=_ship, holds_signals=True)


def _ship(args) -> int:
    # Imported here: the command line must start fast (a Ctrl-C while aiohttp loads is held).
    from dcuscope.probes.ship.relaylink import check_token
    from dcuscope.probes.ship.tailship import TailShipper

    if args.settle < 0 or args.wait <= 0 or args.close_timeout <= 0:
        raise DcuscopeError("--settle must be >= 0, --wait and --close-timeout > 0")
    tls = tls_from_args(args)
    check_token(args.relay, args.token, tls=tls)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if signals.held():
        return 0
    shipper = TailShipper(args.trace, args.relay, args.token, args.node, close_timeout_s=args.close_timeout, tls=tls)
    try:
        return shipper.run(stop, args.settle, args.wait)
    finally:
        signals.finishing()
