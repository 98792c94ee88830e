"""Token checks for nodes, browsers and HTTP clients (``dcuscope relay --token``)."""

from __future__ import annotations

import hmac
from pathlib import Path
from urllib.parse import parse_qs

from relay.errors import RelayError


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


def node_for_token(tokens: dict[str, str], presented: object) -> str | None:
    """The node whose own token ``presented`` is (``--node-tokens``), or None. Every entry is
    compared, in constant time each, so the time taken says nothing about which matched."""
    if not isinstance(presented, str):
        return None
    given = presented.encode("utf-8", "surrogateescape")
    found = None
    for node, token in tokens.items():
        if hmac.compare_digest(given, token.encode()):
            found = node
    return found


def load_node_tokens(path: str | Path) -> dict[str, str]:
    """``NODE TOKEN`` per line (``#`` comments, blank lines); RelayError names a bad line."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise RelayError(f"--node-tokens {path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    tokens: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) != 2 or not words[0].isprintable() or len(words[1]) < 16:
            raise RelayError(f"--node-tokens {path}:{number}: expected 'NODE TOKEN' (a token of 16+ characters)")
        if words[0] in tokens:
            raise RelayError(f"--node-tokens {path}:{number}: node {words[0]!r} listed twice")
        if words[1] in tokens.values():
            raise RelayError(f"--node-tokens {path}:{number}: the same token for two nodes")
        tokens[words[0]] = words[1]
    if not tokens:
        raise RelayError(f"--node-tokens {path}: no 'NODE TOKEN' line")
    return tokens
