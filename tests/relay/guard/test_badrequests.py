"""A request aiohttp could not parse is logged as one INFO line naming the client and what was
wrong, never as an ERROR with a traceback (relay/guard/badrequests.py): aiohttp's own record, as
its handle_error writes it when the garbage came in two reads."""

from __future__ import annotations

import logging

import pytest
from aiohttp.http_exceptions import BadHttpMethod

from dcuscope.relay.guard import badrequests


@pytest.fixture
def lines():
    got: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = got.append
    logger = logging.getLogger(badrequests.LOGGER)
    logger.addHandler(handler)
    saved = logger.filters[:]
    try:
        yield got
    finally:
        logger.removeHandler(handler)
        logger.filters[:] = saved


def test_a_malformed_request_is_one_info_line_without_traceback(lines):
    badrequests.install()
    badrequests.install()  # once only
    garbage = "PROXY TCP4 127.0.0.2 127.0.0.1 56445 3000\r\n\x1b[31m\u00e9"
    logging.getLogger(badrequests.LOGGER).exception("Error handling request from %s", "127.0.0.9",
                                                    exc_info=BadHttpMethod(garbage))
    record, = lines
    text = logging.Formatter("%(levelname)s %(message)s").format(record)
    assert text.startswith("INFO refused a malformed request from 127.0.0.9 (400): Bad HTTP method in status line "
                           "'PROXY TCP4 127.0.0.2 127.0.0.1 56445 3000"), text
    assert "Traceback" not in text and "\n" not in text and "\x1b" not in text and "\\xe9" in text, text
    assert sum(isinstance(f, badrequests.MalformedRequests) for f in logging.getLogger(badrequests.LOGGER).filters) == 1


def test_a_handlers_own_failure_keeps_its_error_and_traceback(lines):
    badrequests.install()
    try:
        raise RuntimeError("a bug of the relay's")
    except RuntimeError:
        logging.getLogger(badrequests.LOGGER).exception("Error handling request from %s", "127.0.0.9")
    record, = lines
    assert record.levelno == logging.ERROR and record.exc_info is not None
