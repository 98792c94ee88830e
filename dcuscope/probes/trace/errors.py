"""The error of trace files: it names the file (and line) at fault."""

from dcuscope.core.errors import DcuscopeError


class TraceError(DcuscopeError):
    """A trace file is missing, is not a dcuscope trace, or holds malformed events."""
