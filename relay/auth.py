"""Token checks for nodes, browsers and HTTP clients (``dcuscope relay --token``)."""

from __future__ import annotations

import hmac
from urllib.parse import parse_qs


def token_matches(expected: str | None, presented: object) -> bool:
    """True when no token is required, or ``presented`` is the token (constant-time compare)."""
    if expected is None:
        return True
    if not isinstance(presented, str):
        return False
    try:
        given = presented.encode()
    except UnicodeEncodeError:  # a header's undecodable bytes (surrogate escapes), a lone surrogate: not the token
        return False
    return hmac.compare_digest(given, expected.encode())


def socket_token(auth: object, environ: dict) -> object:
    """The token a Socket.IO client presented: ``auth={"token": ...}``, else ``?token=``."""
    if isinstance(auth, dict) and "token" in auth:
        return auth["token"]
    query = parse_qs(environ.get("QUERY_STRING", ""))
    values = query.get("token")
    return values[0] if values else None


def http_token(headers, query) -> object:
    """The token of an HTTP request: ``Authorization: Bearer ...``, else ``?token=``."""
    value = headers.get("Authorization", "")
    if value.startswith("Bearer "):
        return value[len("Bearer "):].strip()
    return query.get("token")
