"""Errors of shipping events to a relay: each names the exporter or the payload at fault."""

from dcuscope.core.errors import DcuscopeError


class ExportError(DcuscopeError):
    """An exporter is misconfigured or could not deliver the run's events (the relay is
    unreachable, or refused the node's token)."""


class ProtocolError(DcuscopeError):
    """A payload of the node <-> relay protocol is malformed, truncated, oversize or of another
    version (:mod:`dcuscope.probes.ship.wire`, :mod:`dcuscope.probes.ship.envelope`)."""


class LimitExceeded(ProtocolError):
    """A well-formed payload beyond one of the relay's limits (``limit`` names it, as
    ``--limit NAME=VALUE`` sets it), so that the relay can count refusals per limit."""

    def __init__(self, limit: str, message: str) -> None:
        super().__init__(message)
        self.limit = limit
