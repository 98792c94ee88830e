"""What ``dcuscope stats`` and ``dcuscope export`` read: trace files, or a stored session of a relay's
database (:func:`read_inputs`), and how they answer bad input: one ``dcuscope: error: ...`` line on
stderr and exit status 2 (:func:`user_errors`).

Over a stored session each node carries the correction its timestamps were moved by
(:func:`clocks`); trace files hold the node's own clock, uncorrected.
"""

from __future__ import annotations

import argparse
import os
import sys
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

from dcuscope.core.errors import DcuscopeError
from dcuscope.probes.trace.tracefile import Trace, read_trace
from dcuscope.relay.clock.correction import Correction


def add_input_arguments(p: argparse.ArgumentParser) -> None:
    """TRACE files, or ``--db`` with ``--session``."""
    p.add_argument("traces", nargs="*", metavar="TRACE", help="trace file(s) written by `dcuscope run`")
    p.add_argument("--db", metavar="PATH|URL", help="a relay's store instead of trace files: its SQLite file, or its "
                                                   "PostgreSQL database (postgresql://USER@HOST/DB)")
    p.add_argument("--session", metavar="ID", help="with --db: the stored session's number, or a run's id (its first 6+ "
                                                   "digits): dcuscope sessions --db DB and dcuscope runs --db DB list them")


def read_inputs(args: argparse.Namespace, command: str) -> list:
    """Per node an object with header, events, dropped: trace files, or a stored session's runs."""
    if args.db is None and args.session is None:
        if not args.traces:
            raise DcuscopeError(f"{command}: give at least one TRACE file (or --db PATH --session ID)")
        return [read_trace(path) for path in args.traces]
    if args.traces or args.db is None or args.session is None:
        raise DcuscopeError(f"{command}: give either TRACE files, or --db PATH with --session ID")
    from dcuscope.relay.store.engines import is_url
    from dcuscope.relay.store.runs import load_runs  # the relay's modules load only for this input

    if not is_url(args.db) and not Path(args.db).is_file():
        raise DcuscopeError(f"{command}: {args.db}: no such database")

    return named(args.db, load_runs(args.db, args.session))


def named(db: str, runs: list) -> list:
    """Stored runs under the names the page and ``dcuscope runs`` give them
    (:func:`dcuscope.relay.store.runs.run_name`: ``vm · run fca2e7ed`` where the session holds two runs of vm),
    a run asked for by its id included."""
    from dcuscope.relay.store.runs import run_name, session_nodes

    nodes = {s: session_nodes(db, s) for s in {r.session for r in runs}}
    for r in runs:
        r.header = replace(r.header, node=run_name(r.header.node, r.run, nodes[r.session].count(r.header.node) > 1))
    return runs


def clocks(traces: list) -> list[Correction | None]:
    """Per node the correction its timestamps were moved by, looked up by the moved times (the
    exporters see those): a stored run's; None for a trace file."""
    return [None if isinstance(t, Trace) else t.correction.on_relay_clock() for t in traces]


@contextmanager
def user_errors():
    """Turn a DcuscopeError into one stderr line; the yielded list is non-empty after one."""
    failed: list[str] = []
    try:
        yield failed
    except DcuscopeError as exc:
        failed.append(str(exc))
        print(f"dcuscope: error: {exc}", file=sys.stderr)


@contextmanager
def open_output(path: str):
    """The file at ``path``, or stdout for ``-``, where a reader that goes away ends the output quietly."""
    if path == "-":
        try:
            yield sys.stdout
            sys.stdout.flush()
        except BrokenPipeError:
            # The reader stopped early (`-o - | head`): it has what it wanted. What is left goes
            # nowhere, as does the flush at exit, which would otherwise fail on the closed pipe too.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return
    try:
        out = open(path, "w", encoding="utf-8", newline="")
    except OSError as exc:
        raise DcuscopeError(f"{path}: cannot write output: {exc.strerror or exc}") from exc
    with out:
        yield out
