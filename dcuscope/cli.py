"""The ``dcuscope`` command line."""

from __future__ import annotations

import argparse
import os
import importlib.metadata
import sys
from pathlib import Path

from dcuscope.capacity.command import add_capacity_parser
from dcuscope.comparecommand import add_compare_parser
from dcuscope.core import signals
from dcuscope.core.errors import DcuscopeError, PipelineError
from dcuscope.core.pycompat import tomllib
from dcuscope.dbcommand import add_db_parser
from dcuscope.extras import require_pipeline
from dcuscope.helpformat import use_everywhere
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS
from dcuscope.probes.ship.nodetls import add_tls_arguments
from dcuscope.probes.ship.spoolargs import add_spool_arguments
from dcuscope.protocol.credentials import TOKEN_ENV
from dcuscope.relay.commands import add_relay_parser
from dcuscope.sessionscommand import add_sessions_parsers
from dcuscope.shipcommand import add_ship_parser
from dcuscope.shipped import add_configs_parser
from dcuscope.spoolcommand import add_spool_parser
from dcuscope.traceapp import add_trace_parser
from dcuscope.tracecommands import add_export_parser, add_stats_parser

DESCRIPTION = """\
dcuscope: see where the time goes in multi-camera video-analytics pipelines.

Pipelines are declared in YAML (see configs/) and run on real GStreamer with dcuscope's
elements mux, infer, tiler, convert and osd; with --probes every element gets per-frame
enter/exit tracepoints, written to a trace file and/or streamed to a relay.
"""

RUN_EPILOG = """\
examples:
  dcuscope run configs/vtest.yaml --num-frames 50
  dcuscope run configs/quad.yaml --output out.mp4 --num-frames 100
  dcuscope run configs/quad.yaml --probes --trace quad.jsonl --duration 20
  dcuscope run configs/quad.yaml --probes --relay http://127.0.0.1:3000 --node DCU-1

--output picks the sink from the path: NAME.mp4 (.mkv, .avi) writes H.264 video in that
container, a folder (or a path ending in /) writes numbered PNG frames into it. Ctrl-C or
SIGTERM ends the run cleanly (end-of-stream, so the MP4 is finalised), as --duration and
--num-frames do; Ctrl-C while it stops aborts, leaving the video incomplete (exit 130), SIGTERM
never does. Files drain: every frame read is processed. Live sources (cameras, streams, live:
true) stop at once instead: frames still queued (a pipeline that cannot keep up) are dropped
and counted (reason "stopped" in the trace), so that the run ends within about a batch's time.
Exit status: 0 done, 1 the pipeline failed, 2 bad configuration or arguments, 3 the run went
well but --relay did not acknowledge every probe event within --close-timeout and the spool did
not keep them (--no-spool, a full spool or disk; the summary's "relay:" line counts them; a --trace
file still holds them), 130 aborted. Events kept in the spool are not lost: the next run, or
dcuscope ship --drain, sends them (dcuscope spool lists them).
"""

PLUGIN_EPILOG = """\
example:
  GST_PLUGIN_PATH="$(dcuscope plugin-path)" \\
  GST_TRACERS="dcuscope(node=DCU-1,trace=dcu1.trace.jsonl)" \\
  gst-launch-1.0 videotestsrc num-buffers=300 ! videoconvert ! x264enc ! fakesink
  dcuscope stats dcu1.trace.jsonl

tracer parameters: node (default: the host name), trace (default: NODE.trace.jsonl),
clock (realtime, monotonic or tai; default realtime), capacity (ring size in events).
"""

MAX_DRIFT_PPM = 1000.0
"""Beyond any quartz (tens of ppm): a larger --clock-drift-ppm is a typo."""

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"

CLOSE_TIMEOUT_S = 60.0
"""``--close-timeout``'s default: protocol.events.EXPORTER_CLOSE_S (not imported here: numpy slows the start)."""


