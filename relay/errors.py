"""Exceptions of the relay package."""

from pipeline.errors import DcuscopeError


class RelayError(DcuscopeError):
    """The relay could not start, a node could not reach it, or stored data is unreadable."""


class ProtocolError(RelayError):
    """A node sent a payload the relay cannot accept (malformed, truncated, oversize, wrong version)."""
