"""``dcuscope run``: configuration + command-line overrides -> a built, probed, running pipeline."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from dcuscope.core.console import Console
from dcuscope.core.errors import UsageError
from dcuscope.core.ports import check_port_free
from dcuscope.pipeline.build import build_pipeline
from dcuscope.pipeline.config import PipelineConfig, SinkConfig, load_config
from dcuscope.pipeline.launch import build_launch
from dcuscope.pipeline.outputs import check_frames_folder, check_video_file
from dcuscope.pipeline.run import Runner
from dcuscope.pipeline.stalls import describe
from dcuscope.shipped import resolve

ABORTED_STATUS = 130
"""A run the user aborted with Ctrl-C before end-of-stream reached the sink (128 + SIGINT); one
whose end-of-stream never reached the sink by itself exits 1, a pipeline failure."""

MOST_COMMON = 5
"""Labels named in the detection line at the end of a run."""


def apply_overrides(config: PipelineConfig, args: argparse.Namespace) -> PipelineConfig:
    """The command line wins over the YAML: a new configuration, ``config`` stays as it is."""
    probes = config.probes
    if args.probes or args.trace or args.relay:
        probes = replace(probes, enabled=True)
    if args.trace:
        probes = replace(probes, trace=args.trace)
    if args.clock:
        probes = replace(probes, clock=args.clock)
    sinks = config.sinks if args.output is None else (sink_for_output(args.output, config.sink),)
    return replace(config, node=args.node or config.node, probes=probes, sinks=sinks)


def sink_for_output(path: Path, current: SinkConfig) -> SinkConfig:
    """``x.mp4`` (.mkv, .avi) -> H.264 file; an existing folder, a path ending in a separator or
    without suffix -> PNG frames."""
    text = str(path)
    target = path if path.is_absolute() else Path.cwd() / path
    if text.endswith(("/", "\\")) or target.is_dir() or not target.suffix:
        return SinkConfig(kind="frames", path=target, sync=current.sync)
    return SinkConfig(kind="file", path=target, sync=current.sync, bitrate=current.bitrate)


def check_socket_path(path: Path) -> str | None:
    """Why a shm sink cannot make its socket at ``path``, or None."""
    if not path.parent.is_dir():
        return f"no folder {path.parent} for the socket"
    if path.exists():
        return "exists already (another shmsink's socket? remove it, or give another path)"
    return None


def check_sink(config: PipelineConfig, output: Path | None) -> None:
    """Before anything runs: each sink can write where it is told to (``output``: as given on the
    command line, else the YAML's ``path``) and serve where it is told to. UsageError or
    ConfigError otherwise."""
    several = "sinks" in config.document.data if isinstance(config.document.data, dict) else False
    for index, sink in enumerate(config.sinks):
        where = ("sinks", index) if several and output is None else ("sink",)
        if sink.kind == "rtsp":
            try:
                check_port_free(sink.host, sink.port, hint="pick a free one with port:", option=None)
            except UsageError as exc:
                raise config.document.error(where + ("port",), str(exc)) from exc
        if sink.path is None:
            continue
        problem = (check_video_file(sink.path) if sink.kind == "file" else check_socket_path(sink.path)
                   if sink.kind == "shm" else check_frames_folder(sink.path))
        if problem is None:
            continue
        if output is not None:
            raise UsageError(f"--output {output}: {problem}")
        raise config.document.error(where + ("path",), f"{sink.path}: {problem}")


def run_command(args: argparse.Namespace) -> int:
    if args.relay:
        from dcuscope.probes.ship.relaylink import parse_relays

        parse_relays(args.relay)  # a bad list ends the run before the pipeline is built
    config = apply_overrides(load_config(resolve(args.config)), args)
    if config.launch is not None and args.output is not None:
        raise UsageError("--output: a launch: pipeline says its own sinks")
    check_sink(config, args.output)
    built = build_launch(config) if config.launch is not None else build_pipeline(config)
    try:
        return _run_built(args, config, built)
    finally:
        built.close()


def _run_built(args: argparse.Namespace, config: PipelineConfig, built) -> int:
    console = Console(sys.stderr)
    progress = None if args.quiet else console
    for sink in config.sinks:
        if sink.kind == "rtsp":
            console.write(f"serving {sink.url} (sink {sink.name})\n")
    runner = Runner(built, num_frames=args.num_frames, duration=args.duration, progress=progress,
                    progress_every=1.0 if console.isatty() else 5.0, traced=config.probes.enabled)
    probing = delivery = None
    if config.probes.enabled:
        from dcuscope.probes.instrument import start_probes

        from dcuscope.probes.ship.nodetls import tls_from_args
        from dcuscope.probes.ship.spoolargs import spool_from_args

        tls = tls_from_args(args)
        spool = spool_from_args(args, lambda line: console.write(line + "\n"), relay=args.relay, token=args.token,
                                tls=tls) if args.relay else None
        probing = start_probes(built, config, relay=args.relay, token=args.token, tls=tls, spool=spool,
                               clock_offset_ns=int(args.clock_offset_ms * 1e6), progress=progress,
                               clock_drift_ppm=args.clock_drift_ppm, ptp_socket=args.ptp_socket,
                               close_timeout_s=args.close_timeout)
    try:
        result = runner.run()
    finally:
        if probing is not None:
            delivery = probing.stop()
    for index, reason in result.dead_sources.items():
        console.write(f"dcuscope: source {index} ({config.sources[index].description}) was lost: {reason}\n")
    for index, stalls in result.stalls.items():
        console.write(f"dcuscope: source {index} ({config.sources[index].description}) {describe(stalls)}\n")
    if result.discarded:
        counted = ", counted in the trace (reason stopped)" if config.probes.enabled else ""
        frames = "1 frame still queued at the stop was" if result.discarded == 1 else \
            f"{result.discarded} frames still queued at the stop were"
        console.write(f"dcuscope: {frames} dropped (live sources are not drained){counted}\n")
    if result.aborted is not None:
        incomplete = "".join({"file": f": {sink.path} is incomplete (not finalised, may not play)",
                              "frames": f": the frames in {sink.path} end early"}.get(sink.kind, "")
                             for sink in config.sinks)
        console.write(f"dcuscope: {result.aborted}{incomplete}\n")
        return ABORTED_STATUS if result.interrupted else 1
    if progress is not None:
        for line in detection_lines(built.stages):
            console.write(line + "\n")
    for sink in config.sinks:
        if sink.path is not None and progress is not None:
            console.write(f"output: {sink.path}\n")
    if delivery is not None and not delivery.complete:
        from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS

        if progress is None:  # --quiet: the summary said nothing, the exit status must not stand alone
            console.write(f"dcuscope: {delivery.line()}\n")
        return UNACKNOWLEDGED_STATUS
    return 0


def detection_lines(stages) -> list[str]:
    """What each infer stage found: 'infer0: 57 objects in 20 frames (person 52, car 5)'."""
    lines = []
    for stage in stages:
        found = getattr(stage, "found", None)  # dcuscope's infer (plugins/infer.py)
        if found is None:
            continue
        kinds = ", ".join(f"{label} {n}" for label, n in found.most_common(MOST_COMMON))
        more = len(found) - MOST_COMMON
        kinds += f", {more} more {'kind' if more == 1 else 'kinds'}" if more > 0 else ""
        lines.append(f"{stage.get_name()}: {found.total()} objects in {stage.inferred_frames} frames"
                     + (f" ({kinds})" if kinds else ""))
    return lines
