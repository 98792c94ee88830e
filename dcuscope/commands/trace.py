"""``dcuscope trace [--node N] [-o TRACE] [--relay URL] -- CMD [ARGS...]``: run any GStreamer program
traced per frame, as ``perf record -- CMD`` or ``nsys profile CMD`` would.

CMD runs with dcuscope's plugin on ``GST_PLUGIN_PATH`` and the ``dcuscope`` tracer in
``GST_TRACERS`` (docs/tracer.md), so gst-launch-1.0, a C program and a Python program are traced
alike, unchanged. With ``--relay`` the trace is shipped live while CMD runs
(:class:`dcuscope.probes.ship.tailship.TailShipper`). When CMD ends, its trace's ``stats`` summary goes to
stderr (CMD's stdout stays its own) and CMD's exit status is returned (128 + N for a signal N);
a CMD that failed is reported with its status and the last line of its stderr (which passes
through dcuscope for that). An earlier TRACE waits as ``TRACE.previous`` while CMD runs, and is
put back when CMD's trace names no stage (it ran no pipeline): never replaced by an empty one.

Signals: CMD runs in a process group of its own; SIGINT (Ctrl-C), SIGTERM and SIGHUP sent to
dcuscope go to that group first, and dcuscope waits for CMD to end (a second Ctrl-C is passed
on too: gst-launch-1.0 -e ends at the first with end-of-stream). As for coreutils' ``timeout``,
CMD therefore does not read the terminal.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

from dcuscope.commands.options import add_relay_arguments
from dcuscope.core.errors import DcuscopeError
from dcuscope.core.pycompat import NEW_PROCESS_GROUP
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.nodetls import tls_from_args
from dcuscope.probes.ship.spoolargs import spool_from_args

if TYPE_CHECKING:
    from dcuscope.probes.ship.tailship import TailShipper


EPILOG = """\
examples:
  dcuscope trace -- gst-launch-1.0 -e videotestsrc num-buffers=300 ! videoconvert ! x264enc ! fakesink
  dcuscope trace --node CAM-1 -o cam1.trace.jsonl -- ./my-gst-app --camera 0
  dcuscope trace --relay http://monitor:3000 --node DCU-7 -- python3 app.py

CMD's environment gets GST_PLUGIN_PATH (dcuscope's plugin first) and GST_TRACERS (dcuscope's tracer
after any already set there). TRACE is replaced; an earlier one waits as TRACE.previous while
CMD runs, put back if CMD traced nothing (it ran no pipeline), removed otherwise. The
summary goes to stderr when CMD ends; `dcuscope stats TRACE`, `dcuscope export TRACE` and
`dcuscope compare` read TRACE later. CMD's stderr passes through dcuscope: a CMD that failed is
reported with its exit status and its stderr's last line. Ctrl-C and SIGTERM go to CMD, and
dcuscope waits for it. Exit status: CMD's (128 + N if signal N ended it); when CMD exits 0 but
--relay did not acknowledge every event and the spool did not keep them (--no-spool, a full spool),
{unacknowledged}; 2 when CMD cannot be started or an option is wrong. Events kept in the spool are sent
by the next run or dcuscope ship --drain.
""".format(unacknowledged=UNACKNOWLEDGED_STATUS)

FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
SHIP_DRAIN_S = 5.0
"""After CMD ended, how long the shipper may take to reach the trace's end line by itself."""
STDERR_DRAIN_S = 2.0
"""After CMD ended, how long its stderr may stay open (a child of CMD holding it) before dcuscope goes on."""


def add_trace_parser(sub) -> None:
    p = sub.add_parser(
        "trace", help="run any GStreamer program (gst-launch-1.0, C, Python) traced per frame: -- CMD [ARGS...]",
        description="Run CMD with dcuscope's tracer (GST_TRACERS=dcuscope): every element of every pipeline it\n"
                    "runs gets per-frame enter/exit tracepoints, written to TRACE and, with --relay, shipped live.\n"
                    "When CMD ends, print the trace's statistics (as `dcuscope stats`) and return CMD's exit status.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        usage="dcuscope trace [-h] [--node NAME] [-o TRACE] [--relay URL[,URL...]] [--token TOKEN]\n"
              "                      [--relay-ca FILE] [--relay-cert FILE [--relay-key FILE]] [--close-timeout S]\n"
              "                      [--spool DIR | --no-spool] [--spool-max SIZE]\n"
              "                      [--quiet] -- CMD [ARGS...]")
    p.add_argument("--node", metavar="NAME", help="the node's name in the trace and on the relay (default: the host name)")
    p.add_argument("-o", "--output", type=Path, metavar="TRACE", help="the trace file (default NODE.trace.jsonl)")
    add_relay_arguments(p, "ship the trace live to this relay (several, comma-separated: the next when one cannot be "
                           "reached)", after="once CMD ended", keeps="TRACE still holds it")
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
    previous = trace.with_name(trace.name + ".previous")
    try:
        if trace.exists():  # moved aside, not removed: put back should CMD trace nothing
            trace.replace(previous)
    except OSError as exc:
        raise DcuscopeError(f"trace: {trace}: cannot replace it: {exc.strerror or exc}") from exc
    if args.relay:
        from dcuscope.probes.ship.relaylink import check_token

        check_token(args.relay, args.token, tls=tls_from_args(args))
    env = dict(os.environ)
    env["GST_PLUGIN_PATH"] = os.pathsep.join(p for p in (str(plugin_dir), env.get("GST_PLUGIN_PATH")) if p)
    env["GST_TRACERS"] = ";".join(t for t in (env.get("GST_TRACERS"), tracer_spec(node, trace)) if t)

    try:
        child = subprocess.Popen(command, env=env, **NEW_PROCESS_GROUP, stderr=subprocess.PIPE)
    except OSError as exc:
        raise DcuscopeError(f"trace: cannot start {command[0]}: {exc.strerror or exc}") from exc
    errors = _Tee(child.stderr)
    handlers = {s: signal.signal(s, lambda signum, _f: _forward(child, signum)) for s in FORWARDED}
    stop = threading.Event()
    shipping = _start_shipper(args, trace, stop) if args.relay else None
    try:
        code = _wait(child)
        errors.join(STDERR_DRAIN_S)
    finally:
        if shipping is not None:
            shipping.thread.join(SHIP_DRAIN_S)
            stop.set()
            shipping.thread.join()
        for s, handler in handlers.items():
            signal.signal(s, handler)
    traced = _settle(trace, previous)
    if not args.quiet:
        _summary(trace if traced else None, trace, command[0])
    if code != 0:
        said = f": {errors.last}" if errors.last else " (nothing on its stderr)"
        print(f"dcuscope: {command[0]} {_ended(code)}{said}", file=sys.stderr)
    if code == 0 and shipping is not None and not shipping.shipper.delivery.complete:
        return UNACKNOWLEDGED_STATUS
    return code


