"""A bound on how often the relay logs the same thing: a hostile or broken client must not be
able to fill the disk with the relay's log.

:class:`RateFilter` lets the same message (logger and format string, so the same failure for
different clients counts as one) through ``per_min`` times a minute and counts the rest; a record
logged with ``extra={"rate_key": KEY}`` counts apart per KEY (a TLS refusal per reason and client
address: the first line of each is never held back, while fewer than :data:`MAX_KEYS` are tracked);
:meth:`RateFilter.flush`, called now and then, logs one "suppressed N similar messages" line
per message that was held back. :func:`install` puts one on the handlers of the root logger,
where the relay's, aiohttp's, Socket.IO's and asyncio's records all end.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

WINDOW_S = 60.0
MAX_KEYS = 1000
"""Distinct messages tracked; beyond, the rest of a logger share one count (format strings are
few, but a record may carry a client's text as its message)."""


@dataclass
class _Seen:
    start: float
    passed: int = 0
    suppressed: int = 0
    level: int = logging.WARNING


class RateFilter(logging.Filter):
    """Passes each message ``per_min`` times per minute (DEBUG records always: they are asked for)."""

    def __init__(self, per_min: int) -> None:
        super().__init__()
        self.per_min = per_min
        self.suppressed = 0
        """Records held back so far, in all."""
        self._seen: dict[tuple[str, str, object], _Seen] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.INFO:
            return True
        verdict = getattr(record, "_rate_verdict", None)
        if verdict is not None:  # one record, several handlers: counted once
            return verdict
        key = (record.name, str(record.msg)[:200], getattr(record, "rate_key", None))
        if key not in self._seen and len(self._seen) >= MAX_KEYS:
            key = (record.name, "(other messages)", None)
        now = time.monotonic()
        seen = self._seen.get(key)
        if seen is None or now - seen.start >= WINDOW_S:
            if seen is not None and seen.suppressed:
                self._summarise(key, seen)
            seen = self._seen[key] = _Seen(now, level=record.levelno)
        verdict = seen.passed < self.per_min
        if verdict:
            seen.passed += 1
        else:
            seen.suppressed += 1
            self.suppressed += 1
        record._rate_verdict = verdict
        return verdict

    def flush(self, everything: bool = False) -> None:
        """Log a summary for each message held back in a window that is over (``everything``: in
        any window, as the relay stops), and forget those windows."""
        now = time.monotonic()
        for key, seen in list(self._seen.items()):
            if everything or now - seen.start >= WINDOW_S:
                del self._seen[key]
                if seen.suppressed:
                    self._summarise(key, seen)

    def _summarise(self, key: tuple[str, str, object], seen: _Seen) -> None:
        name, text, _ = key
        # Logged with a format of its own, so a flood of summaries is itself bounded.
        logging.getLogger(name).log(seen.level, "suppressed %d similar messages in %d s: %s",
                                    seen.suppressed, WINDOW_S, text)


def install(per_min: int) -> RateFilter:
    """Put a :class:`RateFilter` on every handler of the root logger (Python's last-resort one if none)."""
    rate = RateFilter(per_min)
    handlers = logging.getLogger().handlers or [logging.lastResort]
    for handler in handlers:
        if handler is not None:
            handler.addFilter(rate)
    return rate
