"""A request the relay could not parse is the client's fault, not the relay's: one INFO line, never
an ERROR with a traceback.

aiohttp answers such a request (a PROXY header without ``--trusted-proxy``, TLS on a plain port,
any garbage) with a 400 and logs it at DEBUG, but only when it was the connection's first message:
when the garbage came in two reads, the second counts as a second request, and aiohttp logs the
first at ERROR with its traceback (``web_protocol.RequestHandler.handle_error``), which a loaded
machine makes happen now and then. :class:`MalformedRequests`, on aiohttp's server logger, turns
those into one line naming the client and what was wrong (whitespace collapsed, anything else
unprintable or non-ASCII escaped: the text is the client's).
"""

from __future__ import annotations

import logging

from aiohttp.http_exceptions import HttpProcessingError

LOGGER = "aiohttp.server"
MAX_CHARS = 200
"""Of the parser's message, which quotes the client's bytes."""


class MalformedRequests(logging.Filter):
    """Rewrites aiohttp's ERROR record of a request it could not parse as one INFO line."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if record.levelno >= logging.ERROR and isinstance(exc, HttpProcessingError) and exc.code < 500:
            what = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in " ".join(str(exc.message).split()))
            what = what[:MAX_CHARS].encode("ascii", "backslashreplace").decode()
            record.msg, record.args = "refused a malformed request from %s (%d): %s", (
                record.args[0] if record.args else "?", exc.code, what)
            record.levelno, record.levelname = logging.INFO, "INFO"
            record.exc_info = record.exc_text = None
        return True


def install() -> None:
    """Put a :class:`MalformedRequests` on aiohttp's server logger (once)."""
    logger = logging.getLogger(LOGGER)
    if not any(isinstance(f, MalformedRequests) for f in logger.filters):
        logger.addFilter(MalformedRequests())
