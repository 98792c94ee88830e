"""Stored runs read back, on either engine: a session's runs, their events, clock-corrected.

For ``dcuscope stats/export --db``, the stored sessions' API and the relay itself (a run resumed
after a relay restart, or taken over from another relay, rebuilds its live state from here).
"""

from __future__ import annotations

import json
import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dcuscope.protocol.events import CAPTURE, EVENT_DTYPE, TraceHeader
from dcuscope.relay.clock.correction import NO_CORRECTION, Correction, Segment, stored_correction
from dcuscope.relay.clock.entry import stored_run_correction
from dcuscope.relay.clock.model import segment_fault
from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.base import Database, StoreUnavailable
from dcuscope.relay.store.engines import open_database

MAX_SESSION_DIGITS = 18
RUN_DIGITS_SHOWN = 8
"""A run is shown by its id's first 8 hex digits (``run fcef7528``), which ``run:ID`` takes back (6 or more)."""

log = logging.getLogger(__name__)


@dataclass
class StoredRun:
    run: str
    session: int
    header: TraceHeader
    events: np.ndarray
    dropped: int
    lost: int
    clock: dict
    ended: bool
    correction: Correction = NO_CORRECTION
    """What brings the run's node timestamps to the relay's clock, per timestamp, and its bound
    (already applied to ``events`` when loaded ``corrected``)."""
    last_ns: int = 0
    """Node time of the run's last event (where its ``clock`` entry is evaluated), 0 without events."""


def run_events(database: Database, run: str) -> np.ndarray:
    """Every stored event of a run, in batch order (raw node timestamps), compacted or not."""
    parts = database.event_parts(run)
    return np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)


def load_runs(db: str | Path, session_id: int | str, corrected: bool = True) -> list[StoredRun]:
    """The runs of session ``session_id`` (a number), or the one run whose id starts with it.

    With ``corrected`` each run's timestamps are moved to the relay's clock, each by the estimate
    in force at its time (the run's stored clock history), or, for a run stored without one, by
    the correction its last clock estimate called for (see :func:`dcuscope.relay.clock.correction.correction_ns`).
    """
    key = str(session_id).strip()
    is_run = len(key) >= 6 and all(c in "0123456789abcdef" for c in key.lower())
    if not key.isdigit() and not is_run:
        raise RelayError(f"{db}: session must be a number or a run id, not {session_id!r}")
    database = open_database(db, create=False)
    try:
        rows = []
        if key.isdigit() and len(key) <= MAX_SESSION_DIGITS:
            rows = database.session_runs(int(key))
        if not rows and is_run:  # a run id may begin with digits only (1 in 43 do, over 8 of them)
            rows = database.runs_with_prefix(key.lower())
        if not rows:
            raise RelayError(f"{database.location}: no session or run {session_id!r}")
        out = []
        for row in rows:
            events = run_events(database, row.run)
            last = int(events["ts"].max()) if len(events) else 0
            clock, correction = run_clock(row.run, row.clock, database.run_history(row.run))
            if corrected and correction.segments and len(events):
                events = events.copy()
                # A capture time is the camera's clock (RTCP sender reports), not the node's: kept.
                node_time = events["point"] != CAPTURE
                events["ts"] = np.where(node_time, correction.correct(events["ts"], frame_starts(events, node_time)),
                                        events["ts"])
            out.append(StoredRun(row.run, int(row.session), TraceHeader.from_dict(json.loads(row.header)), events,
                                 int(row.dropped), int(row.lost), clock, row.ended_ns is not None, correction, last))
        return out
    except StoreUnavailable as exc:
        raise RelayError(f"cannot read session {session_id!r}: {exc}") from exc
    finally:
        database.close()