def version() -> str:
    """The installed package's version, else (a source tree not installed) pyproject.toml's."""
    try:
        return importlib.metadata.version("dcuscope")
    except importlib.metadata.PackageNotFoundError:
        try:
            return tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dcuscope", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"dcuscope {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    run = sub.add_parser("run", help="run a pipeline from a YAML configuration",
                         description="Run a pipeline from a YAML configuration (see configs/).", epilog=RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    run.add_argument("config", type=Path, metavar="CONFIG",
                     help="pipeline configuration (YAML), or the name of a shipped one (dcuscope configs lists them)")
    run.add_argument("--output", "-o", type=Path, metavar="PATH",
                     help="write the osd's frames: NAME.mp4, .mkv or .avi (H.264) or a folder/ for PNG frames (overrides sink:)")
    limit = run.add_mutually_exclusive_group()
    limit.add_argument("--num-frames", "-n", type=_positive_int, metavar="N",
                       help="stop cleanly after N frames reached the sink")
    limit.add_argument("--duration", "-d", type=_positive_float, metavar="S",
                       help="stop cleanly after S seconds (live sources: at S seconds, frames still queued dropped)")
    run.add_argument("--node", metavar="NAME", help="name of this machine in traces and the relay (default: node: of the config, else DCU-1)")
    run.add_argument("--quiet", "-q", action="store_true", help="no progress lines")
    probes = run.add_argument_group("probes")
    probes.add_argument("--probes", action="store_true", help="put enter/exit tracepoints on every element")
    probes.add_argument("--trace", type=Path, metavar="PATH", help="write probe events to this trace file (JSON Lines)")
    probes.add_argument("--clock", choices=("realtime", "tai", "monotonic"),
                        help="clock of the timestamps (default realtime, the clock PTP's phc2sys disciplines)")
    probes.add_argument("--relay", metavar="URL[,URL...]",
                        help="stream probe events to a relay, e.g. http://127.0.0.1:3000; several, comma-separated "
                             "(sharing one database): the node moves to the next when its relay cannot be reached")
    probes.add_argument("--token", metavar="TOKEN", default=os.environ.get(TOKEN_ENV),
                        help=f"the credential the relay asks for (default ${TOKEN_ENV}, which keeps it out of process listings)")
    add_tls_arguments(probes)
    add_spool_arguments(probes)
    probes.add_argument("--close-timeout", type=_positive_float, default=CLOSE_TIMEOUT_S, metavar="S",
                        help="at the end of the run, keep trying every --relay for up to S seconds until all that "
                             "was sent is acknowledged, saying what it waits for (default %(default)g); what is "
                             "still unacknowledged then is reported lost (a --trace file still holds it)")
    probes.add_argument("--clock-offset-ms", type=float, default=0.0, metavar="MS",
                        help="TESTING AID: shift this node's clock by MS milliseconds, to check clock alignment (default 0)")
    probes.add_argument("--clock-drift-ppm", type=_drift_ppm, default=0.0, metavar="PPM",
                        help="TESTING AID: make this node's clock run PPM parts per million fast (negative: slow) "
                             "from the start of the run, on top of --clock-offset-ms, for its events and its clock "
                             "exchanges alike: the relay must recover both offset and drift (default 0)")
    probes.add_argument("--ptp-socket", default=DEFAULT_UDS, metavar="PATH",
                        help=f"the local ptp4l's UDS (its uds_address), read with pmc for the relay (default {DEFAULT_UDS})")
    run.set_defaults(func=_run, holds_signals=True)

    demo = sub.add_parser("demo", help="run a relay and two DCU pipelines with probes on the shipped clips",
                          description="Start a relay on loopback and two DCU pipelines (DCU-1: 2 cameras, "
                                      "CenterNet; DCU-2: 4 cameras, SSD) streaming probe events to it; print "
                                      "the UI's URL and a status line every few seconds; Ctrl-C stops all.")
    demo.add_argument("--port", type=int, default=3000, help="relay and UI port (default 3000)")
    demo.add_argument("--duration", type=_positive_float, metavar="S", help="stop after S seconds (default: Ctrl-C)")
    demo.add_argument("--db", type=Path, help="SQLite file for the sessions (default ./dcuscope-demo.db; the DCUs' "
                                              "spool beside it, ./dcuscope-demo.spool/)")
    demo.set_defaults(func=_demo)

    rtsp = sub.add_parser("serve-rtsp", help="serve video files as live RTSP streams on loopback (looped, real time)",
                          description="Serve each CLIP at rtsp://HOST:PORT/camN (N from 0), looped forever, "
                                      "re-encoded as H.264 in real time, until Ctrl-C.")
    rtsp.add_argument("clips", type=Path, nargs="+", metavar="CLIP", help="video files")
    rtsp.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    rtsp.add_argument("--port", type=int, default=8554, help="RTSP port (default 8554)")
    rtsp.add_argument("--bitrate", type=_positive_int, default=2000, help="H.264 bitrate in kbit/s (default 2000)")
    rtsp.set_defaults(func=_serve_rtsp, holds_signals=True)

    plugin = sub.add_parser(
        "plugin-path", help="print the folder of dcuscope's GStreamer plugin (the dcuscope tracer), building it if needed",
        description="Print the folder that holds dcuscope's GStreamer plugin, for GST_PLUGIN_PATH: with it any "
                    "GStreamer application, unchanged, is traced per frame by GST_TRACERS=dcuscope.",
        epilog=PLUGIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    plugin.set_defaults(func=_plugin_path)

    add_configs_parser(sub)
    add_ship_parser(sub)
    add_spool_parser(sub)
    add_stats_parser(sub)
    add_export_parser(sub)
    add_compare_parser(sub)
    add_capacity_parser(sub)
    add_trace_parser(sub)
    add_relay_parser(sub)
    add_db_parser(sub)
    add_sessions_parsers(sub)
    use_everywhere(parser)
    return parser


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be a positive integer")
    return value


def _drift_ppm(text: str) -> float:
    value = float(text)
    if not abs(value) <= MAX_DRIFT_PPM:
        raise argparse.ArgumentTypeError(f"must be within +-{MAX_DRIFT_PPM:g} ppm")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError("must be positive")
    return value


def _run(args: argparse.Namespace) -> int:
    require_pipeline("run")
    from dcuscope.runcommand import run_command

    return run_command(args)


def _demo(args: argparse.Namespace) -> int:
    require_pipeline("demo")
    from dcuscope.demo import run_demo

    return run_demo(port=args.port, duration=args.duration, db=args.db)


def _plugin_path(args: argparse.Namespace) -> int:
    from dcuscope.probes.capture.native import BuildError, build

    try:
        print(build().parent)
    except BuildError as exc:
        print(f"dcuscope: error: no GStreamer plugin: {exc}", file=sys.stderr)
        return 1
    return 0


def _serve_rtsp(args: argparse.Namespace) -> int:
    from dcuscope.pipeline.rtsp import serve

    serve(args.clips, host=args.host, port=args.port, bitrate=args.bitrate, announce=lambda line: print(line, flush=True))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "holds_signals", False):
        signals.hold()  # the command's main loop acts on a Ctrl-C that comes while it starts
    try:
        return int(args.func(args) or 0)
    except DcuscopeError as exc:
        print(f"dcuscope: error: {exc}", file=sys.stderr)
        return 1 if isinstance(exc, PipelineError) else 2
    except KeyboardInterrupt:
        print("dcuscope: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
