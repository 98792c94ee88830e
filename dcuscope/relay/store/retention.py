"""``dcuscope relay --retain raw=7d,rollups=400d`` (or ``--retain DAYS``, raw only): what leaves the store.

Raw: a whole session goes once every run of it was last heard from more than that long ago and
none is live (on a shared store: owned by a relay). Rollups (:mod:`dcuscope.relay.rollup.compute`) go by
row, once their minute or hour began more than their own time ago: kept longer, they answer
questions over months without the events. It is deleted in parts (PART_ROWS batches per short
transaction, through the writer thread between the ingest's own commits), so that deleting
days of data never holds ingest up. Any relay may run it; two relays deleting the same session
delete disjoint rows, or nothing.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

from dcuscope.relay.errors import RelayError
from dcuscope.relay.store.history import parse_duration_ns
from dcuscope.relay.store.writer import Storage

PART_ROWS = 2000
CHECK_S = 60.0
"""How often old sessions are looked for."""
DAY_NS = 86_400 * 10**9

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Retention:
    raw_days: float | None = None
    """Sessions (their events) last heard from longer ago go; None: kept."""
    rollup_days: float | None = None
    """Rollup rows that began longer ago go; None: kept."""


def parse_retention(text: str) -> Retention:
    """``DAYS`` (raw events, as before rollups) or ``raw=7d,rollups=400d`` (either or both; durations
    in d, h, m, s or w, or a number of days); RelayError with what is wrong."""
    text = str(text).strip()
    if "=" not in text:
        return Retention(raw_days=_days(text))
    parts = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        name = name.strip()
        if name not in ("raw", "rollups") or name in parts:
            raise RelayError(f"--retain takes DAYS or raw=DURATION,rollups=DURATION (e.g. raw=7d,rollups=400d), "
                             f"not {text!r}")
        parts[name] = _days(value)
    return Retention(parts.get("raw"), parts.get("rollups"))


def _days(text: str) -> float:
    text = text.strip()
    try:
        days = float(text)
    except ValueError:
        try:
            days = parse_duration_ns(text) / DAY_NS
        except RelayError as exc:
            raise RelayError(f"--retain: {exc}") from None
    if not days > 0 or days != days:
        raise RelayError(f"--retain: a time above 0 (days, or e.g. 7d, 400d), not {text!r}")
    return days


async def retain(storage: Storage, retention: Retention, check_s: float = CHECK_S) -> None:
    """Delete what ``retention`` says is too old, now and every ``check_s``, until cancelled."""
    while True:
        try:
            if retention.raw_days is not None:
                await expire(storage, retention.raw_days)
            if retention.rollup_days is not None:
                await expire_rollups(storage, retention.rollup_days)
        except RelayError:  # the store fails: said where it fails; tried again next time
            pass
        await asyncio.sleep(check_s)


async def expire_rollups(storage: Storage, days: float) -> int:
    """Delete every rollup row that began more than ``days`` ago; the rows deleted."""
    before = time.time_ns() - int(days * DAY_NS)
    rows = 0
    while (n := await storage.call("delete_rollups_part", before, PART_ROWS)):
        rows += n
    if rows:
        log.warning("retention: %d rollup rows deleted (older than %g days)", rows, days)
    return rows


async def expire(storage: Storage, days: float) -> list[int]:
    """Delete every session older than ``days``; the sessions deleted."""
    before = time.time_ns() - int(days * DAY_NS)
    done = []
    for session in await storage.call("expired_sessions", before):
        rows = 0
        while (n := await storage.call("delete_session_part", session, PART_ROWS)):
            rows += n
        done.append(session)
        log.warning("retention: session %d deleted (last heard from over %g days ago; %d rows)", session, days, rows)
    return done