def frame_starts(events: np.ndarray, counted: np.ndarray | None = None) -> np.ndarray:
    """Per event, the earliest timestamp of its frame (source, frame) among the ``counted`` events
    (all by default): every event of a frame is corrected by the estimate in force at its start,
    so that a new estimate arriving while a frame went through the pipeline leaves its delays as
    measured on the node's clock."""
    source, frame, ts = events["source"], events["frame"], events["ts"]
    if counted is not None:  # the others never start a frame: they sort after every counted one
        ts = np.where(counted, ts, np.iinfo(np.int64).max)
    order = np.lexsort((frame, source))  # ~1 s for 10 M events (np.unique on the pair: 15 s)
    s, f = source[order], frame[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (s[1:] != s[:-1]) | (f[1:] != f[:-1])
    first = np.minimum.reduceat(ts[order], np.flatnonzero(new))
    out = np.empty(len(ts), dtype=np.int64)
    out[order] = first[np.cumsum(new) - 1]
    return out


def run_clock(run: str, text: str, history: list[Segment]) -> tuple[dict, Correction]:
    """A stored run's clock view and the correction to apply: its history of estimates when its
    last view applied an estimate, else that view's correction. A correction no relay could have
    computed (written by an older relay from a forged sample, or edited) is ignored, with one
    warning and ``ignored`` in the view: the other runs of the session load as usual."""
    try:
        clock = json.loads(text)
    except ValueError:
        clock = None
    shift, fault = stored_correction(clock)
    if fault is not None:
        log.warning("run %s: stored clock %s; its correction is ignored", run, fault)
        clock = clock if isinstance(clock, dict) else {}
        view = dict(clock, applied="ignored", ignored=fault, correction_ns=0, correction_us=0.0)
        return view, Correction("ignored", fault)
    if history and clock.get("applied") == "estimate":
        bad = next((f for f in map(segment_fault, history) if f is not None), None)
        if bad is None:
            return clock, Correction("estimate", "stored history of estimates", tuple(history))
        log.warning("run %s: stored clock history: %s; its last estimate is applied instead", run, bad)
    return clock, stored_run_correction(clock)


def load_session(db: str | Path, session_id: int | str, corrected: bool = True) -> list[tuple[TraceHeader, np.ndarray]]:
    """``[(header, events), ...]`` of every run of a stored session (for ``dcuscope export``)."""
    return [(r.header, r.events) for r in load_runs(db, session_id, corrected)]


def find_runs(db: str | Path, prefix: str) -> list[tuple[str, int]]:
    """(run, session) of each run, refused ones included, whose id starts with ``prefix`` (lower-case hex)."""
    database = open_database(db, create=False)
    try:
        return [(r.run, int(r.session)) for r in database.runs_with_prefix(prefix)]
    except StoreUnavailable as exc:
        raise RelayError(f"cannot look up run {prefix!r}: {exc}") from exc
    finally:
        database.close()


def session_nodes(db: str | Path, session: int) -> list[str]:
    """The node of each stored run of ``session``: a node that ran twice in it, twice."""
    database = open_database(db, create=False)
    try:
        return [json.loads(r.header)["node"] for r in database.session_runs(session)]
    except StoreUnavailable as exc:
        raise RelayError(f"cannot read session {session}: {exc}") from exc
    finally:
        database.close()


def run_name(node: str, run: str, twins: bool) -> str:
    """A stored run's name in its session, the one name the CLI (``stats --session``, ``runs``,
    ``compare``) and the page give it: its node, and where the session holds ``twins`` (other runs
    of the node) the first 8 digits of its id, as ``run:ID`` takes it: ``vm · run fcef7528``."""
    return node + (f" · run {run[:RUN_DIGITS_SHOWN]}" if twins else "")


def run_names(runs: list[tuple[str, str]]) -> list[str]:
    """The :func:`run_name` of each (node, run id) of one session's runs."""
    count = Counter(node for node, _ in runs)
    return [run_name(node, run, count[node] > 1) for node, run in runs]


def run_label(session: int, node: str, run: str, twins: bool) -> str:
    """A stored run named across sessions (``dcuscope compare``, the page's Compare tab):
    ``session 3 · DCU-1``, ``session 1 · vm · run fcef7528`` (:func:`run_name`)."""
    return f"session {session} · {run_name(node, run, twins)}"


def list_sessions(db: str | Path) -> list[dict]:
    """Sessions stored in ``db``, newest first, each with its runs."""
    database = open_database(db, create=False)
    try:
        return database.list_sessions()
    finally:
        database.close()
