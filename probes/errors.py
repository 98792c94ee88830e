"""Exceptions of the probes package: each names the trace file (and line) at fault."""

from pipeline.errors import DcuscopeError


class TraceError(DcuscopeError):
    """A trace file is missing, is not a dcuscope trace, or holds malformed events."""
