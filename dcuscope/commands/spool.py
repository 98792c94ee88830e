"""``dcuscope spool``: the runs a node keeps on disk until a relay stored them (list, drop one)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from dcuscope.core.errors import DcuscopeError


def add_spool_parser(sub) -> None:
    from dcuscope.probes.ship.spool import default_dir

    p = sub.add_parser(
        "spool", help="list the runs kept on disk until a relay stores them, or drop one",
        description="List the runs this machine's spool keeps (their events were not all stored by a relay: it "
                    "was down, or the process died): node, events, bytes, age of the oldest, relays. "
                    "`dcuscope ship --drain` sends them; `dcuscope spool drop RUN` deletes one.",
        epilog="Exit status: 0; 2 for an unknown RUN or a spool folder that cannot be read.")
    p.add_argument("action", nargs="?", choices=("list", "drop"), default="list", help="list (default) or drop")
    p.add_argument("run", nargs="?", metavar="RUN", help="drop: the run id (as listed)")
    p.add_argument("--spool", type=Path, metavar="DIR", help=f"the spool folder (default {default_dir()})")
    p.set_defaults(func=_spool)


def _age(ns: int | None) -> str:
    if ns is None:
        return "-"
    s = max(0.0, time.time() - ns / 1e9)
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h"


def _spool(args: argparse.Namespace) -> int:
    from dcuscope.probes.ship.spool import Spool, default_dir
    from dcuscope.probes.ship.spoolfile import SpoolError

    try:
        spool = Spool(args.spool or default_dir())
        if args.action == "drop":
            if not args.run:
                raise DcuscopeError("drop which run? dcuscope spool drop RUN (dcuscope spool lists them)")
            gone = spool.drop(args.run)
            print(f"dropped run {gone.run} of {gone.node}: {gone.events} events, {gone.bytes} bytes")
            return 0
        runs = spool.runs()
    except SpoolError as exc:
        raise DcuscopeError(str(exc)) from None
    if not runs:
        print(f"the spool {spool.path} holds no run")
        return 0
    rows = [("RUN", "NODE", "EVENTS", "BYTES", "OLDEST", "STATE", "RELAYS")]
    for r in runs:
        state = "being shipped" if r.in_use else "ended" if r.ended else "cut short"
        rows.append((r.run, r.node, str(r.events), str(r.bytes), _age(r.oldest_ns), state, ",".join(r.relays) or "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(v.ljust(w) for v, w in zip(row, widths)).rstrip())
    total = sum(r.events for r in runs)
    print(f"{len(runs)} run(s), {total} events, {sum(r.bytes for r in runs)} bytes in {spool.path}; "
          "dcuscope ship --drain sends them")
    return 0
