"""The relay process's heap: giving back the memory that runs leave behind.

A run's live state is a few numpy arrays of many megabytes (up to ``--limit run_mb``) held by a
handful of Python objects, and each batch a node ships passes through more of them (the decoded
60,000-event batch, 1.4 MB; the merge's temporaries). Two things kept that memory once a run had
left (benchmarks/bench_relay_soak.py: a node restarting 100 times with its old connection left
open took the relay from 110 MB to 373 MB, 1.7 MB a restart, while ``/api/health`` counted 11 MB of
live state in one run):

- Reference cycles. Python's cyclic collector starts by object counts, not bytes: a cycle holding
  a released run's arrays (its exporters' callback referred back to it, which RelayState.release now
  breaks; a closed aiohttp WebSocketResponse refers to itself through its reader) waits for a
  collection of the generation it reached, which a relay allocating few, large objects seldom
  starts: up to nine released runs (~100 MB) were alive at once.
- glibc's heap. Once a large block was freed, glibc's dynamic mmap threshold rises past it, and
  the next 1.4 MB batches and merge temporaries come from the heap (brk), among small long-lived
  objects: the pages they freed stay resident, and a heap that once held several dead runs stays
  that large.

:class:`Reclaimer` runs on the relay's loop: once runs left memory (``RelayState.released``
moved) it makes a full collection (``gc.collect``: 15-35 ms on a relay of ~100,000 objects) and
then ``malloc_trim(0)`` (1-2 ms: glibc gives the free pages of every arena back, not only the top
of the heap), at most every :data:`MIN_INTERVAL_S`, so that a storm of short runs costs at most
~2 % of the loop. With the cycle broken the relay stays at ~118 MB through the soak; the pass
brings it to ~81 MB between bursts, and alone (a cycle unbroken) it bounds the growth to a sawtooth
of what the runs released within one interval.

Measured and not done (bench_relay_soak.py --env): ``MALLOC_ARENA_MAX=1`` changes nothing (the
relay runs 2-3 threads, so 2-3 arenas); a fixed ``MALLOC_MMAP_THRESHOLD_=131072`` lowers the flat
level by ~30 MB but makes every block over it an mmap/munmap with its page faults, on the ingest path.

:func:`heap_view` is in ``/api/health``'s ``heap``: what malloc holds (in use, free inside its
arenas, mmapped) beside ``memory.live_bytes``, so that a gap between the RSS and the live state
shows where it is. Off glibc (musl) trimming is a no-op and the view says it has no figures.
"""

from __future__ import annotations

import asyncio
import ctypes
import gc
import logging
import time
from collections.abc import Callable

from dcuscope.core.clocks import NEVER

CHECK_S = 1.0
"""How often the reclaimer looks whether runs left memory."""
MIN_INTERVAL_S = 2.0
"""Least time between two reclaim passes (a collection is tens of ms on the loop)."""

log = logging.getLogger(__name__)


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]


def _libc() -> tuple[Callable[[int], int] | None, Callable[[], _MallInfo2] | None]:
    """glibc's malloc_trim and mallinfo2 (2.33+) from the process's own symbols, each None where absent."""
    try:
        lib = ctypes.CDLL(None)
    except OSError:
        return None, None
    trim = getattr(lib, "malloc_trim", None)
    if trim is not None:
        trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    info = getattr(lib, "mallinfo2", None)
    if info is not None:
        info.argtypes, info.restype = [], _MallInfo2
    return trim, info


_TRIM, _INFO = _libc()


def trim() -> bool:
    """Give the free pages of every malloc arena back to the system; False where it cannot (no glibc)."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


def heap_view() -> dict:
    """What malloc holds now, bytes (for /api/health): ``arena`` (taken from the system by its heaps),
    ``in_use`` and ``free`` within them, ``mmapped`` (large blocks outside them); ``{"available": false}``
    off glibc."""
    if _INFO is None:
        return {"available": False}
    mi = _INFO()
    return {"available": True, "arena": mi.arena, "in_use": mi.uordblks, "free": mi.fordblks, "mmapped": mi.hblkhd}


class Reclaimer:
    """After runs left memory: a full collection, then malloc_trim (see the module's docstring)."""

    def __init__(self, released: Callable[[], int], min_interval_s: float = MIN_INTERVAL_S) -> None:
        """``released()``: runs that left memory so far (``RelayState.released``)."""
        self._released = released
        self._min_interval_s = min_interval_s
        self._seen = released()
        self._at = NEVER
        self.passes = 0
        self.collected = 0
        """Objects the passes' collections found in cycles (what the cyclic collector had not freed yet)."""
        self.last_ms = 0.0
        """How long the last pass held the loop."""
        self.last_trim_ms = 0.0
        """Of which malloc_trim."""

    def due(self) -> bool:
        return self._released() != self._seen and time.monotonic() - self._at >= self._min_interval_s

    def reclaim(self) -> None:
        t = time.monotonic()
        self._seen = self._released()
        self.collected += gc.collect()
        collected = time.monotonic()
        trim()
        self._at = time.monotonic()
        self.passes += 1
        self.last_ms, self.last_trim_ms = (self._at - t) * 1e3, (self._at - collected) * 1e3

    async def run(self) -> None:
        while True:
            await asyncio.sleep(CHECK_S)
            try:
                if self.due():
                    self.reclaim()
            except Exception:  # noqa: BLE001 - memory housekeeping must never stop the relay
                log.exception("reclaiming memory failed")

    def view(self) -> dict:
        """For /api/health: the passes made, what they collected, the last one's time, and the heap now."""
        return {"reclaims": self.passes, "collected": self.collected, "last_reclaim_ms": round(self.last_ms, 1),
                "last_trim_ms": round(self.last_trim_ms, 1),
                **heap_view()}
