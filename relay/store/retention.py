"""``dcuscope relay --retain DAYS``: whole sessions older than that leave the store.

A session goes once every run of it was last heard from more than DAYS ago and none is live
(on a shared store: owned by a relay). It is deleted in parts (PART_ROWS batches per short
transaction, through the writer thread between the ingest's own commits), so that deleting
days of data never holds ingest up. Any relay may run it; two relays deleting the same session
delete disjoint rows, or nothing.
"""

from __future__ import annotations

import asyncio
import logging
import time

from relay.errors import RelayError
from relay.store.writer import Storage

PART_ROWS = 2000
CHECK_S = 60.0
"""How often old sessions are looked for."""
DAY_NS = 86_400 * 10**9

log = logging.getLogger(__name__)


async def retain(storage: Storage, days: float, check_s: float = CHECK_S) -> None:
    """Delete sessions older than ``days``, now and every ``check_s``, until cancelled."""
    while True:
        try:
            await expire(storage, days)
        except RelayError:  # the store fails: said where it fails; tried again next time
            pass
        await asyncio.sleep(check_s)


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
