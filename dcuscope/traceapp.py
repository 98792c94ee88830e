"""``dcuscope trace [--node N] [-o TRACE] [--relay URL] -- CMD [ARGS...]``: run any GStreamer program
traced per frame, as ``perf record -- CMD`` or ``nsys profile CMD`` would.

CMD runs with dcuscope's plugin on ``GST_PLUGIN_PATH`` and the ``dcuscope`` tracer in
``GST_TRACERS`` (docs/tracer.md), so gst-launch-1.0, a C program and a Python program are traced
alike, unchanged. With ``--relay`` the trace is shipped live while CMD runs
(:class:`dcuscope.probes.ship.tailship.TailShipper`). When CMD ends, its trace's ``stats`` summary goes to
stderr (CMD's stdout stays its own) and CMD's exit status is returned (128 + N for a signal N).

Signals: CMD runs in a process group of its own; SIGINT (Ctrl-C), SIGTERM and SIGHUP sent to
dcuscope go to that group first, and dcuscope waits for CMD to end (a second Ctrl-C is passed
on too: gst-launch-1.0 -e ends at the first with end-of-stream). As for coreutils' ``timeout``,
CMD therefore does not read the terminal.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.ship.nodetls import TOKEN_ENV, add_tls_arguments, tls_from_args

EPILOG = """\
examples:
  dcuscope trace -- gst-launch-1.0 -e videotestsrc num-buffers=300 ! videoconvert ! x264enc ! fakesink
  dcuscope trace --node CAM-1 -o cam1.trace.jsonl -- ./my-gst-app --camera 0
  dcuscope trace --relay http://monitor:3000 --node DCU-7 -- python3 app.py

CMD's environment gets GST_PLUGIN_PATH (dcuscope's plugin first) and GST_TRACERS (dcuscope's tracer
after any already set there). TRACE is overwritten. The summary goes to stderr when CMD ends;
`dcuscope stats TRACE`, `dcuscope export TRACE` and `dcuscope compare` read TRACE later.
Ctrl-C and SIGTERM go to CMD, and dcuscope waits for it. Exit status: CMD's (128 + N if signal N
ended it); 2 when CMD cannot be started or an option is wrong.
"""

FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
SHIP_DRAIN_S = 5.0
"""After CMD ended, how long the shipper may take to reach the trace's end line by itself."""


def add_trace_parser(sub) -> None:
    p = sub.add_parser(
        "trace", help="run any GStreamer program (gst-launch-1.0, C, Python) traced per frame: -- CMD [ARGS...]",
        description="Run CMD with dcuscope's tracer (GST_TRACERS=dcuscope): every element of every pipeline it "
                    "runs gets per-frame enter/exit tracepoints, written to TRACE and, with --relay, shipped live. "
                    "When CMD ends, print the trace's statistics (as `dcuscope stats`) and return CMD's exit status.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        usage="dcuscope trace [-h] [--node NAME] [-o TRACE] [--relay URL[,URL...]] [--token TOKEN] [--relay-ca FILE] "
              "[--relay-cert FILE [--relay-key FILE]] [--quiet] "
              "-- CMD [ARGS...]")
    p.add_argument("--node", metavar="NAME", help="the node's name in the trace and on the relay (default: the host name)")
    p.add_argument("-o", "--output", type=Path, metavar="TRACE", help="the trace file (default NODE.trace.jsonl)")
    p.add_argument("--relay", metavar="URL[,URL...]", help="ship the trace live to this relay (several, comma-separated: "
                                                          "the next when one cannot be reached)")
    p.add_argument("--token", metavar="TOKEN", default=os.environ.get(TOKEN_ENV),
                   help=f"the relay's node token, if it asks for one (default ${TOKEN_ENV})")
    add_tls_arguments(p)
    p.add_argument("--quiet", "-q", action="store_true", help="no summary when CMD ends (the trace is still written)")
    p.add_argument("command", nargs=argparse.REMAINDER, metavar="CMD", help="the program and its arguments, after --")
    p.set_defaults(func=run_trace)


