"""The relay's bound on repeated log messages (relay.guard.lograte) on a real logging handler."""

from __future__ import annotations

import io
import logging

from dcuscope.relay.guard.lograte import RateFilter


def test_repeats_beyond_the_rate_are_counted_and_summarised():
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    rate = RateFilter(per_min=10)
    handler.addFilter(rate)
    logger = logging.getLogger("dcuscope.relay.test_lograte")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        for i in range(500):
            logger.warning("peer %s misbehaved", i)  # one message, whatever the client
        logger.warning("another message")
        logger.debug("debug output is never held back")
        rate.flush()  # the minute is not over: nothing summarised yet
        assert len(out.getvalue().splitlines()) == 11
        rate.flush(everything=True)
    finally:
        logger.removeHandler(handler)
    lines = out.getvalue().splitlines()
    assert lines[:10] == [f"peer {i} misbehaved" for i in range(10)] and lines[10] == "another message"
    assert lines[11:] == ["suppressed 490 similar messages in 60 s: peer %s misbehaved"]
    assert rate.suppressed == 490
