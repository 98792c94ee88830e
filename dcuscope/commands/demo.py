"""``dcuscope demo``: its options; the demo itself is :mod:`dcuscope.demo`'s."""

from __future__ import annotations

import argparse
from pathlib import Path

from dcuscope.commands.options import positive_float
from dcuscope.extras import require_pipeline


def add_demo_parser(sub) -> None:
    demo = sub.add_parser("demo", help="run a relay and two DCU pipelines with probes on the shipped clips",
                          description="Start a relay on loopback and two DCU pipelines (DCU-1: 2 cameras, "
                                      "CenterNet; DCU-2: 4 cameras, SSD) streaming probe events to it; print "
                                      "the UI's URL and a status line every few seconds; Ctrl-C stops all.")
    demo.add_argument("--port", type=int, default=3000, help="relay and UI port (default 3000)")
    demo.add_argument("--duration", type=positive_float, metavar="S", help="stop after S seconds (default: Ctrl-C)")
    demo.add_argument("--db", type=Path, help="SQLite file for the sessions (default ./dcuscope-demo.db; the DCUs' "
                                              "spool beside it, ./dcuscope-demo.spool/)")
    demo.set_defaults(func=_demo)


def _demo(args: argparse.Namespace) -> int:
    require_pipeline("demo")
    from dcuscope.demo import run_demo

    return run_demo(port=args.port, duration=args.duration, db=args.db)
