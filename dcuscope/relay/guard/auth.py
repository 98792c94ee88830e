"""The relay's credentials (:class:`Credentials`) and its token files: ``--node-tokens`` and
``--viewer-tokens`` (``NAME TOKEN`` per line).

What each credential may do is :mod:`dcuscope.relay.guard.policy`'s to say.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
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


@dataclass(frozen=True)
class Credentials:
    """The relay's credentials, whole: the admin's token (``--token``), the viewers' and the nodes'
    (``--viewer-tokens``, ``--node-tokens``: NAME -> token). What each may do is
    :class:`~dcuscope.relay.guard.policy.Policy`'s."""

    admin: str | None = None
    viewers: Mapping[str, str] = field(default_factory=dict)
    nodes: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def from_files(cls, admin: str | None, viewers: str | Path | None, nodes: str | Path | None) -> Credentials:
        """The admin's token and the token files as the options name them."""
        return cls(admin, load_tokens(viewers, "--viewer-tokens") if viewers else {},
                   load_tokens(nodes, "--node-tokens") if nodes else {})

    @property
    def any(self) -> bool:
        """Whether any credential is asked for (else the relay is open to whoever reaches it)."""
        return self.admin is not None or bool(self.viewers) or bool(self.nodes)

    def secrets(self) -> list[str]:
        """Every token, for the log's redaction."""
        return [*([self.admin] if self.admin is not None else []), *self.viewers.values(), *self.nodes.values()]
