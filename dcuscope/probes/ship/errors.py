"""The error of shipping events to a relay: it names the exporter at fault (the protocol's own
errors are :mod:`dcuscope.protocol.errors`)."""

from dcuscope.core.errors import DcuscopeError


class ExportError(DcuscopeError):
    """An exporter is misconfigured or could not deliver the run's events (the relay is
    unreachable, or refused the node's token)."""
