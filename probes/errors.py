"""Exceptions of the probes package: each names the trace file (and line), or the exporter, at fault."""

from core.errors import DcuscopeError


class TraceError(DcuscopeError):
    """A trace file is missing, is not a dcuscope trace, or holds malformed events."""


class ExportError(DcuscopeError):
    """An exporter is misconfigured or could not deliver the run's events (the relay is
    unreachable, or refused the node's token)."""


class ProtocolError(DcuscopeError):
    """A payload of the node <-> relay protocol is malformed, truncated, oversize or of another
    version (:mod:`probes.wire`, :mod:`probes.envelope`)."""