def tracer_spec(node: str, trace: Path) -> str:
    """The ``dcuscope(...)`` entry of GST_TRACERS, values quoted as GStreamer structures want them."""
    def quoted(value: str) -> str:
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return f"dcuscope(node={quoted(node)},trace={quoted(str(trace))})"


def run_trace(args: argparse.Namespace) -> int:
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        raise DcuscopeError("trace: give the program to run after --, e.g. dcuscope trace -- gst-launch-1.0 ...")
    program = shutil.which(command[0])
    if program is None:
        raise DcuscopeError(f"trace: {command[0]}: no such program (not found on PATH, nor a file that can be run)")
    from dcuscope.probes.capture.native import BuildError, build

    try:
        plugin_dir = build().parent
    except BuildError as exc:
        raise DcuscopeError(f"trace: no dcuscope GStreamer plugin: {exc}") from exc
    node = args.node or socket.gethostname()
    trace = (args.output or Path(f"{node}.trace.jsonl")).absolute()
    try:
        trace.unlink(missing_ok=True)  # a shipper must not read a previous run's lines
    except OSError as exc:
        raise DcuscopeError(f"trace: {trace}: cannot replace it: {exc.strerror or exc}") from exc
    if args.relay:
        from dcuscope.probes.ship.relaylink import check_token

        check_token(args.relay, args.token, tls=tls_from_args(args))
    env = dict(os.environ)
    env["GST_PLUGIN_PATH"] = os.pathsep.join(p for p in (str(plugin_dir), env.get("GST_PLUGIN_PATH")) if p)
    env["GST_TRACERS"] = ";".join(t for t in (env.get("GST_TRACERS"), tracer_spec(node, trace)) if t)

    try:
        child = subprocess.Popen(command, env=env, process_group=0)
    except OSError as exc:
        raise DcuscopeError(f"trace: cannot start {command[0]}: {exc.strerror or exc}") from exc
    previous = {s: signal.signal(s, lambda signum, _f: _forward(child, signum)) for s in FORWARDED}
    stop = threading.Event()
    shipper = _start_shipper(args, trace, stop) if args.relay else None
    try:
        code = _wait(child)
    finally:
        if shipper is not None:
            shipper.join(SHIP_DRAIN_S)
            stop.set()
            shipper.join()
        for s, handler in previous.items():
            signal.signal(s, handler)
    if not args.quiet:
        _summary(trace, command[0])
    return code


def _forward(child: subprocess.Popen, signum: int) -> None:
    try:
        os.killpg(child.pid, signum)
    except ProcessLookupError:
        pass


def _wait(child: subprocess.Popen) -> int:
    """CMD's exit status as a shell gives it (128 + N for signal N); the handlers above run meanwhile."""
    code = child.wait()
    return 128 - code if code < 0 else code


def _start_shipper(args: argparse.Namespace, trace: Path, stop: threading.Event) -> threading.Thread:
    from dcuscope.probes.ship.tailship import TailShipper

    shipper = TailShipper(trace, args.relay, args.token, args.node, tls=tls_from_args(args))

    def ship() -> None:
        try:
            shipper.run(stop, wait_s=float("inf"))
        except DcuscopeError as exc:  # the relay refused the node: CMD runs on, the trace file holds all
            print(f"dcuscope: trace: shipping stopped: {exc}", file=sys.stderr)
    thread = threading.Thread(target=ship, name="dcuscope-ship", daemon=True)
    thread.start()
    return thread


def _summary(trace: Path, program: str) -> None:
    from dcuscope.tracecommands import format_stats
    from dcuscope.probes.trace.stats import stats_document
    from dcuscope.probes.trace.tracefile import read_trace

    if not trace.exists():
        print(f"dcuscope: {program} wrote no trace to {trace}: it ran no GStreamer pipeline that carried a frame "
              "(or it set GST_TRACERS itself)", file=sys.stderr)
        return
    try:
        t = read_trace(trace)
        text = format_stats(stats_document([t]), [f"{trace}{'' if t.complete else ', no end line: CMD did not exit cleanly'}"])
    except DcuscopeError as exc:
        print(f"dcuscope: {exc}", file=sys.stderr)
        return
    print(f"\ndcuscope: {program} traced\n{text}", file=sys.stderr, end="")
