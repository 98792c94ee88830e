"""The errors of the node <-> relay protocol: each names the payload or the limit at fault."""

from dcuscope.core.errors import DcuscopeError


class ProtocolError(DcuscopeError):
    """A payload of the node <-> relay protocol is malformed, truncated, oversize or of another
    version (:mod:`dcuscope.protocol.wire`, :mod:`dcuscope.protocol.envelope`)."""


class LimitExceeded(ProtocolError):
    """A well-formed payload beyond one of the relay's limits (``limit`` names it, as
    ``--limit NAME=VALUE`` sets it), so that the relay can count refusals per limit."""

    def __init__(self, limit: str, message: str) -> None:
        super().__init__(message)
        self.limit = limit
