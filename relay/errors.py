"""Exceptions of the relay package."""

from core.errors import DcuscopeError


class RelayError(DcuscopeError):
    """The relay could not start, its storage failed, or stored data is unreadable."""
