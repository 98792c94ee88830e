"""``dcuscope ship TRACE --relay URL``: stream a trace file that another process is writing (the
GStreamer tracer in any application, or ``dcuscope run``) to a relay, live, with the same
lossless, acknowledged, resumable protocol and clock exchange as ``dcuscope run --relay``
(:mod:`dcuscope.probes.ship.tailship`), until the trace ends (its process exited) or Ctrl-C/SIGTERM."""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

from dcuscope.commands.options import add_relay_arguments
from dcuscope.core import signals
from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.nodetls import tls_from_args
from dcuscope.probes.ship.spoolargs import spool_from_args


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
               "and not kept in the\nspool (the last line counts them; TRACE still holds them).\n\n"
               "dcuscope ship --drain [--relay URL]: send every run kept in the spool (a relay was down when it\n"
               "ran, or its process died) to the relays it was spooled for, or to --relay, and exit: 0 when all\n"
               f"were stored, {UNACKNOWLEDGED_STATUS} when some stay in the spool. `dcuscope spool` lists them.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trace", type=Path, nargs="?", metavar="TRACE", help="the trace file being written")
    p.add_argument("--drain", action="store_true",
                   help="instead of a TRACE: send the runs kept in the spool, then exit (see below)")
    add_relay_arguments(p, "the relay, http://HOST:PORT; or several, comma-separated, tried in turn",
                        after="once TRACE ended", keeps="TRACE still holds it")
    p.add_argument("--node", help="the node's name on the relay (default: the trace's)")
    p.add_argument("--settle", type=float, default=1.0, metavar="S",
                   help="seconds the trace's stages must stay the same before connecting (default 1)")
    p.add_argument("--wait", type=float, default=60.0, metavar="S",
                   help="give up when TRACE names no stage after S seconds (default 60)")
    p.set_defaults(func=_ship, holds_signals=True)


def _ship(args) -> int:
    # Imported here: the command line must start fast (a Ctrl-C while aiohttp loads is held).
    from dcuscope.probes.ship.relaylink import check_token
    from dcuscope.probes.ship.tailship import TailShipper

    if args.settle < 0 or args.wait <= 0 or args.close_timeout <= 0:
        raise DcuscopeError("--settle must be >= 0, --wait and --close-timeout > 0")
    if args.drain:
        if args.trace is not None or args.no_spool:
            raise DcuscopeError("--drain sends the spool: give no TRACE, nor --no-spool")
        return _drain(args)
    if args.trace is None or args.relay is None:
        raise DcuscopeError("give TRACE and --relay URL (or --drain)")
    tls = tls_from_args(args)
    check_token(args.relay, args.token, tls=tls)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if signals.held():
        return 0
    shipper = TailShipper(args.trace, args.relay, args.token, args.node, close_timeout_s=args.close_timeout, tls=tls,
                          spool=spool_from_args(args, relay=args.relay, token=args.token, tls=tls))
    try:
        return shipper.run(stop, args.settle, args.wait)
    finally:
        signals.finishing()


def _drain(args) -> int:
    from dcuscope.probes.ship.drain import drain
    from dcuscope.probes.ship.spool import Spool, default_dir
    from dcuscope.probes.ship.spoolfile import SpoolError

    try:
        spool = Spool(args.spool or default_dir(), args.spool_max)
    except SpoolError as exc:
        raise DcuscopeError(str(exc)) from None
    if not spool.runs():
        print(f"drain: the spool {spool.path} holds no run")
        return 0
    tls = tls_from_args(args)
    delivery = drain(spool, args.relay, args.token, tls, close_timeout_s=args.close_timeout,
                     say=lambda line: print(line, flush=True))
    left = spool.runs()
    print(f"drain: {delivery.stored} events stored; "
          + (f"{len(left)} run(s) still in {spool.path}" if left else f"the spool {spool.path} is empty"))
    return UNACKNOWLEDGED_STATUS if left else 0
