"""Host and Origin checks of a relay without a token (DNS rebinding, cross-site pages).

Without ``--token`` anyone who reaches the relay may read and feed it; a web page elsewhere
must not be able to. A page of ``evil.example`` whose name is made to resolve to 127.0.0.1
(DNS rebinding) sends ``Host: evil.example``; a page that opens ``ws://127.0.0.1:3000/ingest``
sends its own ``Origin``. So every request (API, page, ``/ingest``, Socket.IO) must name as
Host an IP address, ``localhost`` or a name given with ``--allow-host``, and a browser's
``Origin``, when present, must be the relay itself (same host and port as Host) or an allowed
name. One exception: an ``/ingest`` upgrade without ``Origin`` comes from a node, not a page
(browsers send ``Origin`` with every WebSocket handshake), so nodes may name the relay by any
host name. Once reading takes a credential (``--token``, ``--viewer-tokens``), the credential is
the guard (:mod:`dcuscope.relay.guard.policy`) and these checks are off.
"""

from __future__ import annotations

import ipaddress
from collections import Counter
from collections.abc import Iterable

from aiohttp import web

from dcuscope.protocol.wire import INGEST_PATH
from dcuscope.relay.errors import http_error


def host_name(netloc: str) -> str:
    """The host part of ``host[:port]`` (``[v6]:port`` too), lower case, without a final dot."""
    netloc = netloc.strip().lower()
    if netloc.startswith("["):
        end = netloc.find("]")
        return netloc[1:end] if end > 0 else netloc
    if netloc.count(":") == 1:
        netloc = netloc.split(":", 1)[0]
    return netloc.rstrip(".")


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def origin_netloc(origin: str) -> str | None:
    """``host[:port]`` of an Origin header (``scheme://host[:port]``); None if it is not one ("null")."""
    scheme, sep, rest = origin.strip().partition("://")
    if not sep or not scheme or not rest or "/" in rest:
        return None
    return rest.lower()


class HostCheck:
    """The middleware of the module docstring; counts what it refused in ``refused["host"]``."""

    def __init__(self, allowed: Iterable[str], refused: Counter, exempt: str | None = None) -> None:
        self.allowed = frozenset(host_name(name) for name in allowed)
        self.refused = refused
        self.exempt = exempt
        """A path guarded otherwise (``/ingest`` when nodes have tokens of their own)."""

    def host_allowed(self, name: str) -> bool:
        return name == "localhost" or name in self.allowed or _is_ip(name)

    def problem(self, headers, path: str = "/") -> str | None:
        """Why a request for ``path`` with these headers is refused, or None."""
        if path == INGEST_PATH and "Origin" not in headers:
            return None
        host = headers.get("Host")
        # No Host: HTTP/1.0 scripts; browsers always send one.
        if host is not None and not self.host_allowed(host_name(host)):
            return (f"host {host_name(host)[:100]!r} refused: without --token the relay answers only requests "
                    f"to an IP address, localhost or a name given with --allow-host")
        origin = headers.get("Origin")
        if origin is None:
            return None
        netloc = origin_netloc(origin)
        same = netloc is not None and host is not None and netloc == host.strip().lower()
        if not same and (netloc is None or host_name(netloc) not in self.allowed):
            return (f"origin {origin[:100]!r} refused: without --token the relay answers browsers only on pages "
                    f"of its own (or of a name given with --allow-host)")
        return None

    @web.middleware
    async def middleware(self, request: web.Request, handler) -> web.StreamResponse:
        problem = self.problem(request.headers, request.path) if request.path != self.exempt else None
        if problem is not None:
            self.refused["host"] += 1
            raise http_error(web.HTTPForbidden, problem)
        return await handler(request)
