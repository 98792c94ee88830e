"""The ``dcuscope`` command line."""

from __future__ import annotations

import argparse
import importlib.metadata
import sys
from pathlib import Path

from dcuscope.capacity.command import add_capacity_parser
from dcuscope.commands.compare import add_compare_parser
from dcuscope.commands.configs import add_configs_parser
from dcuscope.commands.db import add_db_parser
from dcuscope.commands.demo import add_demo_parser
from dcuscope.commands.export import add_export_parser
from dcuscope.commands.pluginpath import add_plugin_path_parser
from dcuscope.commands.rtsp import add_rtsp_parser
from dcuscope.commands.run import add_run_parser
from dcuscope.commands.sessions import add_sessions_parsers
from dcuscope.commands.ship import add_ship_parser
from dcuscope.commands.spool import add_spool_parser
from dcuscope.commands.stats import add_stats_parser
from dcuscope.commands.trace import add_trace_parser
from dcuscope.core import signals
from dcuscope.core.errors import DcuscopeError, PipelineError
from dcuscope.core.pycompat import tomllib
from dcuscope.helpformat import use_everywhere
from dcuscope.relay.commands import add_relay_parser

DESCRIPTION = """\
dcuscope: see where the time goes in multi-camera video-analytics pipelines.

Pipelines are declared in YAML (see configs/) and run on real GStreamer with dcuscope's
elements mux, infer, tiler, convert and osd; with --probes every element gets per-frame
enter/exit tracepoints, written to a trace file and/or streamed to a relay.
"""

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


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
    """Every command, each added by its own module (``dcuscope/commands/``, the relay's in
    ``relay/commands.py``, capacity's in ``capacity/command.py``)."""
    parser = argparse.ArgumentParser(prog="dcuscope", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"dcuscope {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in (add_run_parser, add_demo_parser, add_rtsp_parser, add_plugin_path_parser, add_configs_parser,
                add_ship_parser, add_spool_parser, add_stats_parser, add_export_parser, add_compare_parser,
                add_capacity_parser, add_trace_parser, add_relay_parser, add_db_parser, add_sessions_parsers):
        add(sub)
    use_everywhere(parser)
    return parser


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
