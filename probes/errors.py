"""Exceptions of the probes package: each names the trace file (and line), or the exporter, at fault."""

from pipeline.errors import DcuscopeError


class TraceError(DcuscopeError):
    """A trace file is missing, is not a dcuscope trace, or holds malformed events."""


class ExportError(DcuscopeError):
    """An exporter could not deliver the run's events (the relay refused the node's token)."""