class _Tee:
    """Passes CMD's stderr on to dcuscope's, keeping its last line (a failed CMD is reported with it)."""

    def __init__(self, pipe) -> None:
        self._pipe, self._tail = pipe, b""
        self._thread = threading.Thread(target=self._copy, name="dcuscope-stderr", daemon=True)
        self._thread.start()

    def _copy(self) -> None:
        fd, out = self._pipe.fileno(), sys.stderr.buffer
        while chunk := os.read(fd, 65536):
            out.write(chunk)
            out.flush()
            self._tail = (self._tail + chunk)[-4096:]

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)

    @property
    def last(self) -> str:
        lines = [line.strip() for line in self._tail.decode(errors="replace").splitlines() if line.strip()]
        return lines[-1] if lines else ""


def _ended(code: int) -> str:
    try:
        return f"was ended by {signal.Signals(code - 128).name} (exit status {code})" if code > 128 else \
            f"failed (exit status {code})"
    except ValueError:  # above 128 but no signal's: its own status
        return f"failed (exit status {code})"


def _settle(trace: Path, previous: Path) -> bool:
    """Whether CMD traced something (its trace names a stage): then ``previous`` (an earlier trace)
    goes; else CMD's empty trace goes and ``previous`` is put back."""
    if trace.exists() and _names_a_stage(trace):
        previous.unlink(missing_ok=True)
        return True
    try:
        trace.unlink(missing_ok=True)
        if previous.exists():
            previous.replace(trace)
    except OSError as exc:
        print(f"dcuscope: cannot put back {trace}: {exc.strerror or exc}; the earlier trace is {previous}",
              file=sys.stderr)
    return False


def _names_a_stage(path: Path) -> bool:
    """Whether the trace's header (its first line) lists a stage; an unreadable header counts as
    one (the summary then says what is wrong with it), so that a run's frames are never thrown away."""
    try:
        with open(path, "rb") as f:
            header = json.loads(f.readline()).get("header", {})
        return bool(header.get("stages"))
    except (OSError, ValueError, AttributeError):
        return True


def _forward(child: subprocess.Popen, signum: int) -> None:
    try:
        os.killpg(child.pid, signum)
    except ProcessLookupError:
        pass


def _wait(child: subprocess.Popen) -> int:
    """CMD's exit status as a shell gives it (128 + N for signal N); the handlers above run meanwhile."""
    code = child.wait()
    return 128 - code if code < 0 else code


class _Shipping(NamedTuple):
    shipper: TailShipper
    thread: threading.Thread


def _start_shipper(args: argparse.Namespace, trace: Path, stop: threading.Event) -> _Shipping:
    from dcuscope.probes.ship.tailship import TailShipper

    tls = tls_from_args(args)
    shipper = TailShipper(trace, args.relay, args.token, args.node, close_timeout_s=args.close_timeout, tls=tls,
                          spool=spool_from_args(args, relay=args.relay, token=args.token, tls=tls))

    def ship() -> None:
        try:
            shipper.run(stop, wait_s=float("inf"))
        except DcuscopeError as exc:  # the relay refused the node: CMD runs on, the trace file holds all
            print(f"dcuscope: trace: shipping stopped: {exc}", file=sys.stderr)
    thread = threading.Thread(target=ship, name="dcuscope-ship", daemon=True)
    thread.start()
    return _Shipping(shipper, thread)


def _summary(trace: Path | None, named: Path, program: str) -> None:
    """The stats of ``trace`` (this run's), or why there is none (``named``: where it was to go)."""
    from dcuscope.commands.stats import format_stats
    from dcuscope.probes.trace.stats import stats_document
    from dcuscope.probes.trace.tracefile import read_trace

    if trace is None:
        earlier = f"; {named}, an earlier run's, is kept as it was" if named.exists() else ""
        print(f"dcuscope: {program} wrote no trace to {named}: it ran no GStreamer pipeline that carried a frame "
              f"(or it set GST_TRACERS itself){earlier}", file=sys.stderr)
        return
    try:
        t = read_trace(trace)
        text = format_stats(stats_document([t]), [f"{trace}{'' if t.complete else ', no end line: CMD did not exit cleanly'}"])
    except DcuscopeError as exc:
        print(f"dcuscope: {exc}", file=sys.stderr)
        return
    print(f"\ndcuscope: {program} traced\n{text}", file=sys.stderr, end="")

