"""Exceptions of the relay package, and the JSON error its HTTP handlers raise."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from dcuscope.core.errors import DcuscopeError

if TYPE_CHECKING:  # aiohttp is not imported by the command line's start (relay.commands imports this)
    from aiohttp import web


class RelayError(DcuscopeError):
    """The relay could not start, its storage failed, or stored data is unreadable."""


def http_error(kind: type[web.HTTPException], message: str) -> web.HTTPException:
    """A JSON ``{"error": message}`` HTTP error to raise from a handler."""
    return kind(text=json.dumps({"error": message}), content_type="application/json")
