"""``dcuscope sessions`` and ``dcuscope runs``: what a relay's store holds, for ``--session ID``
(``stats``, ``export``) and ``session:ID`` / ``run:ID`` (``compare``).

A session and its runs come from the store's own listing (:meth:`dcuscope.relay.store.base.Database.list_sessions`,
what ``GET /api/sessions`` serves); a run is named as everywhere else
(:func:`dcuscope.relay.store.runs.run_name`). Frames are the complete frames of ``dcuscope stats
--session``, found by pairing the run's events (:mod:`dcuscope.model.delays`), so they are
counted only in sessions of up to ``MAX_COUNTED_EVENTS`` events, unless ``runs --session`` names it.

Each ``func`` returns the exit code: 0, or 2 after one ``dcuscope: error: ...`` line on stderr for
a missing or foreign database, an unknown session, or a store that cannot be read.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from dcuscope.core.errors import DcuscopeError

LIVE_S = 10.0
"""A run not ended and heard from this recently is live (a node syncs its clock every 2 s)."""
MAX_COUNTED_EVENTS = 5_000_000
"""A session with more stored events has its frames counted only when ``runs --session`` names it:
pairing reads every event (about 1 s and 200 MB a 5 M)."""
STATES = ("live", "interrupted", "ended")
"""A run's state: still sending; stopped without an end (its node or relay was stopped or killed);
ended by its node. A session's is the first of these that one of its runs is in."""


def add_sessions_parsers(sub) -> None:
    """``dcuscope sessions`` and ``dcuscope runs``."""
    s = sub.add_parser(
        "sessions", help="list a relay store's sessions: ids, nodes, start and end, frames, state",
        description="List the sessions a relay stored, newest first: each with its number (for --session ID and "
                    "session:ID), its nodes and runs, when it started and ended, its complete frames (as dcuscope "
                    "stats --session counts them), its events, and its state: live (a run still sending), ended "
                    "(every run ended by its node) or interrupted (a run that stopped without an end: its node or "
                    "relay was killed). Times are local.")
    _add_arguments(s)
    s.set_defaults(func=run_sessions)
    r = sub.add_parser(
        "runs", help="list a relay store's runs (one node's run each): ids, names, times, frames, state",
        description="List the runs a relay stored, one row per run of a node, newest session first: its session, "
                    "its id's first 8 digits (for run:ID and --session ID), its name (its node, and its run where "
                    "the session holds several runs of the node, as the page names it), when it started and "
                    "ended, its complete frames and events, and its state (live, ended or interrupted).")
    _add_arguments(r)
    r.add_argument("--session", metavar="ID", help="only this session's runs (its number; dcuscope sessions lists them)")
    r.set_defaults(func=run_runs)


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", metavar="PATH|URL", required=True,
                   help="the relay's store: its SQLite file, or its PostgreSQL database (postgresql://USER@HOST/DB)")
    p.add_argument("--json", action="store_true", help="print JSON (times in ns since the epoch) instead of a table")


def run_sessions(args: argparse.Namespace) -> int:
    return _listing(args, "sessions", None, lambda sessions: sessions, format_sessions)


def run_runs(args: argparse.Namespace) -> int:
    session = args.session
    if session is not None and not (session.isascii() and session.isdigit() and len(session) <= 18):
        return _fail(f"runs: --session {session!r}: a session is a number (dcuscope sessions --db DB lists them)")
    return _listing(args, "runs", None if session is None else int(session),
                    lambda sessions: [run for s in sessions for run in s["runs"]], format_runs)


def _listing(args: argparse.Namespace, command: str, session: int | None, shape, fmt) -> int:
    try:
        sessions = listing(args.db, session)
    except DcuscopeError as exc:
        return _fail(f"{command}: {exc}")
    doc = shape(sessions)
    sys.stdout.write(json.dumps(doc, indent=1, ensure_ascii=False) + "\n" if args.json else fmt(doc))
    return 0


def _fail(message: str) -> int:
    print(f"dcuscope: error: {message}", file=sys.stderr)
    return 2


