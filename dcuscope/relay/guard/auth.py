"""Token files of the relay: ``--node-tokens`` and ``--viewer-tokens`` (``NAME TOKEN`` per line).

What each credential may do is :mod:`dcuscope.relay.guard.policy`'s to say.
"""

from __future__ import annotations

from pathlib import Path

from dcuscope.relay.errors import RelayError

MIN_TOKEN_CHARS = 16


def load_tokens(path: str | Path, option: str = "--node-tokens") -> dict[str, str]:
    """``NAME TOKEN`` per line (``#`` comments, blank lines); RelayError names ``option``, the file and a bad line."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise RelayError(f"{option} {path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    tokens: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) != 2 or not words[0].isprintable() or len(words[1]) < MIN_TOKEN_CHARS:
            raise RelayError(f"{option} {path}:{number}: expected 'NAME TOKEN' (a token of {MIN_TOKEN_CHARS}+ characters)")
        if words[0] in tokens:
            raise RelayError(f"{option} {path}:{number}: {words[0]!r} listed twice")
        if words[1] in tokens.values():
            raise RelayError(f"{option} {path}:{number}: the same token for two names")
        tokens[words[0]] = words[1]
    if not tokens:
        raise RelayError(f"{option} {path}: no 'NAME TOKEN' line")
    return tokens
