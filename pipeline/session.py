"""``dcuscope run``: configuration + command-line overrides -> a built, probed, running pipeline."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.build import build_pipeline
from pipeline.config import PipelineConfig, SinkConfig, load_config
from pipeline.console import Console
from pipeline.run import Runner
from pipeline.stalls import describe


def apply_overrides(config: PipelineConfig, args: argparse.Namespace) -> PipelineConfig:
    """The command line wins over the YAML."""
    if args.node:
        config.node = args.node
    if args.output is not None:
        config.sink = sink_for_output(args.output, config.sink)
    if args.probes or args.trace or args.relay:
        config.probes.enabled = True
    if args.trace:
        config.probes.trace = args.trace
    if args.clock:
        config.probes.clock = args.clock
    return config


def sink_for_output(path: Path, current: SinkConfig) -> SinkConfig:
    """``x.mp4`` -> H.264 file; an existing folder or a path ending in a separator -> PNG frames."""
    text = str(path)
    target = path if path.is_absolute() else Path.cwd() / path
    if text.endswith(("/", "\\")) or target.is_dir() or not target.suffix:
        return SinkConfig(kind="frames", path=target, sync=current.sync)
    return SinkConfig(kind="file", path=target, sync=current.sync, bitrate=current.bitrate)


def run_session(args: argparse.Namespace) -> int:
    config = apply_overrides(load_config(args.config), args)
    built = build_pipeline(config)
    console = Console(sys.stderr)
    progress = None if args.quiet else console
    runner = Runner(built, num_frames=args.num_frames, duration=args.duration, progress=progress,
                    progress_every=1.0 if console.isatty() else 5.0)
    probing = None
    if config.probes.enabled:
        from probes.session import start_probes

        probing = start_probes(built, config, relay=args.relay, token=args.token,
                               clock_offset_ns=int(args.clock_offset_ms * 1e6), progress=progress)
    try:
        result = runner.run()
    finally:
        if probing is not None:
            probing.stop()
    for index, reason in result.dead_sources.items():
        console.write(f"dcuscope: source {index} ({config.sources[index].description}) was lost: {reason}\n")
    for index, stalls in result.stalls.items():
        console.write(f"dcuscope: source {index} ({config.sources[index].description}) {describe(stalls)}\n")
    if config.sink.path is not None and progress is not None:
        console.write(f"output: {config.sink.path}\n")
    return 0