def listing(db: str, session: int | None = None, now_ns: int | None = None) -> list[dict]:
    """The store's sessions, newest first (only ``session`` if given), each ``{session, nodes, runs,
    start_ns, end_ns, frames, events, state}``; each run ``{session, run, name, node, start_ns, end_ns,
    frames, events, dropped, lost, state}``. ``frames`` is None where not counted (see module)."""
    from dcuscope.relay.errors import RelayError
    from dcuscope.relay.store.engines import is_url
    from dcuscope.relay.store.runs import list_sessions, run_names
    from dcuscope.relay.urls import redact

    if not is_url(db) and not Path(db).is_file():
        raise DcuscopeError(f"{db}: no such database")
    now_ns = time.time_ns() if now_ns is None else now_ns
    try:
        stored = list_sessions(db)
    except RelayError as exc:
        raise DcuscopeError(str(exc)) from exc
    if session is not None:
        stored = [s for s in stored if s["session"] == session]
        if not stored:
            raise DcuscopeError(f"{redact(db)} has no session {session} (dcuscope sessions --db DB lists them)")
    out = []
    for s in stored:
        runs = s["runs"]
        counted = session is not None or sum(r["events"] for r in runs) <= MAX_COUNTED_EVENTS
        frames = _frames(db, s["session"]) if counted else {}
        rows = [{"session": s["session"], "run": r["run"], "name": name, "node": r["node"],
                 "start_ns": r["first_seen_ns"], "end_ns": r["ended_ns"] or r["last_seen_ns"],
                 "frames": frames.get(r["run"]), "events": r["events"], "dropped": r["dropped"], "lost": r["lost"],
                 "state": _state(r, now_ns)}
                for r, name in zip(runs, run_names([(r["node"], r["run"]) for r in runs]))]
        states = {r["state"] for r in rows}
        out.append({"session": s["session"], "nodes": list(dict.fromkeys(r["node"] for r in rows)), "runs": rows,
                    "start_ns": min(r["start_ns"] for r in rows), "end_ns": max(r["end_ns"] for r in rows),
                    "frames": sum(r["frames"] for r in rows) if counted else None,
                    "events": sum(r["events"] for r in rows),
                    "state": next(st for st in STATES if st in states)})
    return out


def _frames(db: str, session: int) -> dict[str, int]:
    """Run id -> its complete frames, paired as ``dcuscope stats --session`` pairs them."""
    from dcuscope.model.delays import frame_delays
    from dcuscope.model.frametable import frame_table
    from dcuscope.relay.errors import RelayError
    from dcuscope.relay.store.runs import load_runs

    try:
        runs = load_runs(db, str(session), corrected=False)
    except RelayError as exc:
        raise DcuscopeError(str(exc)) from exc
    return {r.run: int(frame_delays(frame_table(r.header, r.events)).chains.complete.sum()) for r in runs}


def _state(run: dict, now_ns: int) -> str:
    if run["ended_ns"] is not None:
        return "ended"
    return "live" if now_ns - run["last_seen_ns"] <= LIVE_S * 1e9 else "interrupted"


def _when(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ns / 1e9))


def _table(head: list[str], rows: list[list[str]], right: set[int]) -> list[str]:
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
    return ["  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [head, *rows]]


def _count(n: int | None) -> str:
    return "–" if n is None else f"{n:,}"


def _zone() -> str:
    return time.strftime("%Z")


def format_sessions(sessions: list[dict]) -> str:
    if not sessions:
        return "no sessions stored\n"
    head = ["session", f"start ({_zone()})", "end", "runs", "nodes", "frames", "events", "state"]
    rows = [[str(s["session"]), _when(s["start_ns"]), _when(s["end_ns"]), str(len(s["runs"])), ", ".join(s["nodes"]),
             _count(s["frames"]), _count(s["events"]), s["state"]] for s in sessions]
    lines = _table(head, rows, {0, 3, 5, 6})
    if any(s["frames"] is None for s in sessions):
        lines.append(f"frames –: over {MAX_COUNTED_EVENTS:,} events, not counted here: dcuscope runs --db DB "
                     "--session ID counts them")
    lines.append("a session's runs: dcuscope runs --db DB --session ID; its statistics: dcuscope stats --db DB "
                 "--session ID")
    return "\n".join(lines) + "\n"


def format_runs(runs: list[dict]) -> str:
    if not runs:
        return "no runs stored\n"
    head = ["session", "run", "name", f"start ({_zone()})", "end", "frames", "events", "state"]
    rows = [[str(r["session"]), r["run"][:8], r["name"], _when(r["start_ns"]), _when(r["end_ns"]), _count(r["frames"]),
             _count(r["events"]), r["state"]] for r in runs]
    lines = _table(head, rows, {0, 5, 6})
    lines.append("one run: run:ID in dcuscope compare, --session ID in dcuscope stats and export (ID: the run's "
                 "first 6+ digits)")
    return "\n".join(lines) + "\n"
