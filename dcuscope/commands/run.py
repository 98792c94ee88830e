"""``dcuscope run CONFIG``: its options; the run itself is :mod:`dcuscope.commands.runpipeline`'s (GStreamer
loads only for it)."""

from __future__ import annotations

import argparse
from pathlib import Path

from dcuscope.commands.options import add_relay_arguments, drift_ppm, positive_float, positive_int
from dcuscope.extras import require_pipeline
from dcuscope.probes.clocks.sysclock import DEFAULT_UDS

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



def add_run_parser(sub) -> None:
    run = sub.add_parser("run", help="run a pipeline from a YAML configuration",
                         description="Run a pipeline from a YAML configuration (see configs/).", epilog=RUN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    run.add_argument("config", type=Path, metavar="CONFIG",
                     help="pipeline configuration (YAML), or the name of a shipped one (dcuscope configs lists them)")
    run.add_argument("--output", "-o", type=Path, metavar="PATH",
                     help="write the osd's frames: NAME.mp4, .mkv or .avi (H.264) or a folder/ for PNG frames (overrides sink:)")
    limit = run.add_mutually_exclusive_group()
    limit.add_argument("--num-frames", "-n", type=positive_int, metavar="N",
                       help="stop cleanly after N frames reached the sink")
    limit.add_argument("--duration", "-d", type=positive_float, metavar="S",
                       help="stop cleanly after S seconds (live sources: at S seconds, frames still queued dropped)")
    run.add_argument("--node", metavar="NAME", help="name of this machine in traces and the relay (default: node: of the config, else DCU-1)")
    run.add_argument("--quiet", "-q", action="store_true", help="no progress lines")
    probes = run.add_argument_group("probes")
    probes.add_argument("--probes", action="store_true", help="put enter/exit tracepoints on every element")
    probes.add_argument("--trace", type=Path, metavar="PATH", help="write probe events to this trace file (JSON Lines)")
    probes.add_argument("--clock", choices=("realtime", "tai", "monotonic"),
                        help="clock of the timestamps (default realtime, the clock PTP's phc2sys disciplines)")
    add_relay_arguments(probes, "stream probe events to a relay, e.g. http://127.0.0.1:3000; several, comma-separated "
                                "(sharing one database): the node moves to the next when its relay cannot be reached",
                        after="at the end of the run", keeps="a --trace file still holds it")
    probes.add_argument("--clock-offset-ms", type=float, default=0.0, metavar="MS",
                        help="TESTING AID: shift this node's clock by MS milliseconds, to check clock alignment (default 0); "
                             "a launch: pipeline shifts what it sends the relay, its trace file keeps the true clock")
    probes.add_argument("--clock-drift-ppm", type=drift_ppm, default=0.0, metavar="PPM",
                        help="TESTING AID: make this node's clock run PPM parts per million fast (negative: slow) "
                             "from the start of the run, on top of --clock-offset-ms, for its events and its clock "
                             "exchanges alike: the relay must recover both offset and drift (default 0)")
    probes.add_argument("--ptp-socket", default=DEFAULT_UDS, metavar="PATH",
                        help=f"the local ptp4l's UDS (its uds_address), read with pmc for the relay (default {DEFAULT_UDS})")
    run.set_defaults(func=_run, holds_signals=True)


def _run(args: argparse.Namespace) -> int:
    require_pipeline("run")
    from dcuscope.commands.runpipeline import run_command

    return run_command(args)
